//! Signed distances in one pass of the GPU a chunk: the chunk's points go up once, the
//! closest-point search measures their distances (`closest.rs`), and in the same command buffer
//! one exact ray from each point (RAY_SOURCE = RAYS_FROM_POINTS: read from the search's own
//! points buffer) counts its crossings, by parity or through the winding cap; last,
//! sign_points.comp negates the distances of the points inside and marks those it cannot tell.
//! The host copies the signed distances out and decides on the CPU only the few points marked (as
//! `contains` does). Two queries instead (distances, then `contains`) would pack every point
//! twice, 64 bytes of f64 ray each for the sign; signing on the host would read back 20 bytes a
//! point instead of 8 (and a bit).

use ash::vk;
use glam::DVec3;

use super::closest::{PointJob, PointSlot, SignTrace};
use super::fields::Field;
use super::request::{Cull, Precision, Query, Request, SignedDistance};
use super::tiers;
use super::tracer::Tracer;
use super::variants::{VariantKey, RAYS_FROM_POINTS};
use crate::error::Result;
use crate::geometry::arrays::Vec3s;
use crate::geometry::parallel;
use crate::gpu::context::{Backend, Interrupt};
use crate::gpu::memory::memory_barrier;
use crate::gpu::records::{Params, PointRays, SignPointsParams};
use crate::scene::Scene;

/// Whether VKRAY_SIGNED_DISTANCE=separate asks for distances and signs as two queries (to measure
/// what one pass buys, and as the tests' second path).
fn signs_separately() -> bool {
    std::env::var("VKRAY_SIGNED_DISTANCE").is_ok_and(|v| v == "separate")
}

/// A point whose sign the GPU could not tell: its index, and the first pass's mark
/// (`tiers::decide_on_the_cpu`).
type Unsure = (usize, u8);

impl Tracer {
    /// Signed distances in one pass (see the module), into `out`, where the query allows it:
    /// `contains` at the exact tier, one instance, f64 shaders, distances at `exact` or `fast`,
    /// and for winding numbers a cap (`Scene::winding_cap`). Returns false, having written
    /// nothing, where it does not: the caller then asks two queries. The caller checked the
    /// points, `max_distance` and `out`'s length.
    pub(super) fn signed_distance_in_one_pass(
        &self,
        scene: &Scene,
        points: Vec3s,
        query: SignedDistance,
        out: &mut [f64],
        interrupt: &dyn Interrupt,
    ) -> Result<bool> {
        let SignedDistance { max_distance, precision, contains_precision, winding } = query;
        let one_pass = contains_precision == Precision::Exact
            && matches!(precision, Precision::Exact | Precision::Fast)
            && self.ctx.info.shader_float64
            && scene.placements.len() == 1
            && !signs_separately();
        if !one_pass || out.is_empty() {
            return Ok(false);
        }
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        let cap = match winding {
            true => match scene.winding_cap()? {
                Some(cap) => Some(cap),
                None => return Ok(false),
            },
            false => None,
        };
        self.check_paths(scene, true)?;
        let exact = scene.exact()?;
        let structures = scene.closest()?;
        let query = if cap.is_some() { Query::Winding } else { Query::Parity };
        // Every triangle counts, whatever its opacity: inside is a question of the surface.
        let request = Request { opacity_threshold: 0.0, ..Request::new(query, Precision::Exact, Cull::None) };
        let outputs = Field::Prim.bit() | if cap.is_some() { Field::T.bit() } else { 0 };
        let key = VariantKey { ray_source: RAYS_FROM_POINTS, ..self.variant_key(scene, request, true, outputs, false) };
        let variant = self.variants.get(key)?;
        let params = Params {
            instances: exact.instances_address(),
            tlas: exact.tlas_address(),
            bounds: exact.bounds_f32(),
            // QUERY_WINDING reads `scratch` as the cap.
            scratch: cap.as_ref().map_or(0, |cap| cap.address()),
            ray_mask: 0xFF,
            ..Default::default()
        };
        let job = PointJob {
            sign: Some(SignTrace {
                variant: &variant,
                params,
                direction: tiers::PARITY_DIRECTION.to_array(),
                cap_winding: cap.is_some(),
                combine: self.points.sign.pipeline(&[])?,
                band: cap.as_ref().map_or(0.0, |cap| cap.band()),
            }),
            ..self.closest_job(scene, &structures, points, max_distance, precision, false)?
        };
        let capacity = self.point_capacity(points.rows(), false).min(self.max_dispatch_rays());
        let mut slots = self.with_memory(|| self.points.take_slots(capacity, false, true))?;
        let mut unsure: Vec<Unsure> = Vec::new();
        let result = self.closest_chunks(&job, &mut slots, capacity, interrupt, |start, len, slot| {
            let found = sign_chunk(slot, &mut out[start..start + len]);
            unsure.extend(found.into_iter().map(|(k, mark)| (start + k, mark)));
        });
        self.points.give_back(slots);
        result?;
        decide_unsure(scene, points, &unsure, out, interrupt)?;
        Ok(true)
    }

