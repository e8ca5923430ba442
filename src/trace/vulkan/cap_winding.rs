//! The caps' winding numbers of a winding query (`Query::Winding`), summed after its ray pass by
//! cap_winding.comp: a workgroup a ray rather than one invocation. The ray pass counts each ray's
//! crossings with the mesh and with the cap (the fans that close the mesh's holes), and marks the
//! rays whose fans' solid angles are needed (their caps' winding numbers +infinity); this pass
//! sums those fans over a workgroup's invocations. One invocation a ray took 6.5–8 ms of
//! bunny-x16's `contains` on an H200 (each of 28.6k points summing 892 triangles of its fans, in
//! too few warps to hide their latency).

use ash::vk;
use glam::DVec3;

use crate::error::Result;
use crate::gpu::compute::ComputeKernel;
use crate::gpu::context::Context;
use crate::gpu::memory::memory_barrier;
use crate::gpu::records::CapWindingParams;
use crate::gpu::shaders;
use crate::scene::WindingCap;

use std::sync::Arc;

/// Most workgroups of one dispatch: each loops over the chunk's rays from its own, by this many.
const MAX_GROUPS: u32 = 1 << 16;

/// cap_winding.comp on one device.
pub struct CapWinding {
    kernel: ComputeKernel,
}

impl CapWinding {
    pub fn new(ctx: &Arc<Context>) -> Result<CapWinding> {
        let needs = "the exact tier needs; precision='reference' gives the same answers on the CPU";
        let kernel =
            ComputeKernel::new(ctx, shaders::CAP_WINDING, std::mem::size_of::<CapWindingParams>(), Some(needs))?;
        Ok(CapWinding { kernel })
    }

    /// The pass of one query through `cap`.
    pub fn pass<'a>(&'a self, cap: &'a WindingCap) -> Result<CapPass<'a>> {
        Ok(CapPass { cap, pipeline: self.kernel.pipeline(&[])?, kernel: &self.kernel })
    }
}

/// A winding query's cap and the pass that sums its fans' solid angles.
#[derive(Clone, Copy)]
pub struct CapPass<'a> {
    pub cap: &'a WindingCap,
    pipeline: vk::Pipeline,
    kernel: &'a ComputeKernel,
}

/// Where one chunk's ray pass left what the cap pass reads and writes (device addresses).
pub struct CapChunk {
    /// Each ray's origin (xyz, f64; or f32 where tagged, as points are), less `shift`.
    pub origins: u64,
    pub shift: DVec3,
    /// i32 per ray: its crossings.
    pub counts: u64,
    /// f64 per ray: the caps' winding numbers.
    pub winding: u64,
    pub len: usize,
}

impl CapPass<'_> {
    /// Records the pass over `chunk`, whose ray pass ran in `after` (its writes made visible
    /// here); its own writes are the compute stage's.
    pub fn record(&self, ctx: &Context, cmd: vk::CommandBuffer, chunk: &CapChunk, after: vk::PipelineStageFlags) {
        // Without holes the ray pass wrote every winding number (0) itself.
        if chunk.len == 0 || !self.cap.has_holes() {
            return;
        }
        memory_barrier(
            ctx,
            cmd,
            (after, vk::AccessFlags::SHADER_WRITE),
            (vk::PipelineStageFlags::COMPUTE_SHADER, vk::AccessFlags::SHADER_READ | vk::AccessFlags::SHADER_WRITE),
        );
        let params = CapWindingParams {
            cap: self.cap.address(),
            origins: chunk.origins,
            counts: chunk.counts,
            winding: chunk.winding,
            shift: chunk.shift.to_array(),
            count: chunk.len as u32,
            unused: 0,
        };
        let groups = (chunk.len as u64).min(MAX_GROUPS as u64).min(ctx.limits.max_compute_work_group_count[0] as u64);
        self.kernel.record_dispatch(cmd, self.pipeline, &params, groups as u32);
    }
}
