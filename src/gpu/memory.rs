//! Buffers in device memory (through gpu-allocator) and their uploads.

use std::sync::Arc;

use ash::vk;
use bytemuck::Pod;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
pub use gpu_allocator::MemoryLocation;

use crate::error::{Error, Result, VkResultExt};
pub use crate::geometry::align::align_up;
use crate::gpu::context::Context;

/// Usage of buffers that acceleration-structure builds and shaders read (vertices, indices, boxes,
/// instance records, records shaders reach by address).
pub const GEOMETRY_INPUT: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(
    vk::BufferUsageFlags::ACCELERATION_STRUCTURE_BUILD_INPUT_READ_ONLY_KHR.as_raw()
        | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS.as_raw()
        | vk::BufferUsageFlags::STORAGE_BUFFER.as_raw(),
);

/// Where a discrete GPU's upload staging lives, the host writing it and a copy reading it:
/// `CpuToGpu` (gpu-allocator's choice: device memory the host reaches through the PCIe BAR, where
/// the device has it) unless VKRAY_UPLOAD_STAGING=system asks for system memory (`GpuToCpu`: host
/// memory, cached), which the copy then reads over the bus. A knob to measure which is faster.
pub fn upload_staging() -> MemoryLocation {
    match std::env::var("VKRAY_UPLOAD_STAGING").as_deref() {
        Ok("system") => MemoryLocation::GpuToCpu,
        _ => MemoryLocation::CpuToGpu,
    }
}

/// A Vulkan buffer with its own memory allocation; freed when dropped.
pub struct Buffer {
    ctx: Arc<Context>,
    raw: vk::Buffer,
    allocation: Option<Allocation>,
    size: u64,
    address: u64,
}

impl Buffer {
    /// A buffer of `size` bytes (at least 1). Buffers used by shaders or acceleration-structure
    /// builds get `SHADER_DEVICE_ADDRESS` so they can be reached by address.
    pub fn new(
        ctx: &Arc<Context>,
        size: u64,
        usage: vk::BufferUsageFlags,
        location: MemoryLocation,
        name: &str,
    ) -> Result<Buffer> {
        ctx.check_usable()?;
        let size = size.max(1);
        let info = vk::BufferCreateInfo::default().size(size).usage(usage).sharing_mode(vk::SharingMode::EXCLUSIVE);
        let device = &ctx.device;
        // SAFETY: a valid create info (size at least 1) on a live device.
        let raw = unsafe { device.create_buffer(&info, None) }.vk("vkCreateBuffer")?;
        let mut buffer = Buffer { ctx: ctx.clone(), raw, allocation: None, size, address: 0 };
        // SAFETY: `raw` was just created on this device.
        let requirements = unsafe { device.get_buffer_memory_requirements(raw) };
        let allocation = ctx.allocator().allocate(&AllocationCreateDesc {
            name,
            requirements,
            location,
            linear: true,
            allocation_scheme: AllocationScheme::GpuAllocatorManaged,
        })?;
        // Stored first, so that every return below frees it with the buffer.
        buffer.allocation = Some(allocation);
        let allocation = buffer.allocation.as_ref().expect("just stored");
        if mapping_failed(allocation) {
            return Err(Error::OutOfMemory(format!(
                "{size} bytes of host-visible memory for {name} could not be mapped (the address space is exhausted)"
            )));
        }
        // SAFETY: `raw` is unbound and `allocation` was made for its memory requirements.
        unsafe { device.bind_buffer_memory(raw, allocation.memory(), allocation.offset()) }.vk("vkBindBufferMemory")?;
        if usage.contains(vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS) {
            let info = vk::BufferDeviceAddressInfo::default().buffer(raw);
            // SAFETY: `raw` is bound to memory and has SHADER_DEVICE_ADDRESS usage (the device has
            // bufferDeviceAddress on, and the allocator allocates with the device-address flag).
            buffer.address = unsafe { device.get_buffer_device_address(&info) };
        }
        ctx.name_object(raw, name);
        Ok(buffer)
    }

    pub fn raw(&self) -> vk::Buffer {
        self.raw
    }

    pub fn size(&self) -> u64 {
        self.size
    }

    /// The buffer's device address (0 unless created with `SHADER_DEVICE_ADDRESS`).
    pub fn address(&self) -> u64 {
        self.address
    }

    /// The buffer's bytes, where its memory is host-visible.
    pub fn mapped(&self) -> Option<&[u8]> {
        let allocation = self.allocation.as_ref()?;
        let slice = allocation.mapped_slice()?;
        Some(&slice[..self.size as usize])
    }

