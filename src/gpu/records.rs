//! The records the host writes and shaders read, mirrored from `shaders/records.glsl` (their one
//! definition). Each struct is `#[repr(C)]` plain data (bytemuck) with its size and field offsets
//! asserted at compile time against the std430 layout the shaders use; a test also reads the
//! offsets glslc assigned out of the compiled SPIR-V.

use bytemuck::{Pod, Zeroable};

/// The push constants of every query (`Params` in shaders/records.glsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct Params {
    pub rays: u64,
    /// InstanceGeometries (fast tier) or ExactInstances (exact tier).
    pub instances: u64,
    pub tlas: u64,
    /// Where each hit field goes, in `trace::Field` order (0: not written).
    pub outputs: [u64; 7],
    /// Exact tier, pipeline backend: the per-ray `ExactBest` records its intersection shader keeps.
    pub scratch: u64,
    /// Per-ray masks (one u32 each), or 0 when every ray uses `ray_mask`.
    pub masks: u64,
    pub count: u32,
    /// Exact tier: the scene's bounds (min xyz, max xyz) in its frame, rounded outward to f32.
    pub bounds: [f32; 6],
    pub ray_mask: u32,
}

/// The exact tier's best hit so far, per ray (`ExactBest` in shaders/records.glsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct ExactBest {
    pub t: f64,
    pub u: f64,
    pub v: f64,
    pub instance: i32,
    pub prim: i32,
    pub custom: i32,
    pub geometry: i32,
}

/// Checks a record's size and field offsets at compile time.
macro_rules! layout {
    ($record:ty, size $size:expr, $($field:ident @ $offset:expr),* $(,)?) => {
        const _: () = assert!(std::mem::size_of::<$record>() == $size);
        $(const _: () = assert!(std::mem::offset_of!($record, $field) == $offset);)*
    };
}

layout!(Params, size 128, rays @ 0, instances @ 8, tlas @ 16, outputs @ 24, scratch @ 80, masks @ 88, count @ 96,
    bounds @ 100, ray_mask @ 124);
layout!(ExactBest, size 40, t @ 0, u @ 8, v @ 16, instance @ 24, prim @ 28, custom @ 32, geometry @ 36);
