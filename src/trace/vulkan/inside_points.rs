//! `contains` at the exact tier on the GPU from end to end, through the scene's inside grid (a
//! scene of one instance): the points go up once, or already lie in memory shared with CUDA;
//! point_order.comp sorts each chunk's points by cell, so that the points near a surface (the
//! grid's undecided cells) share warps; the sign's trace (`SignRays`: one exact ray a point, as
//! signed distances cast) casts no ray from a point whose cell the grid decides; and
//! sign_points.comp writes each answer as a byte. Only the answers come back (a byte a point, and
//! a bit a point for the CPU), or, for CUDA points, they are copied into CUDA memory. The few
//! points the GPU cannot tell (winding numbers within its rounding of 1/2) are the CPU's, as are
//! points that are not finite, which it reports. The host's own pass over the grid
//! (`grid_contains::contains_by_grid`) marks every point on the host's cores instead.

use std::sync::Arc;

use super::closest_points::{ClosestPoints, JobPoints, PointJob, SignAnswers};
use super::cuda_rays::{CudaArray, CudaLease, CudaRaysPath};
use super::probes::Probes;
use super::shared::Shared;
use super::signed_distance::{unsure_rows, SignRays};
use crate::error::{invalid_value, Result};
use crate::geometry::arrays::{fmt_row, Vec3s};
use crate::geometry::interrupt::Interrupt;
use crate::geometry::parallel;
use crate::gpu::cuda::{read_number, CudaAllocation, Event};
use crate::scene::{InsideGrid, Scene, VulkanScene};
use crate::trace::host_tiers;
use crate::trace::request::PointBatch;
use ash::vk;

/// The answers of CUDA points: a byte a point (1 inside) in CUDA memory, written once `ready` is
/// reached.
pub struct CudaInside {
    pub inside: CudaAllocation,
    pub ready: Arc<Event>,
}

/// The `contains` path through the grid on the device. Owns nothing of its own.
pub struct InsidePointsPath {
    shared: Arc<Shared>,
    points: Arc<ClosestPoints>,
    probes: Arc<Probes>,
}

impl InsidePointsPath {
    pub fn new(shared: &Arc<Shared>, points: &Arc<ClosestPoints>, probes: &Arc<Probes>) -> InsidePointsPath {
        InsidePointsPath { shared: shared.clone(), points: points.clone(), probes: probes.clone() }
    }

    /// `contains` of the batch's points through `grid` into `out`, where this path answers (see
    /// `SignRays::new`): true; else false, nothing written.
    pub fn run(&self, batch: PointBatch, grid: &Arc<InsideGrid>, winding: bool, out: &mut [u8]) -> Result<bool> {
        let PointBatch { scene, points, interrupt } = batch;
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        let Some(sign) = SignRays::new(&self.shared, &self.probes, scene, winding, |_| Ok(Some(grid.clone())))? else {
            return Ok(false);
        };
        let unsure = self.answer(scene, JobPoints::Host(points), &sign, None, interrupt, |start, len, answers| {
            parallel::copy(&mut out[start..start + len], &answers[..len]);
        })?;
        let decided = decide(scene, &unsure, |i| Ok(points.row_f64(i)), interrupt)?;
        for (&i, &inside) in unsure.iter().zip(&decided) {
            out[i] = inside;
        }
        Ok(true)
    }

