//! Acceleration structures: build flags, size queries, scratch memory, building and compaction.
//! This is the "build data → builder" level; `scene` composes it into meshes and scenes.

use std::sync::Arc;
use std::time::Instant;

use crate::geometry::vertex_format::VertexFormat;
use ash::vk;

use crate::error::{invalid_value, Result, VkResultExt};
use crate::gpu::context::Context;
use crate::gpu::memory::{align_up, memory_barrier, Buffer, MemoryLocation, Uploads};

/// What a build optimizes for (the `VK_BUILD_ACCELERATION_STRUCTURE_PREFER_*` flags).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BuildPreference {
    FastTrace,
    FastBuild,
    LowMemory,
}

impl BuildPreference {
    pub fn parse(name: &str) -> Result<BuildPreference> {
        match name {
            "fast_trace" => Ok(BuildPreference::FastTrace),
            "fast_build" => Ok(BuildPreference::FastBuild),
            "low_memory" => Ok(BuildPreference::LowMemory),
            other => {
                Err(invalid_value(format!("build must be 'fast_trace', 'fast_build' or 'low_memory', got {other:?}")))
            }
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            BuildPreference::FastTrace => "fast_trace",
            BuildPreference::FastBuild => "fast_build",
            BuildPreference::LowMemory => "low_memory",
        }
    }
}

#[derive(Clone, Copy, Debug)]
pub struct BuildOptions {
    pub preference: BuildPreference,
    pub allow_update: bool,
    pub compact: bool,
}

impl BuildOptions {
    pub fn flags(&self) -> vk::BuildAccelerationStructureFlagsKHR {
        use vk::BuildAccelerationStructureFlagsKHR as F;
        let mut flags = match self.preference {
            BuildPreference::FastTrace => F::PREFER_FAST_TRACE,
            BuildPreference::FastBuild => F::PREFER_FAST_BUILD,
            BuildPreference::LowMemory => F::LOW_MEMORY,
        };
        if self.allow_update {
            flags |= F::ALLOW_UPDATE;
        }
        if self.compact {
            flags |= F::ALLOW_COMPACTION;
        }
        flags
    }
}

/// Sizes and time of one build.
#[derive(Clone, Copy, Debug, Default)]
pub struct BuildStats {
    /// Bytes of the structure as built.
    pub built_size: u64,
    /// Bytes it occupies now (after compaction where asked).
    pub size: u64,
    pub scratch_size: u64,
    pub update_scratch_size: u64,
    /// Wall time from submission to a usable structure, compaction included (for structures
    /// built together, their batch's time).
    pub build_seconds: f64,
    /// Which submission of a batched build made it (0 for a single build).
    pub batch: u32,
}

/// A VkAccelerationStructureKHR and the buffer holding it.
pub struct AccelerationStructure {
    ctx: Arc<Context>,
    raw: vk::AccelerationStructureKHR,
    _storage: Buffer,
    address: u64,
}

impl AccelerationStructure {
    fn new(ctx: &Arc<Context>, ty: vk::AccelerationStructureTypeKHR, size: u64, name: &str) -> Result<Self> {
        let storage = Buffer::new(
            ctx,
            size,
            vk::BufferUsageFlags::ACCELERATION_STRUCTURE_STORAGE_KHR | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
            MemoryLocation::GpuOnly,
            name,
        )?;
        let info = vk::AccelerationStructureCreateInfoKHR::default().buffer(storage.raw()).size(size).ty(ty);
        let raw =
            unsafe { ctx.accel.create_acceleration_structure(&info, None) }.vk("vkCreateAccelerationStructureKHR")?;
        let address_info = vk::AccelerationStructureDeviceAddressInfoKHR::default().acceleration_structure(raw);
        let address = unsafe { ctx.accel.get_acceleration_structure_device_address(&address_info) };
        ctx.name_object(raw, name);
        Ok(AccelerationStructure { ctx: ctx.clone(), raw, _storage: storage, address })
    }

