//! The Vulkan side: instance and device selection, memory, acceleration-structure builds, the
//! records shaders read, and the embedded shaders.

pub mod context;

pub mod shaders;

pub mod external;

pub mod memory;

pub mod compute;

pub mod records;

pub mod cuda;

pub mod accel;
