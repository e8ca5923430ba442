//! Where the storing pass of all hits keeps each ray's hits (`ListBuffers`), and the kernel that
//! places them (`ListOffsets`, shaders/list_offsets.comp): from the counting pass's counts, still
//! on the GPU, each ray's list and its offset among the chunk's records, by a scan in three
//! dispatches. The counting pass may keep each ray's nearest few hits (`nearest`): the rays it
//! kept whole have them copied into place by the last dispatch, and the storing pass skips them.
//! The host reads back only the chunk's total (and whether any ray needs the storing pass) before
//! the storing pass, and the offsets with the records (the columns' way: where a list is not
//! settled).

use std::mem::size_of;
use std::sync::Arc;

use ash::vk;

use crate::error::Result;
use crate::gpu::compute::ComputeKernel;
use crate::gpu::context::Context;
use crate::gpu::memory::{memory_barrier, Buffer, MemoryLocation};
use crate::gpu::records::{HitList, ListParams, LIST_SCAN, LIST_SCAN_BLOCKS, LIST_SUMS, LIST_WRITE};
use crate::gpu::shaders;
use crate::trace::idle::Held;

/// Rays a run of list_offsets.comp covers: an invocation each in its first and last passes (a
/// million rays make 16k runs; 16 or 32 were no faster on an H200).
const LIST_RUN: usize = 64;

/// Runs each thread of list_offsets.comp's LIST_SCAN_BLOCKS sums (its `BLOCK_STRETCH`): a block
/// of runs a workgroup.
const BLOCK_STRETCH: usize = 4;

/// Sums list_offsets.comp keeps for a chunk of `rays` rays in workgroups of `local_size`: each
/// run's, the chunk's total and the storing flag, and each block's.
fn sums_len(rays: usize, local_size: usize) -> usize {
    let runs = rays.div_ceil(LIST_RUN);
    runs + 2 + runs.div_ceil(local_size * BLOCK_STRETCH)
}

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
    /// The counting pass's records: its nearest few hits of each ray (as many bytes as `records`).
    nearest: Buffer,
    /// u64 per run of rays, then the chunk's total and whether any ray needs the storing pass.
    sums: Buffer,
    /// u64 per ray: its list's first record among the chunk's.
    offsets: Buffer,
    /// Host-visible: the chunk's total and whether any ray needs the storing pass (`read_placed`),
    /// then the offsets (`read_offsets`).
    pub offsets_host: Buffer,
    /// Host-visible records (written by the shaders on shared-memory devices, copied there on
    /// discrete ones).
    pub records_host: Buffer,
    /// The records' device copy (discrete GPUs).
    pub records_device: Option<Buffer>,
    /// A stored chunk's columns, as hit_columns.comp writes them (made on first use, grown as
    /// needed).
    columns: Option<ColumnBuffers>,
    /// Lists, and bytes of records, they have room for.
    pub rays: usize,
    pub record_bytes: usize,
}

impl Held for ListBuffers {
    fn bytes(&self) -> u64 {
        [&self.lists, &self.nearest, &self.sums, &self.offsets, &self.offsets_host, &self.records_host]
            .iter()
            .map(|b| b.size())
            .sum::<u64>()
            + self.records_device.as_ref().map_or(0, Buffer::size)
            + self.columns.as_ref().map_or(0, ColumnBuffers::bytes)
    }
}

