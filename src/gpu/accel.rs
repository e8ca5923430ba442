//! Acceleration structures: build flags, size queries, scratch memory, building and compaction.
//! This is the "build data → builder" level; `scene` composes it into meshes and scenes.

use std::ops::Range;
use std::sync::Arc;
use std::time::Instant;

use ash::vk;

use crate::error::{invalid_value, Result, VkResultExt};
use crate::geometry::align::align_up;
use crate::geometry::build_options::{BuildOptions, BuildPreference, BuildStats};
use crate::geometry::interrupt::{Interrupt, NoInterrupt};
use crate::gpu::context::Context;
use crate::gpu::memory::{memory_barrier, Buffer, MemoryLocation, Uploads, GEOMETRY_INPUT};

/// Vulkan's build flags for `options`.
pub fn build_flags(options: &BuildOptions) -> vk::BuildAccelerationStructureFlagsKHR {
    use vk::BuildAccelerationStructureFlagsKHR as F;
    let mut flags = match options.preference {
        BuildPreference::FastTrace => F::PREFER_FAST_TRACE,
        BuildPreference::FastBuild => F::PREFER_FAST_BUILD,
        BuildPreference::LowMemory => F::LOW_MEMORY,
    };
    if options.allow_update {
        flags |= F::ALLOW_UPDATE;
    }
    if options.compact {
        flags |= F::ALLOW_COMPACTION;
    }
    flags
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
        // SAFETY: `storage` is a live buffer of `size` bytes, bound to memory, with
        // acceleration-structure storage usage; it lives as long as the structure (a field).
        let raw =
            unsafe { ctx.accel.create_acceleration_structure(&info, None) }.vk("vkCreateAccelerationStructureKHR")?;
        let address_info = vk::AccelerationStructureDeviceAddressInfoKHR::default().acceleration_structure(raw);
        // SAFETY: `raw` was just created on this device (whose accelerationStructure feature is on).
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
        if !self.ctx.can_free() {
            return;
        }
        // SAFETY: `raw` is destroyed once (before its storage, a later field), and no work in
        // flight uses it: builds and traces wait for their submissions before returning, while
        // their caller holds the structure; where a wait gave up, `can_free` leaks it instead.
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
    let mut built = build_many(ctx, std::slice::from_ref(input), options, uploads, u64::MAX, &NoInterrupt)?;
    Ok(built.pop().expect("one structure per input"))
}

/// Builds many acceleration structures in as few submissions as a scratch budget allows (the
/// Vulkan guides' build-until-the-budget-is-spent loop): each batch's builds share one scratch
/// buffer at aligned offsets, and where compaction is asked each batch is compacted before the
/// next starts, so the uncompacted copies never all exist at once. `uploads` are recorded before
/// the first batch. Stats carry their batch's wall time and number. `interrupt` hears how many
/// structures are built after each batch, and may stop the work between batches.
pub fn build_many(
    ctx: &Arc<Context>,
    inputs: &[BuildInput],
    options: BuildOptions,
    uploads: &Uploads,
    scratch_budget: u64,
    interrupt: &dyn Interrupt,
) -> Result<Vec<(AccelerationStructure, BuildStats)>> {
    let plan = BuildPlan::new(ctx, inputs, options);
    if let Some((k, scratch)) = plan.scratch.iter().enumerate().find(|(_, &scratch)| scratch > scratch_budget) {
        return Err(invalid_value(format!(
            "structure {k} needs {scratch} bytes of build scratch, more than the budget of {scratch_budget}"
        )));
    }
    let batches = plan.batches(scratch_budget);
    let scratch_size = batches.iter().map(|b| plan.scratch[b.clone()].iter().sum::<u64>()).max().unwrap_or(0);
    let scratch = Scratch::new(ctx, scratch_size)?;
    let mut built = Vec::with_capacity(inputs.len());
    for (number, batch) in batches.into_iter().enumerate() {
        interrupt.check()?;
        let uploads = (number == 0).then_some(uploads);
        built.extend(plan.build_batch(ctx, batch, scratch.address, uploads, number as u32)?);
        interrupt.progress(built.len(), inputs.len());
    }
    Ok(built)
}

/// What `build_many` works out before building: each input's build info (without its
/// destination and scratch), sizes, and scratch rounded up to the device's scratch alignment.
struct BuildPlan<'a> {
    inputs: &'a [BuildInput<'a>],
    options: BuildOptions,
    infos: Vec<vk::AccelerationStructureBuildGeometryInfoKHR<'a>>,
    sizes: Vec<vk::AccelerationStructureBuildSizesInfoKHR<'static>>,
    scratch: Vec<u64>,
}

