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
    /// Device memory could not be allocated.
    #[error("GPU memory allocation failed: {0}")]
    Allocation(#[from] gpu_allocator::AllocationError),
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
        self.map_err(|result| Error::Vulkan { call, result })
    }
}

pub(crate) fn invalid_value(message: impl Into<String>) -> Error {
    Error::InvalidValue(message.into())
}
