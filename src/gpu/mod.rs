//! The Vulkan side: instance and device selection, memory, acceleration-structure builds, the
//! records shaders read, and the embedded shaders.

pub mod accel;
pub mod compute;
pub mod context;
pub mod cuda;
pub mod external;
pub mod memory;
pub mod records;
pub mod shaders;
