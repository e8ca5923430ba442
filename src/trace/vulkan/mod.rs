//! The Vulkan engine (`VulkanEngine`, the `Engine` seam over one Vulkan device). Its files, lowest
//! first (each imports only files above it in this list): the device's timestamps, pipeline
//! variants, staging, sensor records, the all-hits lists and their columns, the caps' winding pass; the value every path shares; then
//! each path, owning its state and borrowing the shared value: the host-packed chunk loop
//! (closest hit and the other ray queries), the probes, GPU-packed rays, the two together, CUDA
//! rays, all hits, all hits of CUDA rays, closest points, signed distances, `contains` through the inside grid and `contains`; last the engine that makes
//! them and dispatches to them.

pub mod timestamps;

pub mod variants;

pub mod staging;

pub mod sensor_upload;

pub mod hit_lists;

pub mod list_columns;

pub mod cap_winding;

pub mod shared;

pub mod ray_chunks;

pub mod probes;

pub mod packed_rays;

pub mod gpu_rays;

pub mod cuda_rays;

pub mod all_hits;

pub mod cuda_all_hits;

pub mod closest_points;

pub mod signed_distance;

pub mod inside_points;

pub mod containment;

pub mod vulkan_engine;

pub use vulkan_engine::{Explanation, VulkanEngine};