impl ListBuffers {
    /// Room for `rays` lists and `record_bytes` bytes of records.
    pub fn new(ctx: &Arc<Context>, rays: usize, record_bytes: usize) -> Result<ListBuffers> {
        use vk::BufferUsageFlags as U;
        let storage = U::STORAGE_BUFFER | U::SHADER_DEVICE_ADDRESS;
        let gpu =
            |bytes: usize, usage, name| Buffer::new(ctx, bytes as u64, storage | usage, MemoryLocation::GpuOnly, name);
        let offsets_bytes = 8 * (rays + 2);
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
            nearest: gpu(record_bytes, U::empty(), "nearest hit records")?,
            // (Blocks of one run each: room for any workgroup size.)
            sums: gpu(8 * sums_len(rays, 1), U::TRANSFER_SRC, "hit list sums")?,
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
            columns: None,
            rays,
            record_bytes,
        })
    }

    /// Memory for at least `bytes` of a chunk's columns: the buffers kept from an earlier chunk
    /// or query where they are large enough, else new ones (a quarter larger, for the chunks
    /// after).
    pub fn columns(&mut self, ctx: &Arc<Context>, bytes: usize) -> Result<&ColumnBuffers> {
        if self.columns.as_ref().is_none_or(|c| (c.host.size() as usize) < bytes) {
            self.columns = None;
            self.columns = Some(ColumnBuffers::new(ctx, (bytes + bytes / 4).max(1 << 16))?);
        }
        Ok(self.columns.as_ref().expect("made above"))
    }

    /// Drops the column buffers where they hold more than `bytes` (before going idle).
    pub fn drop_columns_over(&mut self, bytes: usize) {
        if self.columns.as_ref().is_some_and(|c| c.host.size() as usize > bytes) {
            self.columns = None;
        }
    }

    /// The column buffers, once `columns` made them.
    pub fn column_buffers(&self) -> Option<&ColumnBuffers> {
        self.columns.as_ref()
    }

    /// The first `bytes` of the columns hit_columns.comp wrote, once they reached the host.
    pub fn written_columns(&self, bytes: usize) -> &[u8] {
        let columns = self.columns.as_ref().expect("columns were written");
        &columns.host.mapped().expect("hit columns are host-visible")[..bytes]
    }

    /// The address of the u64 where the list of ray `len - 1` ends, of a chunk of `counted` rays
    /// placed by `ListOffsets::record`: the next ray's offset, or the chunk's total.
    pub fn end_address(&self, counted: usize, len: usize) -> u64 {
        if len < counted {
            self.offsets.address() + 8 * len as u64
        } else {
            self.sums.address() + 8 * counted.div_ceil(LIST_RUN) as u64
        }
    }

    pub fn offsets_address(&self) -> u64 {
        self.offsets.address()
    }

    pub fn lists_address(&self) -> u64 {
        self.lists.address()
    }

    pub fn records_address(&self) -> u64 {
        self.records_device.as_ref().unwrap_or(&self.records_host).address()
    }

    pub fn nearest_address(&self) -> u64 {
        self.nearest.address()
    }

    /// Records the counting pass may keep per ray of a chunk of `rays` (at most
    /// `MOST_NEAREST_HITS`; none where the buffer has no room for one a ray).
    pub fn nearest_hits(&self, rays: usize) -> usize {
        (self.record_bytes / RECORD_BYTES / rays.max(1)).min(MOST_NEAREST_HITS)
    }

    /// What `ListOffsets::record` found, once its copy finished.
    pub fn read_placed(&self) -> Placed {
        let bytes = self.offsets_host.mapped().expect("offsets readback is host-visible");
        let head: &[u64] = bytemuck::cast_slice(&bytes[..16]);
        Placed { total: head[0], storing: head[1] != 0 }
    }

    /// The first `len` rays' offsets, once `record_offsets`'s copy finished.
    pub fn read_offsets(&self, len: usize) -> &[u64] {
        let bytes = self.offsets_host.mapped().expect("offsets readback is host-visible");
        &bytemuck::cast_slice(&bytes[16..8 * (self.rays + 2)])[..len]
    }
}

/// Where hit_columns.comp writes a chunk's columns: device memory copied to the host's on a
/// discrete GPU (shader writes across the bus cost four times the copy: 2.4 ms for 334k hits on
/// an H200), the host-visible memory itself on a shared-memory device.
pub struct ColumnBuffers {
    pub host: Buffer,
    pub device: Option<Buffer>,
}

impl ColumnBuffers {
    fn new(ctx: &Arc<Context>, bytes: usize) -> Result<ColumnBuffers> {
        use vk::BufferUsageFlags as U;
        let storage = U::STORAGE_BUFFER | U::SHADER_DEVICE_ADDRESS;
        if ctx.unified_memory {
            // (Transfers clear the check word: `ListColumns::record`.)
            let host =
                Buffer::new(ctx, bytes as u64, storage | U::TRANSFER_DST, MemoryLocation::GpuToCpu, "hit columns")?;
            return Ok(ColumnBuffers { host, device: None });
        }
        let host = Buffer::new(ctx, bytes as u64, U::TRANSFER_DST, MemoryLocation::GpuToCpu, "hit columns readback")?;
        let device = Buffer::new(
            ctx,
            bytes as u64,
            storage | U::TRANSFER_SRC | U::TRANSFER_DST,
            MemoryLocation::GpuOnly,
            "hit columns",
        )?;
        Ok(ColumnBuffers { host, device: Some(device) })
    }

