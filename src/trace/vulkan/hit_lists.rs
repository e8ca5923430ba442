//! Where the storing pass of all hits keeps each ray's hits (`ListBuffers`), and the kernel that
//! places them (`ListOffsets`, shaders/list_offsets.comp): from the counting pass's counts, still
//! on the GPU, each ray's list and its offset among the chunk's records, by a scan in three
//! dispatches. The host reads back only the chunk's total before the storing pass, and the
//! offsets with the hits.

use std::mem::size_of;
use std::sync::Arc;

use ash::vk;

use crate::error::Result;
use crate::gpu::compute::ComputeKernel;
use crate::gpu::context::Context;
use crate::gpu::memory::{memory_barrier, Buffer, MemoryLocation};
use crate::gpu::records::{HitList, ListParams, LIST_SCAN, LIST_SUMS, LIST_WRITE};
use crate::gpu::shaders;
use crate::trace::idle::Held;

/// Rays a run of list_offsets.comp covers: an invocation each in its first and last passes (one
/// workgroup scans the runs, a stretch a thread: a million rays make 16k runs).
const LIST_RUN: usize = 64;

/// Lists longer than this are filled in the order traversal meets their hits and sorted by the
/// host (`HIT_LIST_APPEND`): insertion costs the square of a list's length.
pub const INSERTION_LIMIT: usize = 32;

/// Whether a list of `capacity` hits (as many as its ray met, unless `max_hits` cut it) is
/// appended to: long, and holding every hit of its ray. list_offsets.comp decides the same.
pub fn appends(capacity: usize, max_hits: usize) -> bool {
    capacity > INSERTION_LIMIT && capacity < max_hits
}

/// The storing pass's memory for one chunk: each ray's `HitList` and offset (written on the GPU),
/// and the records the shaders keep in the lists (read back with the offsets).
pub struct ListBuffers {
    lists: Buffer,
    /// u64 per run of rays, and one more: the chunk's total.
    sums: Buffer,
    /// u64 per ray: its list's first record among the chunk's.
    offsets: Buffer,
    /// Host-visible: the chunk's total, then the offsets (`read_offsets`).
    pub offsets_host: Buffer,
    /// Host-visible records (written by the shaders on shared-memory devices, copied there on
    /// discrete ones).
    pub records_host: Buffer,
    /// The records' device copy (discrete GPUs).
    pub records_device: Option<Buffer>,
    /// Lists, and bytes of records, they have room for.
    pub rays: usize,
    pub record_bytes: usize,
}

impl Held for ListBuffers {
    fn bytes(&self) -> u64 {
        [&self.lists, &self.sums, &self.offsets, &self.offsets_host, &self.records_host]
            .iter()
            .map(|b| b.size())
            .sum::<u64>()
            + self.records_device.as_ref().map_or(0, Buffer::size)
    }
}

impl ListBuffers {
    /// Room for `rays` lists and `record_bytes` bytes of records.
    pub fn new(ctx: &Arc<Context>, rays: usize, record_bytes: usize) -> Result<ListBuffers> {
        use vk::BufferUsageFlags as U;
        let storage = U::STORAGE_BUFFER | U::SHADER_DEVICE_ADDRESS;
        let gpu =
            |bytes: usize, usage, name| Buffer::new(ctx, bytes as u64, storage | usage, MemoryLocation::GpuOnly, name);
        let offsets_bytes = 8 * (rays + 1);
        let (records_host, records_device) = if ctx.unified_memory {
            (Buffer::new(ctx, record_bytes as u64, storage, MemoryLocation::GpuToCpu, "hit records")?, None)
        } else {
            let host = Buffer::new(
                ctx,
                record_bytes as u64,
                U::TRANSFER_DST,
                MemoryLocation::GpuToCpu,
                "hit records readback",
            )?;
            (host, Some(gpu(record_bytes, U::TRANSFER_SRC, "hit records")?))
        };
        Ok(ListBuffers {
            lists: gpu(rays * size_of::<HitList>(), U::empty(), "hit lists")?,
            sums: gpu(8 * (rays.div_ceil(LIST_RUN) + 1), U::TRANSFER_SRC, "hit list sums")?,
            offsets: gpu(offsets_bytes, U::TRANSFER_SRC, "hit list offsets")?,
            offsets_host: Buffer::new(
                ctx,
                offsets_bytes as u64,
                U::TRANSFER_DST,
                MemoryLocation::GpuToCpu,
                "hit list offsets readback",
            )?,
            records_host,
            records_device,
            rays,
            record_bytes,
        })
    }

    pub fn lists_address(&self) -> u64 {
        self.lists.address()
    }

    pub fn records_address(&self) -> u64 {
        self.records_device.as_ref().unwrap_or(&self.records_host).address()
    }

