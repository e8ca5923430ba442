//! Host-side geometry: the caller's arrays and their checks, rays and their packing, vertex
//! formats, Morton order, f64 ray–triangle math, the CPU BVH and winding numbers over it.
//! Nothing here touches Vulkan.

pub mod align;

pub mod build_options;

pub mod parallel;

pub mod interrupt;

pub mod precision;

pub mod sensor;

pub mod arrays;

pub mod bvh;

pub mod wide_tree;

pub mod winding;

pub mod reference;

pub mod morton;

pub mod rays;

pub mod vertex_format;
