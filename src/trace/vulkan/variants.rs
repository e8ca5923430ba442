//! Pipeline variants: one per (outputs, ray flags, tier, sphere shader) a query needs, compiled
//! once per device from specialization constants, with its shader binding table in the pipeline
//! backend. The cache's lock is held only to look up and insert: variants are built outside it.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use ash::vk;

use crate::error::{vulkan_error, Result, VkResultExt};
use crate::geometry::align::align_up;
use crate::geometry::rays::RayLayout;
use crate::gpu::context::{Backend, Context};
use crate::gpu::memory::{Buffer, Uploads};
use crate::gpu::records::Params;
use crate::gpu::shaders;
use crate::trace::request::{Cull, Query};

/// What a variant is specialized to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct VariantKey {
    /// OUTPUTS: the hit fields written.
    pub outputs: u32,
    /// RAY_FLAGS: resolved statically by `ray_flags`.
    pub ray_flags: u32,
    /// The exact tier's f64 test through per-triangle boxes.
    pub exact: bool,
    /// The scene holds sphere sets (boxes for the sphere shader).
    pub spheres: bool,
    /// QUERY: `Query::shader_query`.
    pub query: u32,
    /// CLOSED_EDGES (exact tier): contacts rather than crossings (`Request::contacts`).
    pub closed_edges: bool,
    /// The scene holds triangles whose opacity traversal reads: the pipeline's triangles get the
    /// any-hit stage that reads it.
    pub opacity: bool,
    /// OPACITY_THRESHOLD's bits (f32); the default where the scene has no opacity, so that
    /// opaque scenes share one variant whatever the threshold asked.
    pub threshold_bits: u32,
    /// RAY_SOURCE: `RAYS_FROM_BUFFER` (or its leaner layouts, `ray_source`), `RAYS_FROM_SENSOR`
    /// or `RAYS_FROM_POINTS`.
    pub ray_source: u32,
}

/// RAY_SOURCE: rays packed into the rays buffer.
pub const RAYS_FROM_BUFFER: u32 = 0;
/// RAY_SOURCE: rays the shaders generate from a `Sensor` record.
pub const RAYS_FROM_SENSOR: u32 = 1;
/// RAY_SOURCE (exact tier): one ray from each point of a closest-point search's buffer, described
/// by a `PointRays` record (the sign of a signed distance).
pub const RAYS_FROM_POINTS: u32 = 2;
/// RAY_SOURCE: rays in the buffer as `RayLayout::Compact` lays them out (origin and direction a
/// ray, the interval in a header).
pub const RAYS_FROM_COMPACT: u32 = 3;
/// RAY_SOURCE: rays in the buffer as `RayLayout::Directions` lays them out (a direction a ray,
/// the origin and interval in a header).
pub const RAYS_FROM_DIRECTIONS: u32 = 4;

/// The RAY_SOURCE that reads rays packed in `layout`.
pub fn ray_source(layout: RayLayout) -> u32 {
    match layout {
        RayLayout::Full => RAYS_FROM_BUFFER,
        RayLayout::Compact => RAYS_FROM_COMPACT,
        RayLayout::Directions => RAYS_FROM_DIRECTIONS,
    }
}

impl VariantKey {
    /// Whether the pipeline backend's triangles go through an any-hit stage, and which: every
    /// hit (QUERY_ALL) or opacity (scenes with opacity, transmittance).
    fn any_hit(&self) -> Option<AnyHit> {
        if self.exact {
            return None;
        }
        if self.query == Query::All.shader_query() {
            Some(AnyHit::All)
        } else if self.opacity || self.query == Query::Transmit.shader_query() {
            Some(AnyHit::Opacity)
        } else {
            None
        }
    }
}

/// The shader stages a variant has, by role.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// Ray-query backend: one compute shader traces each ray in a loop over its candidates.
    Compute,
    RayGeneration,
    Miss,
    ClosestHit,
    AnyHit(AnyHit),
    /// The exact tier's f64 test, for its per-triangle boxes.
    ExactIntersection,
    /// The sphere sets' intersection shader.
    SphereIntersection,
}

