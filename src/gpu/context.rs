//! The Vulkan side of a device: loader, instance, device selection, the logical device with only the
//! features vkray uses, its queue, memory allocator, and one-shot command submission.

use std::ffi::{c_void, CStr, CString};
use std::mem::ManuallyDrop;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use ash::{ext, khr, vk};
use gpu_allocator::vulkan::{Allocator, AllocatorCreateDesc};

use crate::error::{Error, Result, VkResultExt};
use crate::geometry::vertex_format::VertexFormat;

/// How rays are traced: ray queries from a compute shader, or a ray-tracing pipeline.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Backend {
    RayQuery,
    Pipeline,
}

impl Backend {
    pub fn name(self) -> &'static str {
        match self {
            Backend::RayQuery => "ray_query",
            Backend::Pipeline => "pipeline",
        }
    }

    pub fn parse(name: &str) -> Result<Backend> {
        match name.trim().to_ascii_lowercase().as_str() {
            "ray_query" | "rayquery" | "query" => Ok(Backend::RayQuery),
            "pipeline" | "ray_tracing_pipeline" | "rt" => Ok(Backend::Pipeline),
            other => Err(Error::InvalidValue(format!("backend must be 'ray_query' or 'pipeline', got {other:?}"))),
        }
    }
}

/// What selecting a device found out about it.
#[derive(Clone, Debug)]
pub struct DeviceInfo {
    /// Position in the ranked list of usable devices (the list `vkray.devices()` returns).
    pub index: usize,
    pub name: String,
    /// "discrete", "integrated", "virtual", "cpu" or "other".
    pub device_type: &'static str,
    pub is_software: bool,
    pub api_version: String,
    pub driver: String,
    pub ray_query: bool,
    pub ray_tracing_pipeline: bool,
    pub shader_float64: bool,
}

/// Device limits vkray depends on; always queried, never assumed.
#[derive(Clone, Debug, Default)]
pub struct Limits {
    pub min_scratch_offset_alignment: u32,
    pub max_primitive_count: u64,
    pub max_instance_count: u64,
    pub max_geometry_count: u64,
    pub max_compute_work_group_count: [u32; 3],
    pub max_compute_work_group_size: [u32; 3],
    pub max_compute_work_group_invocations: u32,
    pub max_push_constants_size: u32,
    pub shader_group_handle_size: u32,
    pub shader_group_handle_alignment: u32,
    pub shader_group_base_alignment: u32,
    pub max_ray_dispatch_invocation_count: u32,
    pub max_shader_group_stride: u32,
    pub ray_traversal_primitive_culling: bool,
    /// Nanoseconds per timestamp tick.
    pub timestamp_period: f32,
    /// Meaningful bits of the queue's timestamps; 0 where the queue cannot write them.
    pub timestamp_valid_bits: u32,
    /// Vertex formats acceleration structures can be built from (float32 always).
    pub vertex_formats: Vec<VertexFormat>,
}

/// What the device offers for sharing memory and synchronization with the host and with other
/// APIs (CUDA); each extension is enabled only where the device lists it.
#[derive(Clone, Debug, Default)]
pub struct Interop {
    /// The device's UUID (`VkPhysicalDeviceIDProperties::deviceUUID`), which CUDA reports too.
    pub device_uuid: [u8; 16],
    /// VK_EXT_external_memory_host: the alignment of host memory imported in place, if supported.
    pub host_import_alignment: Option<u64>,
    /// VK_KHR_external_memory_fd and VK_KHR_external_semaphore_fd with timeline semaphores:
    /// memory and semaphores exported to CUDA as opaque file descriptors.
    pub export_fd: bool,
}

/// Which device and backend to open.
#[derive(Clone, Debug, Default)]
pub struct DeviceRequest {
    /// Index into the ranked device list, or a case-insensitive substring of the device name.
    pub selector: Option<String>,
    pub backend: Option<Backend>,
    /// Enable the Khronos validation layer and report its messages as errors.
    pub validation: bool,
}

impl DeviceRequest {
    /// Fills what the caller left open from `VKRAY_DEVICE`, `VKRAY_BACKEND` and `VKRAY_VALIDATION`.
    pub fn with_environment(mut self) -> Result<DeviceRequest> {
        if self.selector.is_none() {
            self.selector = std::env::var("VKRAY_DEVICE").ok().filter(|s| !s.trim().is_empty());
        }
        if self.backend.is_none() {
            if let Some(name) = std::env::var("VKRAY_BACKEND").ok().filter(|s| !s.trim().is_empty()) {
                self.backend = Some(Backend::parse(&name)?);
            }
        }
        if let Ok(flag) = std::env::var("VKRAY_VALIDATION") {
            self.validation |= !matches!(flag.trim(), "" | "0" | "false" | "no" | "off");
        }
        Ok(self)
    }
}

/// The process that last opened a device with a driver that cannot be used again in a forked
/// child (NVIDIA's: a new instance there hangs), shifted left by one, with bit 0 set for such a
/// driver; 0 while none was opened.
static OPENED_BY: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// Remembers that this process opened a device with `info`'s driver.
fn note_opened(info: &DeviceInfo) {
    let pid = std::process::id() as u64;
    let fork_unsafe = info.driver.to_ascii_lowercase().contains("nvidia");
    // A lavapipe device opened after an NVIDIA one in the same process leaves the mark.
    let _ = OPENED_BY.fetch_update(Ordering::AcqRel, Ordering::Acquire, |old| {
        let marked = fork_unsafe || (old >> 1 == pid && old & 1 == 1);
        Some(pid << 1 | marked as u64)
    });
}

/// Refuses to touch Vulkan in a forked child of a process that opened a device with a driver
/// that hangs there, rather than hang.
fn refuse_fork_unsafe_driver() -> Result<()> {
    let opened = OPENED_BY.load(Ordering::Acquire);
    if opened & 1 == 1 && (opened >> 1) as u32 != std::process::id() {
        return Err(Error::Forked(format!(
            "this process is a fork of process {}, which opened a Vulkan device with NVIDIA's driver, \
             and that driver hangs when a forked child opens one again: start worker processes with \
             multiprocessing's 'spawn' or 'forkserver' start method",
            opened >> 1
        )));
    }
    Ok(())
}

