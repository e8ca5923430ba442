//! Tracing batches of rays against a scene. Each query runs a pipeline variant specialized to what
//! was asked (which hit fields, which ray flags); rays go through in chunks that fit the device's
//! dispatch limits and a bounded staging budget, two chunks in flight so that packing the next
//! overlaps tracing the current one.

use std::collections::HashMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use ash::vk;
use rayon::prelude::*;

use crate::error::{invalid_value, Result, VkResultExt};
use crate::geometry::rays::{Masks, Rays, RAY_FLOATS};
use crate::gpu::context::{Backend, Commands, Context, Wait};
use crate::gpu::memory::{align_up, memory_barrier, Buffer, MemoryLocation, Uploads};
use crate::gpu::shaders;
use crate::scene::{ExactScene, Scene};
use crate::trace::request::{Cull, Precision, Query, Request};
use crate::trace::tiers;

/// A field of the hit record. The discriminant is the field's position among the shaders' output
/// addresses and its bit in their OUTPUTS constant is `1 << discriminant`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Field {
    T = 0,
    Prim = 1,
    Instance = 2,
    Custom = 3,
    Uv = 4,
    Normal = 5,
    Geometry = 6,
}

pub const FIELD_COUNT: usize = 7;
const FIELDS: [Field; FIELD_COUNT] =
    [Field::T, Field::Prim, Field::Instance, Field::Custom, Field::Uv, Field::Normal, Field::Geometry];

impl Field {
    /// Bytes of one ray's value; `wide`: `t` and `uv` in f64 (the f64 precision tiers).
    pub fn bytes_per_ray(self, wide: bool) -> usize {
        match (self, wide) {
            (Field::T, true) => 8,
            (Field::Uv, false) => 8,
            (Field::Uv, true) => 16,
            (Field::Normal, _) => 12,
            _ => 4,
        }
    }

    fn bit(self) -> u32 {
        1 << self as u32
    }
}

/// Where the caller wants each requested field written, as raw bytes of its output array.
/// `position` (the world-space hit point: 3 f32, or 3 f64 in the f64 tiers) is computed on the
/// host from the hit triangle and its barycentrics, never by a shader.
#[derive(Default)]
pub struct HitSink<'a> {
    fields: [Option<&'a mut [u8]>; FIELD_COUNT],
    pub position: Option<&'a mut [u8]>,
}

impl<'a> HitSink<'a> {
    pub fn set(&mut self, field: Field, out: &'a mut [u8]) {
        self.fields[field as usize] = Some(out);
    }

    pub fn field(&self, field: Field) -> Option<&[u8]> {
        self.fields[field as usize].as_deref()
    }

    pub fn field_mut(&mut self, field: Field) -> Option<&mut [u8]> {
        self.fields[field as usize].as_deref_mut()
    }

    pub fn take(&mut self, field: Field) -> Option<&'a mut [u8]> {
        self.fields[field as usize].take()
    }

    fn outputs(&self) -> u32 {
        FIELDS.iter().filter(|f| self.fields[**f as usize].is_some()).map(|f| f.bit()).sum()
    }
}

// Ray flags (SPIR-V RayFlags).
const RAY_FLAG_TERMINATE_ON_FIRST_HIT: u32 = 0x4;
const RAY_FLAG_SKIP_CLOSEST_HIT_SHADER: u32 = 0x8;
const RAY_FLAG_CULL_BACK_FACING_TRIANGLES: u32 = 0x10;
const RAY_FLAG_CULL_FRONT_FACING_TRIANGLES: u32 = 0x20;
const RAY_FLAG_CULL_NO_OPAQUE: u32 = 0x80;
const RAY_FLAG_SKIP_AABBS: u32 = 0x200;

/// Ray flags resolved statically for a query on a scene: where every triangle is opaque the
/// non-opaque path is culled at compile time; AABBs are the exact tier's boxes and sphere sets',
/// so procedural paths are culled too where no AABB can be met; culling is the query's. The exact tier's shader reads the culling bits itself (they do not apply to boxes).
fn ray_flags(query: Query, cull: Cull, backend: Backend, exact: bool, all_opaque: bool, spheres: bool) -> u32 {
    let mut flags = if all_opaque { RAY_FLAG_CULL_NO_OPAQUE } else { 0 };
    flags |= match cull {
        Cull::None => 0,
        Cull::Back => RAY_FLAG_CULL_BACK_FACING_TRIANGLES,
        Cull::Front => RAY_FLAG_CULL_FRONT_FACING_TRIANGLES,
    };
    // The pipeline backend skips AABBs with a pipeline flag instead, which needs no device feature.
    if backend == Backend::RayQuery && !exact && !spheres {
        flags |= RAY_FLAG_SKIP_AABBS;
    }
    if query == Query::Occluded {
        flags |= RAY_FLAG_TERMINATE_ON_FIRST_HIT;
        if backend == Backend::Pipeline {
            flags |= RAY_FLAG_SKIP_CLOSEST_HIT_SHADER;
        }
    }
    flags
}

/// The push constants of `shaders/common.glsl`.
#[repr(C)]
#[derive(Clone, Copy, Default)]
struct Params {
    rays: u64,
    /// InstanceGeometries (fast tier) or ExactInstances (exact tier).
    instances: u64,
    tlas: u64,
    outputs: [u64; FIELD_COUNT],
    /// Exact tier, pipeline backend: the per-ray best-hit records its intersection shader keeps.
    scratch: u64,
    /// Per-ray masks (one u32 each), or 0 when every ray uses `ray_mask`.
    masks: u64,
    count: u32,
    /// Exact tier: the scene's bounds (min xyz, max xyz) in its frame, rounded outward to f32.
    bounds: [f32; 6],
    ray_mask: u32,
}

impl Params {
    fn bytes(&self) -> &[u8] {
        // SAFETY: plain old data, no padding holes (bounds + ray_mask complete the last 8 bytes).
        unsafe { std::slice::from_raw_parts(self as *const Params as *const u8, std::mem::size_of::<Params>()) }
    }
}

const PARAMS_BYTES: u32 = std::mem::size_of::<Params>() as u32;
const _: () = assert!(PARAMS_BYTES <= 128, "within the push-constant size every device offers");

/// Bytes of the exact pipeline's per-ray best-hit record (`ExactBest` in shaders/exact.glsl).
const EXACT_SCRATCH_BYTES: usize = 40;

#[derive(Clone, Copy, PartialEq, Eq, Hash)]
struct VariantKey {
    outputs: u32,
    ray_flags: u32,
    exact: bool,
    /// The scene holds sphere sets (boxes for the sphere shader).
    spheres: bool,
}

struct ShaderBindingTable {
    _buffer: Buffer,
    raygen: vk::StridedDeviceAddressRegionKHR,
    miss: vk::StridedDeviceAddressRegionKHR,
    hit: vk::StridedDeviceAddressRegionKHR,
}