impl<'a> BuildPlan<'a> {
    fn new(ctx: &Context, inputs: &'a [BuildInput<'a>], options: BuildOptions) -> BuildPlan<'a> {
        let alignment = (ctx.limits.min_scratch_offset_alignment as u64).max(1);
        let infos: Vec<_> = inputs
            .iter()
            .map(|input| {
                vk::AccelerationStructureBuildGeometryInfoKHR::default()
                    .ty(input.ty)
                    .flags(build_flags(&options))
                    .mode(vk::BuildAccelerationStructureModeKHR::BUILD)
                    .geometries(&input.geometries)
            })
            .collect();
        let sizes: Vec<_> = infos
            .iter()
            .zip(inputs)
            .map(|(info, input)| {
                let mut sizes = vk::AccelerationStructureBuildSizesInfoKHR::default();
                // SAFETY: `info` describes `input.geometries` (borrowed, live), with one primitive
                // count per geometry; a size query reads no device memory.
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
        let scratch = sizes.iter().map(|s| align_up(s.build_scratch_size, alignment)).collect();
        BuildPlan { inputs, options, infos, sizes, scratch }
    }

    /// Consecutive batches, each as long as its scratch fits the budget.
    fn batches(&self, budget: u64) -> Vec<Range<usize>> {
        let mut batches: Vec<Range<usize>> = Vec::new();
        let mut used = 0u64;
        for (k, &scratch) in self.scratch.iter().enumerate() {
            match batches.last_mut() {
                Some(batch) if used + scratch <= budget => batch.end = k + 1,
                _ => {
                    batches.push(k..k + 1);
                    used = 0;
                }
            }
            used += scratch;
        }
        batches
    }

    /// Builds the structures of `batch` in one submission (after `uploads`, where given), their
    /// scratch at consecutive offsets from `scratch_address`, then compacts them where asked.
    fn build_batch(
        &self,
        ctx: &Arc<Context>,
        batch: Range<usize>,
        scratch_address: u64,
        uploads: Option<&Uploads>,
        number: u32,
    ) -> Result<Vec<(AccelerationStructure, BuildStats)>> {
        let started = Instant::now();
        let (inputs, sizes) = (&self.inputs[batch.clone()], &self.sizes[batch.clone()]);
        let structures = inputs
            .iter()
            .zip(sizes)
            .map(|(input, size)| {
                AccelerationStructure::new(ctx, input.ty, size.acceleration_structure_size, input.name)
            })
            .collect::<Result<Vec<_>>>()?;
        let mut offset = 0;
        let infos: Vec<_> = batch
            .clone()
            .zip(&structures)
            .map(|(k, structure)| {
                let info = self.infos[k]
                    .dst_acceleration_structure(structure.raw())
                    .scratch_data(vk::DeviceOrHostAddressKHR { device_address: scratch_address + offset });
                offset += self.scratch[k];
                info
            })
            .collect();
        let ranges: Vec<_> = inputs.iter().map(build_ranges).collect();
        let range_refs: Vec<&[vk::AccelerationStructureBuildRangeInfoKHR]> = ranges.iter().map(Vec::as_slice).collect();
        let query =
            if self.options.compact { Some(CompactedSizeQuery::new(ctx, structures.len() as u32)?) } else { None };
        ctx.run_commands(|cmd| {
            if let Some(uploads) = uploads {
                uploads.record(ctx, cmd);
            }
            record_builds(ctx, cmd, &infos, &range_refs, &structures, query.as_ref());
            Ok(())
        })?;
        let final_sizes: Vec<u64> = match &query {
            Some(query) => query.read()?,
            None => sizes.iter().map(|s| s.acceleration_structure_size).collect(),
        };
        let structures = match query {
            Some(_) => compact(ctx, inputs, structures, &final_sizes)?,
            None => structures,
        };
        let seconds = started.elapsed().as_secs_f64();
        let stats = sizes.iter().zip(final_sizes).map(|(sizes, size)| BuildStats {
            built_size: sizes.acceleration_structure_size,
            size,
            scratch_size: sizes.build_scratch_size,
            update_scratch_size: sizes.update_scratch_size,
            build_seconds: seconds,
            batch: number,
        });
        Ok(structures.into_iter().zip(stats).collect())
    }
}

