//! The GPU tiers of a ray query, whichever path packs its rays: the GPU itself where the query
//! and its arrays allow it (`PackedRays`), else the host, chunk by chunk (`RayChunks`); each only
//! after the probes say that this driver runs the intersection shaders the scene needs.

use std::sync::Arc;

use super::packed_rays::PackedRays;
use super::probes::Probes;
use super::ray_chunks::RayChunks;
use crate::error::Result;
use crate::geometry::interrupt::Interrupt;
use crate::geometry::rays::Rays;
use crate::scene::Scene;
use crate::trace::hit_fields::HitSink;
use crate::trace::profile::TraceProfile;
use crate::trace::request::Request;

/// The ray paths of the GPU tiers, and the probes that guard them.
pub struct GpuRays {
    pub chunks: RayChunks,
    pub packed: Arc<PackedRays>,
    pub probes: Arc<Probes>,
}

impl GpuRays {
    /// Traces `rays` on the GPU (`exact`: through the scene's per-triangle boxes, each candidate
    /// decided by the f64 test), writing every field `sink` asks for.
    #[allow(clippy::too_many_arguments)]
    pub fn run(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        exact: bool,
        sink: &mut HitSink,
        interrupt: &dyn Interrupt,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        self.probes.check_paths(scene, exact)?;
        // The GPU packing path writes fields into the caller's arrays itself: not `hit`.
        let packs_on_gpu = !exact && sink.hit.is_none();
        if packs_on_gpu
            && self.packed.trace_arrays_packed_on_gpu(scene, rays, request, sink, interrupt, profile)?.is_some()
        {
            return Ok(());
        }
        self.chunks.run(scene, rays, request, exact, sink, interrupt, profile)
    }
}