struct Variant {
    pipeline: vk::Pipeline,
    sbt: Option<ShaderBindingTable>,
}

/// Host-visible staging for one chunk in flight (plus device copies on discrete GPUs). An exact
/// slot holds f64 rays, f64 `t`/`uv` and the pipeline's scratch records.
struct Slot {
    rays_host: Buffer,
    hits_host: Buffer,
    device: Option<(Buffer, Buffer)>,
    capacity: usize,
    exact: bool,
}

impl Slot {
    fn new(ctx: &Arc<Context>, capacity: usize, exact: bool) -> Result<Slot> {
        use vk::BufferUsageFlags as U;
        let storage = U::STORAGE_BUFFER | U::SHADER_DEVICE_ADDRESS;
        let ray_bytes = (capacity * (Slot::ray_bytes(exact) + 4)) as u64;
        let hit_bytes = Slot::layout(capacity, exact).1 as u64;
        let (rays_host, hits_host, device) = if ctx.unified_memory {
            let rays = Buffer::new(ctx, ray_bytes, storage, MemoryLocation::CpuToGpu, "rays")?;
            (rays, Buffer::new(ctx, hit_bytes, storage, MemoryLocation::GpuToCpu, "hits")?, None)
        } else {
            (
                Buffer::new(ctx, ray_bytes, U::TRANSFER_SRC, MemoryLocation::CpuToGpu, "rays staging")?,
                Buffer::new(ctx, hit_bytes, U::TRANSFER_DST, MemoryLocation::GpuToCpu, "hits readback")?,
                Some((
                    Buffer::new(ctx, ray_bytes, storage | U::TRANSFER_DST, MemoryLocation::GpuOnly, "rays")?,
                    Buffer::new(ctx, hit_bytes, storage | U::TRANSFER_SRC, MemoryLocation::GpuOnly, "hits")?,
                )),
            )
        };
        Ok(Slot { rays_host, hits_host, device, capacity, exact })
    }

    /// Bytes of one packed ray; the rays buffer holds `capacity` of them, then one u32 mask each.
    fn ray_bytes(exact: bool) -> usize {
        RAY_FLOATS * if exact { 8 } else { 4 }
    }

    fn masks_offset(&self) -> usize {
        self.capacity * Slot::ray_bytes(self.exact)
    }

    /// Byte offsets of each field's array and of the scratch records, and the total, each array
    /// 8-byte aligned (f64 fields).
    fn layout(capacity: usize, exact: bool) -> ([usize; FIELD_COUNT + 1], usize) {
        let mut offsets = [0; FIELD_COUNT + 1];
        let mut at = 0;
        for field in FIELDS {
            offsets[field as usize] = at;
            at = align_up((at + capacity * field.bytes_per_ray(exact)) as u64, 8) as usize;
        }
        offsets[FIELD_COUNT] = at;
        if exact {
            at += capacity * EXACT_SCRATCH_BYTES;
        }
        (offsets, at)
    }

    /// Byte offset of a field's array within the hits buffer.
    fn field_offset(&self, field: Field) -> usize {
        Slot::layout(self.capacity, self.exact).0[field as usize]
    }

    fn scratch_offset(&self) -> usize {
        Slot::layout(self.capacity, self.exact).0[FIELD_COUNT]
    }

    fn rays_address(&self) -> u64 {
        self.device.as_ref().map_or(self.rays_host.address(), |(rays, _)| rays.address())
    }

    fn hits_address(&self) -> u64 {
        self.device.as_ref().map_or(self.hits_host.address(), |(_, hits)| hits.address())
    }
}

/// Where the time went in the last trace (seconds). The host clock splits the caller's wait;
/// with two chunks in flight, `wait` is the GPU time that packing and unpacking did not hide. The
/// device's own timestamps (where its queue has them) split the GPU's part, summed over chunks.
#[derive(Clone, Copy, Debug, Default)]
pub struct TraceProfile {
    pub rays: usize,
    pub chunks: usize,
    /// Checking rays and converting them into staging (the upload, on shared-memory devices).
    pub pack: f64,
    /// Recording and submitting command buffers.
    pub submit: f64,
    /// Waiting for the GPU.
    pub wait: f64,
    /// Copying hit fields from readback memory into the result arrays.
    pub unpack: f64,
    pub total: f64,
    /// GPU time copying rays from staging to device memory (0 on shared-memory devices).
    pub gpu_upload: Option<f64>,
    /// GPU time tracing (the dispatch or trace-rays command alone).
    pub gpu_trace: Option<f64>,
    /// GPU time copying hits to readback memory (0 on shared-memory devices).
    pub gpu_readback: Option<f64>,
    /// Host time in f64 work: refining hits (`"refined"`) or the CPU tracer (`"reference"`).
    pub host_f64: f64,
}

/// Timestamps around each phase of a chunk: start, after upload, after trace, after readback.
const STAMPS_PER_CHUNK: u32 = 4;

/// A timestamp query pool with one set of stamps per chunk slot.
struct Stamps {
    pool: vk::QueryPool,
    tick_seconds: f64,
    mask: u64,
}

impl Stamps {
    fn new(ctx: &Context) -> Result<Option<Stamps>> {
        let bits = ctx.limits.timestamp_valid_bits;
        if bits == 0 || ctx.limits.timestamp_period <= 0.0 {
            return Ok(None);
        }
        let info =
            vk::QueryPoolCreateInfo::default().query_type(vk::QueryType::TIMESTAMP).query_count(2 * STAMPS_PER_CHUNK);
        let pool = unsafe { ctx.device.create_query_pool(&info, None) }.vk("vkCreateQueryPool")?;
        let mask = if bits >= 64 { u64::MAX } else { (1u64 << bits) - 1 };
        Ok(Some(Stamps { pool, tick_seconds: ctx.limits.timestamp_period as f64 * 1e-9, mask }))
    }

    fn reset(&self, ctx: &Context, cmd: vk::CommandBuffer, slot: usize) {
        unsafe { ctx.device.cmd_reset_query_pool(cmd, self.pool, slot as u32 * STAMPS_PER_CHUNK, STAMPS_PER_CHUNK) };
    }

    /// Writes stamp `k` of `slot` once all earlier commands are done.
    fn write(&self, ctx: &Context, cmd: vk::CommandBuffer, slot: usize, k: u32) {
        let stage = if k == 0 { vk::PipelineStageFlags::TOP_OF_PIPE } else { vk::PipelineStageFlags::BOTTOM_OF_PIPE };
        unsafe { ctx.device.cmd_write_timestamp(cmd, stage, self.pool, slot as u32 * STAMPS_PER_CHUNK + k) };
    }

