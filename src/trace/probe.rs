//! Probes of the paths through intersection shaders: one ray each, once per device, tells whether
//! the driver runs them (lavapipe lost the exact tier's scratch stores until they were made
//! volatile: every ray missed). A driver that fails gets a clear error instead of wrong answers.

use std::sync::Arc;

use super::fields::{Field, HitSink};
use super::profile::TraceProfile;
use super::request::{Cull, Precision, Query, Request};
use super::tracer::Tracer;
use crate::error::{Error, Result};
use crate::geometry::arrays::{Indices, Vec3s};
use crate::geometry::rays::{Masks, PerRay, Rays};
use crate::geometry::vertex_format::VertexFormat;
use crate::gpu::accel::{BuildOptions, BuildPreference};
use crate::gpu::context::{Backend, NoInterrupt};
use crate::scene::{Instance, Mesh, Scene, IDENTITY};

/// The two paths through intersection shaders.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Probe {
    Exact = 0,
    Spheres = 1,
}

impl Tracer {
    /// Fails where this device's pipeline backend does not run `probe`'s intersection shaders.
    /// The answer is computed once, without holding any lock (two threads may both probe).
    pub(super) fn check_intersection_shaders(&self, probe: Probe) -> Result<()> {
        if self.ctx.backend != Backend::Pipeline {
            return Ok(());
        }
        let cell = &self.probes[probe as usize];
        let runs = match cell.get() {
            Some(runs) => *runs,
            None => {
                let runs = self.probe(probe)?;
                *cell.get_or_init(|| runs)
            }
        };
        if runs {
            return Ok(());
        }
        let (what, instead) = match probe {
            Probe::Exact => ("precision='exact'", " or precision='reference' (same answers, on the CPU)"),
            Probe::Spheres => ("spheres", ""),
        };
        Err(Error::Unsupported(format!(
            "{} ({}) does not run the intersection shaders of {what} in ray-tracing pipelines; use backend='ray_query'{instead}",
            self.ctx.info.name, self.ctx.info.driver
        )))
    }

    /// Whether one ray down the `probe` path hits what it must.
    fn probe(&self, probe: Probe) -> Result<bool> {
        let options = BuildOptions { preference: BuildPreference::FastBuild, allow_update: false, compact: false };
        let triangle = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let mesh = match probe {
            Probe::Exact => {
                Mesh::build(&self.ctx, Vec3s::F64(&triangle), Indices::U32(&[0, 1, 2]), options, VertexFormat::F32)?
            }
            Probe::Spheres => Mesh::spheres(&self.ctx, Vec3s::F64(&[0.0; 3]), PerRay::All(1.0), options)?,
        };
        let instance = Instance {
            mesh: Arc::new(mesh),
            transform: IDENTITY,
            custom_index: 0,
            mask: 0xFF,
            flags: Default::default(),
        };
        let scene = Scene::build(&self.ctx, &[instance], options)?;
        let rays = Rays {
            origins: Vec3s::F64(&[0.25, 0.25, 5.0]),
            directions: Vec3s::F64(&[0.0, 0.0, -1.0]),
            tmin: PerRay::All(0.0),
            tmax: PerRay::All(f64::INFINITY),
            mask: Masks::All(0xFF),
            sensor: None,
        };
        let mut prim = [0xFFu8; 4];
        let mut sink = HitSink::default();
        sink.set(Field::Prim, &mut prim);
        let exact = probe == Probe::Exact;
        let precision = if exact { Precision::Exact } else { Precision::Fast };
        let request = Request::new(Query::Closest, precision, Cull::None);
        self.run_gpu(&scene, &rays, request, exact, &mut sink, &NoInterrupt, &mut TraceProfile::default())?;
        Ok(i32::from_ne_bytes(prim) == 0)
    }
}
