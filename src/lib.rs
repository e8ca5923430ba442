//! vkray: Vulkan ray-tracing acceleration structures built from host arrays, and batched ray
//! casting on any Vulkan device with acceleration structures.
//!
//! Layers, each importing only the ones above it in this list:
//! - `geometry`: host arrays and their checks, ray packing, vertex formats, f64 ray–triangle math
//!   and the CPU BVH (no Vulkan);
//! - `gpu`: the Vulkan device, memory, acceleration-structure builds, GPU records, shaders; and
//!   beside it `embree`: the CPU engine's device (Embree 4, loaded at run time);
//! - `scene`: meshes, instances, scenes and the exact tier's structures;
//! - `trace`: queries: hit fields, pipeline variants, staging, the chunk loop, the host tiers;
//! - `python` (behind the `python` feature): the binding module `vkray._core`, the only pyo3 code.

pub mod embree;
pub mod error;
pub mod geometry;
pub mod gpu;
pub mod scene;
pub mod trace;

#[cfg(feature = "python")]
mod python;

pub use error::{Error, Result};
pub use gpu::context::{Backend, Context, DeviceInfo, DeviceRequest, Limits};