    pub fn raw(&self) -> vk::AccelerationStructureKHR {
        self.raw
    }

    pub fn context(&self) -> &Arc<Context> {
        &self.ctx
    }

    pub fn address(&self) -> u64 {
        self.address
    }
}

impl Drop for AccelerationStructure {
    fn drop(&mut self) {
        if self.ctx.forked() {
            return;
        }
        unsafe { self.ctx.accel.destroy_acceleration_structure(self.raw, None) };
    }
}

/// Geometry of one build: what `vkCmdBuildAccelerationStructuresKHR` reads.
pub struct BuildInput<'a> {
    pub ty: vk::AccelerationStructureTypeKHR,
    pub geometries: Vec<vk::AccelerationStructureGeometryKHR<'a>>,
    pub primitive_counts: Vec<u32>,
    pub name: &'a str,
}

/// A scratch buffer whose device address honours the device's scratch alignment.
struct Scratch {
    _buffer: Buffer,
    address: u64,
}

impl Scratch {
    fn new(ctx: &Arc<Context>, size: u64) -> Result<Scratch> {
        let alignment = ctx.limits.min_scratch_offset_alignment as u64;
        let buffer = Buffer::new(
            ctx,
            size + alignment,
            vk::BufferUsageFlags::STORAGE_BUFFER | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS,
            MemoryLocation::GpuOnly,
            "scratch",
        )?;
        let address = align_up(buffer.address(), alignment);
        Ok(Scratch { _buffer: buffer, address })
    }
}

/// Builds one acceleration structure: uploads (recorded in the same submission), the build, and a
/// compacting copy where asked. Returns the structure and its figures.
pub fn build(
    ctx: &Arc<Context>,
    input: &BuildInput,
    options: BuildOptions,
    uploads: &Uploads,
) -> Result<(AccelerationStructure, BuildStats)> {
    let mut built = build_many(ctx, std::slice::from_ref(input), options, uploads, u64::MAX)?;
    Ok(built.pop().expect("one structure per input"))
}