    /// `contains` of CUDA `points` (on `cuda`'s device, ordered before the lease's stream) by
    /// the scene's kept inside grid, answered in new CUDA memory; None where this path does not
    /// answer (no grid kept yet: the host's path, which builds it; see `SignRays::new`).
    pub fn run_cuda(
        &self,
        scene: &Scene,
        cuda_path: &CudaRaysPath,
        lease: &mut CudaLease,
        points: &CudaArray,
        winding: bool,
        interrupt: &dyn Interrupt,
    ) -> Result<Option<CudaInside>> {
        let Some(grid) = scene.inside_grid(winding) else { return Ok(None) };
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        let Some(sign) = SignRays::new(&self.shared, &self.probes, scene, winding, |_| Ok(Some(grid)))? else {
            return Ok(None);
        };
        let n = points.rows;
        let cuda = cuda_path.cuda()?.expect("a lease implies CUDA");
        let address = cuda_path.copy_points_in(&cuda, lease, points)?;
        lease.grow_output(&self.shared, &cuda, n as u64)?;
        let output = lease.output();
        let device_points = JobPoints::Device { address, f32: !points.wide, rows: n };
        let into = Some(output.vulkan.raw());
        let unsure = self.answer(scene, device_points, &sign, into, interrupt, |_, _, _| {})?;
        let read = |i: usize| -> Result<[f64; 3]> {
            let row = points.pointer + (i * points.row_stride) as u64;
            let column = |k: usize| read_number(row + (k * points.column_stride) as u64, points.wide);
            Ok([column(0)?, column(1)?, column(2)?])
        };
        let decided = {
            let _current = cuda.enter()?;
            decide(scene, &unsure, read, interrupt)?
        };
        let _current = cuda.enter()?;
        let stream = &lease.stream;
        let inside = self.shared.with_memory(|| CudaAllocation::new(stream, n))?;
        static INSIDE: u8 = 1;
        let queued = (|| -> Result<Arc<Event>> {
            // SAFETY: both are device memory of this context: the allocation is the caller's from
            // now on; the shared buffer stays in the lease, whose later users queue on the same
            // stream (Vulkan wrote it before the host's wait for the chunks).
            unsafe { stream.copy_2d(inside.pointer, n, output.pointer, n, n, 1)? };
            for (&i, _) in unsure.iter().zip(&decided).filter(|(_, &inside)| inside == 1) {
                // SAFETY: row `i` of the allocation's `n` bytes; the source is a static.
                unsafe { stream.copy_from_host(inside.pointer + i as u64, &INSIDE, 1)? };
            }
            Ok(Arc::new(stream.record()?))
        })();
        match queued {
            Ok(ready) => Ok(Some(CudaInside { inside, ready })),
            Err(error) => {
                // The copies queued write the allocation: done before it is freed.
                let _ = stream.synchronize();
                Err(error)
            }
        }
    }

    /// Runs the chunks of `points` through the sign's trace, `contains`' answers a byte a point:
    /// read back, each chunk handed to `unpack` (its first row, its length, its bytes), or copied
    /// into `into`. Returns the rows the CPU must decide, in order.
    fn answer(
        &self,
        scene: &Scene,
        points: JobPoints,
        sign: &SignRays,
        into: Option<vk::Buffer>,
        interrupt: &dyn Interrupt,
        mut unpack: impl FnMut(usize, usize, &[u8]),
    ) -> Result<Vec<usize>> {
        let structures = VulkanScene::of(scene)?.closest(scene)?;
        let job = PointJob {
            points,
            sign: Some(sign.trace(&self.shared, &self.points, SignAnswers::Inside { into })?),
            // The search's own settings go unused: `contains` searches nothing.
            ..self.points.closest_job(
                scene,
                &structures,
                Vec3s::F64(&[]),
                0.0,
                crate::trace::Precision::Exact,
                false,
            )?
        };
        let capacity = self.points.point_capacity(points.rows()).min(self.shared.max_dispatch_rays());
        let pipelines = self.points.pipelines();
        let mut slots = self.shared.with_memory(|| pipelines.take_slots(capacity, false, true))?;
        let mut unsure = Vec::new();
        let result = self.points.closest_chunks(&job, &mut slots, capacity, interrupt, |start, len, slot| {
            if into.is_none() {
                unpack(start, len, slot.results_host.mapped().expect("readback is host-visible"));
            }
            unsure.extend(unsure_rows(slot, len).into_iter().map(|k| start + k));
        });
        pipelines.give_back(slots);
        result?;
        Ok(unsure)
    }
}

/// The answers of the points the GPU left to the CPU (`rows`, read by `read`), the reference
/// tier's; the first that is not finite is an error.
fn decide(
    scene: &Scene,
    rows: &[usize],
    read: impl Fn(usize) -> Result<[f64; 3]>,
    interrupt: &dyn Interrupt,
) -> Result<Vec<u8>> {
    if rows.is_empty() {
        return Ok(Vec::new());
    }
    let mut coordinates = Vec::with_capacity(3 * rows.len());
    for &i in rows {
        let row = read(i)?;
        if !row.iter().all(|c| c.is_finite()) {
            return Err(invalid_value(format!("points row {i} is not finite: {}", fmt_row(row))));
        }
        coordinates.extend(row);
    }
    let mut marks = vec![host_tiers::UNSURE; rows.len()];
    host_tiers::decide_on_the_cpu(scene, Vec3s::F64(&coordinates), &mut marks, interrupt)?;
    Ok(marks)
}
