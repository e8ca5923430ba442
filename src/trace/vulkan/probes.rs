//! Probes of the paths through intersection shaders: one ray each, once per device, tells whether
//! the driver runs them (lavapipe lost the exact tier's scratch stores until they were made
//! volatile: every ray missed). A driver that fails gets a clear error instead of wrong answers.

use std::sync::{Arc, OnceLock};

use super::ray_chunks::RayChunks;
use super::shared::Shared;
use crate::error::{Error, Result};
use crate::geometry::arrays::{Indices, Vec3s};
use crate::geometry::build_options::{BuildOptions, BuildPreference};
use crate::geometry::interrupt::NoInterrupt;
use crate::geometry::rays::{Masks, PerRay, Rays};
use crate::geometry::vertex_format::VertexFormat;
use crate::gpu::context::Backend;
use crate::scene::{
    build_vulkan_meshes, build_vulkan_scene, build_vulkan_spheres, Instance, MeshBatch, MeshInput, Scene, IDENTITY,
};
use crate::trace::hit_fields::{Field, HitSink};
use crate::trace::profile::TraceProfile;
use crate::trace::request::{Cull, Precision, Query, RayBatch, Request};

/// The two paths through intersection shaders.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Probe {
    Exact = 0,
    Spheres = 1,
}

/// The probes' answers, once known, and the path they run down.
pub struct Probes {
    shared: Arc<Shared>,
    chunks: RayChunks,
    /// Whether this driver runs the intersection shaders of each `Probe` path, once known.
    runs: [OnceLock<bool>; 2],
}

impl Probes {
    pub fn new(shared: &Arc<Shared>, chunks: &RayChunks) -> Probes {
        Probes { shared: shared.clone(), chunks: chunks.clone(), runs: [OnceLock::new(), OnceLock::new()] }
    }

    /// Fails where this driver does not run the intersection shaders a GPU query on `scene`
    /// needs (`exact`: the f64 test through per-triangle boxes; spheres).
    pub fn check_paths(&self, scene: &Scene, exact: bool) -> Result<()> {
        if exact {
            self.check_intersection_shaders(Probe::Exact)?;
        }
        if scene.has_spheres() {
            self.check_intersection_shaders(Probe::Spheres)?;
        }
        Ok(())
    }

    /// Fails where this device's pipeline backend does not run `probe`'s intersection shaders.
    /// The answer is computed once, without holding any lock (two threads may both probe).
    fn check_intersection_shaders(&self, probe: Probe) -> Result<()> {
        if self.shared.ctx.backend != Backend::Pipeline {
            return Ok(());
        }
        let cell = &self.runs[probe as usize];
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
            self.shared.ctx.info.name, self.shared.ctx.info.driver
        )))
    }

    /// Whether one ray down the `probe` path hits what it must.
    fn probe(&self, probe: Probe) -> Result<bool> {
        let options = BuildOptions { preference: BuildPreference::FastBuild, allow_update: false, compact: false };
        let triangle = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let mesh = match probe {
            Probe::Exact => {
                let parts = [(Vec3s::F64(&triangle), Indices::U32(&[0, 1, 2]))];
                let item = MeshInput { parts: &parts, opacity: None };
                let format = VertexFormat::F32;
                let batch =
                    MeshBatch { items: &[item], options, format, scratch_budget: u64::MAX, interrupt: &NoInterrupt };
                build_vulkan_meshes(&self.shared.ctx, batch)?.remove(0)
            }
            Probe::Spheres => build_vulkan_spheres(&self.shared.ctx, Vec3s::F64(&[0.0; 3]), PerRay::All(1.0), options)?,
        };
        let instance = Instance {
            mesh: Arc::new(mesh),
            transform: IDENTITY,
            custom_index: 0,
            mask: 0xFF,
            flags: Default::default(),
        };
        let scene = build_vulkan_scene(&self.shared.ctx, &[instance], options)?;
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
        let batch = RayBatch { scene: &scene, rays: &rays, request, interrupt: &NoInterrupt };
        self.chunks.run(batch, exact, &mut sink, &mut TraceProfile::default())?;
        Ok(i32::from_ne_bytes(prim) == 0)
    }
}
