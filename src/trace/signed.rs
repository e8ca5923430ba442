//! Signed distances in one pass of the GPU a chunk: the chunk's points go up once, the
//! closest-point search measures their distances (`closest.rs`), and in the same command buffer
//! one exact ray from each point (RAY_SOURCE = RAYS_FROM_POINTS: read from the search's own
//! points buffer) counts its crossings, by parity or through the winding cap. The host copies the
//! distances out, negated where the crossings put the point inside, and decides on the CPU only
//! the few points the GPU cannot tell (as `contains` does). Two queries instead (distances, then
//! `contains`) would pack every point twice, 64 bytes of f64 ray each for the sign.

use ash::vk;
use glam::DVec3;
use rayon::prelude::*;

use super::closest::{PointJob, PointSlot, SignTrace};
use super::fields::Field;
use super::request::{Crossings, Cull, Precision, Query, Request, SignedDistance};
use super::tiers;
use super::tracer::Tracer;
use super::variants::{VariantKey, RAYS_FROM_POINTS};
use crate::error::Result;
use crate::geometry::arrays::Vec3s;
use crate::geometry::parallel;
use crate::gpu::context::{Backend, Interrupt};
use crate::gpu::memory::memory_barrier;
use crate::gpu::records::{Params, PointRays};
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
            }),
            ..self.closest_job(scene, &structures, points, max_distance, precision, false)?
        };
        let band = cap.as_ref().map(|cap| cap.band());
        let capacity = self.point_capacity(points.rows(), false).min(self.max_dispatch_rays());
        let mut slots = self.points.take_slots(capacity, false, true)?;
        let mut unsure: Vec<Unsure> = Vec::new();
        let result = self.closest_chunks(&job, &mut slots, capacity, interrupt, |start, len, slot| {
            let found = sign_chunk(slot, band, &mut out[start..start + len]);
            unsure.extend(found.into_iter().map(|(k, mark)| (start + k, mark)));
        });
        self.points.give_back(slots);
        result?;
        decide_unsure(scene, points, &unsure, out, interrupt)?;
        Ok(true)
    }

    /// Records the sign's trace of a chunk after its search: the chunk's `PointRays` record,
    /// then one ray from each of its `len` points, in the search's `order` (its address, or 0:
    /// as they come). Returns the stage whose writes the readback waits for.
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
        let layout = slot.results_layout();
        let results = slot.results_address();
        let mut params = Params { rays: record_buffer.address(), count: len as u32, ..sign.params };
        params.outputs[Field::Prim as usize] = results + layout.crossings as u64;
        if sign.cap_winding {
            params.outputs[Field::T as usize] = results + layout.cap_winding as u64;
        }
        self.record_trace(cmd, sign.variant, &params, len);
        stage
    }
}

/// Copies a finished chunk's distances into `out`, negated where its crossings (and the cap's
/// winding number, with `band` its error) put the point inside. Returns the chunk's points the
/// CPU must decide (their distances copied as they are).
fn sign_chunk(slot: &PointSlot, band: Option<f64>, out: &mut [f64]) -> Vec<Unsure> {
    const PIECE: usize = 4096;
    let len = out.len();
    let results = slot.results_host.mapped().expect("readback is host-visible");
    let layout = slot.results_layout();
    let distances: &[f64] = bytemuck::cast_slice(&results[..8 * len]);
    let crossings: &[i32] = bytemuck::cast_slice(&results[layout.crossings..layout.crossings + 4 * len]);
    let cap_winding: &[f64] = match band {
        Some(_) => bytemuck::cast_slice(&results[layout.cap_winding..layout.cap_winding + 8 * len]),
        None => &[],
    };
    let mark = |i: usize| match band {
        Some(band) => tiers::mark_by_crossings(Crossings(crossings[i]), cap_winding[i], band),
        None => u8::from(tiers::inside_by_parity(Crossings(crossings[i]))),
    };
    parallel::install(|| {
        out.par_chunks_mut(PIECE)
            .enumerate()
            .flat_map_iter(|(piece, out)| {
                let first = piece * PIECE;
                let mut unsure = Vec::new();
                for (k, signed) in out.iter_mut().enumerate() {
                    let i = first + k;
                    let mark = mark(i);
                    *signed = if mark == 1 { -distances[i] } else { distances[i] };
                    if mark > 1 {
                        unsure.push((i, mark));
                    }
                }
                unsure
            })
            .collect()
    })
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