/// How long one fence wait may take before the device is given up as hung (`VKRAY_GPU_TIMEOUT`
/// seconds; 300 by default: far above any one chunk or build, which take milliseconds on a GPU
/// and seconds on lavapipe).
fn gpu_timeout() -> std::time::Duration {
    let seconds = std::env::var("VKRAY_GPU_TIMEOUT").ok().and_then(|s| s.trim().parse::<f64>().ok());
    std::time::Duration::from_secs_f64(seconds.filter(|s| *s > 0.0).unwrap_or(300.0))
}

/// How long a wait for the GPU polls its fence before it blocks (`Context::poll_fence`):
/// `VKRAY_FENCE_POLL_US` microseconds, 2,000 by default (0: block at once).
fn fence_poll() -> std::time::Duration {
    let micros = std::env::var("VKRAY_FENCE_POLL_US").ok().and_then(|s| s.trim().parse::<u64>().ok());
    std::time::Duration::from_micros(micros.unwrap_or(2_000))
}

const VALIDATION_LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";

type MessageSink = Mutex<Vec<String>>;

struct Debug {
    loader: ext::debug_utils::Instance,
    messenger: vk::DebugUtilsMessengerEXT,
    messages: Box<MessageSink>,
}

unsafe extern "system" fn collect_message(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    sink: *mut c_void,
) -> vk::Bool32 {
    // Loader chatter (general warnings) is not about our use of the API; validation findings are.
    let relevant = types.contains(vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION)
        || severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::ERROR);
    if relevant && !data.is_null() && !sink.is_null() {
        // SAFETY: the loader passes callback data valid for this call, and `sink` is the boxed
        // `MessageSink` of `messenger_info`, which outlives the instance and its messengers (see
        // `InstanceHandle`).
        let (data, sink) = unsafe { (&*data, &*(sink as *const MessageSink)) };
        let message = data.message_as_c_str().map(|m| m.to_string_lossy().into_owned());
        if let (Some(message), Ok(mut messages)) = (message, sink.lock()) {
            messages.push(message);
        }
    }
    vk::FALSE
}

fn messenger_info(sink: &MessageSink) -> vk::DebugUtilsMessengerCreateInfoEXT<'static> {
    vk::DebugUtilsMessengerCreateInfoEXT::default()
        .message_severity(vk::DebugUtilsMessageSeverityFlagsEXT::WARNING | vk::DebugUtilsMessageSeverityFlagsEXT::ERROR)
        .message_type(
            vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
                | vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
        )
        .pfn_user_callback(Some(collect_message))
        .user_data(sink as *const MessageSink as *mut c_void)
}

struct InstanceHandle {
    // Holds the loaded libvulkan; every function pointer below comes from it.
    _entry: ash::Entry,
    instance: ash::Instance,
    debug: Option<Debug>,
}

impl InstanceHandle {
    fn new(validation: bool) -> Result<InstanceHandle> {
        refuse_fork_unsafe_driver()?;
        // SAFETY: loads the system's Vulkan loader, which ash trusts to be a conforming one (its
        // initialisation runs no code of ours).
        let entry = unsafe { ash::Entry::load() }.map_err(|e| {
            Error::NoDevice(format!("the Vulkan loader could not be loaded ({e}); install it (Debian: libvulkan1)"))
        })?;
        // SAFETY: `entry` holds a loaded loader.
        let api = unsafe { entry.try_enumerate_instance_version() }
            .vk("vkEnumerateInstanceVersion")?
            .unwrap_or(vk::API_VERSION_1_0);
        if api < vk::API_VERSION_1_2 {
            return Err(Error::NoDevice(format!(
                "the Vulkan loader supports only Vulkan {}; vkray needs 1.2",
                version_string(api)
            )));
        }
        let app_name = c"vkray";
        let app = vk::ApplicationInfo::default()
            .application_name(app_name)
            .engine_name(app_name)
            .api_version(vk::API_VERSION_1_2);
        let mut layers: Vec<*const i8> = Vec::new();
        let mut extensions: Vec<*const i8> = Vec::new();
        let messages: Box<MessageSink> = Box::default();
        let mut early_messenger = messenger_info(&messages);
        if validation {
            // SAFETY: `entry` holds a loaded loader.
            let available =
                unsafe { entry.enumerate_instance_layer_properties() }.vk("vkEnumerateInstanceLayerProperties")?;
            if !available.iter().any(|l| l.layer_name_as_c_str() == Ok(VALIDATION_LAYER)) {
                return Err(Error::Unsupported(
                    "validation was requested (VKRAY_VALIDATION) but the Khronos validation layer is not \
                     installed (Debian: vulkan-validationlayers)"
                        .into(),
                ));
            }
            layers.push(VALIDATION_LAYER.as_ptr());
            extensions.push(ext::debug_utils::NAME.as_ptr());
        }
        let mut info = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_layer_names(&layers)
            .enabled_extension_names(&extensions);
        if validation {
            info = info.push_next(&mut early_messenger);
        }
        // SAFETY: `info` and what it points at (application info, layer and extension names, the
        // messenger info and its sink `messages`, kept until the instance is destroyed) are live.
        let instance = unsafe { entry.create_instance(&info, None) }.map_err(|result| match result {
            vk::Result::ERROR_INCOMPATIBLE_DRIVER => Error::NoDevice(
                "the Vulkan loader found no driver (install Mesa's mesa-vulkan-drivers, or point \
                 VK_DRIVER_FILES at your GPU driver's ICD JSON, e.g. \
                 /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json)"
                    .into(),
            ),
            result => crate::error::vulkan_error("vkCreateInstance", result),
        })?;
        let debug = if validation {
            let loader = ext::debug_utils::Instance::new(&entry, &instance);
            // SAFETY: `instance` is live with VK_EXT_debug_utils enabled; the sink `messages` is
            // kept in `Debug` until the messenger is destroyed.
            let messenger = unsafe { loader.create_debug_utils_messenger(&messenger_info(&messages), None) };
            match messenger {
                Ok(messenger) => Some(Debug { loader, messenger, messages }),
                Err(result) => {
                    // SAFETY: nothing was created from `instance` yet; `messages` is still live.
                    unsafe { instance.destroy_instance(None) };
                    return Err(Error::Vulkan { call: "vkCreateDebugUtilsMessengerEXT", result });
                }
            }
        } else {
            None
        };
        Ok(InstanceHandle { _entry: entry, instance, debug })
    }
}