    /// The chunk's total records, once `record_total`'s copy finished.
    pub fn read_total(&self) -> u64 {
        self.read_offsets(1)[0]
    }

    /// The first `len` entries of the host's copy: the total, then (after `record_offsets`'s
    /// copy) the rays' offsets from the second entry on.
    pub fn read_offsets(&self, len: usize) -> &[u64] {
        let bytes = self.offsets_host.mapped().expect("offsets readback is host-visible");
        &bytemuck::cast_slice(&bytes[..8 * (self.rays + 1)])[..len]
    }
}

/// list_offsets.comp's pipeline (compiled on first use).
pub struct ListOffsets {
    ctx: Arc<Context>,
    kernel: ComputeKernel,
}

impl ListOffsets {
    pub fn new(ctx: &Arc<Context>) -> Result<ListOffsets> {
        let kernel = ComputeKernel::new(ctx, shaders::LIST_OFFSETS, size_of::<ListParams>(), None)?;
        Ok(ListOffsets { ctx: ctx.clone(), kernel })
    }

    /// Records the three passes that turn `counts` (i32 per ray, written by the counting pass in
    /// an earlier command of `cmd`, whose writes a barrier made visible to compute shaders) into
    /// the lists and offsets of `len` rays keeping at most `max_hits` hits each; then the copy of
    /// the total to the host.
    pub fn record(
        &self,
        cmd: vk::CommandBuffer,
        counts: u64,
        buffers: &ListBuffers,
        len: usize,
        max_hits: usize,
    ) -> Result<()> {
        let ctx = &self.ctx;
        let pipeline = self.kernel.pipeline(&[])?;
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        let read_write = vk::AccessFlags::SHADER_READ | vk::AccessFlags::SHADER_WRITE;
        let runs = len.div_ceil(LIST_RUN);
        let pass = |pass: u32, groups: u32| {
            let params = ListParams {
                counts,
                sums: buffers.sums.address(),
                lists: buffers.lists.address(),
                offsets: buffers.offsets.address(),
                count: len as u32,
                max_hits: max_hits.min(i32::MAX as usize) as u32,
                insertion_limit: INSERTION_LIMIT as u32,
                run: LIST_RUN as u32,
                pass,
                unused: 0,
            };
            // SAFETY: `cmd` is recording; the pipeline and its layout are live; the push
            // constants cover exactly the layout's range; `groups` is within
            // maxComputeWorkGroupCount (runs are a 64th of a chunk's rays, which a dispatch
            // covers).
            unsafe {
                ctx.device.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::COMPUTE, pipeline);
                ctx.device.cmd_push_constants(
                    cmd,
                    self.kernel.layout(),
                    vk::ShaderStageFlags::COMPUTE,
                    0,
                    bytemuck::bytes_of(&params),
                );
                ctx.device.cmd_dispatch(cmd, groups, 1, 1);
            }
        };
        let groups = (runs as u32).div_ceil(self.kernel.local_size);
        let between = |src, dst| memory_barrier(ctx, cmd, (compute, vk::AccessFlags::SHADER_WRITE), (src, dst));
        pass(LIST_SUMS, groups);
        between(compute, read_write);
        pass(LIST_SCAN, 1);
        between(compute, read_write);
        pass(LIST_WRITE, groups);
        // The lists for the storing pass's shaders (any stage), the total for the host.
        between(vk::PipelineStageFlags::ALL_COMMANDS, vk::AccessFlags::SHADER_READ | vk::AccessFlags::TRANSFER_READ);
        let total = [vk::BufferCopy::default().src_offset(8 * runs as u64).size(8)];
        // SAFETY: `cmd` is recording; the sums hold `runs + 1` entries and the readback at least one.
        unsafe { ctx.device.cmd_copy_buffer(cmd, buffers.sums.raw(), buffers.offsets_host.raw(), &total) };
        to_host(ctx, cmd);
        Ok(())
    }

    /// Records the copy of `len` rays' offsets to the host (after the total).
    pub fn record_offsets(&self, cmd: vk::CommandBuffer, buffers: &ListBuffers, len: usize) {
        let region = [vk::BufferCopy::default().dst_offset(8).size(8 * len as u64)];
        // SAFETY: `cmd` is recording; both buffers hold `rays + 1 >= len + 1` entries; the
        // offsets were written by an earlier command whose writes `record` made visible to
        // transfers.
        unsafe { self.ctx.device.cmd_copy_buffer(cmd, buffers.offsets.raw(), buffers.offsets_host.raw(), &region) };
        to_host(&self.ctx, cmd);
    }
}

/// Makes transfers' writes visible to the host.
fn to_host(ctx: &Context, cmd: vk::CommandBuffer) {
    memory_barrier(
        ctx,
        cmd,
        (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE),
        (vk::PipelineStageFlags::HOST, vk::AccessFlags::HOST_READ),
    );
}