/// Builds many acceleration structures in as few submissions as a scratch budget allows (the
/// Vulkan guides' build-until-the-budget-is-spent loop): each batch's builds share one scratch
/// buffer at aligned offsets, and where compaction is asked each batch is compacted before the
/// next starts, so the uncompacted copies never all exist at once. `uploads` are recorded before
/// the first batch. Stats carry their batch's wall time and number.
pub fn build_many(
    ctx: &Arc<Context>,
    inputs: &[BuildInput],
    options: BuildOptions,
    uploads: &Uploads,
    scratch_budget: u64,
) -> Result<Vec<(AccelerationStructure, BuildStats)>> {
    let alignment = (ctx.limits.min_scratch_offset_alignment as u64).max(1);
    let infos: Vec<vk::AccelerationStructureBuildGeometryInfoKHR> = inputs
        .iter()
        .map(|input| {
            vk::AccelerationStructureBuildGeometryInfoKHR::default()
                .ty(input.ty)
                .flags(options.flags())
                .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
                .geometries(&input.geometries)
        })
        .collect();
    let sizes: Vec<vk::AccelerationStructureBuildSizesInfoKHR> = infos
        .iter()
        .zip(inputs)
        .map(|(info, input)| {
            let mut sizes = vk::AccelerationStructureBuildSizesInfoKHR::default();
            unsafe {
                ctx.accel.get_acceleration_structure_build_sizes(
                    vk::AccelerationStructureBuildTypeKHR::DEVICE,
                    info,
                    &input.primitive_counts,
                    &mut sizes,
                )
            };
            sizes
        })
        .collect();
    let scratch_of = |k: usize| align_up(sizes[k].build_scratch_size, alignment);
    if let Some(k) = (0..inputs.len()).find(|&k| scratch_of(k) > scratch_budget) {
        return Err(invalid_value(format!(
            "structure {k} needs {} bytes of build scratch, more than the budget of {scratch_budget}",
            scratch_of(k)
        )));
    }
    // Consecutive batches, each as long as its scratch fits the budget.
    let mut batches: Vec<std::ops::Range<usize>> = Vec::new();
    let mut used = 0u64;
    for k in 0..inputs.len() {
        match batches.last_mut() {
            Some(batch) if used + scratch_of(k) <= scratch_budget => batch.end = k + 1,
            _ => {
                batches.push(k..k + 1);
                used = 0;
            }
        }
        used += scratch_of(k);
    }
    let scratch_size = batches.iter().map(|b| b.clone().map(scratch_of).sum::<u64>()).max().unwrap_or(0);
    let scratch = Scratch::new(ctx, scratch_size)?;

    let mut built = Vec::with_capacity(inputs.len());
    for (number, batch) in batches.into_iter().enumerate() {
        let started = Instant::now();
        let structures = batch
            .clone()
            .map(|k| {
                AccelerationStructure::new(ctx, inputs[k].ty, sizes[k].acceleration_structure_size, inputs[k].name)
            })
            .collect::<Result<Vec<_>>>()?;
        let mut offset = 0;
        let batch_infos: Vec<_> = batch
            .clone()
            .zip(&structures)
            .map(|(k, structure)| {
                let info = infos[k]
                    .dst_acceleration_structure(structure.raw())
                    .scratch_data(vk::DeviceOrHostAddressKHR { device_address: scratch.address + offset });
                offset += scratch_of(k);
                info
            })
            .collect();
        let ranges: Vec<_> = batch.clone().map(|k| build_ranges(&inputs[k])).collect();
        let range_refs: Vec<&[vk::AccelerationStructureBuildRangeInfoKHR]> = ranges.iter().map(Vec::as_slice).collect();
        let query = if options.compact { Some(CompactedSizeQuery::new(ctx, structures.len() as u32)?) } else { None };
        ctx.run_commands(|cmd| {
            if number == 0 {
                uploads.record(ctx, cmd);
            }
            if let Some(query) = &query {
                unsafe { ctx.device.cmd_reset_query_pool(cmd, query.pool, 0, query.count) };
            }
            unsafe { ctx.accel.cmd_build_acceleration_structures(cmd, &batch_infos, &range_refs) };
            structures_written(ctx, cmd);
            if let Some(query) = &query {
                let raw: Vec<_> = structures.iter().map(|s| s.raw()).collect();
                unsafe {
                    ctx.accel.cmd_write_acceleration_structures_properties(
                        cmd,
                        &raw,
                        vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR,
                        query.pool,
                        0,
                    )
                };
            }
            Ok(())
        })?;
        let final_sizes: Vec<u64> = match &query {
            Some(query) => query.read()?,
            None => batch.clone().map(|k| sizes[k].acceleration_structure_size).collect(),
        };
        let structures = match query {
            Some(_) => compact(ctx, &inputs[batch.clone()], structures, &final_sizes)?,
            None => structures,
        };
        let seconds = started.elapsed().as_secs_f64();
        for ((k, structure), size) in batch.zip(structures).zip(final_sizes) {
            let stats = BuildStats {
                built_size: sizes[k].acceleration_structure_size,
                size,
                scratch_size: sizes[k].build_scratch_size,
                update_scratch_size: sizes[k].update_scratch_size,
                build_seconds: seconds,
                batch: number as u32,
            };
            built.push((structure, stats));
        }
    }
    Ok(built)
}

