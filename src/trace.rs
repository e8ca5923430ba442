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

use crate::context::{Backend, Commands, Context, Wait};
use crate::error::{invalid_value, Result, VkResultExt};
use crate::input::{Rays, RAY_FLOATS};
use crate::memory::{align_up, memory_barrier, Buffer, MemoryLocation, Uploads};
use crate::scene::Scene;
use crate::shaders;

/// What a query asks of each ray.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Query {
    /// The closest hit in [tmin, tmax].
    Closest,
    /// Whether anything is hit in [tmin, tmax]; traversal stops at the first hit.
    Occluded,
}

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
    pub fn bytes_per_ray(self) -> usize {
        match self {
            Field::Uv => 8,
            Field::Normal => 12,
            _ => 4,
        }
    }

    fn bit(self) -> u32 {
        1 << self as u32
    }
}

/// Where the caller wants each requested field written, as raw bytes of its output array.
#[derive(Default)]
pub struct HitSink<'a> {
    fields: [Option<&'a mut [u8]>; FIELD_COUNT],
}

impl<'a> HitSink<'a> {
    pub fn set(&mut self, field: Field, out: &'a mut [u8]) {
        self.fields[field as usize] = Some(out);
    }

    fn outputs(&self) -> u32 {
        FIELDS.iter().filter(|f| self.fields[**f as usize].is_some()).map(|f| f.bit()).sum()
    }
}

// Ray flags (SPIR-V RayFlags).
const RAY_FLAG_TERMINATE_ON_FIRST_HIT: u32 = 0x4;
const RAY_FLAG_SKIP_CLOSEST_HIT_SHADER: u32 = 0x8;
const RAY_FLAG_CULL_NO_OPAQUE: u32 = 0x80;
const RAY_FLAG_SKIP_AABBS: u32 = 0x200;

