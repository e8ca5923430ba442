//! Signed distances in one pass of the GPU a chunk: the chunk's points go up once, the
//! closest-point search measures their distances (`closest.rs`), and in the same command buffer
//! one exact ray from each point (RAY_SOURCE = RAYS_FROM_POINTS: read from the search's own
//! points buffer) counts its crossings, by parity or through the winding cap; last,
//! sign_points.comp negates the distances of the points inside and marks those it cannot tell.
//! The host copies the signed distances out and decides on the CPU only the few points marked (as
//! `contains` does). Two queries instead (distances, then `contains`) would pack every point
//! twice, 64 bytes of f64 ray each for the sign; signing on the host would read back 20 bytes a
//! point instead of 8 (and a bit).

use std::sync::Arc;

use super::closest_points::{ClosestPoints, PointJob, PointSlot, SignAnswers, SignTrace};
use super::probes::Probes;
use super::shared::Shared;
use super::variants::{Variant, VariantKey, RAYS_FROM_POINTS};
use crate::error::Result;
use crate::geometry::arrays::Vec3s;
use crate::geometry::parallel;
use crate::gpu::records::Params;
use crate::scene::closest::InsideGridBuffer;
use crate::scene::{InsideGrid, Scene, VulkanScene, WindingCap};
use crate::trace::grid_contains::{inside_grid, GridUse};
use crate::trace::hit_fields::Field;
use crate::trace::host_tiers;
use crate::trace::request::{Cull, PointBatch, Precision, Query, Request, SignedDistance};

/// Whether VKRAY_SIGNED_DISTANCE=separate asks for distances and signs as two queries (to measure
/// what one pass buys, and as the tests' second path).
fn signs_separately() -> bool {
    std::env::var("VKRAY_SIGNED_DISTANCE").is_ok_and(|v| v == "separate")
}

/// A point whose sign the GPU could not tell: its index, and the first pass's mark
/// (`host_tiers::decide_on_the_cpu`).
type Unsure = (usize, u8);

/// The signed-distance path: the closest-points path's search and an exact ray a point, in one
/// command buffer a chunk. Owns nothing of its own.
pub struct SignedDistancePath {
    shared: Arc<Shared>,
    points: Arc<ClosestPoints>,
    probes: Arc<Probes>,
}

impl SignedDistancePath {
    pub fn new(shared: &Arc<Shared>, points: &Arc<ClosestPoints>, probes: &Arc<Probes>) -> SignedDistancePath {
        SignedDistancePath { shared: shared.clone(), points: points.clone(), probes: probes.clone() }
    }

    /// Signed distances in one pass (see the module), into `out`, where the query allows it:
    /// `contains` at the exact tier, one instance, f64 shaders, distances at `exact` or `fast`,
    /// and for winding numbers a cap (`Scene::winding_cap`). Returns false, having written
    /// nothing, where it does not: the caller then asks two queries. The caller checked the
    /// points, `max_distance` and `out`'s length.
    pub fn run(&self, batch: PointBatch, query: SignedDistance, out: &mut [f64]) -> Result<bool> {
        let PointBatch { scene, points, interrupt } = batch;
        let SignedDistance { max_distance, precision, contains_precision, winding } = query;
        let one_pass = contains_precision == Precision::Exact
            && matches!(precision, Precision::Exact | Precision::Fast)
            && !signs_separately();
        if !one_pass || out.is_empty() {
            return Ok(false);
        }
        let _in_use = scene.hold_meshes();
        scene.check_current()?;
        // The grid `contains` would use (kept, or built as `contains` on this device builds it):
        // the points whose cells it decides cast no sign's ray. Asked only once one pass can sign.
        let grid = |winding| match GridUse::of_engine(self.shared.ctx.info.is_software) {
            Some(grid_use) => inside_grid(scene, winding, points.rows(), grid_use, interrupt),
            None => Ok(None),
        };
        let Some(sign) = SignRays::new(&self.shared, &self.probes, scene, winding, grid)? else {
            return Ok(false);
        };
        let structures = VulkanScene::of(scene)?.closest(scene)?;
        let job = PointJob {
            sign: Some(sign.trace(&self.shared, &self.points, SignAnswers::Distances)?),
            ..self.points.closest_job(scene, &structures, points, max_distance, precision, false)?
        };
        let capacity = self.points.point_capacity(points.rows()).min(self.shared.max_dispatch_rays());
        let pipelines = self.points.pipelines();
        let mut slots = self.shared.with_memory(|| pipelines.take_slots(capacity, false, true))?;
        let mut unsure: Vec<Unsure> = Vec::new();
        let result = self.points.closest_chunks(&job, &mut slots, capacity, interrupt, |start, len, slot| {
            let results = slot.results_host.mapped().expect("readback is host-visible");
            parallel::copy(bytemuck::cast_slice_mut(&mut out[start..start + len]), &results[..8 * len]);
            unsure.extend(unsure_rows(slot, len).into_iter().map(|k| (start + k, host_tiers::UNSURE)));
        });
        pipelines.give_back(slots);
        result?;
        decide_unsure(batch, &unsure, out)?;
        Ok(true)
    }
}