impl Stage {
    pub fn name(self) -> &'static str {
        match self {
            Stage::Compute => "compute (ray query)",
            Stage::RayGeneration => "ray generation",
            Stage::Miss => "miss",
            Stage::ClosestHit => "closest-hit",
            Stage::AnyHit(AnyHit::All) => "any-hit (every hit)",
            Stage::AnyHit(AnyHit::Opacity) => "any-hit (opacity)",
            Stage::ExactIntersection => "intersection (exact f64 test)",
            Stage::SphereIntersection => "intersection (spheres)",
        }
    }
}

impl VariantKey {
    /// The stages of this variant on `backend`, in the pipeline's stage order.
    pub fn stages(&self, backend: Backend) -> Vec<Stage> {
        if backend == Backend::RayQuery {
            return vec![Stage::Compute];
        }
        let mut stages = vec![Stage::RayGeneration, Stage::Miss];
        if self.exact {
            stages.push(Stage::ExactIntersection);
            return stages;
        }
        // Queries that skip the closest-hit shader (occlusion, every hit, transmittance) have none.
        if self.ray_flags & RAY_FLAG_SKIP_CLOSEST_HIT_SHADER == 0 {
            stages.push(Stage::ClosestHit);
        }
        stages.extend(self.any_hit().map(Stage::AnyHit));
        if self.spheres {
            stages.push(Stage::SphereIntersection);
        }
        stages
    }

    /// The branches the ray-query backend's candidate loop keeps for this variant (the others
    /// are compiled out by the specialization constants).
    pub fn candidate_branches(&self) -> Vec<&'static str> {
        let mut branches = Vec::new();
        let query = self.query;
        if self.exact {
            branches.push("boxes: the f64 test of each box's triangle");
            return branches;
        }
        if query == Query::All.shader_query() {
            branches.push("triangles: every candidate kept (all hits, counts)");
        } else if query == Query::Transmit.shader_query() {
            branches.push("triangles: every candidate multiplies the light left");
        } else if self.ray_flags & RAY_FLAG_CULL_NO_OPAQUE == 0 {
            branches.push("triangles: non-opaque candidates confirmed where their opacity reaches the threshold");
        }
        if self.ray_flags & RAY_FLAG_SKIP_AABBS == 0 {
            branches.push("boxes: spheres intersected and committed");
        }
        branches
    }
}

/// The names of the ray flags set in `flags`.
pub fn ray_flag_names(flags: u32) -> Vec<&'static str> {
    [
        (RAY_FLAG_NO_OPAQUE, "NoOpaque"),
        (RAY_FLAG_TERMINATE_ON_FIRST_HIT, "TerminateOnFirstHit"),
        (RAY_FLAG_SKIP_CLOSEST_HIT_SHADER, "SkipClosestHitShader"),
        (RAY_FLAG_CULL_BACK_FACING_TRIANGLES, "CullBackFacingTriangles"),
        (RAY_FLAG_CULL_FRONT_FACING_TRIANGLES, "CullFrontFacingTriangles"),
        (RAY_FLAG_CULL_NO_OPAQUE, "CullNoOpaque"),
        (RAY_FLAG_SKIP_AABBS, "SkipAABBs"),
    ]
    .into_iter()
    .filter(|(bit, _)| flags & bit != 0)
    .map(|(_, name)| name)
    .collect()
}

/// The pipeline backend's any-hit shaders.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AnyHit {
    /// any_hit_all.rahit: counts and keeps every hit.
    All,
    /// any_hit_opacity.rahit: lets rays through translucent triangles; multiplies transmittance.
    Opacity,
}

/// Ray flags resolved statically for a query on a scene: where every triangle is opaque the
/// non-opaque path is culled at compile time; AABBs are the exact tier's boxes and sphere sets',
/// so procedural paths are culled too where no AABB can be met; culling is the query's. The exact
/// tier's shader reads the culling bits itself (they do not apply to boxes). Queries that meet every
/// hit make triangles non-opaque, so that each comes to the any-hit stage (or the ray query's
/// candidate loop), which keeps it and goes on.
pub fn ray_flags(query: Query, cull: Cull, backend: Backend, exact: bool, all_opaque: bool, spheres: bool) -> u32 {
    let every_triangle = query.meets_every_hit() && !exact;
    let mut flags = match (every_triangle, all_opaque) {
        (true, _) => RAY_FLAG_NO_OPAQUE,
        (false, true) => RAY_FLAG_CULL_NO_OPAQUE,
        (false, false) => 0,
    };
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
    }
    if backend == Backend::Pipeline && (query == Query::Occluded || every_triangle) {
        flags |= RAY_FLAG_SKIP_CLOSEST_HIT_SHADER;
    }
    flags
}