impl Drop for InstanceHandle {
    fn drop(&mut self) {
        // SAFETY: no device of this instance is left (a `Context` destroys its device before its
        // `InstanceHandle`, or never drops the handle); the messenger goes first, while its sink
        // (a field, dropped after this) is still live.
        unsafe {
            if let Some(debug) = &self.debug {
                debug.loader.destroy_debug_utils_messenger(debug.messenger, None);
            }
            self.instance.destroy_instance(None);
        }
    }
}

fn version_string(v: u32) -> String {
    format!("{}.{}.{}", vk::api_version_major(v), vk::api_version_minor(v), vk::api_version_patch(v))
}

fn device_type_name(t: vk::PhysicalDeviceType) -> &'static str {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => "discrete",
        vk::PhysicalDeviceType::INTEGRATED_GPU => "integrated",
        vk::PhysicalDeviceType::VIRTUAL_GPU => "virtual",
        vk::PhysicalDeviceType::CPU => "cpu",
        _ => "other",
    }
}

/// Real GPUs first, software rasterizers last.
fn device_rank(t: vk::PhysicalDeviceType) -> u32 {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => 0,
        vk::PhysicalDeviceType::INTEGRATED_GPU => 1,
        vk::PhysicalDeviceType::VIRTUAL_GPU => 2,
        vk::PhysicalDeviceType::CPU => 4,
        _ => 3,
    }
}

struct Candidate {
    physical: vk::PhysicalDevice,
    kind: vk::PhysicalDeviceType,
    info: DeviceInfo,
    limits: Limits,
    queue_family: u32,
    unified_memory: bool,
    interop: Interop,
}

/// Usable devices: Vulkan 1.2, acceleration structures, buffer device addresses, 64-bit integers in
/// shaders, a compute queue, and ray queries or a ray-tracing pipeline. Ranked, GPUs first.
fn candidates(instance: &ash::Instance) -> Result<Vec<Candidate>> {
    // SAFETY: `instance` is live.
    let physicals = unsafe { instance.enumerate_physical_devices() }.vk("vkEnumeratePhysicalDevices")?;
    let mut found = Vec::new();
    for physical in physicals {
        if let Some(candidate) = inspect(instance, physical)? {
            found.push(candidate);
        }
    }
    found.sort_by_key(|c| device_rank(c.kind));
    for (index, candidate) in found.iter_mut().enumerate() {
        candidate.info.index = index;
    }
    Ok(found)
}

/// The device as a `Candidate`, or None where it lacks what vkray needs.
fn inspect(instance: &ash::Instance, physical: vk::PhysicalDevice) -> Result<Option<Candidate>> {
    // SAFETY: `physical` was enumerated from `instance`, which is live.
    let base = unsafe { instance.get_physical_device_properties(physical) };
    if base.api_version < vk::API_VERSION_1_2 {
        return Ok(None);
    }
    // SAFETY: `physical` was enumerated from `instance`, which is live.
    let extensions = unsafe { instance.enumerate_device_extension_properties(physical) }
        .vk("vkEnumerateDeviceExtensionProperties")?;
    let has = |name: &CStr| extensions.iter().any(|e| e.extension_name_as_c_str() == Ok(name));
    if !has(khr::acceleration_structure::NAME) || !has(khr::deferred_host_operations::NAME) {
        return Ok(None);
    }
    let has_pipeline_ext = has(khr::ray_tracing_pipeline::NAME);
    let features = Features::query(instance, physical, has(khr::ray_query::NAME), has_pipeline_ext);
    let host_import = has(ext::external_memory_host::NAME);
    if !features.required || !(features.ray_query || features.ray_tracing_pipeline) {
        return Ok(None);
    }
    // SAFETY: `physical` was enumerated from `instance`, which is live.
    let families = unsafe { instance.get_physical_device_queue_family_properties(physical) };
    let Some(queue_family) =
        families.iter().position(|f| f.queue_flags.contains(vk::QueueFlags::COMPUTE) && f.queue_count > 0)
    else {
        return Ok(None);
    };
    let (props, driver, mut limits, mut interop) = query_properties(instance, physical, has_pipeline_ext, host_import);
    interop.export_fd =
        has(khr::external_memory_fd::NAME) && has(khr::external_semaphore_fd::NAME) && features.timeline_semaphore;
    limits.ray_traversal_primitive_culling = features.primitive_culling;
    limits.timestamp_valid_bits = families[queue_family].timestamp_valid_bits;
    let info = DeviceInfo {
        index: 0,
        name: props.device_name_as_c_str().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default(),
        device_type: device_type_name(props.device_type),
        is_software: props.device_type == vk::PhysicalDeviceType::CPU,
        api_version: version_string(props.api_version),
        driver,
        ray_query: features.ray_query,
        ray_tracing_pipeline: features.ray_tracing_pipeline,
        shader_float64: features.shader_float64,
    };
    // Where the device and the host share memory, device buffers are written and read in place;
    // a discrete GPU gets staging copies instead (its host-visible device memory is slow to read).
    // VKRAY_STAGING=1 forces the discrete-GPU path anywhere (to test it on lavapipe).
    let unified_memory =
        matches!(props.device_type, vk::PhysicalDeviceType::CPU | vk::PhysicalDeviceType::INTEGRATED_GPU)
            && std::env::var("VKRAY_STAGING").map_or(true, |v| v != "1");
    Ok(Some(Candidate {
        physical,
        kind: props.device_type,
        info,
        limits,
        queue_family: queue_family as u32,
        unified_memory,
        interop,
    }))
}