    /// Where a host-visible buffer is mapped, for writers that hold it shared.
    pub fn mapped_ptr(&self) -> Option<*mut u8> {
        self.allocation.as_ref()?.mapped_ptr().map(|p| p.as_ptr() as *mut u8)
    }

    pub fn mapped_mut(&mut self) -> Option<&mut [u8]> {
        let size = self.size as usize;
        let slice = self.allocation.as_mut()?.mapped_slice_mut()?;
        Some(&mut slice[..size])
    }
}

/// Whether the driver "mapped" the allocation's memory block at `MAP_FAILED` (`(void*)-1`): lavapipe
/// reports success with that pointer when `mmap` fails under an address-space limit, and writing
/// through it would crash the process.
fn mapping_failed(allocation: &Allocation) -> bool {
    allocation
        .mapped_ptr()
        .is_some_and(|p| (p.as_ptr() as usize).wrapping_sub(allocation.offset() as usize) == usize::MAX)
}

impl Drop for Buffer {
    fn drop(&mut self) {
        if !self.ctx.can_free() {
            return;
        }
        // SAFETY: `raw` is destroyed once, and no work in flight uses it: every submission is
        // waited for before the call that made it returns (the buffer's owner outlives that
        // call), and where a wait gave up, `can_free` leaks the buffer instead.
        unsafe { self.ctx.device.destroy_buffer(self.raw, None) };
        if let Some(allocation) = self.allocation.take() {
            // Freeing only fails for allocations this allocator does not own; nothing to undo.
            let _ = self.ctx.allocator().free(allocation);
        }
    }
}

/// Fills device-local buffers from the host. Where the device shares memory with the host (lavapipe,
/// integrated GPUs) the bytes are written in place; otherwise they go into staging buffers whose
/// copies are recorded by `record` into the command buffer that then uses them.
#[derive(Default)]
pub struct Uploads {
    staging: Vec<(Buffer, vk::Buffer, u64)>,
}

impl Uploads {
    /// A device-local buffer of `size` bytes whose contents `fill` writes; `fill` also gets the
    /// buffer's device address, for contents that must start at an aligned address.
    pub fn buffer(
        &mut self,
        ctx: &Arc<Context>,
        size: u64,
        usage: vk::BufferUsageFlags,
        name: &str,
        fill: impl FnOnce(&mut [u8], u64),
    ) -> Result<Buffer> {
        let location = if ctx.unified_memory { MemoryLocation::CpuToGpu } else { MemoryLocation::GpuOnly };
        let mut buffer = Buffer::new(ctx, size, usage | vk::BufferUsageFlags::TRANSFER_DST, location, name)?;
        let address = buffer.address();
        if let Some(bytes) = buffer.mapped_mut() {
            fill(&mut bytes[..size as usize], address);
            return Ok(buffer);
        }
        let mut staging =
            Buffer::new(ctx, size, vk::BufferUsageFlags::TRANSFER_SRC, MemoryLocation::CpuToGpu, "staging")?;
        let bytes = staging.mapped_mut().expect("CpuToGpu memory is host-visible");
        fill(&mut bytes[..size as usize], address);
        if size > 0 {
            self.staging.push((staging, buffer.raw(), size));
        }
        Ok(buffer)
    }

    /// A device-local buffer holding `records` (plain data: numbers, arrays of them, or the
    /// structs of `gpu::records`), exactly their bytes.
    pub fn records<T: Pod>(
        &mut self,
        ctx: &Arc<Context>,
        records: &[T],
        usage: vk::BufferUsageFlags,
        name: &str,
    ) -> Result<Buffer> {
        let bytes: &[u8] = bytemuck::cast_slice(records);
        self.buffer(ctx, bytes.len() as u64, usage, name, |out, _| out.copy_from_slice(bytes))
    }