// Ray flags (SPIR-V RayFlags; GLSL's gl_RayFlags*EXT).
pub const RAY_FLAG_NO_OPAQUE: u32 = 0x2;
pub const RAY_FLAG_TERMINATE_ON_FIRST_HIT: u32 = 0x4;
pub const RAY_FLAG_SKIP_CLOSEST_HIT_SHADER: u32 = 0x8;
pub const RAY_FLAG_CULL_BACK_FACING_TRIANGLES: u32 = 0x10;
pub const RAY_FLAG_CULL_FRONT_FACING_TRIANGLES: u32 = 0x20;
pub const RAY_FLAG_CULL_NO_OPAQUE: u32 = 0x80;
pub const RAY_FLAG_SKIP_AABBS: u32 = 0x200;

pub struct ShaderBindingTable {
    _buffer: Buffer,
    pub raygen: vk::StridedDeviceAddressRegionKHR,
    pub miss: vk::StridedDeviceAddressRegionKHR,
    pub hit: vk::StridedDeviceAddressRegionKHR,
}

/// A compiled variant; its pipeline is destroyed with the last query holding it.
pub struct Variant {
    ctx: Arc<Context>,
    pub pipeline: vk::Pipeline,
    pub sbt: Option<ShaderBindingTable>,
}

impl Drop for Variant {
    fn drop(&mut self) {
        if self.ctx.forked() {
            return;
        }
        // SAFETY: queries hold an `Arc<Variant>` until their last chunk finished, so the
        // pipeline is no longer in use when the last reference goes.
        unsafe { self.ctx.device.destroy_pipeline(self.pipeline, None) };
    }
}

/// The stages that read the push constants.
pub fn push_constant_stages(backend: Backend) -> vk::ShaderStageFlags {
    use vk::ShaderStageFlags as S;
    match backend {
        Backend::RayQuery => S::COMPUTE,
        Backend::Pipeline => S::RAYGEN_KHR | S::CLOSEST_HIT_KHR | S::MISS_KHR | S::INTERSECTION_KHR | S::ANY_HIT_KHR,
    }
}

/// The shader modules of a backend, by role.
struct Modules {
    query: vk::ShaderModule,
    query_exact: Option<vk::ShaderModule>,
    raygen: vk::ShaderModule,
    miss: vk::ShaderModule,
    closest_hit: vk::ShaderModule,
    sphere: vk::ShaderModule,
    any_hit_all: vk::ShaderModule,
    any_hit_opacity: vk::ShaderModule,
    raygen_exact: Option<vk::ShaderModule>,
    intersection_exact: Option<vk::ShaderModule>,
}

/// The pipeline layout, shader modules and compiled variants of one device.
pub struct Variants {
    ctx: Arc<Context>,
    pub layout: vk::PipelineLayout,
    modules: Modules,
    /// Compute workgroup size (ray-query backend).
    pub local_size: u32,
    cache: Mutex<HashMap<VariantKey, Arc<Variant>>>,
}

impl Variants {
    /// Records the trace of `len` rays (within the device's dispatch limits) by `variant`.
    pub fn record_trace(&self, cmd: vk::CommandBuffer, variant: &Variant, params: &Params, len: usize) {
        let ctx = &self.ctx;
        let bind_point = match ctx.backend {
            Backend::RayQuery => vk::PipelineBindPoint::COMPUTE,
            Backend::Pipeline => vk::PipelineBindPoint::RAY_TRACING_KHR,
        };
        // SAFETY: `cmd` is recording; the pipeline and its layout are live, and the push
        // constants cover exactly the range the layout declares.
        unsafe {
            ctx.device.cmd_bind_pipeline(cmd, bind_point, variant.pipeline);
            ctx.device.cmd_push_constants(
                cmd,
                self.layout,
                push_constant_stages(ctx.backend),
                0,
                bytemuck::bytes_of(params),
            );
        }
        match (&variant.sbt, ctx.pipeline_ext.as_ref()) {
            // SAFETY: the SBT regions were laid out from this device's handle size and alignments
            // and `len` is within the device's dispatch limits (`Shared::max_dispatch_rays`).
            (Some(sbt), Some(rt)) => unsafe {
                let callable = vk::StridedDeviceAddressRegionKHR::default();
                rt.cmd_trace_rays(cmd, &sbt.raygen, &sbt.miss, &sbt.hit, &callable, len as u32, 1, 1);
            },
            // SAFETY: as above, for the compute dispatch's group count.
            _ => unsafe { ctx.device.cmd_dispatch(cmd, (len as u32).div_ceil(self.local_size), 1, 1) },
        }
    }
}