/// Records the builds of `structures` (`infos` and `ranges` describe them), a barrier after them,
/// and where `query` is given, the query of their compacted sizes.
fn record_builds(
    ctx: &Context,
    cmd: vk::CommandBuffer,
    infos: &[vk::AccelerationStructureBuildGeometryInfoKHR],
    ranges: &[&[vk::AccelerationStructureBuildRangeInfoKHR]],
    structures: &[AccelerationStructure],
    query: Option<&CompactedSizeQuery>,
) {
    if let Some(query) = query {
        // SAFETY: `cmd` is recording; the pool is live and holds `count` queries, none in use.
        unsafe { ctx.device.cmd_reset_query_pool(cmd, query.pool, 0, query.count) };
    }
    // SAFETY: `cmd` is recording; every info names a live destination structure, scratch of its
    // size at a disjoint aligned range, and geometries whose buffers outlive the submission.
    unsafe { ctx.accel.cmd_build_acceleration_structures(cmd, infos, ranges) };
    structures_written(ctx, cmd);
    if let Some(query) = query {
        let raw: Vec<_> = structures.iter().map(|s| s.raw()).collect();
        // SAFETY: `cmd` is recording; the structures were built (and made visible) above, and the
        // pool holds one reset query per structure.
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
            // SAFETY: `cmd` is recording; `from` was built with ALLOW_COMPACTION by a submission
            // already waited for, and `to` is live and as large as the compacted size queried.
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
        .flags(build_flags(&options))
        .mode(vk::BuildAccelerationStructureModeKHR::UPDATE)
        .geometries(&input.geometries)
        .src_acceleration_structure(structure.raw())
        .dst_acceleration_structure(structure.raw())
        .scratch_data(vk::DeviceOrHostAddressKHR { device_address: scratch.address });
    let ranges = build_ranges(input);
    ctx.run_commands(|cmd| {
        uploads.record(ctx, cmd);
        // SAFETY: `cmd` is recording; `structure` is live and was built with ALLOW_UPDATE from the
        // same geometry counts (the caller's contract), nothing in flight uses it (its owner holds
        // it exclusively: `Mesh::update` and `Scene::update`), and the scratch is
        // `update_scratch_size` bytes at an aligned address; the submission is waited for.
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
        (vk::PipelineStageFlags::ACCELERATION_STRUCTURE_BUILD_KHR, vk::AccessFlags::ACCELERATION_STRUCTURE_WRITE_KHR),
        (
            vk::PipelineStageFlags::ALL_COMMANDS,
            vk::AccessFlags::MEMORY_READ | vk::AccessFlags::ACCELERATION_STRUCTURE_READ_KHR,
        ),
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
        // SAFETY: a valid create info on a live device (with accelerationStructure enabled).
        let pool = unsafe { ctx.device.create_query_pool(&info, None) }.vk("vkCreateQueryPool")?;
        Ok(CompactedSizeQuery { ctx, pool, count })
    }

    fn read(&self) -> Result<Vec<u64>> {
        let mut sizes = vec![0u64; self.count as usize];
        // SAFETY: the pool is live and holds `count` queries, room for as many 64-bit results;
        // WAIT makes the call wait for queries written by a submission already waited for.
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
        if !self.ctx.can_free() {
            return;
        }
        // SAFETY: the pool is destroyed once, and the submission using it was waited for (or
        // never made): `run_commands` waits before returning, and where a wait gave up,
        // `can_free` leaks the pool instead.
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

/// One `VkAccelerationStructureInstanceKHR`: transform, 24-bit custom index and 8-bit mask,
/// 24-bit hit-group offset and 8-bit flags, and the BLAS address.
pub fn instance_record(
    transform: &[f32; 12],
    bits: InstanceBits,
    blas_address: u64,
) -> vk::AccelerationStructureInstanceKHR {
    let InstanceBits { custom_index, mask, flags, sbt_offset } = bits;
    debug_assert!(custom_index < (1 << 24) && sbt_offset < (1 << 24));
    vk::AccelerationStructureInstanceKHR {
        transform: vk::TransformMatrixKHR { matrix: *transform },
        instance_custom_index_and_mask: vk::Packed24_8::new(custom_index, mask),
        instance_shader_binding_table_record_offset_and_flags: vk::Packed24_8::new(sbt_offset, flags),
        acceleration_structure_reference: vk::AccelerationStructureReferenceKHR { device_handle: blas_address },
    }
}

// What `instance_bytes` relies on: Vulkan's 64-byte record, without padding.
const _: () = {
    use std::mem::{offset_of, size_of};
    type Instance = vk::AccelerationStructureInstanceKHR;
    assert!(size_of::<Instance>() == 64);
    assert!(offset_of!(Instance, instance_custom_index_and_mask) == 48);
    assert!(offset_of!(Instance, instance_shader_binding_table_record_offset_and_flags) == 52);
    assert!(offset_of!(Instance, acceleration_structure_reference) == 56);
    assert!(size_of::<vk::AccelerationStructureReferenceKHR>() == 8);
};

/// Instance records as the bytes a TLAS build reads.
pub fn instance_bytes(records: &[vk::AccelerationStructureInstanceKHR]) -> &[u8] {
    // SAFETY: the record is repr(C) f32s, u32s and a u64-sized union with no padding (asserted
    // above), and `instance_record` writes the union's whole 8 bytes (`device_handle`), so every
    // byte of the slice is initialised; u8 has no alignment or validity requirements.
    unsafe { std::slice::from_raw_parts(records.as_ptr().cast::<u8>(), std::mem::size_of_val(records)) }
}

/// The flags of every geometry: opaque (no any-hit stage runs unless a query's ray flags ask for
/// it), and each primitive met at most once per ray where they do (all hits, counts).
pub const GEOMETRY_FLAGS: vk::GeometryFlagsKHR = vk::GeometryFlagsKHR::from_raw(
    vk::GeometryFlagsKHR::OPAQUE.as_raw() | vk::GeometryFlagsKHR::NO_DUPLICATE_ANY_HIT_INVOCATION.as_raw(),
);

/// The flags of a geometry some of whose triangles let light through (`Device.mesh(opacity=)`):
/// not opaque, so that traversal hands its triangles to the any-hit stage (or the ray query's
/// candidate loop), which reads their opacity; each at most once per ray.
pub const TRANSLUCENT_GEOMETRY_FLAGS: vk::GeometryFlagsKHR = vk::GeometryFlagsKHR::NO_DUPLICATE_ANY_HIT_INVOCATION;

/// One opaque geometry of boxes at `address`: tightly packed `VkAabbPositionsKHR`, which hosts
/// write as `[f32; 6]` (min xyz, max xyz: `Aabb::outward_f32`).
pub fn aabbs_geometry(address: u64) -> vk::AccelerationStructureGeometryKHR<'static> {
    let data = vk::AccelerationStructureGeometryAabbsDataKHR::default()
        .data(vk::DeviceOrHostAddressConstKHR { device_address: address })
        .stride(std::mem::size_of::<vk::AabbPositionsKHR>() as u64);
    vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::AABBS)
        .geometry(vk::AccelerationStructureGeometryDataKHR { aabbs: data })
        .flags(GEOMETRY_FLAGS)
}

const _: () = assert!(std::mem::size_of::<vk::AabbPositionsKHR>() == std::mem::size_of::<[f32; 6]>());

/// A buffer of TLAS instance records, recorded for upload.
pub fn upload_instances(
    ctx: &Arc<Context>,
    uploads: &mut Uploads,
    records: &[vk::AccelerationStructureInstanceKHR],
    name: &str,
) -> Result<Buffer> {
    let bytes = instance_bytes(records);
    let buffer = uploads.buffer(ctx, bytes.len() as u64, GEOMETRY_INPUT, name, |out, _| out.copy_from_slice(bytes))?;
    debug_assert_eq!(buffer.address() % 16, 0, "Vulkan wants instance data 16-byte aligned");
    Ok(buffer)
}

/// The build input of a TLAS over `count` instance records at `address`.
pub fn instances_input(address: u64, count: usize) -> BuildInput<'static> {
    let data = vk::AccelerationStructureGeometryInstancesDataKHR::default()
        .array_of_pointers(false)
        .data(vk::DeviceOrHostAddressConstKHR { device_address: address });
    let geometry = vk::AccelerationStructureGeometryKHR::default()
        .geometry_type(vk::GeometryTypeKHR::INSTANCES)
        .geometry(vk::AccelerationStructureGeometryDataKHR { instances: data });
    BuildInput {
        ty: vk::AccelerationStructureTypeKHR::TOP_LEVEL,
        geometries: vec![geometry],
        primitive_counts: vec![count as u32],
        name: "scene TLAS",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instance_record_matches_vulkan_layout() {
        let transform = [1.0, 0.0, 0.0, 5.0, 0.0, 1.0, 0.0, 6.0, 0.0, 0.0, 1.0, 7.0];
        let bits = InstanceBits { custom_index: 0x00AB_CDEF, mask: 0x0F, flags: 0x1, sbt_offset: 2 };
        let records = [instance_record(&transform, bits, 0x1122_3344_5566_7788)];
        let bytes = instance_bytes(&records);
        let word = |at: usize| u32::from_ne_bytes(bytes[at..at + 4].try_into().unwrap());
        assert_eq!(bytes.len(), 64);
        assert_eq!(f32::from_bits(word(12)), 5.0);
        assert_eq!(word(48), 0x0FAB_CDEF);
        assert_eq!(word(52), 0x0100_0002);
        assert_eq!(u64::from_ne_bytes(bytes[56..64].try_into().unwrap()), 0x1122_3344_5566_7788);
    }

    #[test]
    fn build_flags_follow_options() {
        use vk::BuildAccelerationStructureFlagsKHR as F;
        let options = BuildOptions { preference: BuildPreference::FastBuild, allow_update: true, compact: true };
        assert_eq!(build_flags(&options), F::PREFER_FAST_BUILD | F::ALLOW_UPDATE | F::ALLOW_COMPACTION);
        for name in ["fast_trace", "fast_build", "low_memory"] {
            assert_eq!(BuildPreference::parse(name).unwrap().name(), name);
        }
        assert!(BuildPreference::parse("fastest").is_err());
    }
}