/// What a sign's trace needs, owned for the length of a query: the variant its rays run (exact,
/// from the points: `RAYS_FROM_POINTS`), their push constants, the cap (by winding number) and
/// the scene's inside grid on the device.
pub(super) struct SignRays {
    variant: Arc<Variant>,
    params: Params,
    cap: Option<Arc<WindingCap>>,
    grid: Option<Arc<InsideGridBuffer>>,
}

impl SignRays {
    /// The sign's rays of `scene`'s points, where one ray a point can tell `contains` at the
    /// exact tier: f64 shaders, one instance, and for winding numbers a cap
    /// (`VulkanScene::winding_cap`); else None. `grid(winding)`: the scene's inside grid, asked
    /// only once the rest holds. The caller holds the scene's meshes.
    pub(super) fn new(
        shared: &Shared,
        probes: &Probes,
        scene: &Scene,
        winding: bool,
        grid: impl FnOnce(bool) -> Result<Option<Arc<InsideGrid>>>,
    ) -> Result<Option<SignRays>> {
        if !shared.ctx.info.shader_float64 || scene.placements.len() != 1 {
            return Ok(None);
        }
        let vulkan = VulkanScene::of(scene)?;
        let cap = match winding {
            true => match vulkan.winding_cap(scene)? {
                Some(cap) => Some(cap),
                None => return Ok(None),
            },
            false => None,
        };
        probes.check_paths(scene, true)?;
        let exact = vulkan.exact(scene)?;
        let query = if cap.is_some() { Query::Winding } else { Query::Parity };
        // Every triangle counts, whatever its opacity: inside is a question of the surface.
        let request = Request { opacity_threshold: 0.0, ..Request::new(query, Precision::Exact, Cull::None) };
        let outputs = Field::Prim.bit() | if cap.is_some() { Field::T.bit() } else { 0 };
        let key =
            VariantKey { ray_source: RAYS_FROM_POINTS, ..shared.variant_key(scene, request, true, outputs, false) };
        let params = Params {
            instances: exact.instances_address(),
            tlas: exact.tlas_address(),
            bounds: exact.bounds_f32(),
            // QUERY_WINDING reads `scratch` as the cap.
            scratch: cap.as_ref().map_or(0, |cap| cap.address()),
            ray_mask: 0xFF,
            ..Default::default()
        };
        let grid = grid(winding)?.map(|grid| vulkan.inside_grid_buffer(&grid, winding)).transpose()?;
        Ok(Some(SignRays { variant: shared.variants.get(key)?, params, cap, grid }))
    }

    /// The chunks' sign's trace, answering `answers`.
    pub(super) fn trace<'a>(
        &'a self,
        shared: &'a Shared,
        points: &ClosestPoints,
        answers: SignAnswers,
    ) -> Result<SignTrace<'a>> {
        Ok(SignTrace {
            variant: &self.variant,
            params: self.params,
            direction: host_tiers::PARITY_DIRECTION.to_array(),
            cap: self.cap.as_deref().map(|cap| shared.cap_winding.pass(cap)).transpose()?,
            grid: self.grid.as_ref().map_or(0, |grid| grid.address()),
            combine: points.pipelines().sign.pipeline(&[])?,
            band: self.cap.as_ref().map_or(0.0, |cap| cap.band()),
            answers,
        })
    }
}

/// The rows of a finished chunk of `len` points (indices within it) its unsure bits mark: the
/// points the CPU decides.
pub(super) fn unsure_rows(slot: &PointSlot, len: usize) -> Vec<usize> {
    let results = slot.results_host.mapped().expect("readback is host-visible");
    let layout = slot.results_layout();
    let words: &[u32] = bytemuck::cast_slice(&results[layout.unsure..layout.unsure + 4 * len.div_ceil(32)]);
    let mut unsure = Vec::new();
    for (w, &word) in words.iter().enumerate().filter(|(_, &word)| word != 0) {
        let mut bits = word;
        while bits != 0 {
            unsure.push(32 * w + bits.trailing_zeros() as usize);
            bits &= bits - 1;
        }
    }
    unsure
}

/// Decides the `unsure` points on the CPU (`host_tiers::decide_on_the_cpu`) and negates the
/// distances of those inside.
fn decide_unsure(batch: PointBatch, unsure: &[Unsure], out: &mut [f64]) -> Result<()> {
    let PointBatch { scene, points, interrupt } = batch;
    if unsure.is_empty() {
        return Ok(());
    }
    let rows: Vec<f64> = unsure.iter().flat_map(|&(i, _)| points.row_f64(i)).collect();
    let mut marks: Vec<u8> = unsure.iter().map(|&(_, mark)| mark).collect();
    host_tiers::decide_on_the_cpu(scene, Vec3s::F64(&rows), &mut marks, interrupt)?;
    for (&(i, _), &mark) in unsure.iter().zip(&marks) {
        if mark == 1 {
            out[i] = -out[i];
        }
    }
    Ok(())
}