/// Ray flags resolved statically for a query on a scene: every triangle is opaque and no scene
/// holds AABBs yet, so non-opaque and procedural paths are culled at compile time.
fn ray_flags(query: Query, backend: Backend) -> u32 {
    let mut flags = RAY_FLAG_CULL_NO_OPAQUE;
    // The pipeline backend skips AABBs with a pipeline flag instead, which needs no device feature.
    if backend == Backend::RayQuery {
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
    instances: u64,
    tlas: u64,
    outputs: [u64; FIELD_COUNT],
    count: u32,
    pad: u32,
}

impl Params {
    fn bytes(&self) -> &[u8] {
        // SAFETY: plain old data, no padding holes (count + pad complete the last 8 bytes).
        unsafe { std::slice::from_raw_parts(self as *const Params as *const u8, std::mem::size_of::<Params>()) }
    }
}

const PARAMS_BYTES: u32 = std::mem::size_of::<Params>() as u32;
const _: () = assert!(PARAMS_BYTES <= 128, "within the push-constant size every device offers");

/// Bytes of all hit fields of one ray.
const HIT_BYTES_PER_RAY: usize = 40;

#[derive(Clone, Copy, PartialEq, Eq, Hash)]
struct VariantKey {
    outputs: u32,
    ray_flags: u32,
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

/// Host-visible staging for one chunk in flight (plus device copies on discrete GPUs).
struct Slot {
    rays_host: Buffer,
    hits_host: Buffer,
    device: Option<(Buffer, Buffer)>,
    capacity: usize,
}

impl Slot {
    fn new(ctx: &Arc<Context>, capacity: usize) -> Result<Slot> {
        use vk::BufferUsageFlags as U;
        let storage = U::STORAGE_BUFFER | U::SHADER_DEVICE_ADDRESS;
        let ray_bytes = (capacity * RAY_FLOATS * 4) as u64;
        let hit_bytes = (capacity * HIT_BYTES_PER_RAY) as u64;
        if ctx.unified_memory {
            Ok(Slot {
                rays_host: Buffer::new(ctx, ray_bytes, storage, MemoryLocation::CpuToGpu, "rays")?,
                hits_host: Buffer::new(ctx, hit_bytes, storage, MemoryLocation::GpuToCpu, "hits")?,
                device: None,
                capacity,
            })
        } else {
            Ok(Slot {
                rays_host: Buffer::new(ctx, ray_bytes, U::TRANSFER_SRC, MemoryLocation::CpuToGpu, "rays staging")?,
                hits_host: Buffer::new(ctx, hit_bytes, U::TRANSFER_DST, MemoryLocation::GpuToCpu, "hits readback")?,
                device: Some((
                    Buffer::new(ctx, ray_bytes, storage | U::TRANSFER_DST, MemoryLocation::GpuOnly, "rays")?,
                    Buffer::new(ctx, hit_bytes, storage | U::TRANSFER_SRC, MemoryLocation::GpuOnly, "hits")?,
                )),
                capacity,
            })
        }
    }

    /// Byte offset of a field's array within the hits buffer.
    fn field_offset(&self, field: Field) -> usize {
        FIELDS[..field as usize].iter().map(|f| f.bytes_per_ray()).sum::<usize>() * self.capacity
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

impl Tracer {
    pub fn new(ctx: &Arc<Context>) -> Result<Tracer> {
        let stages = match ctx.backend {
            Backend::RayQuery => vk::ShaderStageFlags::COMPUTE,
            Backend::Pipeline => {
                vk::ShaderStageFlags::RAYGEN_KHR
                    | vk::ShaderStageFlags::CLOSEST_HIT_KHR
                    | vk::ShaderStageFlags::MISS_KHR
            }
        };
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
            chunk_rays: AtomicUsize::new(default_chunk_rays(ctx)),
            local_size: 64u32
                .min(ctx.limits.max_compute_work_group_size[0])
                .min(ctx.limits.max_compute_work_group_invocations),
        };
        let sources: &[&[u8]] = match ctx.backend {
            Backend::RayQuery => &[shaders::TRACE_RAY_QUERY],
            Backend::Pipeline => &[shaders::RAYGEN, shaders::MISS, shaders::CLOSEST_HIT],
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
            .module(self.modules[0])
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
        let stages = [
            stage(vk::ShaderStageFlags::RAYGEN_KHR, self.modules[0]),
            stage(vk::ShaderStageFlags::MISS_KHR, self.modules[1]),
            stage(vk::ShaderStageFlags::CLOSEST_HIT_KHR, self.modules[2]),
        ];
        let general = |index| {
            vk::RayTracingShaderGroupCreateInfoKHR::default()
                .ty(vk::RayTracingShaderGroupTypeKHR::GENERAL)
                .general_shader(index)
                .closest_hit_shader(vk::SHADER_UNUSED_KHR)
                .any_hit_shader(vk::SHADER_UNUSED_KHR)
                .intersection_shader(vk::SHADER_UNUSED_KHR)
        };
        let groups = [
            general(0),
            general(1),
            vk::RayTracingShaderGroupCreateInfoKHR::default()
                .ty(vk::RayTracingShaderGroupTypeKHR::TRIANGLES_HIT_GROUP)
                .general_shader(vk::SHADER_UNUSED_KHR)
                .closest_hit_shader(2)
                .any_hit_shader(vk::SHADER_UNUSED_KHR)
                .intersection_shader(vk::SHADER_UNUSED_KHR),
        ];
        // No scene holds AABBs yet: traversal skips them for the whole pipeline (a flag Vulkan
        // allows only with the primitive-culling feature).
        let flags = if ctx.limits.ray_traversal_primitive_culling {
            vk::PipelineCreateFlags::RAY_TRACING_SKIP_AABBS_KHR
        } else {
            vk::PipelineCreateFlags::empty()
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
                for (group, offset) in layout.offsets.iter().enumerate() {
                    let at = pad + *offset as usize;
                    out[at..at + handle_size].copy_from_slice(&handles[group * handle_size..(group + 1) * handle_size]);
                }
            },
        )?;
        ctx.run_commands(wait, |cmd| {
            uploads.record(ctx, cmd);
            Ok(())
        })?;
        let region = |group: usize| {
            vk::StridedDeviceAddressRegionKHR::default()
                .device_address(start + layout.offsets[group])
                .stride(layout.strides[group])
                .size(layout.sizes[group])
        };
        Ok(ShaderBindingTable { raygen: region(0), miss: region(1), hit: region(2), _buffer: buffer })
    }

    fn take_slots(&self, capacity: usize) -> Result<[Slot; 2]> {
        let mut idle = self.idle_slots.lock().unwrap_or_else(|e| e.into_inner());
        idle.retain(|s| s.capacity >= capacity);
        let mut take = || idle.pop().map_or_else(|| Slot::new(&self.ctx, capacity), Ok);
        Ok([take()?, take()?])
    }

    fn return_slots(&self, slots: [Slot; 2]) {
        let mut idle = self.idle_slots.lock().unwrap_or_else(|e| e.into_inner());
        idle.extend(slots);
        // Two slots serve one caller; keep at most two callers' worth around.
        idle.truncate(4);
    }

    /// Traces `rays` against `scene`, writing the fields `sink` asks for. Each chunk's rays are
    /// checked as they are packed; an invalid ray stops the trace with an error naming it (chunks
    /// already in flight finish first, and what they wrote is not the caller's to read). `wait`
    /// runs every blocking wait (the binding frees the GIL).
    pub fn trace(&self, scene: &Scene, rays: &Rays, query: Query, sink: &mut HitSink, wait: &dyn Wait) -> Result<()> {
        let started = Instant::now();
        rays.check_shapes()?;
        let mut profile = TraceProfile { rays: rays.len(), ..Default::default() };
        let n = rays.len();
        for field in FIELDS {
            if let Some(out) = &sink.fields[field as usize] {
                if out.len() != n * field.bytes_per_ray() {
                    return Err(invalid_value(format!("output for {field:?} has {} bytes for {n} rays", out.len())));
                }
            }
        }
        let outputs = sink.outputs();
        if n == 0 || outputs == 0 {
            return Ok(());
        }
        let key = VariantKey { outputs, ray_flags: ray_flags(query, self.ctx.backend) };
        let variant = self.variant(key, wait)?;
        let capacity = self.chunk_rays().min(self.max_dispatch_rays()).min(n).max(1);
        let mut slots = self.take_slots(capacity)?;
        let result = self.trace_chunks(scene, rays, &variant, outputs, sink, &mut slots, capacity, wait, &mut profile);
        self.return_slots(slots);
        result?;
        profile.total = started.elapsed().as_secs_f64();
        *self.last_profile.lock().unwrap_or_else(|e| e.into_inner()) = profile;
        self.ctx.check_validation()
    }

    #[allow(clippy::too_many_arguments)]
    fn trace_chunks(
        &self,
        scene: &Scene,
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
            let packed = slot.rays_host.mapped_mut().expect("ray staging is host-visible");
            // SAFETY: the staging buffer holds `capacity` rays of 8 f32 each, suitably aligned.
            let floats = unsafe { std::slice::from_raw_parts_mut(packed.as_mut_ptr() as *mut f32, len * RAY_FLOATS) };
            // On an invalid ray, dropping `commands` waits for the chunks in flight.
            rays.pack(start, floats)?;
            lap(&mut profile.pack);
            profile.chunks += 1;
            commands[s].begin()?;
            self.record_chunk(commands[s].buffer, scene, variant, outputs, slot, s, len, stamps);
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

    #[allow(clippy::too_many_arguments)]
    fn record_chunk(
        &self,
        cmd: vk::CommandBuffer,
        scene: &Scene,
        variant: &Variant,
        outputs: u32,
        slot: &Slot,
        slot_index: usize,
        len: usize,
        stamps: Option<&Stamps>,
    ) {
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
            let region = [vk::BufferCopy::default().size((len * RAY_FLOATS * 4) as u64)];
            unsafe { device.cmd_copy_buffer(cmd, slot.rays_host.raw(), rays_device.raw(), &region) };
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
        let mut params = Params {
            rays: slot.rays_address(),
            instances: scene.instance_geometries_address(),
            tlas: scene.tlas_address(),
            count: len as u32,
            ..Default::default()
        };
        for field in FIELDS {
            if outputs & field.bit() != 0 {
                params.outputs[field as usize] = slot.hits_address() + slot.field_offset(field) as u64;
            }
        }
        let stages = match ctx.backend {
            Backend::RayQuery => vk::ShaderStageFlags::COMPUTE,
            Backend::Pipeline => {
                vk::ShaderStageFlags::RAYGEN_KHR
                    | vk::ShaderStageFlags::CLOSEST_HIT_KHR
                    | vk::ShaderStageFlags::MISS_KHR
            }
        };
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
                            .size((len * f.bytes_per_ray()) as u64)
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

/// Copies a finished chunk's requested fields into the caller's arrays, on all cores.
fn unpack(slot: &Slot, start: usize, len: usize, outputs: u32, sink: &mut HitSink) {
    const PIECE_BYTES: usize = 1 << 20;
    let hits = slot.hits_host.mapped().expect("hit readback is host-visible");
    for field in FIELDS {
        if outputs & field.bit() == 0 {
            continue;
        }
        let Some(out) = sink.fields[field as usize].as_deref_mut() else { continue };
        let width = field.bytes_per_ray();
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

/// Offsets, strides and sizes of the raygen, miss and hit regions of a shader binding table.
#[derive(Debug, PartialEq)]
struct SbtLayout {
    offsets: [u64; 3],
    strides: [u64; 3],
    sizes: [u64; 3],
    total: u64,
    base_alignment: u64,
}

impl SbtLayout {
    fn new(handle_size: u64, handle_alignment: u64, base_alignment: u64) -> SbtLayout {
        let stride = align_up(handle_size, handle_alignment);
        let region = align_up(stride, base_alignment);
        // raygen: size must equal stride.
        let strides = [region, stride, stride];
        let sizes = [region, region, region];
        SbtLayout { offsets: [0, region, 2 * region], strides, sizes, total: 3 * region, base_alignment }
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
        // 10 addresses and a count, padded to 8 bytes: the GLSL block's std430 size.
        assert_eq!(PARAMS_BYTES, 88);
    }

    #[test]
    fn hit_fields_fill_their_record() {
        assert_eq!(FIELDS.iter().map(|f| f.bytes_per_ray()).sum::<usize>(), HIT_BYTES_PER_RAY);
        for (i, f) in FIELDS.iter().enumerate() {
            assert_eq!(*f as usize, i);
        }
    }

    #[test]
    fn sbt_layout_follows_device_alignments() {
        // lavapipe: handle 32, handle alignment 16, base alignment 32.
        let lavapipe = SbtLayout::new(32, 16, 32);
        assert_eq!(lavapipe.offsets, [0, 32, 64]);
        assert_eq!(lavapipe.strides, [32, 32, 32]);
        // H100/H200: handle 32, handle alignment 32, base alignment 64.
        let nvidia = SbtLayout::new(32, 32, 64);
        assert_eq!(nvidia.offsets, [0, 64, 128]);
        assert_eq!(nvidia.strides[0], nvidia.sizes[0]);
        assert_eq!(nvidia.strides[1], 32);
        for offset in nvidia.offsets {
            assert_eq!(offset % 64, 0);
        }
    }

    #[test]
    fn occlusion_flags_terminate_on_first_hit() {
        for backend in [Backend::RayQuery, Backend::Pipeline] {
            assert_ne!(ray_flags(Query::Occluded, backend) & RAY_FLAG_TERMINATE_ON_FIRST_HIT, 0);
            assert_eq!(ray_flags(Query::Closest, backend) & RAY_FLAG_TERMINATE_ON_FIRST_HIT, 0);
        }
        assert_ne!(ray_flags(Query::Occluded, Backend::Pipeline) & RAY_FLAG_SKIP_CLOSEST_HIT_SHADER, 0);
        assert_eq!(ray_flags(Query::Closest, Backend::Pipeline) & RAY_FLAG_SKIP_AABBS, 0);
    }
}