    /// Adds a finished chunk's upload, trace and readback times to `profile`.
    fn add(&self, ctx: &Context, slot: usize, profile: &mut TraceProfile) -> Result<()> {
        let mut ticks = [0u64; STAMPS_PER_CHUNK as usize];
        unsafe {
            ctx.device.get_query_pool_results(
                self.pool,
                slot as u32 * STAMPS_PER_CHUNK,
                &mut ticks,
                vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
            )
        }
        .vk("vkGetQueryPoolResults")?;
        let span = |k: usize| (ticks[k + 1].wrapping_sub(ticks[k]) & self.mask) as f64 * self.tick_seconds;
        for (k, phase) in
            [&mut profile.gpu_upload, &mut profile.gpu_trace, &mut profile.gpu_readback].into_iter().enumerate()
        {
            *phase = Some(phase.unwrap_or(0.0) + span(k));
        }
        Ok(())
    }
}

/// The two paths through intersection shaders, probed once per device.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Probe {
    Exact = 0,
    Spheres = 1,
}

/// Traces rays on one device; owns the pipeline variants and reusable staging.
pub struct Tracer {
    ctx: Arc<Context>,
    layout: vk::PipelineLayout,
    modules: Vec<vk::ShaderModule>,
    variants: Mutex<HashMap<VariantKey, Arc<Variant>>>,
    idle_slots: Mutex<Vec<Slot>>,
    last_profile: Mutex<TraceProfile>,
    /// Timestamps of the chunks in flight; one trace at a time uses them (the lock is held).
    stamps: Mutex<Option<Stamps>>,
    /// Whether this driver runs the intersection shaders of each `Probe` path.
    intersection_shaders_run: Mutex<[Option<bool>; 2]>,
    /// Rays per chunk: bounds staging memory (two chunks in flight).
    chunk_rays: AtomicUsize,
    local_size: u32,
}

/// Default rays per chunk: CPU devices gain nothing from big chunks; GPUs amortize each submit.
fn default_chunk_rays(ctx: &Context) -> usize {
    if ctx.unified_memory {
        1 << 20
    } else {
        1 << 22
    }
}

/// The stages that read the push constants.
fn push_constant_stages(backend: Backend) -> vk::ShaderStageFlags {
    use vk::ShaderStageFlags as S;
    match backend {
        Backend::RayQuery => S::COMPUTE,
        Backend::Pipeline => S::RAYGEN_KHR | S::CLOSEST_HIT_KHR | S::MISS_KHR | S::INTERSECTION_KHR,
    }
}

// Positions of the shader modules in `Tracer::modules`, per backend.
const QUERY_MODULE: usize = 0;
const QUERY_EXACT_MODULE: usize = 1;
const RAYGEN_MODULE: usize = 0;
const MISS_MODULE: usize = 1;
const CLOSEST_HIT_MODULE: usize = 2;
const SPHERE_MODULE: usize = 3;
const RAYGEN_EXACT_MODULE: usize = 4;
const INTERSECTION_EXACT_MODULE: usize = 5;

impl Tracer {
    pub fn new(ctx: &Arc<Context>) -> Result<Tracer> {
        let stages = push_constant_stages(ctx.backend);
        let ranges = [vk::PushConstantRange::default().stage_flags(stages).size(PARAMS_BYTES)];
        let layout_info = vk::PipelineLayoutCreateInfo::default().push_constant_ranges(&ranges);
        let layout = unsafe { ctx.device.create_pipeline_layout(&layout_info, None) }.vk("vkCreatePipelineLayout")?;
        let mut tracer = Tracer {
            ctx: ctx.clone(),
            layout,
            modules: Vec::new(),
            variants: Mutex::new(HashMap::new()),
            idle_slots: Mutex::new(Vec::new()),
            last_profile: Mutex::new(TraceProfile::default()),
            stamps: Mutex::new(Stamps::new(ctx)?),
            intersection_shaders_run: Mutex::new([None; 2]),
            chunk_rays: AtomicUsize::new(default_chunk_rays(ctx)),
            local_size: 64u32
                .min(ctx.limits.max_compute_work_group_size[0])
                .min(ctx.limits.max_compute_work_group_invocations),
        };
        // The exact tier's modules use f64, which only devices with shaderFloat64 may load.
        let sources: &[&[u8]] = match (ctx.backend, ctx.info.shader_float64) {
            (Backend::RayQuery, false) => &[shaders::TRACE_RAY_QUERY],
            (Backend::RayQuery, true) => &[shaders::TRACE_RAY_QUERY, shaders::TRACE_EXACT_RAY_QUERY],
            (Backend::Pipeline, false) => {
                &[shaders::RAYGEN, shaders::MISS, shaders::CLOSEST_HIT, shaders::SPHERE_INTERSECTION]
            }
            (Backend::Pipeline, true) => &[
                shaders::RAYGEN,
                shaders::MISS,
                shaders::CLOSEST_HIT,
                shaders::SPHERE_INTERSECTION,
                shaders::RAYGEN_EXACT,
                shaders::INTERSECTION_EXACT,
            ],
        };
        for source in sources {
            let code = shaders::words(source);
            let info = vk::ShaderModuleCreateInfo::default().code(&code);
            let module = unsafe { ctx.device.create_shader_module(&info, None) }.vk("vkCreateShaderModule")?;
            tracer.modules.push(module);
        }
        ctx.check_validation()?;
        Ok(tracer)
    }

