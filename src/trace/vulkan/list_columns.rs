//! A stored chunk of all hits written out as the answer's columns on the GPU
//! (shaders/hit_columns.comp): each hit's t, uv, prim, instance and geometry, as many as asked,
//! into the lists' host-visible columns buffer, from which the host copies each column once into
//! the answer's. (Each hit's ray follows from the offsets: the GPU writes it for CUDA rays'
//! answers alone, `ColumnTargets::ray_index`.)

use std::mem::size_of;
use std::sync::Arc;

use ash::vk;

use super::hit_lists::{ListBuffers, INSERTION_LIMIT};
use crate::error::Result;
use crate::gpu::compute::ComputeKernel;
use crate::gpu::context::Context;
use crate::gpu::memory::{memory_barrier, Buffer};
use crate::gpu::records::ColumnParams;
use crate::gpu::shaders;
use crate::trace::hit_fields::Field;

/// The fields hit_columns.comp writes (the others need the host: position, normal, custom index).
pub const GPU_COLUMN_FIELDS: [Field; 5] = [Field::T, Field::Uv, Field::Prim, Field::Instance, Field::Geometry];

/// Where a chunk's columns lie in the columns buffer: each asked field, 16-byte aligned, then the check (a u32: 1 where some list of the chunk is not settled).
pub struct ColumnLayout {
    pub hits: usize,
    /// (field, its first byte, its bytes), in the order asked.
    pub fields: Vec<(Field, usize, usize)>,
    /// The check's first byte.
    pub check_at: usize,
    pub bytes: usize,
}

impl ColumnLayout {
    /// The layout of `hits` hits' `asked` fields (f64 t and uv where `wide`).
    pub fn new(asked: &[Field], wide: bool, hits: usize) -> ColumnLayout {
        let mut at = 0;
        let fields = asked
            .iter()
            .map(|&field| {
                let bytes = hits * field.bytes_per_ray(wide);
                let placed = (field, at, bytes);
                at = (at + bytes).next_multiple_of(16);
                placed
            })
            .collect();
        ColumnLayout { hits, fields, check_at: at, bytes: at + 16 }
    }

    /// Whether hit_columns.comp found every list of the chunk settled, in `written` (the
    /// layout's bytes, back on the host).
    pub fn settled(&self, written: &[u8]) -> bool {
        let check: &[u32] = bytemuck::cast_slice(&written[self.check_at..self.check_at + 4]);
        check[0] == 0
    }

    /// The address of `field`'s column in a buffer at `base`, or 0 where not asked.
    fn address(&self, base: u64, field: Field) -> u64 {
        self.fields.iter().find(|(f, ..)| *f == field).map_or(0, |&(_, at, _)| base + at as u64)
    }
}

/// Rays of a chunk whose hits hit_columns.comp writes: the first's index among the query's, how
/// many, and how many the counting pass placed (`len` of them, or more where the records' room
/// held only the first `len`'s lists); where the hits each met lie (i32 a ray), and how many a ray
/// keeps.
pub struct ChunkRays {
    pub first: usize,
    pub len: usize,
    pub counted: usize,
    pub seen: u64,
    pub max_hits: usize,
}

/// Where hit_columns.comp writes a chunk's columns (each address 0 where not asked) and, for
/// CUDA rays' answers, each ray's offset among the query's hits (`base`: the chunk's first hit).
pub struct ColumnTargets {
    pub ray_index: u64,
    pub t: u64,
    pub uv: u64,
    pub prim: u64,
    pub instance: u64,
    pub geometry: u64,
    pub offsets_out: u64,
    pub base: u64,
}

/// hit_columns.comp's pipelines (compiled on first use).
pub struct ListColumns {
    ctx: Arc<Context>,
    kernel: ComputeKernel,
}

impl ListColumns {
    pub fn new(ctx: &Arc<Context>) -> Result<ListColumns> {
        let kernel = ComputeKernel::new(ctx, shaders::HIT_COLUMNS, size_of::<ColumnParams>(), None)?;
        Ok(ListColumns { ctx: ctx.clone(), kernel })
    }

    /// The pipeline for `ExactHit` records where `exact`, else `FastHit`.
    pub fn pipeline(&self, exact: bool) -> Result<vk::Pipeline> {
        self.kernel.pipeline(&[exact as u32])
    }

