//! The CPU engine's device: Embree 4 (Intel's CPU ray-tracing kernels, SIMD chosen at run time
//! for the machine's vector width), loaded at run time, and its objects as owned values.

pub mod api;

pub mod objects;