/// Copies freshly built structures into new ones of their compacted sizes (one submission).
fn compact(
    ctx: &Arc<Context>,
    inputs: &[BuildInput],
    structures: Vec<AccelerationStructure>,
    compacted_sizes: &[u64],
) -> Result<Vec<AccelerationStructure>> {
    let compacted = inputs
        .iter()
        .zip(compacted_sizes)
        .map(|(input, &size)| AccelerationStructure::new(ctx, input.ty, size, input.name))
        .collect::<Result<Vec<_>>>()?;
    ctx.run_commands(|cmd| {
        for (from, to) in structures.iter().zip(&compacted) {
            let copy = vk::CopyAccelerationStructureInfoKHR::default()
                .src(from.raw())
                .dst(to.raw())
                .mode(vk::CopyAccelerationStructureModeKHR::COMPACT);
            unsafe { ctx.accel.cmd_copy_acceleration_structure(cmd, &copy) };
        }
        structures_written(ctx, cmd);
        Ok(())
    })?;
    Ok(compacted)
}

/// Refits `structure` in place to new contents of the buffers `input` reads (Vulkan's UPDATE mode
/// with source = destination): same geometry counts and flags as its build, which must have
/// allowed updates. Returns the seconds from submission to a usable structure.
pub fn update(
    ctx: &Arc<Context>,
    structure: &AccelerationStructure,
    input: &BuildInput,
    options: BuildOptions,
    update_scratch_size: u64,
    uploads: &Uploads,
) -> Result<f64> {
    let started = Instant::now();
    let scratch = Scratch::new(ctx, update_scratch_size)?;
    let info = vk::AccelerationStructureBuildGeometryInfoKHR::default()
        .ty(input.ty)
        .flags(options.flags())
        .mode(vk::BuildAccelerationStructureModeKHR::UPDATE)
        .geometries(&input.geometries)
        .src_acceleration_structure(structure.raw())
        .dst_acceleration_structure(structure.raw())
        .scratch_data(vk::DeviceOrHostAddressKHR { device_address: scratch.address });
    let ranges = build_ranges(input);
    ctx.run_commands(|cmd| {
        uploads.record(ctx, cmd);
        unsafe { ctx.accel.cmd_build_acceleration_structures(cmd, std::slice::from_ref(&info), &[&ranges]) };
        structures_written(ctx, cmd);
        Ok(())
    })?;
    Ok(started.elapsed().as_secs_f64())
}

/// One build range per geometry: all of its primitives.
fn build_ranges(input: &BuildInput) -> Vec<vk::AccelerationStructureBuildRangeInfoKHR> {
    input
        .primitive_counts
        .iter()
        .map(|&count| vk::AccelerationStructureBuildRangeInfoKHR::default().primitive_count(count))
        .collect()
}

/// Later commands, in this submission or any after it, see the structures built or copied so far.
fn structures_written(ctx: &Context, cmd: vk::CommandBuffer) {
    memory_barrier(
        ctx,
        cmd,
        vk::PipelineStageFlags::ACCELERATION_STRUCTURE_BUILD_KHR,
        vk::AccessFlags::ACCELERATION_STRUCTURE_WRITE_KHR,
        vk::PipelineStageFlags::ALL_COMMANDS,
        vk::AccessFlags::MEMORY_READ | vk::AccessFlags::ACCELERATION_STRUCTURE_READ_KHR,
    );
}

/// A query pool reading back the compacted sizes of `count` acceleration structures.
struct CompactedSizeQuery<'a> {
    ctx: &'a Context,
    pool: vk::QueryPool,
    count: u32,
}

impl<'a> CompactedSizeQuery<'a> {
    fn new(ctx: &'a Context, count: u32) -> Result<Self> {
        let info = vk::QueryPoolCreateInfo::default()
            .query_type(vk::QueryType::ACCELERATION_STRUCTURE_COMPACTED_SIZE_KHR)
            .query_count(count);
        let pool = unsafe { ctx.device.create_query_pool(&info, None) }.vk("vkCreateQueryPool")?;
        Ok(CompactedSizeQuery { ctx, pool, count })
    }

    fn read(&self) -> Result<Vec<u64>> {
        let mut sizes = vec![0u64; self.count as usize];
        unsafe {
            self.ctx.device.get_query_pool_results(
                self.pool,
                0,
                &mut sizes,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        }
        .vk("vkGetQueryPoolResults")?;
        Ok(sizes)
    }
}

impl Drop for CompactedSizeQuery<'_> {
    fn drop(&mut self) {
        unsafe { self.ctx.device.destroy_query_pool(self.pool, None) };
    }
}

