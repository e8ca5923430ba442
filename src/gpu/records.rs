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

/// Where the triangles of one geometry live, for shaders (`GeometrySource` in shaders/records.glsl):
/// one per geometry of a mesh's BLAS.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct GeometrySource {
    /// f32 xyz tightly packed, or 4 halves / 4 snorm16 per vertex; or spheres (f32 centre, radius).
    pub vertices: u64,
    /// u32 corner triples, or u16 triples packed into words; 0 for spheres.
    pub indices: u64,
    /// Device triangle -> caller's triangle (u32 each), or 0 where they agree.
    pub primitive_order: u64,
    pub index_is_u16: u32,
    /// A `VertexFormat` (as u32), or `SPHERE_SOURCE`.
    pub vertex_format: u32,
}

/// `GeometrySource::vertex_format` of sphere sets (after the `VertexFormat`s).
pub const SPHERE_SOURCE: u32 = 3;

/// The exact tier's record of one instance (`ExactInstance` in shaders/records.glsl): the f64 map
/// from the scene's frame to the mesh's and where the mesh's exact-tier buffers live. 136 bytes
/// of data, 160 apart in arrays (std430 aligns the record to its dvec4s' 32 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct ExactInstance {
    /// Rows of the scene-to-mesh map: xyz linear, w offset.
    pub rows: [[f64; 4]; 3],
    /// f64 xyz per vertex, all parts.
    pub vertices: u64,
    /// u32 corner triples, in box order.
    pub indices: u64,
    /// Box -> caller's triangle among all parts (u32 each), or 0 where they agree.
    pub primitive_order: u64,
    /// u32: the first triangle of each part, then the total.
    pub part_offsets: u64,
    pub part_count: u32,
    /// `EXACT_CULL_DISABLE` | `EXACT_FLIP_FACING`.
    pub flags: u32,
    /// Up to the array stride (no data).
    pub _padding: [u64; 3],
}

/// `ExactInstance::flags`: query culling does not apply to the instance.
pub const EXACT_CULL_DISABLE: u32 = 1;
/// `ExactInstance::flags`: front is the side opposite the object-space normal.
pub const EXACT_FLIP_FACING: u32 = 2;

/// Checks a record's size and field offsets at compile time.
macro_rules! layout {
    ($record:ty, size $size:expr, $($field:ident @ $offset:expr),* $(,)?) => {
        const _: () = assert!(std::mem::size_of::<$record>() == $size);
        $(const _: () = assert!(std::mem::offset_of!($record, $field) == $offset);)*
    };
}

layout!(Params, size 128, rays @ 0, instances @ 8, tlas @ 16, outputs @ 24, scratch @ 80, masks @ 88, count @ 96,
    bounds @ 100, ray_mask @ 124);
layout!(GeometrySource, size 32, vertices @ 0, indices @ 8, primitive_order @ 16, index_is_u16 @ 24, vertex_format @ 28);
layout!(ExactInstance, size 160, rows @ 0, vertices @ 96, indices @ 104, primitive_order @ 112, part_offsets @ 120,
    part_count @ 128, flags @ 132, _padding @ 136);
layout!(ExactBest, size 40, t @ 0, u @ 8, v @ 16, instance @ 24, prim @ 28, custom @ 32, geometry @ 36);
