//! The one error type of the core. The Python binding maps each variant to one exception class.

use ash::vk;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An argument has a bad value (maps to `ValueError`).
    #[error("{0}")]
    InvalidValue(String),
    /// An argument has a bad type, dtype or shape (maps to `TypeError`).
    #[error("{0}")]
    InvalidType(String),
    /// The Vulkan loader or a suitable device could not be found.
    #[error("{0}")]
    NoDevice(String),
    /// The device lacks something this request needs.
    #[error("{0}")]
    Unsupported(String),
    /// A Vulkan call failed.
    #[error("{call} failed: {result}")]
    Vulkan { call: &'static str, result: vk::Result },
    /// Device memory could not be allocated for another reason than running out.
    #[error("GPU memory allocation failed: {0}")]
    Allocation(gpu_allocator::AllocationError),
    /// Host or device memory ran out, or a request could never fit (maps to `MemoryError`).
    #[error("{0}")]
    OutOfMemory(String),
    /// A CUDA driver call failed (arrays shared with CUDA; maps to `VulkanError`'s sibling
    /// `VkrayError`).
    #[error("{call} failed: CUDA error {code}")]
    Cuda { call: &'static str, code: i32 },
    /// The device was opened by the parent of this forked process (maps to `ForkedDeviceError`).
    #[error("{0}")]
    Forked(String),
    /// The caller asked the work to stop (Ctrl-C); the binding raises what its check raised.
    #[error("interrupted")]
    Interrupted,
    /// A bug in vkray: a panic caught before it reached the caller.
    #[error("internal error in vkray (please report it): {0}")]
    Internal(String),
    /// The Khronos validation layer reported problems (only with validation enabled).
    #[error("Vulkan validation layer reported:\n{0}")]
    Validation(String),
}

pub type Result<T> = std::result::Result<T, Error>;

/// Attaches the name of the failing Vulkan call to its result code.
pub(crate) trait VkResultExt<T> {
    fn vk(self, call: &'static str) -> Result<T>;
}

impl<T> VkResultExt<T> for std::result::Result<T, vk::Result> {
    fn vk(self, call: &'static str) -> Result<T> {
        self.map_err(|result| vulkan_error(call, result))
    }
}

/// A failed Vulkan call as an error: running out of memory is `OutOfMemory`, the rest `Vulkan`.
pub(crate) fn vulkan_error(call: &'static str, result: vk::Result) -> Error {
    match result {
        vk::Result::ERROR_OUT_OF_HOST_MEMORY | vk::Result::ERROR_OUT_OF_DEVICE_MEMORY => {
            Error::OutOfMemory(format!("{call} ran out of memory ({result})"))
        }
        result => Error::Vulkan { call, result },
    }
}

impl From<gpu_allocator::AllocationError> for Error {
    fn from(error: gpu_allocator::AllocationError) -> Error {
        match error {
            gpu_allocator::AllocationError::OutOfMemory => {
                Error::OutOfMemory("the device ran out of memory for a buffer".into())
            }
            other => Error::Allocation(other),
        }
    }
}

pub(crate) fn invalid_value(message: impl Into<String>) -> Error {
    Error::InvalidValue(message.into())
}

#[cfg(test)]
pub(crate) mod tests {
    use super::{Error, Result};

    /// The message of an `InvalidValue` error; panics on anything else.
    pub(crate) fn invalid_message(r: Result<()>) -> String {
        match r {
            Err(Error::InvalidValue(m)) => m,
            other => panic!("expected InvalidValue, got {other:?}"),
        }
    }
}
