//! The CPU engine (`CpuEngine`, the `Engine` seam over Embree on the host's cores). Its files,
//! lowest first: what each query decides about a candidate hit (`hit_filter`), the fast tier's
//! traversal (`cpu_rays`), and the engine.

pub mod hit_filter;

pub mod cpu_rays;

pub mod cpu_engine;

pub use cpu_engine::CpuEngine;