    fn bytes(&self) -> u64 {
        self.host.size() + self.device.as_ref().map_or(0, Buffer::size)
    }

    /// Where the shader writes.
    pub fn address(&self) -> u64 {
        self.device.as_ref().unwrap_or(&self.host).address()
    }
}

/// Bytes of a hit record of either tier (`FastHit`, `ExactHit`), which list_offsets.comp copies.
const RECORD_BYTES: usize = 32;
const _: () = assert!(size_of::<crate::gpu::records::FastHit>() == RECORD_BYTES);
const _: () = assert!(size_of::<crate::gpu::records::ExactHit>() == RECORD_BYTES);

/// Most hits the counting pass keeps per ray: most rays meet fewer (a closed mesh twice or four
/// times), and insertion costs the square of a list's length.
const MOST_NEAREST_HITS: usize = 8;

/// A chunk's lists as `ListOffsets::record` placed them: their records, and whether any ray needs
/// the storing pass (the counting pass did not keep its hits whole).
pub struct Placed {
    pub total: u64,
    pub storing: bool,
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

    /// Records the four passes that turn `counts` (i32 per ray, written by the counting pass in
    /// an earlier command of `cmd`, whose writes a barrier made visible to compute shaders) into
    /// the lists and offsets of `len` rays keeping at most `max_hits` hits each, copying into
    /// place (within `room` records) the hits of rays the counting pass kept whole
    /// (`nearest_hits` of each in the buffers' `nearest`, where not 0); then the copy of what
    /// they found to the host.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        &self,
        cmd: vk::CommandBuffer,
        counts: u64,
        buffers: &ListBuffers,
        len: usize,
        max_hits: usize,
        nearest_hits: usize,
        room: usize,
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
                nearest: if nearest_hits > 0 { buffers.nearest.address() } else { 0 },
                records: buffers.records_address(),
                count: len as u32,
                max_hits: max_hits.min(i32::MAX as usize) as u32,
                insertion_limit: INSERTION_LIMIT as u32,
                run: LIST_RUN as u32,
                pass,
                nearest_hits: nearest_hits as u32,
                room: room.min(u32::MAX as usize) as u32,
                unused: 0,
            };
            // (Runs are a 64th of a chunk's rays, which a dispatch covers.)
            self.kernel.record_dispatch(cmd, pipeline, &params, groups);
        };
        let groups = (runs as u32).div_ceil(self.kernel.local_size);
        let blocks = (runs as u32).div_ceil(self.kernel.local_size * BLOCK_STRETCH as u32);
        let between = |src, dst| memory_barrier(ctx, cmd, (compute, vk::AccessFlags::SHADER_WRITE), (src, dst));
        pass(LIST_SUMS, groups);
        between(compute, read_write);
        pass(LIST_SCAN_BLOCKS, blocks);
        between(compute, read_write);
        pass(LIST_SCAN, 1);
        between(compute, read_write);
        pass(LIST_WRITE, groups);
        // The lists for the storing pass's shaders (any stage), the total for the host.
        between(vk::PipelineStageFlags::ALL_COMMANDS, vk::AccessFlags::SHADER_READ | vk::AccessFlags::TRANSFER_READ);
        let total = [vk::BufferCopy::default().src_offset(8 * runs as u64).size(16)];
        // SAFETY: `cmd` is recording; the sums hold `runs + 2` entries and the readback more.
        unsafe { ctx.device.cmd_copy_buffer(cmd, buffers.sums.raw(), buffers.offsets_host.raw(), &total) };
        to_host(ctx, cmd);
        Ok(())
    }

    /// Records the copy of `len` rays' offsets to the host (after what `record` found).
    pub fn record_offsets(&self, cmd: vk::CommandBuffer, buffers: &ListBuffers, len: usize) {
        let region = [vk::BufferCopy::default().dst_offset(16).size(8 * len as u64)];
        // SAFETY: `cmd` is recording; the offsets hold `rays + 2` entries, the readback too; the
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
