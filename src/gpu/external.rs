//! Memory the device shares: the caller's host memory imported in place
//! (VK_EXT_external_memory_host), and buffers and timeline semaphores exported as file descriptors
//! for another API (CUDA) to import (VK_KHR_external_memory_fd, VK_KHR_external_semaphore_fd).

use std::sync::Arc;

use ash::vk;

use crate::error::{Error, Result, VkResultExt};
use crate::gpu::context::Context;

/// Usage of every shared buffer: shaders reach it by address, copies may read and write it.
const SHARED_USAGE: vk::BufferUsageFlags = vk::BufferUsageFlags::from_raw(
    vk::BufferUsageFlags::STORAGE_BUFFER.as_raw()
        | vk::BufferUsageFlags::SHADER_DEVICE_ADDRESS.as_raw()
        | vk::BufferUsageFlags::TRANSFER_SRC.as_raw()
        | vk::BufferUsageFlags::TRANSFER_DST.as_raw(),
);

/// A buffer over memory of its own (not the allocator's): imported or exportable.
struct RawBuffer {
    ctx: Arc<Context>,
    buffer: vk::Buffer,
    memory: vk::DeviceMemory,
    address: u64,
}

impl RawBuffer {
    /// A buffer of `size` bytes created with `external` handle types, bound to memory allocated
    /// from `allocate` (which chains what the import or export needs) of a type in `type_bits`.
    fn new(
        ctx: &Arc<Context>,
        size: u64,
        external: vk::ExternalMemoryHandleTypeFlags,
        type_bits: u32,
        allocate: impl FnOnce(vk::MemoryAllocateInfo, vk::Buffer) -> Result<vk::DeviceMemory>,
        name: &str,
    ) -> Result<RawBuffer> {
        ctx.check_usable()?;
        let mut external_info = vk::ExternalMemoryBufferCreateInfo::default().handle_types(external);
        let info = vk::BufferCreateInfo::default()
            .size(size)
            .usage(SHARED_USAGE)
            .sharing_mode(vk::SharingMode::EXCLUSIVE)
            .push_next(&mut external_info);
        // SAFETY: a valid create info (size > 0, checked by the callers) on a live device.
        let buffer = unsafe { ctx.device.create_buffer(&info, None) }.vk("vkCreateBuffer")?;
        let mut raw = RawBuffer { ctx: ctx.clone(), buffer, memory: vk::DeviceMemory::null(), address: 0 };
        // SAFETY: `buffer` was just created on this device.
        let requirements = unsafe { ctx.device.get_buffer_memory_requirements(buffer) };
        let Some(memory_type) = first_bit(requirements.memory_type_bits & type_bits) else {
            return Err(Error::Unsupported(format!("no memory type of {} can hold {name}", ctx.info.name)));
        };
        let info = vk::MemoryAllocateInfo::default().allocation_size(requirements.size).memory_type_index(memory_type);
        raw.memory = allocate(info, buffer)?;
        // SAFETY: `buffer` is unbound; `memory` was allocated for its requirements (the callers
        // allocate at least `requirements.size` bytes of a type the buffer accepts).
        unsafe { ctx.device.bind_buffer_memory(buffer, raw.memory, 0) }.vk("vkBindBufferMemory")?;
        let info = vk::BufferDeviceAddressInfo::default().buffer(buffer);
        // SAFETY: the buffer is bound and has SHADER_DEVICE_ADDRESS usage; its memory was
        // allocated with the device-address flag (`device_address_flags`).
        raw.address = unsafe { ctx.device.get_buffer_device_address(&info) };
        ctx.name_object(buffer, name);
        Ok(raw)
    }
}

impl Drop for RawBuffer {
    fn drop(&mut self) {
        if !self.ctx.can_free() {
            return;
        }
        // SAFETY: the owners drop these only once no submitted work uses them (every query waits
        // for its own); each is destroyed once; a null memory handle is ignored by Vulkan.
        unsafe {
            self.ctx.device.destroy_buffer(self.buffer, None);
            self.ctx.device.free_memory(self.memory, None);
        }
    }
}

/// Lowest set bit's index.
fn first_bit(bits: u32) -> Option<u32> {
    (bits != 0).then(|| bits.trailing_zeros())
}

/// The allocate flags every shared allocation needs: shaders reach it by address.
fn device_address_flags() -> vk::MemoryAllocateFlagsInfo<'static> {
    vk::MemoryAllocateFlagsInfo::default().flags(vk::MemoryAllocateFlags::DEVICE_ADDRESS)
}

