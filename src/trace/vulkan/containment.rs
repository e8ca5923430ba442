//! `contains` on the Vulkan engine, exactly: one ray a point cast by the GPU, its crossings
//! counted by parity or through the winding cap, or each instance's winding number by the point
//! kernels; the points the GPU cannot tell are decided on the host (`host_tiers`).

use std::sync::Arc;
use std::time::Instant;

use rayon::prelude::*;

use super::all_hits::AllHitsPath;
use super::closest_points::{points_as_they_come, points_in_grid_order, ClosestPoints, ORDER_MIN_POINTS};
use super::gpu_rays::GpuRays;
use super::shared::Shared;
use crate::error::Result;
use crate::geometry::arrays::Vec3s;
use crate::geometry::morton;
use crate::geometry::parallel;
use crate::geometry::parallel::try_vec;
use crate::geometry::rays::{Masks, PerRay, Rays};
use crate::gpu::records::ExactHit;
use crate::scene::{VulkanScene, WindingCap};
use crate::trace::hit_fields::{Field, HitSink};
use crate::trace::host_tiers;
use crate::trace::request::{Crossings, Cull, PointBatch, Precision, Query, RayBatch, Request};

/// The exact `contains` path: it owns nothing; it runs the ray paths, the all-hits path and the
/// point kernels.
pub struct Containment {
    shared: Arc<Shared>,
    rays: Arc<GpuRays>,
    all_hits: Arc<AllHitsPath>,
    points: Arc<ClosestPoints>,
}

impl Containment {
    pub fn new(
        shared: &Arc<Shared>,
        rays: &Arc<GpuRays>,
        all_hits: &Arc<AllHitsPath>,
        points: &Arc<ClosestPoints>,
    ) -> Containment {
        Containment { shared: shared.clone(), rays: rays.clone(), all_hits: all_hits.clone(), points: points.clone() }
    }

    /// Whether each point is inside (1) or not (0): by parity (`winding` false: the caller
    /// checked that every mesh is closed) or by winding number (f64 shaders).
    pub fn run(&self, batch: PointBatch, winding: bool, out: &mut [u8]) -> Result<()> {
        if !winding {
            return self.by_gpu_rays(batch, None, out);
        }
        let _in_use = batch.scene.hold_meshes();
        batch.scene.check_current()?;
        match VulkanScene::of(batch.scene)?.winding_cap(batch.scene)? {
            Some(cap) => self.by_gpu_rays(batch, Some(&cap), out),
            None => self.points.contains_by_winding(batch, out),
        }
    }

    /// One exact GPU query of the batch (the scene's meshes held for it), its profile kept as the
    /// device's last.
    fn trace(&self, batch: RayBatch, sink: &mut HitSink) -> Result<()> {
        let started = Instant::now();
        self.shared.ctx.check_usable()?;
        let _in_use = batch.scene.hold_meshes();
        batch.scene.check_current()?;
        self.shared.profiled(batch.rays.len(), started, |profile| self.rays.run(batch, true, sink, profile))
    }

    /// `contains_by_gpu_crossings` with the rays of 4,096 points or more cast in grid order on a
    /// software device (`morton::point_order`: neighbouring invocations then cross the same
    /// nodes; lavapipe, 1M points: 140 -> 95 ms), each answer written to its point's own row. Not
    /// on a hardware GPU: there the sort, the gather and the scatter on the host (7–10 ms for 1M
    /// points on an H100's 16 cores) cost more than the trace gains (2–7 ms). VKRAY_POINT_ORDER:
    /// `input` casts them as they come everywhere, `grid` orders them everywhere.
    fn by_gpu_rays(&self, batch: PointBatch, cap: Option<&WindingCap>, out: &mut [u8]) -> Result<()> {
        let PointBatch { scene, points, .. } = batch;
        let n = points.rows();
        let bounds = scene.bounds();
        let worth_it = self.shared.ctx.info.is_software || points_in_grid_order();
        let ordered = n >= ORDER_MIN_POINTS && worth_it && !points_as_they_come();
        if !(ordered && bounds.min.is_finite() && bounds.max.is_finite()) {
            return self.by_gpu_crossings(batch, cap, out);
        }
        let started = Instant::now();
        let order = morton::point_order(points, bounds.min + scene.center, bounds.max + scene.center);
        let mut sorted = try_vec(3 * n, 0.0f64, "the points in grid order")?;
        let mut inside = try_vec(n, 0u8, "contains in grid order")?;
        parallel::install(|| {
            sorted.par_chunks_exact_mut(3).zip(order.as_slice()).with_min_len(4096).for_each(|(row, &i)| {
                row.copy_from_slice(&points.row_f64(i as usize));
            })
        });
        let sorting = started.elapsed();
        self.by_gpu_crossings(PointBatch { points: Vec3s::F64(&sorted), ..batch }, cap, &mut inside)?;
        let scattering = Instant::now();
        order.scatter(&inside, out);
        let mut profile = self.shared.profile_mut();
        profile.order = (sorting + scattering.elapsed()).as_secs_f64();
        Ok(())
    }