/// Threads per compute workgroup, within the device's limits.
const WORKGROUP_SIZE: u32 = 64;

impl Variants {
    pub fn new(ctx: &Arc<Context>) -> Result<Variants> {
        let ranges = [vk::PushConstantRange::default()
            .stage_flags(push_constant_stages(ctx.backend))
            .size(std::mem::size_of::<Params>() as u32)];
        let layout_info = vk::PipelineLayoutCreateInfo::default().push_constant_ranges(&ranges);
        // SAFETY: a valid create info on a live device.
        let layout = unsafe { ctx.device.create_pipeline_layout(&layout_info, None) }.vk("vkCreatePipelineLayout")?;
        let load = |source: &[u8]| -> Result<vk::ShaderModule> {
            let code = shaders::words(source);
            let info = vk::ShaderModuleCreateInfo::default().code(&code);
            // SAFETY: the code is SPIR-V compiled by glslc at build time (validated by the tests).
            unsafe { ctx.device.create_shader_module(&info, None) }.vk("vkCreateShaderModule")
        };
        // The exact tier's modules use f64, which only devices with shaderFloat64 may load; each
        // backend loads its own modules only.
        let f64s = ctx.info.shader_float64;
        let null = vk::ShaderModule::null();
        let modules = match ctx.backend {
            Backend::RayQuery => Modules {
                query: load(shaders::TRACE_RAY_QUERY)?,
                query_exact: f64s.then(|| load(shaders::TRACE_EXACT_RAY_QUERY)).transpose()?,
                raygen: null,
                miss: null,
                closest_hit: null,
                sphere: null,
                any_hit_all: null,
                any_hit_opacity: null,
                raygen_exact: None,
                intersection_exact: None,
            },
            Backend::Pipeline => Modules {
                query: null,
                query_exact: None,
                raygen: load(shaders::RAYGEN)?,
                miss: load(shaders::MISS)?,
                closest_hit: load(shaders::CLOSEST_HIT)?,
                sphere: load(shaders::SPHERE_INTERSECTION)?,
                any_hit_all: load(shaders::ANY_HIT_ALL)?,
                any_hit_opacity: load(shaders::ANY_HIT_OPACITY)?,
                raygen_exact: f64s.then(|| load(shaders::RAYGEN_EXACT)).transpose()?,
                intersection_exact: f64s.then(|| load(shaders::INTERSECTION_EXACT)).transpose()?,
            },
        };
        ctx.check_validation()?;
        let local_size = WORKGROUP_SIZE
            .min(ctx.limits.max_compute_work_group_size[0])
            .min(ctx.limits.max_compute_work_group_invocations);
        Ok(Variants { ctx: ctx.clone(), layout, modules, local_size, cache: Mutex::new(HashMap::new()) })
    }

    /// The variant for `key`: cached, or compiled now (outside the lock; where two threads
    /// compile the same variant at once, the first inserted is kept and the other dropped).
    pub fn get(&self, key: VariantKey) -> Result<Arc<Variant>> {
        if let Some(variant) = self.cache.lock().unwrap_or_else(|e| e.into_inner()).get(&key) {
            return Ok(variant.clone());
        }
        let built = Arc::new(match self.ctx.backend {
            Backend::RayQuery => self.compute_variant(key)?,
            Backend::Pipeline => self.pipeline_variant(key)?,
        });
        let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        Ok(cache.entry(key).or_insert(built).clone())
    }

    fn compute_variant(&self, key: VariantKey) -> Result<Variant> {
        let values = key.constants(self.local_size);
        let entries = specialization_entries();
        let spec = vk::SpecializationInfo::default().map_entries(&entries).data(bytemuck::cast_slice(&values));
        let module = if key.exact { self.modules.query_exact } else { Some(self.modules.query) };
        let stage = vk::PipelineShaderStageCreateInfo::default()
            .stage(vk::ShaderStageFlags::COMPUTE)
            .module(module.expect("exact variants are asked for only on devices with shaderFloat64"))
            .name(c"main")
            .specialization_info(&spec);
        let info = [vk::ComputePipelineCreateInfo::default().stage(stage).layout(self.layout)];
        // SAFETY: the module and layout are live objects of this device; the specialization
        // data outlives the call.
        let pipeline = unsafe { self.ctx.device.create_compute_pipelines(vk::PipelineCache::null(), &info, None) }
            .map_err(|(_, result)| vulkan_error("vkCreateComputePipelines", result))?[0];
        let variant = Variant { ctx: self.ctx.clone(), pipeline, sbt: None };
        self.ctx.check_validation()?;
        Ok(variant)
    }