/// Instance flags of `VkGeometryInstanceFlagBitsKHR`.
pub const INSTANCE_TRIANGLE_FACING_CULL_DISABLE: u8 = 0x1;

/// Where an instance's hits go: the bits of `VkAccelerationStructureInstanceKHR` besides its
/// transform and structure.
#[derive(Clone, Copy, Debug, Default)]
pub struct InstanceBits {
    /// 24 bits, read by shaders.
    pub custom_index: u32,
    pub mask: u8,
    /// `VkGeometryInstanceFlagBitsKHR`.
    pub flags: u8,
    /// 24 bits: which hit group of the shader binding table its hits use.
    pub sbt_offset: u32,
}

/// One `VkAccelerationStructureInstanceKHR` (64 bytes): transform, 24-bit custom index and 8-bit
/// mask, 24-bit hit-group offset and 8-bit flags, and the BLAS address.
pub fn instance_record(transform: &[f32; 12], bits: InstanceBits, blas_address: u64) -> [u8; 64] {
    let InstanceBits { custom_index, mask, flags, sbt_offset } = bits;
    debug_assert!(custom_index < (1 << 24) && sbt_offset < (1 << 24));
    let mut record = [0u8; 64];
    for (dst, value) in record.chunks_exact_mut(4).zip(transform.iter()) {
        dst.copy_from_slice(&value.to_ne_bytes());
    }
    record[48..52].copy_from_slice(&(custom_index | (mask as u32) << 24).to_ne_bytes());
    record[52..56].copy_from_slice(&(sbt_offset | (flags as u32) << 24).to_ne_bytes());
    record[56..64].copy_from_slice(&blas_address.to_ne_bytes());
    record
}

/// The Vulkan format of a vertex buffer in `format`.
pub fn vulkan_vertex_format(format: VertexFormat) -> vk::Format {
    match format {
        VertexFormat::F32 => vk::Format::R32G32B32_SFLOAT,
        VertexFormat::F16 => vk::Format::R16G16B16A16_SFLOAT,
        VertexFormat::Snorm16 => vk::Format::R16G16B16A16_SNORM,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instance_record_matches_vulkan_layout() {
        let transform = [1.0, 0.0, 0.0, 5.0, 0.0, 1.0, 0.0, 6.0, 0.0, 0.0, 1.0, 7.0];
        let bits = InstanceBits { custom_index: 0x00AB_CDEF, mask: 0x0F, flags: 0x1, sbt_offset: 2 };
        let record = instance_record(&transform, bits, 0x1122_3344_5566_7788);
        assert_eq!(&record[12..16], &5.0f32.to_ne_bytes());
        assert_eq!(u32::from_ne_bytes(record[48..52].try_into().unwrap()), 0x0FAB_CDEF);
        assert_eq!(u32::from_ne_bytes(record[52..56].try_into().unwrap()), 0x0100_0002);
        assert_eq!(u64::from_ne_bytes(record[56..64].try_into().unwrap()), 0x1122_3344_5566_7788);
        // Vulkan's own struct is the same size.
        assert_eq!(std::mem::size_of::<vk::AccelerationStructureInstanceKHR>(), 64);
    }

    #[test]
    fn build_flags_follow_options() {
        use vk::BuildAccelerationStructureFlagsKHR as F;
        let options = BuildOptions { preference: BuildPreference::FastBuild, allow_update: true, compact: true };
        assert_eq!(options.flags(), F::PREFER_FAST_BUILD | F::ALLOW_UPDATE | F::ALLOW_COMPACTION);
        for name in ["fast_trace", "fast_build", "low_memory"] {
            assert_eq!(BuildPreference::parse(name).unwrap().name(), name);
        }
        assert!(BuildPreference::parse("fastest").is_err());
    }
}