    /// `contains` from one ray a point on the GPU, its crossings counted exactly: by parity
    /// (`cap` None: the caller checked that every mesh is closed), or by the winding number of
    /// the scene's one mesh through its `cap` (its signed crossings plus the cap's winding number).
    /// With one instance the GPU also tests whether the point lies on a surface (a ray cannot
    /// tell: its t there rounds to either side of 0). With several (parity only), the crossings
    /// are found with their instances (a parity each) and the CPU tells points on a surface.
    fn by_gpu_crossings(&self, batch: PointBatch, cap: Option<&WindingCap>, out: &mut [u8]) -> Result<()> {
        let PointBatch { scene, points, interrupt } = batch;
        let direction = host_tiers::PARITY_DIRECTION.to_array();
        let rays = Rays {
            origins: points,
            directions: Vec3s::F64(&direction),
            tmin: PerRay::All(0.0),
            tmax: PerRay::All(f64::INFINITY),
            mask: Masks::All(0xFF),
            sensor: None,
        };
        // Every triangle counts, whatever its opacity: inside is a question of the surface.
        let request = Request { opacity_threshold: 0.0, ..Request::new(Query::Count, Precision::Exact, Cull::None) };
        let batch = RayBatch { scene, rays: &rays, request, interrupt };
        let mut odd = try_vec(points.rows(), 0i32, "the crossings of contains")?;
        if let Some(cap) = cap {
            let mut cap_winding = try_vec(points.rows(), 0.0f64, "the cap's winding numbers")?;
            let mut sink = HitSink::default();
            sink.set(Field::Prim, bytemuck::cast_slice_mut(&mut odd));
            sink.set(Field::T, bytemuck::cast_slice_mut(&mut cap_winding));
            self.trace(batch.asking(Request { query: Query::Winding, ..request }), &mut sink)?;
            return host_tiers::inside_by_crossings(scene, points, &odd, &cap_winding, cap.band(), out, interrupt);
        }
        if scene.placements.len() == 1 {
            let mut sink = HitSink::default();
            sink.set(Field::Prim, bytemuck::cast_slice_mut(&mut odd));
            self.trace(batch.asking(Request { query: Query::Parity, ..request }), &mut sink)?;
            parallel::install(|| {
                out.par_iter_mut().zip(&odd).with_min_len(4096).for_each(|(inside, &count)| {
                    *inside = u8::from(host_tiers::inside_by_parity(Crossings(count)));
                })
            });
            return Ok(());
        }
        let all = self.all_hits.gpu_all_hits::<ExactHit>(batch, usize::MAX, 0)?;
        for (odd, pair) in odd.iter_mut().zip(all.offsets.windows(2)) {
            *odd = i32::from(host_tiers::odd_crossings(
                &all.hits[pair[0] as usize..pair[1] as usize],
                scene.placements.len(),
            ));
        }
        self.all_hits.recycle(all.hits);
        let _in_use = scene.hold_meshes();
        host_tiers::inside_by_counts(scene, points, &odd, out, interrupt)
    }
}