    fn pipeline_variant(&self, key: VariantKey) -> Result<Variant> {
        let ctx = &self.ctx;
        let rt = ctx.pipeline_ext.as_ref().expect("pipeline backend loads its extension");
        let values = key.constants(0);
        // Every constant but the workgroup size (2), which ray-tracing stages do not have.
        let entries = specialization_entries();
        let entries = [entries[0], entries[1], entries[3], entries[4], entries[5], entries[6]];
        let spec = vk::SpecializationInfo::default().map_entries(&entries).data(bytemuck::cast_slice(&values));
        let stage = |flags, module| {
            vk::PipelineShaderStageCreateInfo::default()
                .stage(flags)
                .module(module)
                .name(c"main")
                .specialization_info(&spec)
        };
        use vk::ShaderStageFlags as S;
        let m = &self.modules;
        let exact_only = "exact variants are asked for only on devices with shaderFloat64";
        let raygen = if key.exact { m.raygen_exact.expect(exact_only) } else { m.raygen };
        // Stages 0 raygen, 1 miss, 2 closest-hit or the exact intersection, then any-hit and the
        // sphere intersection where the variant has them (`hit_groups` numbers them alike).
        let stages: Vec<_> = key
            .stages(Backend::Pipeline)
            .into_iter()
            .map(|role| match role {
                Stage::RayGeneration => stage(S::RAYGEN_KHR, raygen),
                Stage::Miss => stage(S::MISS_KHR, m.miss),
                Stage::ClosestHit => stage(S::CLOSEST_HIT_KHR, m.closest_hit),
                Stage::AnyHit(AnyHit::All) => stage(S::ANY_HIT_KHR, m.any_hit_all),
                Stage::AnyHit(AnyHit::Opacity) => stage(S::ANY_HIT_KHR, m.any_hit_opacity),
                Stage::ExactIntersection => stage(S::INTERSECTION_KHR, m.intersection_exact.expect(exact_only)),
                Stage::SphereIntersection => stage(S::INTERSECTION_KHR, m.sphere),
                Stage::Compute => unreachable!("pipeline variants have no compute stage"),
            })
            .collect();
        let groups = hit_groups(key);
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
        // SAFETY: modules and layout are live objects of this device; the stage and group arrays
        // and the specialization data outlive the call.
        let pipeline = unsafe {
            rt.create_ray_tracing_pipelines(vk::DeferredOperationKHR::null(), vk::PipelineCache::null(), &info, None)
        }
        .map_err(|(_, result)| vulkan_error("vkCreateRayTracingPipelinesKHR", result))?[0];
        // From here the variant owns the pipeline, so an error below destroys it.
        let mut variant = Variant { ctx: ctx.clone(), pipeline, sbt: None };
        variant.sbt = Some(self.shader_binding_table(pipeline, groups.len() as u32)?);
        ctx.check_validation()?;
        Ok(variant)
    }

    /// One record per group (raygen, miss, hit), laid out by the device's own handle size and
    /// alignments; the raygen region's size equals its stride, as Vulkan requires.
    fn shader_binding_table(&self, pipeline: vk::Pipeline, group_count: u32) -> Result<ShaderBindingTable> {
        let ctx = &self.ctx;
        let rt = ctx.pipeline_ext.as_ref().expect("pipeline backend loads its extension");
        let layout = SbtLayout::new(
            ctx.limits.shader_group_handle_size as u64,
            ctx.limits.shader_group_handle_alignment as u64,
            ctx.limits.shader_group_base_alignment as u64,
            group_count as u64 - 2,
        );
        let handle_size = ctx.limits.shader_group_handle_size as usize;
        // SAFETY: `pipeline` is a live ray-tracing pipeline with `group_count` groups.
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
        ctx.run_commands(|cmd| {
            uploads.record(ctx, cmd);
            Ok(())
        })?;
        let region = |k: usize| {
            let (offset, stride, size) = layout.regions[k];
            vk::StridedDeviceAddressRegionKHR::default().device_address(start + offset).stride(stride).size(size)
        };
        Ok(ShaderBindingTable { raygen: region(0), miss: region(1), hit: region(2), _buffer: buffer })
    }
}

