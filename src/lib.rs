//! vkray: Vulkan ray-tracing acceleration structures built from host arrays, and batched ray
//! casting on any Vulkan device with acceleration structures.
//!
//! The core has no Python in it; `python` (behind the `python` feature) maps it to `vkray._core`.

pub mod accel;
pub mod context;
pub mod error;
pub mod input;
pub mod memory;
pub mod precision;
pub mod reference;
pub mod scene;
pub mod shaders;
pub mod tiers;
pub mod trace;

#[cfg(feature = "python")]
mod python;

pub use context::{Backend, Context, DeviceInfo, DeviceRequest, Limits, Wait, WaitInPlace};
pub use error::{Error, Result};