/// The features `inspect` judges a device by.
struct Features {
    /// Acceleration structures, buffer device addresses and 64-bit integers in shaders.
    required: bool,
    ray_query: bool,
    ray_tracing_pipeline: bool,
    primitive_culling: bool,
    shader_float64: bool,
    timeline_semaphore: bool,
}

impl Features {
    fn query(
        instance: &ash::Instance,
        physical: vk::PhysicalDevice,
        has_ray_query_ext: bool,
        has_pipeline_ext: bool,
    ) -> Features {
        // Only chain structures of extensions the device has: anything else is invalid usage.
        let mut f12 = vk::PhysicalDeviceVulkan12Features::default();
        let mut f_accel = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default();
        let mut f_query = vk::PhysicalDeviceRayQueryFeaturesKHR::default();
        let mut f_pipeline = vk::PhysicalDeviceRayTracingPipelineFeaturesKHR::default();
        let mut features = vk::PhysicalDeviceFeatures2::default().push_next(&mut f12).push_next(&mut f_accel);
        if has_ray_query_ext {
            features = features.push_next(&mut f_query);
        }
        if has_pipeline_ext {
            features = features.push_next(&mut f_pipeline);
        }
        // SAFETY: `physical` belongs to the live `instance`; the chain holds only structures of
        // Vulkan 1.2 and of extensions the device lists, each living through the call.
        unsafe { instance.get_physical_device_features2(physical, &mut features) };
        let core = features.features;
        Features {
            required: f_accel.acceleration_structure == vk::TRUE
                && f12.buffer_device_address == vk::TRUE
                && core.shader_int64 == vk::TRUE,
            ray_query: has_ray_query_ext && f_query.ray_query == vk::TRUE,
            ray_tracing_pipeline: has_pipeline_ext && f_pipeline.ray_tracing_pipeline == vk::TRUE,
            primitive_culling: has_pipeline_ext && f_pipeline.ray_traversal_primitive_culling == vk::TRUE,
            shader_float64: core.shader_float64 == vk::TRUE,
            timeline_semaphore: f12.timeline_semaphore == vk::TRUE,
        }
    }
}

/// The device's core properties, its driver's name and info, its limits (all but those of
/// features and queues: primitive culling, timestamp bits) and what it shares (all but export).
fn query_properties(
    instance: &ash::Instance,
    physical: vk::PhysicalDevice,
    has_pipeline_ext: bool,
    has_host_import: bool,
) -> (vk::PhysicalDeviceProperties, String, Limits, Interop) {
    let mut p_accel = vk::PhysicalDeviceAccelerationStructurePropertiesKHR::default();
    let mut p_pipeline = vk::PhysicalDeviceRayTracingPipelinePropertiesKHR::default();
    let mut p_driver = vk::PhysicalDeviceDriverProperties::default();
    let mut p_id = vk::PhysicalDeviceIDProperties::default();
    let mut p_host = vk::PhysicalDeviceExternalMemoryHostPropertiesEXT::default();
    let mut properties =
        vk::PhysicalDeviceProperties2::default().push_next(&mut p_accel).push_next(&mut p_driver).push_next(&mut p_id);
    if has_pipeline_ext {
        properties = properties.push_next(&mut p_pipeline);
    }
    if has_host_import {
        properties = properties.push_next(&mut p_host);
    }
    // SAFETY: `physical` belongs to the live `instance`; the chain holds only structures of
    // Vulkan 1.2 and of extensions the device lists, each living through the call.
    unsafe { instance.get_physical_device_properties2(physical, &mut properties) };
    let props = properties.properties;
    let driver_name = p_driver.driver_name_as_c_str().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let driver_info = p_driver.driver_info_as_c_str().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let l = props.limits;
    let limits = Limits {
        min_scratch_offset_alignment: p_accel.min_acceleration_structure_scratch_offset_alignment,
        max_primitive_count: p_accel.max_primitive_count,
        max_instance_count: p_accel.max_instance_count,
        max_geometry_count: p_accel.max_geometry_count,
        max_compute_work_group_count: l.max_compute_work_group_count,
        max_compute_work_group_size: l.max_compute_work_group_size,
        max_compute_work_group_invocations: l.max_compute_work_group_invocations,
        max_push_constants_size: l.max_push_constants_size,
        shader_group_handle_size: p_pipeline.shader_group_handle_size,
        shader_group_handle_alignment: p_pipeline.shader_group_handle_alignment,
        shader_group_base_alignment: p_pipeline.shader_group_base_alignment,
        max_ray_dispatch_invocation_count: p_pipeline.max_ray_dispatch_invocation_count,
        max_shader_group_stride: p_pipeline.max_shader_group_stride,
        ray_traversal_primitive_culling: false,
        timestamp_period: l.timestamp_period,
        timestamp_valid_bits: 0,
        vertex_formats: vertex_formats(instance, physical),
    };
    let interop = Interop {
        device_uuid: p_id.device_uuid,
        host_import_alignment: has_host_import.then_some(p_host.min_imported_host_pointer_alignment),
        export_fd: false,
    };
    (props, format!("{driver_name} {driver_info}").trim().to_string(), limits, interop)
}