/// The caller's host memory, imported in place: the device reads and writes it through
/// `address` with no copy. The import covers the whole pages around the bytes.
pub struct HostImport {
    raw: RawBuffer,
    /// Bytes from the start of the imported pages to the caller's first byte.
    offset: u64,
}

impl HostImport {
    /// Imports `len` bytes at `ptr`, or `None` where this device cannot (no
    /// VK_EXT_external_memory_host, or the driver refuses this memory).
    ///
    /// # Safety
    /// The bytes must stay allocated, and not be read or written by the host while the device
    /// may use them, until the import is dropped.
    pub unsafe fn new(ctx: &Arc<Context>, ptr: *const u8, len: usize) -> Result<Option<HostImport>> {
        let (Some(loader), Some(alignment)) = (&ctx.host_memory, ctx.interop.host_import_alignment) else {
            return Ok(None);
        };
        if len == 0 || alignment == 0 || !alignment.is_power_of_two() {
            return Ok(None);
        }
        let start = ptr as u64 & !(alignment - 1);
        let end = crate::geometry::align::align_up(ptr as u64 + len as u64, alignment);
        let handle_type = vk::ExternalMemoryHandleTypeFlags::HOST_ALLOCATION_EXT;
        let mut properties = vk::MemoryHostPointerPropertiesEXT::default();
        // SAFETY: `start` is aligned as the device asks and lies in the caller's allocation's
        // pages, which are mapped (they hold the caller's bytes); `properties` is writable.
        let result = unsafe {
            (loader.fp().get_memory_host_pointer_properties_ext)(
                ctx.device.handle(),
                handle_type,
                start as *const std::ffi::c_void,
                &mut properties,
            )
        };
        if result != vk::Result::SUCCESS {
            return Ok(None);
        }
        let allocate = |info: vk::MemoryAllocateInfo, _| -> Result<vk::DeviceMemory> {
            let mut import =
                vk::ImportMemoryHostPointerInfoEXT::default().handle_type(handle_type).host_pointer(start as *mut _);
            let mut flags = device_address_flags();
            let info = info.allocation_size(end - start).push_next(&mut import).push_next(&mut flags);
            // SAFETY: the pointer and size are aligned to minImportedHostPointerAlignment and
            // cover mapped pages that outlive the import (the caller's contract).
            unsafe { ctx.device.allocate_memory(&info, None) }.vk("vkAllocateMemory (host import)")
        };
        match RawBuffer::new(
            ctx,
            end - start,
            handle_type,
            properties.memory_type_bits,
            allocate,
            "imported host memory",
        ) {
            Ok(raw) => Ok(Some(HostImport { raw, offset: ptr as u64 - start })),
            // The driver may refuse some memory (for example memory it cannot pin): copy instead.
            Err(Error::Vulkan { .. } | Error::Unsupported(_) | Error::OutOfMemory(_)) => Ok(None),
            Err(e) => Err(e),
        }
    }

    /// The device address of the caller's first byte.
    pub fn address(&self) -> u64 {
        self.raw.address + self.offset
    }
}

/// Device-local memory exported as an opaque file descriptor, for another API (CUDA) to import
/// and reach as its own memory: one dedicated allocation.
pub struct ExportedBuffer {
    raw: RawBuffer,
    size: u64,
}

impl ExportedBuffer {
    /// A buffer of `size` bytes (at least 1) whose memory can be exported.
    pub fn new(ctx: &Arc<Context>, size: u64, name: &str) -> Result<ExportedBuffer> {
        if ctx.memory_fd.is_none() {
            return Err(Error::Unsupported(format!(
                "{} cannot export memory (VK_KHR_external_memory_fd)",
                ctx.info.name
            )));
        }
        let size = size.max(1);
        let handle_type = vk::ExternalMemoryHandleTypeFlags::OPAQUE_FD;
        let device_local = device_local_types(ctx);
        let allocate = |info: vk::MemoryAllocateInfo, buffer| -> Result<vk::DeviceMemory> {
            let mut export = vk::ExportMemoryAllocateInfo::default().handle_types(handle_type);
            let mut flags = device_address_flags();
            // Dedicated: CUDA imports it whole (CUDA_EXTERNAL_MEMORY_DEDICATED).
            let mut dedicated = vk::MemoryDedicatedAllocateInfo::default().buffer(buffer);
            let info = info.push_next(&mut export).push_next(&mut flags).push_next(&mut dedicated);
            // SAFETY: a valid allocate info on a live device, its chain live through the call.
            unsafe { ctx.device.allocate_memory(&info, None) }.vk("vkAllocateMemory (exportable)")
        };
        let raw = RawBuffer::new(ctx, size, handle_type, device_local, allocate, name)?;
        // The allocation's size is what the importer must be told.
        // SAFETY: the buffer is live.
        let size = unsafe { ctx.device.get_buffer_memory_requirements(raw.buffer) }.size;
        Ok(ExportedBuffer { raw, size })
    }