    /// Records the sign's trace of a chunk after its search: the chunk's `PointRays` record,
    /// then one ray from each of its `len` points, in the search's `order` (its address, or 0:
    /// as they come), then sign_points.comp over the chunk. Returns the stage whose writes the
    /// readback waits for.
    pub(super) fn record_sign_trace(
        &self,
        cmd: vk::CommandBuffer,
        sign: &SignTrace,
        slot: &PointSlot,
        center: DVec3,
        order: u64,
        len: usize,
    ) -> vk::PipelineStageFlags {
        let ctx = &self.ctx;
        let stage = match ctx.backend {
            Backend::RayQuery => vk::PipelineStageFlags::COMPUTE_SHADER,
            Backend::Pipeline => vk::PipelineStageFlags::RAY_TRACING_SHADER_KHR,
        };
        let record_buffer = slot.rays_record().expect("a slot for signs has a rays record");
        let layout = slot.results_layout();
        let results = slot.results_address();
        // SAFETY: `cmd` is recording outside a render pass; the results buffer is TRANSFER_DST
        // and holds the unsure bits' words at this 4-aligned offset (ResultsLayout).
        unsafe {
            ctx.device.cmd_fill_buffer(cmd, slot.results_buffer(), layout.unsure as u64, 4 * len.div_ceil(32) as u64, 0)
        };
        let record = PointRays {
            points: slot.points_address(),
            order,
            shift: center.to_array(),
            direction: sign.direction,
            tmin: 0.0,
            tmax: f64::INFINITY,
        };
        // SAFETY: `cmd` is recording outside a render pass; the buffer is TRANSFER_DST, holds one
        // record, and the record is a multiple of 4 bytes and at most 65,536.
        unsafe { ctx.device.cmd_update_buffer(cmd, record_buffer.raw(), 0, bytemuck::bytes_of(&record)) };
        // The record (and, on discrete GPUs, the points' upload; and the order) before the rays
        // read them.
        memory_barrier(
            ctx,
            cmd,
            vk::PipelineStageFlags::TRANSFER | vk::PipelineStageFlags::COMPUTE_SHADER,
            vk::AccessFlags::TRANSFER_WRITE | vk::AccessFlags::SHADER_WRITE,
            stage,
            vk::AccessFlags::SHADER_READ,
        );
        let mut params = Params { rays: record_buffer.address(), count: len as u32, ..sign.params };
        params.outputs[Field::Prim as usize] = results + layout.crossings as u64;
        if sign.cap_winding {
            params.outputs[Field::T as usize] = results + layout.cap_winding as u64;
        }
        self.record_trace(cmd, sign.variant, &params, len);
        self.record_sign_points(cmd, sign, slot, stage, len);
        vk::PipelineStageFlags::COMPUTE_SHADER
    }