/// The vertex formats the device builds acceleration structures from.
fn vertex_formats(instance: &ash::Instance, physical: vk::PhysicalDevice) -> Vec<VertexFormat> {
    [VertexFormat::F32, VertexFormat::F16, VertexFormat::Snorm16]
        .into_iter()
        .filter(|f| {
            // SAFETY: `physical` belongs to the live `instance`.
            let properties =
                unsafe { instance.get_physical_device_format_properties(physical, vulkan_vertex_format(*f)) };
            properties.buffer_features.contains(vk::FormatFeatureFlags::ACCELERATION_STRUCTURE_VERTEX_BUFFER_KHR)
        })
        .collect()
}

/// Lists the usable devices, ranked as `Context::new` ranks them.
pub fn list_devices() -> Result<Vec<DeviceInfo>> {
    let handle = InstanceHandle::new(false)?;
    Ok(candidates(&handle.instance)?.into_iter().map(|c| c.info).collect())
}

fn choose(mut found: Vec<Candidate>, selector: Option<&str>) -> Result<Candidate> {
    if found.is_empty() {
        return Err(Error::NoDevice(
            "no Vulkan device with acceleration structures and ray queries or ray-tracing pipelines was \
             found (on a CPU-only machine, install Mesa >= 24.1's lavapipe: mesa-vulkan-drivers)"
                .into(),
        ));
    }
    let Some(selector) = selector else {
        return Ok(found.remove(0));
    };
    let names: Vec<String> = found.iter().map(|c| format!("{}: {}", c.info.index, c.info.name)).collect();
    let position = match selector.trim().parse::<usize>() {
        Ok(index) => (index < found.len()).then_some(index),
        Err(_) => {
            let needle = selector.to_lowercase();
            found.iter().position(|c| c.info.name.to_lowercase().contains(&needle))
        }
    };
    match position {
        Some(index) => Ok(found.swap_remove(index)),
        None => Err(Error::NoDevice(format!(
            "no usable device matches {selector:?}; usable devices are [{}]",
            names.join(", ")
        ))),
    }
}

/// The backend asked for, where the device has it; else ray queries where it has them.
fn choose_backend(candidate: &Candidate, requested: Option<Backend>) -> Result<Backend> {
    match requested {
        Some(Backend::RayQuery) if !candidate.info.ray_query => Err(Error::Unsupported(format!(
            "{} has no ray queries (rayQuery feature); use backend='pipeline'",
            candidate.info.name
        ))),
        Some(Backend::Pipeline) if !candidate.info.ray_tracing_pipeline => Err(Error::Unsupported(format!(
            "{} has no ray-tracing pipeline (rayTracingPipeline feature); use backend='ray_query'",
            candidate.info.name
        ))),
        Some(backend) => Ok(backend),
        // Decided by the feature bit, not the extension list: an extension may be listed while
        // its feature is off.
        None if candidate.info.ray_query => Ok(Backend::RayQuery),
        None => Ok(Backend::Pipeline),
    }
}

/// The logical device, with one queue of the candidate's family and only the extensions and
/// features vkray uses with `backend`.
fn create_device(instance: &ash::Instance, candidate: &Candidate, backend: Backend) -> Result<ash::Device> {
    let mut extensions = vec![khr::acceleration_structure::NAME.as_ptr(), khr::deferred_host_operations::NAME.as_ptr()];
    if candidate.interop.host_import_alignment.is_some() {
        extensions.push(ext::external_memory_host::NAME.as_ptr());
    }
    if candidate.interop.export_fd {
        extensions.extend([khr::external_memory_fd::NAME.as_ptr(), khr::external_semaphore_fd::NAME.as_ptr()]);
    }
    let mut f12 = vk::PhysicalDeviceVulkan12Features::default()
        .buffer_device_address(true)
        .timeline_semaphore(candidate.interop.export_fd);
    let mut f_accel = vk::PhysicalDeviceAccelerationStructureFeaturesKHR::default().acceleration_structure(true);
    let mut f_query = vk::PhysicalDeviceRayQueryFeaturesKHR::default().ray_query(true);
    let mut f_pipeline = vk::PhysicalDeviceRayTracingPipelineFeaturesKHR::default()
        .ray_tracing_pipeline(true)
        .ray_traversal_primitive_culling(candidate.limits.ray_traversal_primitive_culling);
    // f64 is optional: only the exact precision tier needs it.
    let core = vk::PhysicalDeviceFeatures::default().shader_int64(true).shader_float64(candidate.info.shader_float64);
    let mut features =
        vk::PhysicalDeviceFeatures2::default().features(core).push_next(&mut f12).push_next(&mut f_accel);
    match backend {
        Backend::RayQuery => {
            extensions.push(khr::ray_query::NAME.as_ptr());
            features = features.push_next(&mut f_query);
        }
        Backend::Pipeline => {
            extensions.push(khr::ray_tracing_pipeline::NAME.as_ptr());
            features = features.push_next(&mut f_pipeline);
        }
    }
    let priorities = [1.0f32];
    let queues =
        [vk::DeviceQueueCreateInfo::default().queue_family_index(candidate.queue_family).queue_priorities(&priorities)];
    let create = vk::DeviceCreateInfo::default()
        .queue_create_infos(&queues)
        .enabled_extension_names(&extensions)
        .push_next(&mut features);
    // SAFETY: `candidate.physical` belongs to the live `instance`; `create` and what it points at
    // (queue infos, extension names, feature structures of core 1.2 and of the extensions it
    // enables, which the device lists) are live.
    unsafe { instance.create_device(candidate.physical, &create, None) }.vk("vkCreateDevice")
}

