//! Compute shaders outside the trace variants: one module with its push-constant layout, and its
//! pipelines by specialization, compiled on first use outside any lock.

use std::sync::{Arc, Mutex};

use ash::vk;

use super::context::Context;
use super::shaders;
use crate::error::{vulkan_error, Error, Result, VkResultExt};

/// Threads per workgroup the kernels ask for (the device's limits may lower it).
const WORKGROUP_SIZE: u32 = 64;

/// One compute shader of a device, and the pipelines specialized from it.
pub struct ComputeKernel {
    ctx: Arc<Context>,
    layout: vk::PipelineLayout,
    /// Null where the device cannot load the shader (`refusal` says why).
    module: vk::ShaderModule,
    refusal: Option<String>,
    /// Threads per workgroup: specialization constant 0 of every pipeline.
    pub local_size: u32,
    /// (the other specialization constants, the pipeline).
    compiled: Mutex<Vec<(Vec<u32>, vk::Pipeline)>>,
    /// Bytes of its push constants.
    push_bytes: usize,
}

impl ComputeKernel {
    /// `spirv`'s kernel with `push_bytes` of push constants. A shader using f64 is loaded only
    /// on devices with shaderFloat64; elsewhere its pipelines raise `Error::Unsupported`: "<the
    /// device> has no shaderFloat64, which " and `needs_f64` (e.g. "packing rays on the GPU
    /// needs").
    pub fn new(ctx: &Arc<Context>, spirv: &[u8], push_bytes: usize, needs_f64: Option<&str>) -> Result<ComputeKernel> {
        let ranges =
            [vk::PushConstantRange::default().stage_flags(vk::ShaderStageFlags::COMPUTE).size(push_bytes as u32)];
        let layout_info = vk::PipelineLayoutCreateInfo::default().push_constant_ranges(&ranges);
        // SAFETY: a valid create info on a live device.
        let layout = unsafe { ctx.device.create_pipeline_layout(&layout_info, None) }.vk("vkCreatePipelineLayout")?;
        let refusal = needs_f64
            .filter(|_| !ctx.info.shader_float64)
            .map(|what| format!("{} has no shaderFloat64, which {what}", ctx.info.name));
        let module = if refusal.is_some() {
            vk::ShaderModule::null()
        } else {
            let code = shaders::words(spirv);
            let info = vk::ShaderModuleCreateInfo::default().code(&code);
            // SAFETY: SPIR-V compiled by glslc at build time (validated by the tests); where it
            // uses f64 the device has shaderFloat64.
            match unsafe { ctx.device.create_shader_module(&info, None) }.vk("vkCreateShaderModule") {
                Ok(module) => module,
                Err(error) => {
                    // SAFETY: the layout was just created and is used by nothing.
                    unsafe { ctx.device.destroy_pipeline_layout(layout, None) };
                    return Err(error);
                }
            }
        };
        let local_size = WORKGROUP_SIZE
            .min(ctx.limits.max_compute_work_group_size[0])
            .min(ctx.limits.max_compute_work_group_invocations);
        let compiled = Mutex::new(Vec::new());
        Ok(ComputeKernel { ctx: ctx.clone(), layout, module, refusal, local_size, compiled, push_bytes })
    }

    pub fn layout(&self) -> vk::PipelineLayout {
        self.layout
    }

    /// Whether the device loaded the shader.
    pub fn available(&self) -> bool {
        self.refusal.is_none()
    }

    /// Records into `cmd` (recording) one dispatch of `groups` workgroups of `pipeline` (one of
    /// this kernel's, from `pipeline`) with `params` as its push constants.
    pub fn record_dispatch<P: bytemuck::Pod>(
        &self,
        cmd: vk::CommandBuffer,
        pipeline: vk::Pipeline,
        params: &P,
        groups: u32,
    ) {
        assert_eq!(std::mem::size_of::<P>(), self.push_bytes, "push constants of the kernel's layout");
        assert!(groups <= self.ctx.limits.max_compute_work_group_count[0], "{groups} workgroups in one dispatch");
        let device = &self.ctx.device;
        // SAFETY: `cmd` is recording (the caller's promise); the pipeline was made by this kernel
        // with its live layout; the push constants cover exactly the layout's range (asserted);
        // `groups` is within maxComputeWorkGroupCount (asserted).
        unsafe {
            device.cmd_bind_pipeline(cmd, vk::PipelineBindPoint::COMPUTE, pipeline);
            device.cmd_push_constants(cmd, self.layout, vk::ShaderStageFlags::COMPUTE, 0, bytemuck::bytes_of(params));
            device.cmd_dispatch(cmd, groups, 1, 1);
        }
    }

    /// Most invocations one dispatch of `local_size` workgroups along x may cover.
    pub fn max_invocations(&self) -> usize {
        self.ctx.limits.max_compute_work_group_count[0] as usize * self.local_size as usize
    }

    /// The pipeline whose specialization constants 1, 2 ... are `constants` (0 is the local
    /// size): cached, or compiled now outside the lock.
    pub fn pipeline(&self, constants: &[u32]) -> Result<vk::Pipeline> {
        if let Some(refusal) = &self.refusal {
            return Err(Error::Unsupported(refusal.clone()));
        }
        let cached = |compiled: &[(Vec<u32>, vk::Pipeline)]| {
            compiled.iter().find(|(key, _)| key.as_slice() == constants).map(|&(_, pipeline)| pipeline)
        };
        if let Some(pipeline) = cached(&self.compiled.lock().unwrap_or_else(|e| e.into_inner())) {
            return Ok(pipeline);
        }
        let values: Vec<u32> = std::iter::once(self.local_size).chain(constants.iter().copied()).collect();
        let entries: Vec<vk::SpecializationMapEntry> = (0..values.len() as u32)
            .map(|id| vk::SpecializationMapEntry::default().constant_id(id).offset(4 * id).size(4))
            .collect();
        let spec = vk::SpecializationInfo::default().map_entries(&entries).data(bytemuck::cast_slice(&values));
        let stage = vk::PipelineShaderStageCreateInfo::default()
            .stage(vk::ShaderStageFlags::COMPUTE)
            .module(self.module)
            .name(c"main")
            .specialization_info(&spec);
        let info = [vk::ComputePipelineCreateInfo::default().stage(stage).layout(self.layout)];
        // SAFETY: the module and layout are live objects of this device; the specialization data
        // outlives the call.
        let built = unsafe { self.ctx.device.create_compute_pipelines(vk::PipelineCache::null(), &info, None) }
            .map_err(|(_, result)| vulkan_error("vkCreateComputePipelines", result))?[0];
        self.ctx.check_validation()?;
        let mut compiled = self.compiled.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(first) = cached(&compiled) {
            // SAFETY: `built` was never used.
            unsafe { self.ctx.device.destroy_pipeline(built, None) };
            return Ok(first);
        }
        compiled.push((constants.to_vec(), built));
        Ok(built)
    }
}

impl Drop for ComputeKernel {
    fn drop(&mut self) {
        if !self.ctx.can_free() {
            return;
        }
        // SAFETY: the owner drops a kernel only when no work using it is in flight (every query
        // waits for its own). Null modules are ignored by vkDestroyShaderModule.
        unsafe {
            for (_, pipeline) in self.compiled.get_mut().unwrap_or_else(|e| e.into_inner()).iter() {
                self.ctx.device.destroy_pipeline(*pipeline, None);
            }
            self.ctx.device.destroy_shader_module(self.module, None);
            self.ctx.device.destroy_pipeline_layout(self.layout, None);
        }
    }
}
