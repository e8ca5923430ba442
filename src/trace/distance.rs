//! Closest points on the GPU (the exact tier): a zero-length ray at each point meets the boxes of
//! every triangle within a search radius (the exact tier's boxes, grown by it), and the f64
//! distance to each of those triangles keeps the nearest. Points that find nothing within the
//! radius are asked again with twice the radius, until `max_distance`: each round is exact
//! for the points it settles (every triangle within the radius was met), so the answer is the
//! reference tier's (Zhu, "RTNN", PPoPP 2022: radius search on ray-tracing hardware). Points
//! still unsettled after a few rounds are far from every surface, where grown boxes would hold
//! most triangles: the CPU's best-first search (the reference tier's) answers those.

use glam::DVec3;
use rayon::prelude::*;

use super::chunks::GpuJob;
use super::fields::{Field, HitSink};
use super::profile::TraceProfile;
use super::request::{Cull, Precision, Query, Request};
use super::tracer::Tracer;
use crate::error::{try_vec, Result};
use crate::geometry::arrays::Vec3s;
use crate::geometry::rays::{Masks, PerRay, Rays};
use crate::geometry::reference::ClosestHit;
use crate::gpu::context::Interrupt;
use crate::scene::Scene;

/// How many times the search radius grows between rounds.
const GROWTH: f64 = 2.0;
/// Rounds on the GPU; the points still unsettled after them are far from every surface.
const GPU_ROUNDS: usize = 3;
/// Points whose distance the CPU measures first, to choose the first radius.
const SAMPLE: usize = 64;

impl Tracer {
    /// The surface point nearest to each point within `max_distance`, found on the GPU: in f64
    /// (`Precision::Exact`) or f32 (`Fast`: each candidate measured in f32 in the scene's frame;
    /// the nearest to within f32 rounding). Points far from every surface: the CPU, in f64.
    pub(super) fn rt_closest_points(
        &self,
        scene: &Scene,
        points: Vec3s,
        max_distance: f64,
        precision: Precision,
        interrupt: &dyn Interrupt,
    ) -> Result<Vec<Option<ClosestHit>>> {
        let n = points.rows();
        let mut found: Vec<Option<ClosestHit>> = try_vec(n, None, "the closest points")?;
        let mut pending: Vec<usize> = (0..n).collect();
        let mut radius = first_radius(scene, points, max_distance);
        for _ in 0..GPU_ROUNDS {
            if pending.is_empty() {
                break;
            }
            interrupt.check()?;
            let reach = radius.min(max_distance);
            let settled = self.distance_round(scene, points, &pending, reach, precision, interrupt)?;
            let last = reach >= max_distance;
            let mut still = Vec::new();
            for (&i, hit) in pending.iter().zip(settled) {
                match hit {
                    Some(hit) => found[i] = Some(hit),
                    None if !last => still.push(i),
                    None => {}
                }
            }
            pending = still;
            radius *= GROWTH;
        }
        // Points still far from every surface: boxes grown to their distance would hold most of
        // the scene's triangles, while the CPU's best-first search prunes by the nearest found.
        let tracer = scene.reference_tracer();
        let far: Vec<(usize, Option<ClosestHit>)> = crate::geometry::parallel::install(|| {
            pending
                .par_iter()
                .with_min_len(64)
                .map(|&i| {
                    let p = DVec3::from_array(points.row_f64(i)) - scene.center;
                    (i, tracer.closest_point(p, 0xFF, max_distance))
                })
                .collect()
        });
        for (i, hit) in far {
            found[i] = hit;
        }
        Ok(found)
    }

