//! Which engine a device runs: the dispatcher over either engine (`DeviceTracer`), and what only
//! one engine has (the Vulkan engine's CUDA rays paths).

use std::sync::Arc;

use crate::error::Result;
use crate::gpu::cuda::Cuda;
use crate::trace::vulkan::cuda_all_hits::CudaAllHitsPath;
use crate::trace::vulkan::cuda_rays::CudaRaysPath;
use crate::trace::vulkan::inside_points::InsidePointsPath;
use crate::trace::{Engine, Tracer, VulkanEngine};

/// What a device's tracer is: a dispatcher over either engine.
pub(super) type DeviceTracer = Tracer<dyn Engine>;

/// The device's CUDA device where it was opened already (nothing is started: no cuInit, no
/// context), else None.
pub(super) fn opened_cuda(tracer: &DeviceTracer) -> Option<Arc<Cuda>> {
    tracer.engine().as_any().downcast_ref::<VulkanEngine>().and_then(|engine| engine.cuda.opened_cuda())
}

/// The device's CUDA rays path, where its engine has one (the Vulkan engine), and its CUDA
/// device, where its GPU shares memory with CUDA.
pub(super) fn cuda_of(tracer: &DeviceTracer) -> Result<(Option<&CudaRaysPath>, Option<Arc<Cuda>>)> {
    match tracer.engine().as_any().downcast_ref::<VulkanEngine>() {
        Some(engine) => Ok((Some(&engine.cuda), engine.cuda.cuda()?)),
        None => Ok((None, None)),
    }
}

/// The device's path for all hits of CUDA rays, where its engine has one (the Vulkan engine).
pub(super) fn cuda_all_hits_of(tracer: &DeviceTracer) -> Option<&CudaAllHitsPath> {
    tracer.engine().as_any().downcast_ref::<VulkanEngine>().map(|engine| &engine.cuda_all_hits)
}

/// The device's path for `contains` of CUDA points, where its engine has one (the Vulkan engine).
pub(super) fn inside_points_of(tracer: &DeviceTracer) -> Option<&InsidePointsPath> {
    tracer.engine().as_any().downcast_ref::<VulkanEngine>().map(|engine| &engine.inside_points)
}