/// An open Vulkan device and everything bound to its lifetime.
pub struct Context {
    /// Dropped by `Drop for Context`, after the device (never where the device is left alone).
    instance: ManuallyDrop<InstanceHandle>,
    pub physical: vk::PhysicalDevice,
    pub device: ash::Device,
    queue: Mutex<vk::Queue>,
    pub queue_family: u32,
    pub accel: khr::acceleration_structure::Device,
    pub pipeline_ext: Option<khr::ray_tracing_pipeline::Device>,
    /// Where enabled (`Interop`): host memory imported in place; memory and semaphores exported.
    pub host_memory: Option<ext::external_memory_host::Device>,
    pub memory_fd: Option<khr::external_memory_fd::Device>,
    pub semaphore_fd: Option<khr::external_semaphore_fd::Device>,
    object_names: Option<ext::debug_utils::Device>,
    allocator: ManuallyDrop<Mutex<Allocator>>,
    pub info: DeviceInfo,
    pub limits: Limits,
    pub backend: Backend,
    pub validation: bool,
    pub unified_memory: bool,
    pub interop: Interop,
    /// Whether meshes go to the device with triangles in spatial (Morton) order. lavapipe's BVH
    /// builder splits primitives in the order given, so its trees are only as good as that order;
    /// GPU drivers sort spatially themselves.
    pub presort_primitives: bool,
    /// The process that opened the device: a forked child inherits the handles but not a usable
    /// device (nor the driver's threads), so it must not touch them.
    pid: u32,
    /// Set when a wait timed out or the device was lost: later work fails at once.
    lost: AtomicBool,
    /// Idle command pools (each with its buffer and fence) for the next `Commands`: creating and
    /// destroying them costs NVIDIA's driver about a millisecond a query. The lock is held only
    /// to take or return one.
    idle_commands: Mutex<Vec<CommandSet>>,
}

/// A command pool, its one primary buffer, and a fence.
type CommandSet = (vk::CommandPool, vk::CommandBuffer, vk::Fence);

/// Idle command sets a device keeps: two per query in flight, for a few threads.
const IDLE_COMMANDS: usize = 8;

impl Context {
    pub fn new(request: &DeviceRequest) -> Result<Arc<Context>> {
        let instance = InstanceHandle::new(request.validation)?;
        let candidate = choose(candidates(&instance.instance)?, request.selector.as_deref())?;
        let backend = choose_backend(&candidate, request.backend)?;
        let device = create_device(&instance.instance, &candidate, backend)?;
        // SAFETY: the device was created with one queue of `queue_family`.
        let queue = unsafe { device.get_device_queue(candidate.queue_family, 0) };
        let allocator = Allocator::new(&AllocatorCreateDesc {
            instance: instance.instance.clone(),
            device: device.clone(),
            physical_device: candidate.physical,
            debug_settings: Default::default(),
            buffer_device_address: true,
            allocation_sizes: Default::default(),
        });
        let allocator = match allocator {
            Ok(a) => a,
            Err(e) => {
                // SAFETY: nothing was created from `device` yet.
                unsafe { device.destroy_device(None) };
                return Err(e.into());
            }
        };
        let accel = khr::acceleration_structure::Device::new(&instance.instance, &device);
        let pipeline_ext =
            (backend == Backend::Pipeline).then(|| khr::ray_tracing_pipeline::Device::new(&instance.instance, &device));
        let object_names = request.validation.then(|| ext::debug_utils::Device::new(&instance.instance, &device));
        let interop = &candidate.interop;
        let host_memory =
            interop.host_import_alignment.map(|_| ext::external_memory_host::Device::new(&instance.instance, &device));
        let memory_fd = interop.export_fd.then(|| khr::external_memory_fd::Device::new(&instance.instance, &device));
        let semaphore_fd =
            interop.export_fd.then(|| khr::external_semaphore_fd::Device::new(&instance.instance, &device));
        let context = Context {
            host_memory,
            memory_fd,
            semaphore_fd,
            object_names,
            physical: candidate.physical,
            device,
            queue: Mutex::new(queue),
            queue_family: candidate.queue_family,
            accel,
            pipeline_ext,
            allocator: ManuallyDrop::new(Mutex::new(allocator)),
            presort_primitives: candidate.info.is_software,
            info: candidate.info,
            limits: candidate.limits,
            backend,
            validation: request.validation,
            unified_memory: candidate.unified_memory,
            interop: candidate.interop,
            instance: ManuallyDrop::new(instance),
            pid: std::process::id(),
            lost: AtomicBool::new(false),
            idle_commands: Mutex::new(Vec::new()),
        };
        context.check_validation()?;
        note_opened(&context.info);
        Ok(Arc::new(context))
    }

    pub fn instance(&self) -> &ash::Instance {
        &self.instance.instance
    }

    pub(crate) fn allocator(&self) -> std::sync::MutexGuard<'_, Allocator> {
        // A panic while allocating leaves the allocator consistent; keep using it.
        self.allocator.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Turns what the validation layer reported since the last check into an error.
    pub fn check_validation(&self) -> Result<()> {
        let Some(debug) = &self.instance.debug else { return Ok(()) };
        let mut messages = debug.messages.lock().unwrap_or_else(|e| e.into_inner());
        if messages.is_empty() {
            return Ok(());
        }
        let text = messages.drain(..).collect::<Vec<_>>().join("\n");
        Err(Error::Validation(text))
    }

    /// Submits one recorded command buffer and signals `fence` when it completes; with `timeline`,
    /// the work first waits for the semaphore to reach one value and then signals another.
    fn submit(&self, command_buffer: vk::CommandBuffer, fence: vk::Fence, timeline: Option<Timeline>) -> Result<()> {
        let buffers = [command_buffer];
        let queue = self.queue.lock().unwrap_or_else(|e| e.into_inner());
        let Some(timeline) = timeline else {
            let submit = [vk::SubmitInfo::default().command_buffers(&buffers)];
            // SAFETY: the caller ended `command_buffer` and reset `fence` (see `Commands`); the
            // mutex gives the queue the external synchronisation Vulkan requires.
            return unsafe { self.device.queue_submit(*queue, &submit, fence) }.vk("vkQueueSubmit");
        };
        let (semaphores, stages) = ([timeline.semaphore], [vk::PipelineStageFlags::ALL_COMMANDS]);
        let waits = [timeline.wait];
        let signals: &[u64] = match &timeline.signal {
            Some(value) => std::slice::from_ref(value),
            None => &[],
        };
        let mut values =
            vk::TimelineSemaphoreSubmitInfo::default().wait_semaphore_values(&waits).signal_semaphore_values(signals);
        let submit = [vk::SubmitInfo::default()
            .command_buffers(&buffers)
            .wait_semaphores(&semaphores)
            .wait_dst_stage_mask(&stages)
            .signal_semaphores(&semaphores[..signals.len()])
            .push_next(&mut values)];
        // SAFETY: as above; the semaphore is a live timeline semaphore of this device and the
        // values are past every value signalled before (`Timeline`'s contract).
        unsafe { self.device.queue_submit(*queue, &submit, fence) }.vk("vkQueueSubmit")
    }