    pub fn address(&self) -> u64 {
        self.raw.address
    }

    /// The buffer, for Vulkan's copies into and out of it.
    pub fn raw(&self) -> vk::Buffer {
        self.raw.buffer
    }

    /// Bytes of the allocation (at least the buffer's).
    pub fn size(&self) -> u64 {
        self.size
    }

    /// A new file descriptor for the memory; whoever imports it owns it.
    pub fn export_fd(&self) -> Result<std::os::fd::OwnedFd> {
        let loader = self.raw.ctx.memory_fd.as_ref().expect("checked at creation");
        let info = vk::MemoryGetFdInfoKHR::default()
            .memory(self.raw.memory)
            .handle_type(vk::ExternalMemoryHandleTypeFlags::OPAQUE_FD);
        // SAFETY: the memory was allocated exportable as OPAQUE_FD on this device.
        let fd = unsafe { loader.get_memory_fd(&info) }.vk("vkGetMemoryFdKHR")?;
        // SAFETY: vkGetMemoryFdKHR returns a new descriptor the caller owns.
        Ok(unsafe { std::os::fd::FromRawFd::from_raw_fd(fd) })
    }
}

/// The device-local memory types' bits.
fn device_local_types(ctx: &Context) -> u32 {
    // SAFETY: the physical device belongs to the live instance.
    let memory = unsafe { ctx.instance().get_physical_device_memory_properties(ctx.physical) };
    (0..memory.memory_type_count)
        .filter(|&k| memory.memory_types[k as usize].property_flags.contains(vk::MemoryPropertyFlags::DEVICE_LOCAL))
        .fold(0, |bits, k| bits | (1 << k))
}

/// A timeline semaphore exported as an opaque file descriptor: another API signals and waits
/// for its values too.
pub struct ExportedSemaphore {
    ctx: Arc<Context>,
    pub semaphore: vk::Semaphore,
}

impl ExportedSemaphore {
    pub fn new(ctx: &Arc<Context>) -> Result<ExportedSemaphore> {
        if ctx.semaphore_fd.is_none() {
            return Err(Error::Unsupported(format!(
                "{} cannot export semaphores (VK_KHR_external_semaphore_fd)",
                ctx.info.name
            )));
        }
        let mut kind = vk::SemaphoreTypeCreateInfo::default().semaphore_type(vk::SemaphoreType::TIMELINE);
        let mut export =
            vk::ExportSemaphoreCreateInfo::default().handle_types(vk::ExternalSemaphoreHandleTypeFlags::OPAQUE_FD);
        let info = vk::SemaphoreCreateInfo::default().push_next(&mut kind).push_next(&mut export);
        // SAFETY: a valid create info (timeline semaphores are on with export) on a live device.
        let semaphore = unsafe { ctx.device.create_semaphore(&info, None) }.vk("vkCreateSemaphore")?;
        Ok(ExportedSemaphore { ctx: ctx.clone(), semaphore })
    }

    /// A new file descriptor for the semaphore; whoever imports it owns it.
    pub fn export_fd(&self) -> Result<std::os::fd::OwnedFd> {
        let loader = self.ctx.semaphore_fd.as_ref().expect("checked at creation");
        let info = vk::SemaphoreGetFdInfoKHR::default()
            .semaphore(self.semaphore)
            .handle_type(vk::ExternalSemaphoreHandleTypeFlags::OPAQUE_FD);
        // SAFETY: the semaphore was created exportable as OPAQUE_FD on this device.
        let fd = unsafe { loader.get_semaphore_fd(&info) }.vk("vkGetSemaphoreFdKHR")?;
        // SAFETY: vkGetSemaphoreFdKHR returns a new descriptor the caller owns.
        Ok(unsafe { std::os::fd::FromRawFd::from_raw_fd(fd) })
    }
}

impl Drop for ExportedSemaphore {
    fn drop(&mut self) {
        if !self.ctx.can_free() {
            return;
        }
        // SAFETY: the owner drops it only once no submitted work waits for or signals it.
        unsafe { self.ctx.device.destroy_semaphore(self.semaphore, None) };
    }
}