    pub fn last_profile(&self) -> TraceProfile {
        *self.last_profile.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Rays per chunk: staging holds two chunks of rays and hits (72 bytes a ray each).
    pub fn chunk_rays(&self) -> usize {
        self.chunk_rays.load(Ordering::Relaxed)
    }

    pub fn set_chunk_rays(&self, rays: usize) -> Result<()> {
        if rays == 0 {
            return Err(invalid_value("chunk_rays must be at least 1"));
        }
        self.chunk_rays.store(rays, Ordering::Relaxed);
        Ok(())
    }

    /// Most rays one dispatch may cover on this device.
    fn max_dispatch_rays(&self) -> usize {
        let limits = &self.ctx.limits;
        match self.ctx.backend {
            Backend::RayQuery => limits.max_compute_work_group_count[0] as usize * self.local_size as usize,
            Backend::Pipeline => (limits.max_ray_dispatch_invocation_count as usize)
                .min(limits.max_compute_work_group_count[0] as usize * limits.max_compute_work_group_size[0] as usize),
        }
    }

    fn variant(&self, key: VariantKey, wait: &dyn Wait) -> Result<Arc<Variant>> {
        let mut variants = self.variants.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(variant) = variants.get(&key) {
            return Ok(variant.clone());
        }
        let variant = Arc::new(match self.ctx.backend {
            Backend::RayQuery => self.compute_variant(key)?,
            Backend::Pipeline => self.pipeline_variant(key, wait)?,
        });
        variants.insert(key, variant.clone());
        Ok(variant)
    }

    fn compute_variant(&self, key: VariantKey) -> Result<Variant> {
        let values = [key.outputs, key.ray_flags, self.local_size];
        let entries = specialization_entries();
        let spec = vk::SpecializationInfo::default().map_entries(&entries).data(as_bytes(&values));
        let stage = vk::PipelineShaderStageCreateInfo::default()
            .stage(vk::ShaderStageFlags::COMPUTE)
            .module(self.modules[if key.exact { QUERY_EXACT_MODULE } else { QUERY_MODULE }])
            .name(c"main")
            .specialization_info(&spec);
        let info = [vk::ComputePipelineCreateInfo::default().stage(stage).layout(self.layout)];
        let pipeline = unsafe { self.ctx.device.create_compute_pipelines(vk::PipelineCache::null(), &info, None) }
            .map_err(|(_, result)| crate::error::Error::Vulkan { call: "vkCreateComputePipelines", result })?[0];
        self.ctx.check_validation()?;
        Ok(Variant { pipeline, sbt: None })
    }

    fn pipeline_variant(&self, key: VariantKey, wait: &dyn Wait) -> Result<Variant> {
        let ctx = &self.ctx;
        let rt = ctx.pipeline_ext.as_ref().expect("pipeline backend loads its extension");
        let values = [key.outputs, key.ray_flags, 0];
        let entries = specialization_entries();
        let spec = vk::SpecializationInfo::default().map_entries(&entries[..2]).data(as_bytes(&values));
        let stage = |flags, module| {
            vk::PipelineShaderStageCreateInfo::default()
                .stage(flags)
                .module(module)
                .name(c"main")
                .specialization_info(&spec)
        };
        use vk::ShaderStageFlags as S;
        let mut stages = vec![
            stage(S::RAYGEN_KHR, self.modules[if key.exact { RAYGEN_EXACT_MODULE } else { RAYGEN_MODULE }]),
            stage(S::MISS_KHR, self.modules[MISS_MODULE]),
        ];
        if key.exact {
            stages.push(stage(S::INTERSECTION_KHR, self.modules[INTERSECTION_EXACT_MODULE]));
        } else {
            stages.push(stage(S::CLOSEST_HIT_KHR, self.modules[CLOSEST_HIT_MODULE]));
            if key.spheres {
                stages.push(stage(S::INTERSECTION_KHR, self.modules[SPHERE_MODULE]));
            }
        }
        let group = |ty, general, closest_hit, intersection| {
            vk::RayTracingShaderGroupCreateInfoKHR::default()
                .ty(ty)
                .general_shader(general)
                .closest_hit_shader(closest_hit)
                .any_hit_shader(vk::SHADER_UNUSED_KHR)
                .intersection_shader(intersection)
        };
        use vk::RayTracingShaderGroupTypeKHR as G;
        const NONE: u32 = vk::SHADER_UNUSED_KHR;
        let mut groups = vec![group(G::GENERAL, 0, NONE, NONE), group(G::GENERAL, 1, NONE, NONE)];
        if key.exact {
            // Boxes whose intersection shader runs the f64 test and keeps the best hit itself.
            groups.push(group(G::PROCEDURAL_HIT_GROUP, NONE, NONE, 2));
        } else {
            // Triangles first (instances' hit-group offset 0); spheres second (offset 1), sharing
            // the closest-hit shader, which tells them apart by hit kind.
            groups.push(group(G::TRIANGLES_HIT_GROUP, NONE, 2, NONE));
            if key.spheres {
                groups.push(group(G::PROCEDURAL_HIT_GROUP, NONE, 2, 3));
            }
        }
        // Traversal skips the primitives the structures cannot hold, for the whole pipeline (a
        // flag Vulkan allows only with the primitive-culling feature).
        let flags = match (ctx.limits.ray_traversal_primitive_culling, key.exact, key.spheres) {
            (false, _, _) | (true, false, true) => vk::PipelineCreateFlags::empty(),
            (true, false, false) => vk::PipelineCreateFlags::RAY_TRACING_SKIP_AABBS_KHR,
            (true, true, _) => vk::PipelineCreateFlags::RAY_TRACING_SKIP_TRIANGLES_KHR,
        };
        let info = [vk::RayTracingPipelineCreateInfoKHR::default()
            .flags(flags)
            .stages(&stages)
            .groups(&groups)
            .max_pipeline_ray_recursion_depth(1)
            .layout(self.layout)];
        let pipeline = unsafe {
            rt.create_ray_tracing_pipelines(vk::DeferredOperationKHR::null(), vk::PipelineCache::null(), &info, None)
        }
        .map_err(|(_, result)| crate::error::Error::Vulkan { call: "vkCreateRayTracingPipelinesKHR", result })?[0];
        let sbt = match self.shader_binding_table(pipeline, groups.len() as u32, wait) {
            Ok(sbt) => sbt,
            Err(e) => {
                unsafe { ctx.device.destroy_pipeline(pipeline, None) };
                return Err(e);
            }
        };
        ctx.check_validation()?;
        Ok(Variant { pipeline, sbt: Some(sbt) })
    }

    /// One record per group (raygen, miss, hit), laid out by the device's own handle size and
    /// alignments; the raygen region's size equals its stride, as Vulkan requires.
    fn shader_binding_table(
        &self,
        pipeline: vk::Pipeline,
        group_count: u32,
        wait: &dyn Wait,
    ) -> Result<ShaderBindingTable> {
        let ctx = &self.ctx;
        let rt = ctx.pipeline_ext.as_ref().expect("pipeline backend loads its extension");
        let layout = SbtLayout::new(
            ctx.limits.shader_group_handle_size as u64,
            ctx.limits.shader_group_handle_alignment as u64,
            ctx.limits.shader_group_base_alignment as u64,
            group_count as u64 - 2,
        );
        let handle_size = ctx.limits.shader_group_handle_size as usize;
        let handles = unsafe {
            rt.get_ray_tracing_shader_group_handles(pipeline, 0, group_count, group_count as usize * handle_size)
        }
        .vk("vkGetRayTracingShaderGroupHandlesKHR")?;
        let usage = vk::BufferUsageFlags::SHADER_BINDING_TABLE_KHR | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS;
        let mut uploads = Uploads::default();
        let mut start = 0;
        let buffer = uploads.buffer(
            ctx,
            layout.total + layout.base_alignment,
            usage,
            "shader binding table",
            |out, address| {
                start = align_up(address, layout.base_alignment);
                let pad = (start - address) as usize;
                for (group, offset) in layout.records.iter().enumerate() {
                    let at = pad + *offset as usize;
                    out[at..at + handle_size].copy_from_slice(&handles[group * handle_size..(group + 1) * handle_size]);
                }
            },
        )?;
        ctx.run_commands(wait, |cmd| {
            uploads.record(ctx, cmd);
            Ok(())
        })?;
        let region = |k: usize| {
            let (offset, stride, size) = layout.regions[k];
            vk::StridedDeviceAddressRegionKHR::default().device_address(start + offset).stride(stride).size(size)
        };
        Ok(ShaderBindingTable { raygen: region(0), miss: region(1), hit: region(2), _buffer: buffer })
    }

    fn take_slots(&self, capacity: usize, exact: bool) -> Result<[Slot; 2]> {
        let mut idle = self.idle_slots.lock().unwrap_or_else(|e| e.into_inner());
        idle.retain(|s| s.capacity >= capacity || s.exact != exact);
        let mut take = || match idle.iter().position(|s| s.exact == exact) {
            Some(k) => Ok(idle.swap_remove(k)),
            None => Slot::new(&self.ctx, capacity, exact),
        };
        Ok([take()?, take()?])
    }

    fn return_slots(&self, slots: [Slot; 2]) {
        let mut idle = self.idle_slots.lock().unwrap_or_else(|e| e.into_inner());
        idle.extend(slots);
        // Two slots serve one caller; keep at most two callers' worth around.
        idle.truncate(4);
    }

    /// Traces `rays` against `scene` at `precision`, writing the fields `sink` asks for (`t` and
    /// `uv` as f64 in the f64 tiers). Each chunk's rays are checked as they are packed; an invalid
    /// ray stops the trace with an error naming it (chunks already in flight finish first, and
    /// what they wrote is not the caller's to read). `wait` runs every blocking wait (the binding
    /// frees the GIL).
    pub fn trace(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        sink: &mut HitSink,
        wait: &dyn Wait,
    ) -> Result<()> {
        let Request { query, precision, cull } = request;
        let started = Instant::now();
        scene.check_current()?;
        rays.check_shapes()?;
        let mut profile = TraceProfile { rays: rays.len(), ..Default::default() };
        let n = rays.len();
        for field in FIELDS {
            if let Some(out) = &sink.fields[field as usize] {
                if out.len() != n * field.bytes_per_ray(precision.is_f64()) {
                    return Err(invalid_value(format!("output for {field:?} has {} bytes for {n} rays", out.len())));
                }
            }
        }
        if let Some(out) = &sink.position {
            if out.len() != n * 3 * if precision.is_f64() { 8 } else { 4 } {
                return Err(invalid_value(format!("output for position has {} bytes for {n} rays", out.len())));
            }
        }
        if scene.has_spheres() && precision != Precision::Fast {
            return Err(crate::error::Error::Unsupported(
                "scenes with spheres trace at precision='fast' (the f64 tiers are for triangle meshes)".into(),
            ));
        }
        let position = if query == Query::Closest { sink.position.take() } else { None };
        if n == 0 || (sink.outputs() == 0 && position.is_none()) {
            return Ok(());
        }
        // The host needs the hit triangles (and barycentrics) of rays whose caller did not ask.
        let refine = precision == Precision::Refined && query == Query::Closest;
        let mut work = HitSink::default();
        for (field, out) in FIELDS.iter().zip(sink.fields.iter_mut()) {
            if let Some(out) = out.as_deref_mut() {
                work.set(*field, out);
            }
        }
        let (mut prim_temp, mut instance_temp, mut geometry_temp) = (Vec::new(), Vec::new(), Vec::new());
        let mut uv_temp;
        if refine || position.is_some() {
            let temps = [
                (Field::Prim, &mut prim_temp),
                (Field::Instance, &mut instance_temp),
                (Field::Geometry, &mut geometry_temp),
            ];
            for (field, temp) in temps {
                if work.field(field).is_none() {
                    *temp = vec![0u8; 4 * n];
                    work.set(field, temp);
                }
            }
        }
        if position.is_some() && work.field(Field::Uv).is_none() {
            uv_temp = vec![0u8; n * Field::Uv.bytes_per_ray(precision.is_f64())];
            work.set(Field::Uv, &mut uv_temp);
        }
        // Sphere hits' positions come from t.
        let mut t_temp;
        if position.is_some() && scene.has_spheres() && work.field(Field::T).is_none() {
            t_temp = vec![0u8; n * Field::T.bytes_per_ray(precision.is_f64())];
            work.set(Field::T, &mut t_temp);
        }
        match (precision, refine) {
            (Precision::Fast, _) | (Precision::Refined, false) => {
                self.trace_gpu(scene, rays, request, false, &mut work, wait, &mut profile)?
            }
            (Precision::Exact, _) => self.trace_gpu(scene, rays, request, true, &mut work, wait, &mut profile)?,
            (Precision::Refined, true) => {
                // The GPU finds which triangle; the host recomputes where, in f64.
                let mut host_fields = HitSink::default();
                for field in [Field::T, Field::Uv, Field::Normal] {
                    if let Some(out) = work.take(field) {
                        host_fields.set(field, out);
                    }
                }
                self.trace_gpu(scene, rays, request, false, &mut work, wait, &mut profile)?;
                for field in [Field::T, Field::Uv, Field::Normal] {
                    if let Some(out) = host_fields.take(field) {
                        work.set(field, out);
                    }
                }
                let host = Instant::now();
                let sink = Mutex::new(&mut work);
                wait.wait(&|| {
                    tiers::refine(scene, rays, cull, &mut sink.lock().unwrap_or_else(|e| e.into_inner()));
                    Ok(())
                })?;
                profile.host_f64 = host.elapsed().as_secs_f64();
            }
            (Precision::Reference, _) => {
                rays.check()?;
                let host = Instant::now();
                let sink = Mutex::new(&mut work);
                wait.wait(&|| {
                    let mut sink = sink.lock().unwrap_or_else(|e| e.into_inner());
                    tiers::reference(scene, rays, cull, query == Query::Occluded, &mut sink);
                    Ok(())
                })?;
                profile.host_f64 = host.elapsed().as_secs_f64();
            }
        }
        if let Some(out) = position {
            let hits = tiers::HitTriangles {
                prim: work.field(Field::Prim).unwrap_or_default(),
                instance: work.field(Field::Instance).unwrap_or_default(),
                geometry: work.field(Field::Geometry).unwrap_or_default(),
                t: work.field(Field::T).unwrap_or_default(),
                uv: work.field(Field::Uv).unwrap_or_default(),
                wide: precision.is_f64(),
            };
            tiers::positions(scene, rays, &hits, out);
        }
        profile.total = started.elapsed().as_secs_f64();
        *self.last_profile.lock().unwrap_or_else(|e| e.into_inner()) = profile;
        self.ctx.check_validation()
    }

    /// The pipeline backend's exact tier and sphere sets need intersection shaders to run and
    /// their side effects to be seen (lavapipe lost the exact tier's scratch stores until they
    /// were made volatile: every ray missed). One ray through each path, once per device, tells;
    /// a driver that fails gets a clear error instead of wrong answers.
    fn check_intersection_shaders(&self, probe: Probe, wait: &dyn Wait) -> Result<()> {
        if self.ctx.backend != Backend::Pipeline {
            return Ok(());
        }
        let mut known = self.intersection_shaders_run.lock().unwrap_or_else(|e| e.into_inner());
        let runs = match known[probe as usize] {
            Some(runs) => runs,
            None => *known[probe as usize].insert(self.probe(probe, wait)?),
        };
        if runs {
            return Ok(());
        }
        let (what, instead) = match probe {
            Probe::Exact => ("precision='exact'", " or precision='reference' (same answers, on the CPU)"),
            Probe::Spheres => ("spheres", ""),
        };
        Err(crate::error::Error::Unsupported(format!(
            "{} ({}) does not run the intersection shaders of {what} in ray-tracing pipelines; use backend='ray_query'{instead}",
            self.ctx.info.name, self.ctx.info.driver
        )))
    }

    /// Whether one ray down the `probe` path hits what it must.
    fn probe(&self, probe: Probe, wait: &dyn Wait) -> Result<bool> {
        use crate::geometry::arrays::{Indices, Vec3s};
        use crate::geometry::rays::{Masks, PerRay};
        use crate::geometry::vertex_format::VertexFormat;
        use crate::scene::{Instance, Mesh, IDENTITY};
        let options = crate::gpu::accel::BuildOptions {
            preference: crate::gpu::accel::BuildPreference::FastBuild,
            allow_update: false,
            compact: false,
        };
        let triangle = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        let mesh = match probe {
            Probe::Exact => Mesh::build(
                &self.ctx,
                Vec3s::F64(&triangle),
                Indices::U32(&[0, 1, 2]),
                options,
                VertexFormat::F32,
                wait,
            )?,
            Probe::Spheres => Mesh::spheres(&self.ctx, Vec3s::F64(&[0.0; 3]), PerRay::All(1.0), options, wait)?,
        };
        let instance = Instance {
            mesh: Arc::new(mesh),
            transform: IDENTITY,
            custom_index: 0,
            mask: 0xFF,
            flags: Default::default(),
        };
        let scene = Scene::build(&self.ctx, &[instance], options, wait)?;
        let rays = Rays {
            origins: Vec3s::F64(&[0.25, 0.25, 5.0]),
            directions: Vec3s::F64(&[0.0, 0.0, -1.0]),
            tmin: PerRay::All(0.0),
            tmax: PerRay::All(f64::INFINITY),
            mask: Masks::All(0xFF),
        };
        let mut prim = [0xFFu8; 4];
        let mut sink = HitSink::default();
        sink.set(Field::Prim, &mut prim);
        let exact = probe == Probe::Exact;
        let precision = if exact { Precision::Exact } else { Precision::Fast };
        let request = Request { query: Query::Closest, precision, cull: Cull::None };
        self.run_gpu(&scene, &rays, request, exact, &mut sink, wait, &mut TraceProfile::default())?;
        Ok(i32::from_ne_bytes(prim) == 0)
    }

    /// The GPU's part of a query: traversal in f32 (`exact`: through the scene's per-triangle
    /// boxes, each candidate decided by the f64 test).
    #[allow(clippy::too_many_arguments)]
    fn trace_gpu(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        exact: bool,
        sink: &mut HitSink,
        wait: &dyn Wait,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        if exact {
            self.check_intersection_shaders(Probe::Exact, wait)?;
        }
        if scene.has_spheres() {
            self.check_intersection_shaders(Probe::Spheres, wait)?;
        }
        self.run_gpu(scene, rays, request, exact, sink, wait, profile)
    }

    #[allow(clippy::too_many_arguments)]
    fn run_gpu(
        &self,
        scene: &Scene,
        rays: &Rays,
        request: Request,
        exact: bool,
        sink: &mut HitSink,
        wait: &dyn Wait,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let outputs = sink.outputs();
        // Before any exact variant: this fails on devices without shaderFloat64 (no exact modules).
        let exact_scene = if exact { Some(scene.exact(wait)?) } else { None };
        let spheres = scene.has_spheres();
        let flags = ray_flags(request.query, request.cull, self.ctx.backend, exact, scene.all_opaque(), spheres);
        let key = VariantKey { outputs, ray_flags: flags, exact, spheres };
        let variant = self.variant(key, wait)?;
        let capacity = self.chunk_rays().min(self.max_dispatch_rays()).min(rays.len()).max(1);
        let mut slots = self.take_slots(capacity, exact)?;
        let result = self.trace_chunks(
            scene,
            exact_scene.as_deref(),
            rays,
            &variant,
            outputs,
            sink,
            &mut slots,
            capacity,
            wait,
            profile,
        );
        self.return_slots(slots);
        result
    }

    #[allow(clippy::too_many_arguments)]
    fn trace_chunks(
        &self,
        scene: &Scene,
        exact: Option<&ExactScene>,
        rays: &Rays,
        variant: &Variant,
        outputs: u32,
        sink: &mut HitSink,
        slots: &mut [Slot; 2],
        capacity: usize,
        wait: &dyn Wait,
        profile: &mut TraceProfile,
    ) -> Result<()> {
        let n = rays.len();
        let mut clock = Instant::now();
        let mut lap = |into: &mut f64| {
            let now = Instant::now();
            *into += (now - clock).as_secs_f64();
            clock = now;
        };
        let stamps_lock = self.stamps.lock().unwrap_or_else(|e| e.into_inner());
        let stamps = stamps_lock.as_ref();
        let mut commands = [Commands::new(&self.ctx)?, Commands::new(&self.ctx)?];
        let mut in_flight: [Option<(usize, usize)>; 2] = [None, None];
        for (chunk, start) in (0..n).step_by(capacity).enumerate() {
            let s = chunk % 2;
            let len = capacity.min(n - start);
            lap(&mut profile.submit);
            commands[s].wait(wait)?;
            lap(&mut profile.wait);
            if let Some((prev_start, prev_len)) = in_flight[s].take() {
                if let Some(stamps) = stamps {
                    stamps.add(&self.ctx, s, profile)?;
                }
                unpack(&slots[s], prev_start, prev_len, outputs, sink);
            }
            lap(&mut profile.unpack);
            let slot = &mut slots[s];
            let masks_at = slot.masks_offset();
            let packed = slot.rays_host.mapped_mut().expect("ray staging is host-visible");
            // SAFETY: the staging buffer holds `capacity` rays of 8 f32 (8 f64 in an exact slot),
            // aligned for either. On an invalid ray, dropping `commands` waits for the chunks in flight.
            unsafe {
                if slot.exact {
                    let out = std::slice::from_raw_parts_mut(packed.as_mut_ptr() as *mut f64, len * RAY_FLOATS);
                    rays.pack_f64(start, out, scene.center)?;
                } else {
                    let out = std::slice::from_raw_parts_mut(packed.as_mut_ptr() as *mut f32, len * RAY_FLOATS);
                    rays.pack(start, out, scene.center)?;
                }
            }
            if let Masks::Each(masks) = rays.mask {
                for (dst, m) in packed[masks_at..masks_at + 4 * len].chunks_exact_mut(4).zip(&masks[start..start + len])
                {
                    dst.copy_from_slice(&(*m as u32).to_ne_bytes());
                }
            }
            lap(&mut profile.pack);
            profile.chunks += 1;
            commands[s].begin()?;
            let job = Chunk { scene, exact, variant, outputs, slot, slot_index: s, len, mask: rays.mask };
            self.record_chunk(commands[s].buffer, &job, stamps);
            commands[s].submit()?;
            in_flight[s] = Some((start, len));
        }
        lap(&mut profile.submit);
        for s in 0..2 {
            commands[s].wait(wait)?;
            lap(&mut profile.wait);
            if let Some((start, len)) = in_flight[s].take() {
                if let Some(stamps) = stamps {
                    stamps.add(&self.ctx, s, profile)?;
                }
                unpack(&slots[s], start, len, outputs, sink);
            }
            lap(&mut profile.unpack);
        }
        Ok(())
    }

    fn record_chunk(&self, cmd: vk::CommandBuffer, job: &Chunk, stamps: Option<&Stamps>) {
        let Chunk { scene, exact, variant, outputs, slot, slot_index, len, mask } = *job;
        let stamp = |k| {
            if let Some(stamps) = stamps {
                stamps.write(&self.ctx, cmd, slot_index, k);
            }
        };
        if let Some(stamps) = stamps {
            stamps.reset(&self.ctx, cmd, slot_index);
        }
        stamp(0);
        let ctx = &self.ctx;
        let device = &ctx.device;
        let (bind_point, shader_stage) = match ctx.backend {
            Backend::RayQuery => (vk::PipelineBindPoint::COMPUTE, vk::PipelineStageFlags::COMPUTE_SHADER),
            Backend::Pipeline => {
                (vk::PipelineBindPoint::RAY_TRACING_KHR, vk::PipelineStageFlags::RAY_TRACING_SHADER_KHR)
            }
        };
        if let Some((rays_device, _)) = &slot.device {
            let masks_at = slot.masks_offset() as u64;
            let rays_region = vk::BufferCopy::default().size((len * Slot::ray_bytes(slot.exact)) as u64);
            let masks_region = vk::BufferCopy::default().src_offset(masks_at).dst_offset(masks_at).size(4 * len as u64);
            let regions = match mask {
                Masks::Each(_) => vec![rays_region, masks_region],
                Masks::All(_) => vec![rays_region],
            };
            unsafe { device.cmd_copy_buffer(cmd, slot.rays_host.raw(), rays_device.raw(), &regions) };
            memory_barrier(
                ctx,
                cmd,
                vk::PipelineStageFlags::TRANSFER,
                vk::AccessFlags::TRANSFER_WRITE,
                shader_stage,
                vk::AccessFlags::SHADER_READ,
            );
        }
        stamp(1);
        let mut params = Params { rays: slot.rays_address(), count: len as u32, ..Default::default() };
        match mask {
            Masks::All(m) => params.ray_mask = m as u32,
            Masks::Each(_) => params.masks = slot.rays_address() + slot.masks_offset() as u64,
        }
        match exact {
            Some(exact) => {
                params.instances = exact.instances_address();
                params.tlas = exact.tlas_address();
                params.scratch = slot.hits_address() + slot.scratch_offset() as u64;
                params.bounds = exact.bounds_f32();
            }
            None => {
                params.instances = scene.instance_geometries_address();
                params.tlas = scene.tlas_address();
            }
        }
        for field in FIELDS {
            if outputs & field.bit() != 0 {
                params.outputs[field as usize] = slot.hits_address() + slot.field_offset(field) as u64;
            }
        }
        let stages = push_constant_stages(ctx.backend);
        unsafe {
            device.cmd_bind_pipeline(cmd, bind_point, variant.pipeline);
            device.cmd_push_constants(cmd, self.layout, stages, 0, params.bytes());
        }
        match (&variant.sbt, ctx.pipeline_ext.as_ref()) {
            (Some(sbt), Some(rt)) => unsafe {
                let callable = vk::StridedDeviceAddressRegionKHR::default();
                rt.cmd_trace_rays(cmd, &sbt.raygen, &sbt.miss, &sbt.hit, &callable, len as u32, 1, 1);
            },
            _ => unsafe { device.cmd_dispatch(cmd, (len as u32).div_ceil(self.local_size), 1, 1) },
        }
        stamp(2);
        match &slot.device {
            Some((_, hits_device)) => {
                memory_barrier(
                    ctx,
                    cmd,
                    shader_stage,
                    vk::AccessFlags::SHADER_WRITE,
                    vk::PipelineStageFlags::TRANSFER,
                    vk::AccessFlags::TRANSFER_READ,
                );
                let regions: Vec<vk::BufferCopy> = FIELDS
                    .iter()
                    .filter(|f| outputs & f.bit() != 0)
                    .map(|f| {
                        let offset = slot.field_offset(*f) as u64;
                        vk::BufferCopy::default()
                            .src_offset(offset)
                            .dst_offset(offset)
                            .size((len * f.bytes_per_ray(slot.exact)) as u64)
                    })
                    .collect();
                unsafe { device.cmd_copy_buffer(cmd, hits_device.raw(), slot.hits_host.raw(), &regions) };
                memory_barrier(
                    ctx,
                    cmd,
                    vk::PipelineStageFlags::TRANSFER,
                    vk::AccessFlags::TRANSFER_WRITE,
                    vk::PipelineStageFlags::HOST,
                    vk::AccessFlags::HOST_READ,
                );
            }
            None => memory_barrier(
                ctx,
                cmd,
                shader_stage,
                vk::AccessFlags::SHADER_WRITE,
                vk::PipelineStageFlags::HOST,
                vk::AccessFlags::HOST_READ,
            ),
        }
        stamp(3);
    }
}

/// One chunk's trace, as recorded into a command buffer.
#[derive(Clone, Copy)]
struct Chunk<'a> {
    scene: &'a Scene,
    exact: Option<&'a ExactScene>,
    variant: &'a Variant,
    outputs: u32,
    slot: &'a Slot,
    slot_index: usize,
    len: usize,
    mask: Masks<'a>,
}