    /// Records sign_points.comp over a chunk whose distances and crossings were written (by
    /// `stage`'s shaders, and its unsure bits cleared by a copy).
    fn record_sign_points(
        &self,
        cmd: vk::CommandBuffer,
        sign: &SignTrace,
        slot: &PointSlot,
        stage: vk::PipelineStageFlags,
        len: usize,
    ) {
        let ctx = &self.ctx;
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        memory_barrier(
            ctx,
            cmd,
            compute | stage | vk::PipelineStageFlags::TRANSFER,
            vk::AccessFlags::SHADER_WRITE | vk::AccessFlags::TRANSFER_WRITE,
            compute,
            vk::AccessFlags::SHADER_READ | vk::AccessFlags::SHADER_WRITE,
        );
        let layout = slot.results_layout();
        let results = slot.results_address();
        let params = SignPointsParams {
            distances: results,
            crossings: results + layout.crossings as u64,
            cap_winding: if sign.cap_winding { results + layout.cap_winding as u64 } else { 0 },
            unsure: results + layout.unsure as u64,
            // As tiers::mark_by_crossings computes them.
            inside_from: 0.5 + sign.band,
            outside_below: 0.5 - sign.band,
            count: len as u32,
            unused: 0,
        };
        let kernel = &self.points.sign;
        // SAFETY: `cmd` is recording; the pipeline and its layout are live; the push constants
        // cover exactly the layout's range; the group count is within maxComputeWorkGroupCount
        // (the chunk's capacity is, `point_capacity`).
        unsafe {
            ctx.device.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::COMPUTE, sign.combine);
            ctx.device.cmd_push_constants(
                cmd,
                kernel.layout(),
                vk::ShaderStageFlags::COMPUTE,
                0,
                bytemuck::bytes_of(&params),
            );
            ctx.device.cmd_dispatch(cmd, (len as u32).div_ceil(kernel.local_size), 1, 1);
        }
    }
}

/// Copies a finished chunk's signed distances into `out`. Returns the chunk's points the CPU
/// must decide (their distances copied as they are), from the unsure bits.
fn sign_chunk(slot: &PointSlot, out: &mut [f64]) -> Vec<Unsure> {
    let len = out.len();
    let results = slot.results_host.mapped().expect("readback is host-visible");
    let layout = slot.results_layout();
    parallel::copy(bytemuck::cast_slice_mut(out), &results[..8 * len]);
    let words: &[u32] = bytemuck::cast_slice(&results[layout.unsure..layout.unsure + 4 * len.div_ceil(32)]);
    let mut unsure = Vec::new();
    for (w, &word) in words.iter().enumerate().filter(|(_, &word)| word != 0) {
        let mut bits = word;
        while bits != 0 {
            unsure.push((32 * w + bits.trailing_zeros() as usize, tiers::UNSURE));
            bits &= bits - 1;
        }
    }
    unsure
}
/// Decides the `unsure` points on the CPU (`tiers::decide_on_the_cpu`) and negates the
/// distances of those inside.
fn decide_unsure(
    scene: &Scene,
    points: Vec3s,
    unsure: &[Unsure],
    out: &mut [f64],
    interrupt: &dyn Interrupt,
) -> Result<()> {
    if unsure.is_empty() {
        return Ok(());
    }
    let rows: Vec<f64> = unsure.iter().flat_map(|&(i, _)| points.row_f64(i)).collect();
    let mut marks: Vec<u8> = unsure.iter().map(|&(_, mark)| mark).collect();
    tiers::decide_on_the_cpu(scene, Vec3s::F64(&rows), &mut marks, interrupt)?;
    for (&(i, _), &mark) in unsure.iter().zip(&marks) {
        if mark == 1 {
            out[i] = -out[i];
        }
    }
    Ok(())
}