    /// One round: the points `pending` with boxes grown by `reach`; None where nothing lies within it.
    fn distance_round(
        &self,
        scene: &Scene,
        points: Vec3s,
        pending: &[usize],
        reach: f64,
        precision: Precision,
        interrupt: &dyn Interrupt,
    ) -> Result<Vec<Option<ClosestHit>>> {
        let m = pending.len();
        let mut origins = try_vec(3 * m, 0.0f64, "the points of a distance round")?;
        for (k, &i) in pending.iter().enumerate() {
            origins[3 * k..3 * k + 3].copy_from_slice(&points.row_f64(i));
        }
        let probe = [1.0f64, 0.0, 0.0];
        let rays = Rays {
            origins: Vec3s::F64(&origins),
            directions: Vec3s::F64(&probe),
            tmin: PerRay::All(0.0),
            tmax: PerRay::All(reach),
            mask: Masks::All(0xFF),
            sensor: None,
        };
        let structures = scene.reach(reach)?;
        let request = Request::new(Query::Distance, precision, Cull::None);
        let outputs =
            Field::T.bit() | Field::Prim.bit() | Field::Instance.bit() | Field::Geometry.bit() | Field::Uv.bit();
        let (variant, _) = self.gpu_variant(scene, &rays, request, true, outputs)?;
        let (mut t, mut prim, mut instance, mut geometry, mut uv) = (
            try_vec(m, 0.0f64, "distances")?,
            try_vec(m, 0i32, "triangles")?,
            try_vec(m, 0i32, "instances")?,
            try_vec(m, 0i32, "parts")?,
            try_vec(2 * m, 0.0f64, "barycentrics")?,
        );
        {
            let mut sink = HitSink::default();
            sink.set(Field::T, bytemuck::cast_slice_mut(&mut t));
            sink.set(Field::Prim, bytemuck::cast_slice_mut(&mut prim));
            sink.set(Field::Instance, bytemuck::cast_slice_mut(&mut instance));
            sink.set(Field::Geometry, bytemuck::cast_slice_mut(&mut geometry));
            sink.set(Field::Uv, bytemuck::cast_slice_mut(&mut uv));
            let capacity = self.chunk_capacity(m);
            let mut slots = self.slots.take(capacity, true)?;
            let job = GpuJob {
                scene,
                exact: Some(&structures),
                rays: &rays,
                variant: &variant,
                outputs,
                frame: scene.frame(),
                all_hits: false,
                sensor: None,
            };
            let mut profile = TraceProfile { rays: m, ..Default::default() };
            let result = self.trace_chunks(&job, &mut sink, &mut slots, capacity, interrupt, &mut profile);
            self.slots.give_back(slots);
            result?;
        }
        Ok(crate::geometry::parallel::install(|| {
            (0..m)
                .into_par_iter()
                .with_min_len(4096)
                .map(|k| {
                    if !t[k].is_finite() {
                        return None;
                    }
                    let placement = &scene.placements[instance[k] as usize];
                    let global = placement.triangles.global(geometry[k] as usize, prim[k] as usize);
                    let [a, b, c] = placement.triangles.triangle(global).map(|v| placement.to_scene.point(v));
                    let (u, v) = (uv[2 * k], uv[2 * k + 1]);
                    let point = a * (1.0 - u - v) + b * u + c * v;
                    Some(ClosestHit { distance: t[k], point, u, v, instance: instance[k] as u32, prim: global as u32 })
                })
                .collect()
        }))
    }
}

/// The first search radius: the median distance of a few points (measured on the CPU), so that
/// about half the points settle in the first round, but at most four triangles' spacing (beyond,
/// the boxes overlap by the hundreds); at least a millionth of the scene.
fn first_radius(scene: &Scene, points: Vec3s, max_distance: f64) -> f64 {
    let n = points.rows();
    let size = scene.frame().radius.max(f64::MIN_POSITIVE);
    if n == 0 {
        return size;
    }
    let tracer = scene.reference_tracer();
    let step = n.div_ceil(SAMPLE);
    let mut sample: Vec<f64> = (0..n)
        .step_by(step)
        .map(|i| {
            let p = DVec3::from_array(points.row_f64(i)) - scene.center;
            tracer.closest_point(p, 0xFF, max_distance).map_or(max_distance, |h| h.distance)
        })
        .collect();
    sample.sort_by(f64::total_cmp);
    let median = sample[sample.len() / 2];
    // A few triangles across: boxes grown by more overlap by the hundreds.
    let triangles: usize = scene.placements.iter().map(|p| p.triangles.faces.len()).sum();
    let spacing = 2.0 * size / (triangles.max(1) as f64).sqrt();
    median.min(4.0 * spacing).max(1e-6 * size)
}