    /// Whether this is a forked child of the process that opened the device.
    pub fn forked(&self) -> bool {
        std::process::id() != self.pid
    }

    /// Whether this device's objects may be destroyed now: not in a forked child (they are the
    /// parent's), and not after a wait gave up on the device (a hung device may still be using
    /// them: they are leaked instead).
    pub(crate) fn can_free(&self) -> bool {
        !self.forked() && !self.lost.load(Ordering::Acquire)
    }

    /// Fails unless the device can take work: not in a forked child, not lost or hung.
    pub fn check_usable(&self) -> Result<()> {
        if self.forked() {
            return Err(Error::Forked(format!(
                "this vkray.Device ({}) was opened by process {} and cannot be used in its forked child \
                 (process {}): start worker processes with multiprocessing's 'spawn' or 'forkserver' \
                 start method, or open a new vkray.Device in the child (drivers other than NVIDIA's)",
                self.info.name,
                self.pid,
                std::process::id()
            )));
        }
        if self.lost.load(Ordering::Acquire) {
            return Err(Error::Vulkan {
                call: "an earlier wait (the device was lost or hung; open a new vkray.Device)",
                result: vk::Result::ERROR_DEVICE_LOST,
            });
        }
        Ok(())
    }

    /// Waits for `fence`, at most `gpu_timeout()`: a device that never finishes becomes an error
    /// (and is marked lost) instead of a hang.
    pub(crate) fn wait_fence(&self, fence: vk::Fence) -> Result<()> {
        if self.poll_fence(fence)? {
            return Ok(());
        }
        let timeout = gpu_timeout().as_nanos().min(u64::MAX as u128) as u64;
        // SAFETY: `fence` is a live fence of this device, submitted with work (or never reset).
        match unsafe { self.device.wait_for_fences(&[fence], true, timeout) } {
            Ok(()) => Ok(()),
            Err(result) => {
                self.lost.store(true, Ordering::Release);
                let call = match result {
                    vk::Result::TIMEOUT => "vkWaitForFences (timed out after VKRAY_GPU_TIMEOUT seconds)",
                    _ => "vkWaitForFences",
                };
                Err(Error::Vulkan { call, result })
            }
        }
    }

    /// Polls `fence` for up to `fence_poll()` (hardware GPUs only): true once it is signalled.
    /// A blocking vkWaitForFences on an H200 returned about 0.2 ms after a short submission's
    /// work was done, which every query pays at least once (a 1-point `contains` waited 0.24 ms
    /// for 0.02 of GPU work); a query's wait is short, so the core that polls is not missed. Not
    /// on a software device, whose work runs on the host's cores that polling would take.
    fn poll_fence(&self, fence: vk::Fence) -> Result<bool> {
        let budget = fence_poll();
        if self.info.is_software || budget.is_zero() {
            return Ok(false);
        }
        let started = std::time::Instant::now();
        loop {
            // SAFETY: `fence` is a live fence of this device.
            match unsafe { self.device.get_fence_status(fence) } {
                Ok(true) => return Ok(true),
                Ok(false) if started.elapsed() < budget => std::hint::spin_loop(),
                Ok(false) => return Ok(false),
                Err(result) => {
                    self.lost.store(true, Ordering::Release);
                    return Err(Error::Vulkan { call: "vkGetFenceStatus", result });
                }
            }
        }
    }

    /// Records commands with `record`, submits them, and waits for completion.
    pub fn run_commands(&self, record: impl FnOnce(vk::CommandBuffer) -> Result<()>) -> Result<()> {
        self.check_usable()?;
        let mut commands = Commands::new(self)?;
        commands.begin()?;
        record(commands.buffer)?;
        commands.submit()?;
        commands.wait()?;
        self.check_validation()
    }

    /// Names a Vulkan object for validation messages and debuggers (only with validation on).
    pub(crate) fn name_object<H: vk::Handle>(&self, handle: H, name: &str) {
        if let Some(loader) = &self.object_names {
            let Ok(name) = CString::new(name) else { return };
            let info = vk::DebugUtilsObjectNameInfoEXT::default().object_handle(handle).object_name(&name);
            // Naming is best effort: a failure changes nothing about the work.
            // SAFETY: `handle` is a live object of this device; `info` and `name` outlive the call.
            let _ = unsafe { loader.set_debug_utils_object_name(&info) };
        }
    }
}

impl Drop for Context {
    fn drop(&mut self) {
        if self.forked() || self.lost.load(Ordering::Acquire) {
            // A forked child must not touch the parent's device, and a hung one may never
            // become idle: leave both, and the instance, to the process's end.
            return;
        }
        // SAFETY: every object of the device (buffers, structures, pipelines) holds an
        // `Arc<Context>` and so is already gone; once the device is idle nothing runs on it; the
        // allocator frees its memory before the device goes, and the instance goes last. Each is
        // dropped once, here.
        unsafe {
            let _ = self.device.device_wait_idle();
            for (pool, _, fence) in self.idle_commands.get_mut().unwrap_or_else(|e| e.into_inner()).drain(..) {
                self.device.destroy_fence(fence, None);
                self.device.destroy_command_pool(pool, None);
            }
            ManuallyDrop::drop(&mut self.allocator);
            self.device.destroy_device(None);
            ManuallyDrop::drop(&mut self.instance);
        }
    }
}