/// Copies a finished chunk's requested fields into the caller's arrays, on all cores.
fn unpack(slot: &Slot, start: usize, len: usize, outputs: u32, sink: &mut HitSink) {
    const PIECE_BYTES: usize = 1 << 20;
    let hits = slot.hits_host.mapped().expect("hit readback is host-visible");
    for field in FIELDS {
        if outputs & field.bit() == 0 {
            continue;
        }
        let Some(out) = sink.fields[field as usize].as_deref_mut() else { continue };
        let width = field.bytes_per_ray(slot.exact);
        let from = slot.field_offset(field);
        out[start * width..(start + len) * width]
            .par_chunks_mut(PIECE_BYTES)
            .zip(hits[from..from + len * width].par_chunks(PIECE_BYTES))
            .for_each(|(dst, src)| dst.copy_from_slice(src));
    }
}

fn specialization_entries() -> [vk::SpecializationMapEntry; 3] {
    [0u32, 1, 2].map(|id| vk::SpecializationMapEntry::default().constant_id(id).offset(4 * id).size(4))
}

fn as_bytes(values: &[u32]) -> &[u8] {
    // SAFETY: u32 values viewed as their bytes.
    unsafe { std::slice::from_raw_parts(values.as_ptr() as *const u8, 4 * values.len()) }
}