    /// New contents for an existing device buffer of `Uploads::buffer`'s making: written in place
    /// where mapped, else through staging copied by `record`. The caller makes sure the device is
    /// not reading the buffer meanwhile.
    pub fn overwrite(&mut self, ctx: &Arc<Context>, buffer: &Buffer, fill: impl FnOnce(&mut [u8])) -> Result<()> {
        let size = buffer.size();
        if let Some(ptr) = buffer.mapped_ptr() {
            // SAFETY: the allocation is persistently mapped and at least `size` bytes; the caller
            // keeps the device and other threads off the buffer meanwhile (see above).
            fill(unsafe { std::slice::from_raw_parts_mut(ptr, size as usize) });
            return Ok(());
        }
        let mut staging =
            Buffer::new(ctx, size, vk::BufferUsageFlags::TRANSFER_SRC, MemoryLocation::CpuToGpu, "staging")?;
        fill(&mut staging.mapped_mut().expect("CpuToGpu memory is host-visible")[..size as usize]);
        if size > 0 {
            self.staging.push((staging, buffer.raw(), size));
        }
        Ok(())
    }

    /// Records the staging copies and a barrier that makes them visible to every later command.
    pub fn record(&self, ctx: &Context, cmd: vk::CommandBuffer) {
        if self.staging.is_empty() {
            return;
        }
        for (staging, dst, size) in &self.staging {
            let region = [vk::BufferCopy::default().size(*size)];
            // SAFETY: `cmd` is recording; both buffers are live, at least `size` bytes, with
            // transfer usage; the staging buffer lives in `self` and `dst` with the caller, both
            // until the submission is waited for.
            unsafe { ctx.device.cmd_copy_buffer(cmd, staging.raw(), *dst, &region) };
        }
        memory_barrier(
            ctx,
            cmd,
            (vk::PipelineStageFlags::TRANSFER, vk::AccessFlags::TRANSFER_WRITE),
            (vk::PipelineStageFlags::ALL_COMMANDS, vk::AccessFlags::MEMORY_READ),
        );
    }
}

/// A pipeline stage and the memory access in it that a barrier orders.
pub type StageAccess = (vk::PipelineStageFlags, vk::AccessFlags);

/// A global memory barrier between two stages: what `from` wrote before what `to` reads.
pub fn memory_barrier(ctx: &Context, cmd: vk::CommandBuffer, from: StageAccess, to: StageAccess) {
    let ((src_stage, src_access), (dst_stage, dst_access)) = (from, to);
    let barrier = [vk::MemoryBarrier::default().src_access_mask(src_access).dst_access_mask(dst_access)];
    // SAFETY: `cmd` is recording; a global memory barrier names no objects.
    unsafe {
        ctx.device.cmd_pipeline_barrier(cmd, src_stage, dst_stage, vk::DependencyFlags::empty(), &barrier, &[], &[])
    };
}

/// Host memory a new allocation can still count on, in bytes: the kernel's estimate of available
/// memory, less what an address-space limit (`RLIMIT_AS`) leaves; `None` where neither is known.
pub fn host_memory_available() -> Option<u64> {
    let read = |path: &str| std::fs::read_to_string(path).ok();
    let field = |text: &str, name: &str| -> Option<u64> {
        let line = text.lines().find(|l| l.starts_with(name))?;
        line[name.len()..].split_whitespace().next()?.parse().ok()
    };
    let available = read("/proc/meminfo").and_then(|t| field(&t, "MemAvailable:")).map(|kb| kb * 1024);
    // The process's own size is read only under a limit (a file of /proc less a query).
    let headroom = address_space_limit().and_then(|limit| {
        let used = read("/proc/self/status").and_then(|t| field(&t, "VmSize:"))? * 1024;
        Some(limit.saturating_sub(used))
    });
    match (available, headroom) {
        (Some(a), Some(h)) => Some(a.min(h)),
        (a, h) => a.or(h),
    }
}

/// The soft limit of the process's address space (`RLIMIT_AS`) in bytes, where one is set: a
/// system call, where `/proc/self/limits` was a file to format and parse.
fn address_space_limit() -> Option<u64> {
    let mut limit = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
    // SAFETY: getrlimit only writes the struct it is given.
    let known = unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut limit) } == 0;
    (known && limit.rlim_cur != libc::RLIM_INFINITY).then_some(limit.rlim_cur)
}

/// Requests smaller than this are not checked against the host memory available: reading it (two
/// or three files of /proc) took 80 µs, most of a query of a few rays, and no request this small
/// decides whether a process outgrows its machine.
const SMALLEST_CHECKED_BYTES: u128 = 16 << 20;

/// The host memory available (`host_memory_available`) where `bytes` more exceed it; None where
/// they fit, where it is unknown, or where the request is too small to check.
pub fn short_of_host_memory(bytes: u128) -> Option<u64> {
    if bytes < SMALLEST_CHECKED_BYTES {
        return None;
    }
    host_memory_available().filter(|&available| bytes > u128::from(available))
}