/// A timeline semaphore a submission waits for (`wait`: the value another API signals when the
/// work's inputs are ready) and then, where given, signals (`signal`, greater: its outputs are).
#[derive(Clone, Copy, Debug)]
pub struct Timeline {
    pub semaphore: vk::Semaphore,
    pub wait: u64,
    pub signal: Option<u64>,
}

/// A command pool with one primary command buffer and a fence: one submission at a time.
pub(crate) struct Commands<'a> {
    ctx: &'a Context,
    pool: vk::CommandPool,
    pub buffer: vk::CommandBuffer,
    fence: vk::Fence,
    /// Between `begin` and `submit`.
    recording: bool,
    /// Submitted and not yet waited for.
    pending: bool,
}

impl<'a> Commands<'a> {
    pub fn new(ctx: &'a Context) -> Result<Commands<'a>> {
        let idle = ctx.idle_commands.lock().unwrap_or_else(|e| e.into_inner()).pop();
        if let Some((pool, buffer, fence)) = idle {
            return Ok(Commands { ctx, pool, buffer, fence, recording: false, pending: false });
        }
        let pool_info = vk::CommandPoolCreateInfo::default()
            .queue_family_index(ctx.queue_family)
            .flags(vk::CommandPoolCreateFlags::RESET_COMMAND_BUFFER | vk::CommandPoolCreateFlags::TRANSIENT);
        // SAFETY: a valid create info for a queue family of this live device.
        let pool = unsafe { ctx.device.create_command_pool(&pool_info, None) }.vk("vkCreateCommandPool")?;
        let mut commands = Commands {
            ctx,
            pool,
            buffer: vk::CommandBuffer::null(),
            fence: vk::Fence::null(),
            recording: false,
            pending: false,
        };
        let alloc = vk::CommandBufferAllocateInfo::default()
            .command_pool(pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        // SAFETY: `pool` was just created, and only this `Commands` (one thread at a time) uses it.
        commands.buffer = unsafe { ctx.device.allocate_command_buffers(&alloc) }.vk("vkAllocateCommandBuffers")?[0];
        // SAFETY: a valid create info on a live device.
        commands.fence =
            unsafe { ctx.device.create_fence(&vk::FenceCreateInfo::default(), None) }.vk("vkCreateFence")?;
        Ok(commands)
    }

    /// Starts recording (after waiting for the previous submission, if any).
    pub fn begin(&mut self) -> Result<()> {
        self.wait()?;
        assert!(!self.recording, "Commands::begin while recording");
        let info = vk::CommandBufferBeginInfo::default().flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        // SAFETY: the buffer is neither recording nor pending (checked and waited for above), and
        // its pool lets `begin` reset it (RESET_COMMAND_BUFFER).
        unsafe { self.ctx.device.begin_command_buffer(self.buffer, &info) }.vk("vkBeginCommandBuffer")?;
        self.recording = true;
        Ok(())
    }

    /// Ends the recording and submits it, signalling the fence when it completes.
    pub fn submit(&mut self) -> Result<()> {
        self.submit_ordered(None)
    }

    /// As `submit`, ordered against other work by a timeline semaphore, where given.
    pub fn submit_ordered(&mut self, timeline: Option<Timeline>) -> Result<()> {
        assert!(self.recording, "Commands::submit without begin");
        self.recording = false;
        // SAFETY: the buffer is recording (checked above).
        unsafe { self.ctx.device.end_command_buffer(self.buffer) }.vk("vkEndCommandBuffer")?;
        // SAFETY: no pending submission uses the fence (`begin` waited for the last one).
        unsafe { self.ctx.device.reset_fences(&[self.fence]) }.vk("vkResetFences")?;
        self.ctx.submit(self.buffer, self.fence, timeline)?;
        self.pending = true;
        Ok(())
    }

    /// Waits for the submitted work, if any.
    pub fn wait(&mut self) -> Result<()> {
        if self.pending {
            self.ctx.wait_fence(self.fence)?;
            self.pending = false;
        }
        Ok(())
    }
}

impl Drop for Commands<'_> {
    fn drop(&mut self) {
        if self.ctx.forked() {
            return;
        }
        // Only reached pending on an error path; the GPU must finish before its pool goes away.
        // Where it never does (a hung device), the pool and fence are leaked, never freed in use.
        if self.pending && self.ctx.wait_fence(self.fence).is_err() {
            return;
        }
        // A set whose recording was abandoned (an error between begin and submit) is not reused.
        if !self.recording && self.fence != vk::Fence::null() && self.buffer != vk::CommandBuffer::null() {
            let mut idle = self.ctx.idle_commands.lock().unwrap_or_else(|e| e.into_inner());
            if idle.len() < IDLE_COMMANDS {
                idle.push((self.pool, self.buffer, self.fence));
                return;
            }
        }
        // SAFETY: nothing submitted from the pool is pending (waited for above, or never
        // submitted); the buffer goes with its pool, and each object is destroyed once.
        unsafe {
            if self.fence != vk::Fence::null() {
                self.ctx.device.destroy_fence(self.fence, None);
            }
            self.ctx.device.destroy_command_pool(self.pool, None);
        }
    }
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
    fn backend_names_round_trip() {
        for backend in [Backend::RayQuery, Backend::Pipeline] {
            assert_eq!(Backend::parse(backend.name()).unwrap(), backend);
        }
        assert!(Backend::parse("cuda").is_err());
    }

    #[test]
    fn gpus_rank_before_software() {
        assert!(
            device_rank(vk::PhysicalDeviceType::DISCRETE_GPU) < device_rank(vk::PhysicalDeviceType::INTEGRATED_GPU)
        );
        assert!(device_rank(vk::PhysicalDeviceType::INTEGRATED_GPU) < device_rank(vk::PhysicalDeviceType::CPU));
        assert!(device_rank(vk::PhysicalDeviceType::OTHER) < device_rank(vk::PhysicalDeviceType::CPU));
    }
}