impl Drop for Variants {
    fn drop(&mut self) {
        if self.ctx.forked() {
            return;
        }
        self.cache.get_mut().unwrap_or_else(|e| e.into_inner()).clear();
        let m = &self.modules;
        let modules = [m.query, m.raygen, m.miss, m.closest_hit, m.sphere, m.any_hit_all, m.any_hit_opacity]
            .into_iter()
            .chain([m.query_exact, m.raygen_exact, m.intersection_exact].into_iter().flatten());
        // SAFETY: the tracer owning these is dropped only when no query runs (queries borrow it);
        // pipelines made from the modules were destroyed with the cache above. Null handles are
        // ignored by vkDestroyShaderModule.
        unsafe {
            for module in modules {
                self.ctx.device.destroy_shader_module(module, None);
            }
            self.ctx.device.destroy_pipeline_layout(self.layout, None);
        }
    }
}

/// The groups of a pipeline variant: raygen (stage 0), miss (stage 1), then its hit groups, whose
/// shaders are the variant's other stages (numbered as `VariantKey::stages` orders them).
fn hit_groups(key: VariantKey) -> Vec<vk::RayTracingShaderGroupCreateInfoKHR<'static>> {
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
    let stages = key.stages(Backend::Pipeline);
    let index = |wanted: fn(&Stage) -> bool| stages.iter().position(wanted).map_or(NONE, |k| k as u32);
    let closest_hit = index(|s| *s == Stage::ClosestHit);
    let any_hit = index(|s| matches!(s, Stage::AnyHit(_)));
    let mut groups = vec![group(G::GENERAL, 0, NONE, NONE), group(G::GENERAL, 1, NONE, NONE)];
    if key.exact {
        // Boxes whose intersection shader runs the f64 test and keeps the best hit itself.
        groups.push(group(G::PROCEDURAL_HIT_GROUP, NONE, NONE, index(|s| *s == Stage::ExactIntersection)));
        return groups;
    }
    // Triangles first (instances' hit-group offset 0), with the any-hit stage where the variant
    // has one; spheres second (offset 1), sharing the closest-hit shader, which tells them apart
    // by hit kind.
    groups.push(group(G::TRIANGLES_HIT_GROUP, NONE, closest_hit, NONE).any_hit_shader(any_hit));
    if key.spheres {
        groups.push(group(G::PROCEDURAL_HIT_GROUP, NONE, closest_hit, index(|s| *s == Stage::SphereIntersection)));
    }
    groups
}

/// Constants 0 (OUTPUTS), 1 (RAY_FLAGS), 2 (the workgroup size), 3 (QUERY), 4 (CLOSED_EDGES),
/// 5 (RAY_SOURCE) and 6 (OPACITY_THRESHOLD, f32 bits), four bytes each.
fn specialization_entries() -> [vk::SpecializationMapEntry; 7] {
    [0u32, 1, 2, 3, 4, 5, 6].map(|id| vk::SpecializationMapEntry::default().constant_id(id).offset(4 * id).size(4))
}

impl VariantKey {
    /// The specialization constants' values, in `specialization_entries` order.
    fn constants(&self, local_size: u32) -> [u32; 7] {
        [
            self.outputs,
            self.ray_flags,
            local_size,
            self.query,
            self.closed_edges as u32,
            self.ray_source,
            self.threshold_bits,
        ]
    }
}

/// A shader binding table's layout: the raygen, miss and hit regions (offset, stride, size), and
/// where each group's record lies (raygen, miss, then the hit groups in order).
#[derive(Debug, PartialEq)]
pub struct SbtLayout {
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

#[cfg(test)]
mod tests {
    use super::*;

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
}

#[cfg(test)]
mod flag_tests {
    use super::*;
    use crate::gpu::context::Backend;
    use crate::gpu::records::Params;
    use crate::trace::request::{Cull, Query};

    #[test]
    fn params_fit_every_device_push_constants() {
        // Vulkan guarantees 128 bytes of push constants.
        assert!(std::mem::size_of::<Params>() <= 128);
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