    /// Records the dispatch (of `pipeline`) that writes the columns of the hits of `chunk`'s
    /// rays, as `layout` places them in the lists' column buffers, once the trace shaders' (and
    /// list_offsets.comp's) writes to the records are done; then their copy to the host (on a
    /// discrete GPU) and what makes them visible there.
    pub fn record(
        &self,
        cmd: vk::CommandBuffer,
        pipeline: vk::Pipeline,
        lists: &ListBuffers,
        layout: &ColumnLayout,
        chunk: ChunkRays,
        trace_stage: vk::PipelineStageFlags,
    ) {
        let buffers = lists.column_buffers().expect("made before recording");
        let columns = buffers.address();
        let ctx = &self.ctx;
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        let transfer = vk::PipelineStageFlags::TRANSFER;
        let targets = ColumnTargets {
            ray_index: 0,
            t: layout.address(columns, Field::T),
            uv: layout.address(columns, Field::Uv),
            prim: layout.address(columns, Field::Prim),
            instance: layout.address(columns, Field::Instance),
            geometry: layout.address(columns, Field::Geometry),
            offsets_out: 0,
            base: 0,
        };
        let check = buffers.device.as_ref().unwrap_or(&buffers.host);
        self.record_into(cmd, pipeline, lists, &targets, (check, layout.check_at), chunk, trace_stage);
        let host = (vk::PipelineStageFlags::HOST, vk::AccessFlags::HOST_READ);
        let Some(device) = &buffers.device else {
            memory_barrier(ctx, cmd, (compute, vk::AccessFlags::SHADER_WRITE), host);
            return;
        };
        memory_barrier(ctx, cmd, (compute, vk::AccessFlags::SHADER_WRITE), (transfer, vk::AccessFlags::TRANSFER_READ));
        let region = [vk::BufferCopy::default().size(layout.bytes.max(1) as u64)];
        // SAFETY: `cmd` is recording; both buffers hold at least the layout's bytes (`columns`
        // made them so), written by the dispatch above.
        unsafe { ctx.device.cmd_copy_buffer(cmd, device.raw(), buffers.host.raw(), &region) };
        memory_barrier(ctx, cmd, (transfer, vk::AccessFlags::TRANSFER_WRITE), host);
    }

    /// Records the dispatch (of `pipeline`) that writes the columns of the hits of `chunk`'s
    /// rays into `targets`, once the trace shaders' (and list_offsets.comp's) writes to the records
    /// are done; the check word (cleared first) at byte `check.1` of `check.0` (a buffer that
    /// transfers may write). What reads the columns orders itself after the compute stage.
    #[allow(clippy::too_many_arguments)]
    pub fn record_into(
        &self,
        cmd: vk::CommandBuffer,
        pipeline: vk::Pipeline,
        lists: &ListBuffers,
        targets: &ColumnTargets,
        (check, check_at): (&Buffer, usize),
        chunk: ChunkRays,
        trace_stage: vk::PipelineStageFlags,
    ) {
        let ctx = &self.ctx;
        let compute = vk::PipelineStageFlags::COMPUTE_SHADER;
        let transfer = vk::PipelineStageFlags::TRANSFER;
        // SAFETY: `cmd` is recording; the buffer holds the check's 4 bytes at `check_at`
        // (4-aligned), and no command in flight uses it (its set's last one was waited for).
        unsafe { ctx.device.cmd_fill_buffer(cmd, check.raw(), check_at as u64, 4, 0) };
        let writers = trace_stage | compute;
        memory_barrier(ctx, cmd, (writers, vk::AccessFlags::SHADER_WRITE), (compute, vk::AccessFlags::SHADER_READ));
        memory_barrier(ctx, cmd, (transfer, vk::AccessFlags::TRANSFER_WRITE), (compute, vk::AccessFlags::SHADER_WRITE));
        let ChunkRays { first, len, counted, seen, max_hits } = chunk;
        let params = ColumnParams {
            records: lists.records_address(),
            offsets: lists.offsets_address(),
            total: lists.end_address(counted, len),
            first_ray: first as u64,
            ray_index: targets.ray_index,
            t: targets.t,
            uv: targets.uv,
            prim: targets.prim,
            instance: targets.instance,
            geometry: targets.geometry,
            seen,
            check: check.address() + check_at as u64,
            count: len as u32,
            max_hits: max_hits.min(i32::MAX as usize) as u32,
            insertion_limit: INSERTION_LIMIT as u32,
            unused: 0,
            offsets_out: targets.offsets_out,
            base: targets.base,
        };
        let groups =
            (len.div_ceil(self.kernel.local_size as usize) as u32).clamp(1, ctx.limits.max_compute_work_group_count[0]);
        // (The shader strides over the rays the groups do not cover.)
        self.kernel.record_dispatch(cmd, pipeline, &params, groups);
    }
}
