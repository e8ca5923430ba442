//! The GPU tiers of a ray query, whichever path packs its rays: the GPU itself where the query
//! and its arrays allow it (`PackedRays`), else the host, chunk by chunk (`RayChunks`); each only
//! after the probes say that this driver runs the intersection shaders the scene needs.

use std::sync::Arc;

use super::packed_rays::PackedRays;
use super::probes::Probes;
use super::ray_chunks::RayChunks;
use crate::error::Result;
use crate::trace::hit_fields::HitSink;
use crate::trace::profile::TraceProfile;
use crate::trace::request::RayBatch;

/// The ray paths of the GPU tiers, and the probes that guard them.
pub struct GpuRays {
    pub chunks: RayChunks,
    pub packed: Arc<PackedRays>,
    pub probes: Arc<Probes>,
}

impl GpuRays {
    /// Traces the batch's rays on the GPU (`exact`: through the scene's per-triangle boxes, each
    /// candidate decided by the f64 test), writing every field `sink` asks for.
    pub fn run(&self, batch: RayBatch, exact: bool, sink: &mut HitSink, profile: &mut TraceProfile) -> Result<()> {
        self.probes.check_paths(batch.scene, exact)?;
        // The GPU packing path writes fields into the caller's arrays itself: not `hit`.
        let packs_on_gpu = !exact && sink.hit.is_none();
        if packs_on_gpu && self.packed.trace_arrays_packed_on_gpu(batch, sink, profile)?.is_some() {
            return Ok(());
        }
        self.chunks.run(batch, exact, sink, profile)
    }
}