/// A shader binding table's layout: the raygen, miss and hit regions (offset, stride, size), and
/// where each group's record lies (raygen, miss, then the hit groups in order).
#[derive(Debug, PartialEq)]
struct SbtLayout {
    regions: [(u64, u64, u64); 3],
    records: Vec<u64>,
    total: u64,
    base_alignment: u64,
}

impl SbtLayout {
    fn new(handle_size: u64, handle_alignment: u64, base_alignment: u64, hit_groups: u64) -> SbtLayout {
        let stride = align_up(handle_size, handle_alignment);
        let raygen = align_up(stride, base_alignment);
        let hits = align_up(stride * hit_groups, base_alignment);
        // raygen: size must equal stride.
        let regions = [(0, raygen, raygen), (raygen, stride, raygen), (2 * raygen, stride, hits)];
        let records = [0, raygen].into_iter().chain((0..hit_groups).map(|k| 2 * raygen + k * stride)).collect();
        SbtLayout { regions, records, total: 2 * raygen + hits, base_alignment }
    }
}

impl Drop for Tracer {
    fn drop(&mut self) {
        let device = &self.ctx.device;
        unsafe {
            let _ = device.device_wait_idle();
            for variant in self.variants.get_mut().unwrap_or_else(|e| e.into_inner()).values() {
                device.destroy_pipeline(variant.pipeline, None);
            }
            for module in &self.modules {
                device.destroy_shader_module(*module, None);
            }
            device.destroy_pipeline_layout(self.layout, None);
            if let Some(stamps) = self.stamps.get_mut().unwrap_or_else(|e| e.into_inner()) {
                device.destroy_query_pool(stamps.pool, None);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn params_match_the_shader_block() {
        // 12 addresses, a count, 6 floats and a mask: the GLSL block's std430 size.
        assert_eq!(PARAMS_BYTES, 128);
    }

    #[test]
    fn hit_fields_are_laid_out_aligned() {
        for (i, f) in FIELDS.iter().enumerate() {
            assert_eq!(*f as usize, i);
        }
        // 7 rays: odd counts must still leave every f64 array 8-byte aligned.
        let (offsets, total) = Slot::layout(7, true);
        assert!(offsets.iter().all(|o| o % 8 == 0));
        assert_eq!(offsets[Field::Prim as usize], 56);
        assert_eq!(total, offsets[FIELD_COUNT] + 7 * EXACT_SCRATCH_BYTES);
        let (_, fast_total) = Slot::layout(8, false);
        assert_eq!(fast_total, 8 * 40);
    }

    #[test]
    fn sbt_layout_follows_device_alignments() {
        // lavapipe: handle 32, handle alignment 16, base alignment 32; one hit group.
        let lavapipe = SbtLayout::new(32, 16, 32, 1);
        assert_eq!(lavapipe.records, [0, 32, 64]);
        assert_eq!(lavapipe.regions[0], (0, 32, 32));
        // H100/H200: handle 32, handle alignment 32, base alignment 64; triangles and spheres.
        let nvidia = SbtLayout::new(32, 32, 64, 2);
        assert_eq!(nvidia.records, [0, 64, 128, 160]);
        let (offset, stride, size) = nvidia.regions[0];
        assert_eq!((offset, stride), (0, size), "raygen size equals its stride");
        assert_eq!(nvidia.regions[2], (128, 32, 64));
        for (offset, _, _) in nvidia.regions {
            assert_eq!(offset % 64, 0);
        }
        assert_eq!(nvidia.total, 192);
    }

    #[test]
    fn occlusion_flags_terminate_on_first_hit() {
        for backend in [Backend::RayQuery, Backend::Pipeline] {
            for exact in [false, true] {
                let flags = |query| ray_flags(query, Cull::None, backend, exact, true, false);
                assert_ne!(flags(Query::Occluded) & RAY_FLAG_TERMINATE_ON_FIRST_HIT, 0);
                assert_eq!(flags(Query::Closest) & RAY_FLAG_TERMINATE_ON_FIRST_HIT, 0);
                // The exact tier's structures are all AABBs.
                assert_eq!(ray_flags(Query::Closest, Cull::None, backend, true, true, false) & RAY_FLAG_SKIP_AABBS, 0);
                // Spheres are boxes too.
                assert_eq!(ray_flags(Query::Closest, Cull::None, backend, false, true, true) & RAY_FLAG_SKIP_AABBS, 0);
            }
        }
        let pipeline = |query, cull, all_opaque| ray_flags(query, cull, Backend::Pipeline, false, all_opaque, false);
        assert_ne!(
            ray_flags(Query::Closest, Cull::None, Backend::RayQuery, false, true, false) & RAY_FLAG_SKIP_AABBS,
            0
        );
        assert_ne!(pipeline(Query::Occluded, Cull::None, true) & RAY_FLAG_SKIP_CLOSEST_HIT_SHADER, 0);
        assert_eq!(pipeline(Query::Closest, Cull::None, true) & RAY_FLAG_SKIP_AABBS, 0);
        // Non-opaque instances must not be culled; culling follows the query.
        assert_eq!(pipeline(Query::Closest, Cull::None, false) & RAY_FLAG_CULL_NO_OPAQUE, 0);
        assert_ne!(pipeline(Query::Closest, Cull::Back, true) & RAY_FLAG_CULL_BACK_FACING_TRIANGLES, 0);
        assert_ne!(pipeline(Query::Closest, Cull::Front, true) & RAY_FLAG_CULL_FRONT_FACING_TRIANGLES, 0);
    }
}
