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
    /// Per-ray masks (one u32 each), or 0 when every ray uses `ray_mask`. Rays a sensor
    /// generates (which share `ray_mask`): the chunk's first ray.
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
    /// f32 opacity in [0, 1] per device triangle, or 0 where every triangle is opaque.
    pub opacity: u64,
    pub index_is_u16: u32,
    /// A `VertexFormat` (as u32), or `SPHERE_SOURCE`.
    pub vertex_format: u32,
}

/// `GeometrySource::vertex_format` of sphere sets (after the `VertexFormat`s).
pub const SPHERE_SOURCE: u32 = 3;

/// The exact tier's record of one instance (`ExactInstance` in shaders/records.glsl): the f64 map
/// from the scene's frame to the mesh's and where the mesh's exact-tier buffers live: 160 bytes
/// (std430 aligns the record to its dvec4s' 32 bytes).
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
    /// f32 opacity per caller's triangle among all parts, or 0 where all are opaque.
    pub opacity: u64,
    /// Up to the record's 32-byte alignment (no data).
    pub _padding: [u64; 2],
}

/// `ExactInstance::flags`: query culling does not apply to the instance.
pub const EXACT_CULL_DISABLE: u32 = 1;
/// `ExactInstance::flags`: front is the side opposite the object-space normal.
pub const EXACT_FLIP_FACING: u32 = 2;

/// Where one ray keeps its nearest hits in an all-hits query (`HitList` in shaders/records.glsl):
/// `capacity` records from `first` among its chunk's records (`HIT_LIST_APPEND` set: appended as
/// met, for the host to sort).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct HitList {
    pub first: u32,
    pub capacity: u32,
}

/// `HitList::capacity` flag: the list holds every hit of its ray, in the order traversal met them.
pub const HIT_LIST_APPEND: u32 = 0x8000_0000;

/// One stored hit of the fast tier (`FastHit` in shaders/records.glsl): f32 t and barycentrics,
/// the caller's triangle within its geometry. As large and as aligned as `ExactHit`, so that the
/// host can turn a vector of them into the CPU tracer's records in place.
#[repr(C, align(8))]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct FastHit {
    pub t: f32,
    pub u: f32,
    pub v: f32,
    pub instance: i32,
    pub geometry: i32,
    pub prim: i32,
    pub unused: [u32; 2],
}

/// One stored hit of the exact tier (`ExactHit` in shaders/records.glsl): the CPU tracer's own
/// record, so that both tiers' hits are written out by one function.
pub type ExactHit = crate::geometry::reference::ReferenceHit;

/// A sensor whose rays the shaders generate (`Sensor` in shaders/records.glsl), one per chunk.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct Sensor {
    /// xyz; w: the fast tier's tmin.
    pub origin: [f32; 4],
    /// Three vectors (xyz); `axes[0][3]`: the fast tier's tmax.
    pub axes: [[f32; 4]; 3],
    /// `SENSOR_PINHOLE`, `SENSOR_ORTHOGRAPHIC` or `SENSOR_LIDAR`.
    pub kind: u32,
    /// Image width, or lidar steps.
    pub columns: u32,
    /// Image height, or lidar channels.
    pub rows: u32,
    pub pixel_offset: f32,
    /// Lidar: (cos, sin) per channel, then per step (f32 each).
    pub table: u64,
    /// The exact tier's interval, f64.
    pub tmin64: f64,
    pub tmax64: f64,
    /// The exact tier: the scene frame's offset, f64.
    pub shift: [f64; 3],
}

pub const SENSOR_PINHOLE: u32 = 1;
pub const SENSOR_ORTHOGRAPHIC: u32 = 2;
pub const SENSOR_LIDAR: u32 = 3;

/// The push constants of closest points (`PointParams` in shaders/records.glsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct PointParams {
    /// xyz per point, world: f64, or f32 where bit 0 is set (shaders/points.glsl).
    pub points: u64,
    /// f64 distance per point.
    pub distances: u64,
    /// `PointHit` per point, or 0 when only distances are asked.
    pub hits: u64,
    /// `BvhNode`s of every mesh, one after another.
    pub nodes: u64,
    /// `BvhTriangle`s of every mesh, in its leaves' order.
    pub triangles: u64,
    /// `BvhInstance` per instance.
    pub instances: u64,
    /// `BvhNode`s over the instances' bounds (the scene's frame).
    pub top_nodes: u64,
    /// u32 instance indices in the top hierarchy's leaf order.
    pub top_items: u64,
    /// Winding numbers: `WindingSpan` per node of `nodes` (0 for closest points).
    pub spans: u64,
    /// Winding numbers: `WindingEdge`s, every node's boundary.
    pub edges: u64,
    /// u32 per point: the order to search the points in (point_order.comp), or 0: as they come.
    pub order: u64,
    /// The scene frame's offset: world = scene + center.
    pub center: [f64; 3],
    pub max_distance: f64,
    pub count: u32,
    pub instance_count: u32,
}

/// The push constants of point_order.comp (`PointOrderParams` in shaders/records.glsl): one
/// chunk's points, its grid's cells and the order it writes.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct PointOrderParams {
    /// As `PointParams`'.
    pub points: u64,
    /// u32 per cell.
    pub cells: u64,
    /// u32 per point.
    pub order: u64,
    /// The grid's corner (world) and cells per unit along each axis.
    pub corner: [f64; 3],
    pub scale: [f64; 3],
    pub count: u32,
    /// `POINT_ORDER_*`.
    pub pass: u32,
}

/// The push constants of cap_winding.comp (`CapWindingParams` in shaders/records.glsl): one
/// chunk of a winding query after its ray pass, whose caps' winding numbers it sums.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct CapWindingParams {
    /// The cap's `WindingCapHeader`.
    pub cap: u64,
    /// Each ray's origin less `shift`: xyz per ray, f64 (or f32 where tagged, as points are).
    pub origins: u64,
    /// i32 per ray: its crossings (`trace::Crossings`), as the ray pass left them.
    pub counts: u64,
    /// f64 per ray: the caps' winding number; +infinity where the pass sums it.
    pub winding: u64,
    pub shift: [f64; 3],
    pub count: u32,
    pub unused: u32,
}

/// The push constants of sign_points.comp (`SignPointsParams` in shaders/records.glsl): one
/// chunk of a signed distance query, signed in place on the GPU, or of `contains`, answered in
/// bytes.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct SignPointsParams {
    /// f64 per point: the distances in, signed out.
    pub distances: u64,
    /// i32 per point (`trace::Crossings`).
    pub crossings: u64,
    /// f64 per point, the cap's winding number; or 0: the sign by parity.
    pub cap_winding: u64,
    /// u32 per 32 points, cleared beforehand: the points the CPU decides.
    pub unsure: u64,
    /// Winding numbers at least this are inside (1/2 + the band) ...
    pub inside_from: f64,
    /// ... and below this outside (1/2 − the band); between, unsure.
    pub outside_below: f64,
    /// `contains`: the chunk's points (tagged as `PointRays::points`), whose non-finite ones the
    /// host reports.
    pub points: u64,
    /// `contains`: a byte per point (1 inside), four a u32; or 0: signed distances.
    pub inside: u64,
    pub count: u32,
    pub unused: u32,
}

/// `PointOrderParams::pass`: count each cell's points; scan the counts into first slots; write
/// each point's index into its cell's next slot.
pub const POINT_ORDER_COUNT: u32 = 0;
pub const POINT_ORDER_SCAN: u32 = 1;
pub const POINT_ORDER_SCATTER: u32 = 2;
pub const POINT_ORDER_SCAN_BLOCKS: u32 = 3;

/// The push constants of list_offsets.comp (`ListParams` in shaders/records.glsl): one chunk of
/// an all-hits query, from the counting pass's counts to the storing pass's lists and offsets.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct ListParams {
    /// i32 per ray: the hits the counting pass met.
    pub counts: u64,
    /// u64 per run of `run` rays, then the chunk's records and whether any ray needs the storing
    /// pass.
    pub sums: u64,
    /// Out: `HitList` per ray.
    pub lists: u64,
    /// Out: u64 per ray, its first record among the chunk's.
    pub offsets: u64,
    /// The counting pass's records: `nearest_hits` per ray (or 0: none kept).
    pub nearest: u64,
    /// Out: the chunk's records (the copies of those the counting pass kept whole).
    pub records: u64,
    pub count: u32,
    /// Most hits a list keeps (at most `i32::MAX`).
    pub max_hits: u32,
    /// Lists longer than this, holding every hit of their ray, get `HIT_LIST_APPEND`.
    pub insertion_limit: u32,
    pub run: u32,
    /// `LIST_*`.
    pub pass: u32,
    /// Records the counting pass kept per ray.
    pub nearest_hits: u32,
    /// Records `records` holds.
    pub room: u32,
    pub unused: u32,
}

/// `ListParams::pass`: each run's records; the runs' first records and the total; each ray's
/// list and offset.
pub const LIST_SUMS: u32 = 0;
pub const LIST_SCAN: u32 = 1;
pub const LIST_WRITE: u32 = 2;
pub const LIST_SCAN_BLOCKS: u32 = 3;

/// The push constants of hit_columns.comp (`ColumnParams` in shaders/records.glsl): one stored
/// chunk of an all-hits query, its records written out as the answer's columns (each column's
/// address 0 where not asked).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct ColumnParams {
    /// The chunk's `FastHit` or `ExactHit` records.
    pub records: u64,
    /// u64 per ray: its list's first record among the chunk's.
    pub offsets: u64,
    /// One u64: where the last ray's list ends (the chunk's records).
    pub total: u64,
    /// The chunk's first ray among the query's.
    pub first_ray: u64,
    /// Out: i64 per hit.
    pub ray_index: u64,
    /// Out: f32 per hit (f64 from `ExactHit`).
    pub t: u64,
    /// Out: 2 f32 per hit (f64 from `ExactHit`).
    pub uv: u64,
    /// Out: i32 per hit each.
    pub prim: u64,
    pub instance: u64,
    pub geometry: u64,
    /// i32 per ray: the hits the storing pass (or the counting pass) met.
    pub seen: u64,
    /// Out: one u32, 1 where some ray's list is not settled (its capacity other than its seen
    /// hits up to `max_hits`, or appended to); cleared before the dispatch.
    pub check: u64,
    pub count: u32,
    pub max_hits: u32,
    pub insertion_limit: u32,
    pub unused: u32,
    /// Out, or 0: i64 per ray and one after the last, each ray's first hit among the query's
    /// (`base` plus its offset among the chunk's): the offsets of CUDA rays' answers.
    pub offsets_out: u64,
    /// The chunk's first hit among the query's.
    pub base: u64,
}

/// The push constants of pack_rays.comp (`PackParams` in shaders/records.glsl): one chunk of the
/// caller's rays in its own layout, and where their packed form goes.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct PackParams {
    /// The chunk's first origin: 3 f32, or f64 with `PACK_ORIGINS_F64`.
    pub origins: u64,
    pub directions: u64,
    /// The chunk's first tmin (f32 or f64), or 0: `PackFrame::tmin` for every ray.
    pub tmin: u64,
    pub tmax: u64,
    /// Out: 8 f32 per ray, the trace shaders' rays.
    pub packed: u64,
    /// Out: f64 per ray, how far a far ray was advanced (0: not).
    pub advances: u64,
    /// The query's `PackFrame`.
    pub frame: u64,
    /// FINISH: the chunk's f32 hit distances, to add the advances back to.
    pub t: u64,
    /// Bytes between rows of each array (0: row 0 for every ray).
    pub origin_stride: u32,
    pub direction_stride: u32,
    pub tmin_stride: u32,
    pub tmax_stride: u32,
    pub count: u32,
    /// The chunk's first row among all the rays.
    pub first_row: u32,
    /// `PACK_*_F64` bits.
    pub formats: u32,
    pub unused: u32,
    /// FINISH_HITS: i64 per hit, its ray among the query's (the chunk's from `first_row`), whose
    /// advance is added back to the hit's `t`.
    pub ray_index: u64,
}

pub const PACK_ORIGINS_F64: u32 = 1;
pub const PACK_DIRECTIONS_F64: u32 = 2;
pub const PACK_TMIN_F64: u32 = 4;
pub const PACK_TMAX_F64: u32 = 8;

/// Rays cast from points (`PointRays` in shaders/records.glsl; RAY_SOURCE = RAYS_FROM_POINTS):
/// ray i from point i of `points` (f64 xyz, world) less `shift`, along `direction`, t in
/// [`tmin`, `tmax`]; invocation k casts ray `order[k]` where there is an order.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct PointRays {
    /// As `PointParams`'.
    pub points: u64,
    /// u32 per point (point_order.comp's), or 0: as they come.
    pub order: u64,
    /// Scene frame = world - shift.
    pub shift: [f64; 3],
    /// In the scene's frame.
    pub direction: [f64; 3],
    pub tmin: f64,
    pub tmax: f64,
    /// The scene's `InsideGridHeader` (parity and winding queries: a point whose cell it decides
    /// casts no ray), or 0.
    pub grid: u64,
}

/// The scene's inside grid on the device (`InsideGridHeader` in shaders/records.glsl;
/// `scene::InsideGrid`): its corner and cells per unit (scene frame), cells per axis, and its
/// cells' answers, two bits a cell.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct InsideGridHeader {
    pub min: [f64; 3],
    pub inverse_cell: f64,
    pub dims: [u32; 3],
    pub unused: u32,
    pub marks: u64,
}

/// A query's frame for pack_rays.comp (`PackFrame` in shaders/records.glsl; `geometry::rays::Frame`),
/// and the first invalid ray the shader met.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct PackFrame {
    pub shift: [f64; 3],
    pub bounds_center: [f64; 3],
    pub radius: f64,
    pub far_squared: f64,
    /// The interval of rays without per-ray bounds.
    pub tmin: f64,
    pub tmax: f64,
    /// The first invalid row, or `u32::MAX`.
    pub first_invalid: u32,
    pub unused: u32,
}

/// One node of a bounding-volume hierarchy for closest points (`BvhNode` in shaders/records.glsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct BvhNode {
    pub lo: [f64; 3],
    pub hi: [f64; 3],
    /// Leaf: first item; inner node: the left child (the right follows).
    pub first: u32,
    /// Items of a leaf; 0 for an inner node.
    pub count: u32,
}

/// One triangle of a mesh in its frame, in its hierarchy's leaf order (`BvhTriangle` in
/// shaders/records.glsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct BvhTriangle {
    pub a: [f64; 3],
    pub b: [f64; 3],
    pub c: [f64; 3],
    /// Its index among all parts of the mesh.
    pub prim: u32,
    pub unused: u32,
}

/// One instance for closest points (`BvhInstance` in shaders/records.glsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct BvhInstance {
    /// Rows (3×4) of the map from the scene's frame to the mesh's.
    pub to_local: [f64; 12],
    /// Rows (3×4) of the map from the mesh's frame to the scene's.
    pub to_scene: [f64; 12],
    /// Per local axis, turns the mesh's box gaps squared into lower bounds of the scene's
    /// squared distances (`geometry::reference::gap_weights`).
    pub weights: [f64; 3],
    /// The mesh's first node and first triangle among all meshes'.
    pub nodes: u32,
    pub triangles: u32,
    pub mask: u32,
    /// 1 where `to_scene`'s linear part is the identity.
    pub identity: u32,
    /// The mesh's triangles (all parts).
    pub triangle_count: u32,
    /// 1 where `to_scene` mirrors (a negative determinant).
    pub mirrored: u32,
}

/// Where one node's boundary lies among the `WindingEdge`s (`WindingSpan` in
/// shaders/records.glsl; geometry::winding::Span with absolute indices).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct WindingSpan {
    pub first: u32,
    /// `geometry::winding::NO_CAP`: the node keeps no boundary.
    pub count: u32,
}

/// One oriented boundary edge of a node's triangles, in the mesh's frame (`WindingEdge` in
/// shaders/records.glsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct WindingEdge {
    pub a: [f64; 3],
    pub b: [f64; 3],
}

/// The head of the caps that close one mesh's holes, for the exact tier's winding query
/// (`WindingCapHeader` in shaders/records.glsl): its `WindingCapHole`s and their
/// `WindingCapEdge`s follow it in one buffer, at the addresses it holds.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct WindingCapHeader {
    pub hole_count: u32,
    /// 1 where the instance mirrors (its winding number is the negated sum).
    pub mirrored: u32,
    /// Winding numbers within this of 1/2 are decided on the CPU (the host's band): a ray whose
    /// fans passed over could move its winding number into the band sums them after all.
    pub band: f64,
    /// `hole_count` WindingCapHoles.
    pub holes: u64,
    /// Every hole's WindingCapEdges, each hole's together.
    pub edges: u64,
}

/// One hole's cap: the fan from `apex` over the hole's boundary edges `first..first + count`,
/// with what lets a ray pass it over (`WindingCapHole` in shaders/records.glsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct WindingCapHole {
    /// The fan's apex (the mean of the hole's corners) in the mesh's frame, and in the scene's.
    pub apex: [f64; 3],
    pub apex_scene: [f64; 3],
    /// A radius about the apex holding the whole fan, in the mesh's frame (no ray passing
    /// farther crosses it) and in the scene's.
    pub radius: f64,
    pub radius_scene: f64,
    /// The sum of the fan's triangles' areas in the scene's frame (a bound on its solid angle).
    pub area_scene: f64,
    pub first: u32,
    pub count: u32,
}

/// One boundary edge a -> b of a cap's mesh, in the mesh's frame and in the scene's
/// (`WindingCapEdge` in shaders/records.glsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct WindingCapEdge {
    pub a: [f64; 3],
    pub b: [f64; 3],
    pub a_scene: [f64; 3],
    pub b_scene: [f64; 3],
}

/// The nearest surface point of one point (`PointHit` in shaders/records.glsl).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct PointHit {
    /// World, f64.
    pub position: [f64; 3],
    pub u: f64,
    pub v: f64,
    /// -1: nothing within the search's limit.
    pub instance: i32,
    /// Among all parts of the instance's mesh.
    pub prim: u32,
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
layout!(GeometrySource, size 40, vertices @ 0, indices @ 8, primitive_order @ 16, opacity @ 24, index_is_u16 @ 32,
    vertex_format @ 36);
layout!(ExactInstance, size 160, rows @ 0, vertices @ 96, indices @ 104, primitive_order @ 112, part_offsets @ 120,
    part_count @ 128, flags @ 132, opacity @ 136, _padding @ 144);
layout!(Sensor, size 128, origin @ 0, axes @ 16, kind @ 64, columns @ 68, rows @ 72, pixel_offset @ 76, table @ 80,
    tmin64 @ 88, tmax64 @ 96, shift @ 104);
layout!(PointParams, size 128, points @ 0, distances @ 8, hits @ 16, nodes @ 24, triangles @ 32, instances @ 40,
    top_nodes @ 48, top_items @ 56, spans @ 64, edges @ 72, order @ 80, center @ 88, max_distance @ 112, count @ 120,
    instance_count @ 124);
layout!(PointOrderParams, size 80, points @ 0, cells @ 8, order @ 16, corner @ 24, scale @ 48, count @ 72, pass @ 76);
layout!(ListParams, size 80, counts @ 0, sums @ 8, lists @ 16, offsets @ 24, nearest @ 32, records @ 40, count @ 48,
    max_hits @ 52, insertion_limit @ 56, run @ 60, pass @ 64, nearest_hits @ 68, room @ 72, unused @ 76);
layout!(ColumnParams, size 128, records @ 0, offsets @ 8, total @ 16, first_ray @ 24, ray_index @ 32, t @ 40,
    uv @ 48, prim @ 56, instance @ 64, geometry @ 72, seen @ 80, check @ 88, count @ 96, max_hits @ 100,
    insertion_limit @ 104, unused @ 108, offsets_out @ 112, base @ 120);
layout!(CapWindingParams, size 64, cap @ 0, origins @ 8, counts @ 16, winding @ 24, shift @ 32, count @ 56,
    unused @ 60);
layout!(SignPointsParams, size 72, distances @ 0, crossings @ 8, cap_winding @ 16, unsure @ 24, inside_from @ 32,
    outside_below @ 40, points @ 48, inside @ 56, count @ 64, unused @ 68);
layout!(PackParams, size 104, origins @ 0, directions @ 8, tmin @ 16, tmax @ 24, packed @ 32, advances @ 40,
    frame @ 48, t @ 56, origin_stride @ 64, direction_stride @ 68, tmin_stride @ 72, tmax_stride @ 76, count @ 80,
    first_row @ 84, formats @ 88, unused @ 92, ray_index @ 96);
layout!(PackFrame, size 88, shift @ 0, bounds_center @ 24, radius @ 48, far_squared @ 56, tmin @ 64, tmax @ 72,
    first_invalid @ 80, unused @ 84);
layout!(PointRays, size 88, points @ 0, order @ 8, shift @ 16, direction @ 40, tmin @ 64, tmax @ 72, grid @ 80);
layout!(InsideGridHeader, size 56, min @ 0, inverse_cell @ 24, dims @ 32, unused @ 44, marks @ 48);
layout!(BvhNode, size 56, lo @ 0, hi @ 24, first @ 48, count @ 52);
layout!(BvhTriangle, size 80, a @ 0, b @ 24, c @ 48, prim @ 72, unused @ 76);
layout!(BvhInstance, size 240, to_local @ 0, to_scene @ 96, weights @ 192, nodes @ 216, triangles @ 220, mask @ 224,
    identity @ 228, triangle_count @ 232, mirrored @ 236);
layout!(WindingSpan, size 8, first @ 0, count @ 4);
layout!(WindingEdge, size 48, a @ 0, b @ 24);
layout!(WindingCapHeader, size 32, hole_count @ 0, mirrored @ 4, band @ 8, holes @ 16, edges @ 24);
layout!(WindingCapHole, size 80, apex @ 0, apex_scene @ 24, radius @ 48, radius_scene @ 56, area_scene @ 64, first @ 72,
    count @ 76);
layout!(WindingCapEdge, size 96, a @ 0, b @ 24, a_scene @ 48, b_scene @ 72);
// The holes and the edges follow the header in one buffer: each record keeps the next's alignment.
const _: () = assert!(std::mem::size_of::<WindingCapHeader>() % std::mem::align_of::<WindingCapHole>() == 0);
const _: () = assert!(std::mem::size_of::<WindingCapHole>() % std::mem::align_of::<WindingCapEdge>() == 0);
layout!(PointHit, size 48, position @ 0, u @ 24, v @ 32, instance @ 40, prim @ 44);
layout!(HitList, size 8, first @ 0, capacity @ 4);
layout!(FastHit, size 32, t @ 0, u @ 4, v @ 8, instance @ 12, geometry @ 16, prim @ 20, unused @ 24);
const _: () = assert!(std::mem::align_of::<FastHit>() == std::mem::align_of::<ExactHit>());
layout!(ExactHit, size 32, t @ 0, u @ 8, v @ 16, instance @ 24, prim @ 28);
layout!(ExactBest, size 40, t @ 0, u @ 8, v @ 16, instance @ 24, prim @ 28, custom @ 32, geometry @ 36);

#[cfg(test)]
mod tests {
    use std::collections::HashMap;
    use std::mem::{offset_of, size_of};

    use super::*;
    use crate::gpu::shaders;

    /// What one SPIR-V module says about its struct types' layouts.
    #[derive(Default)]
    struct Layouts {
        names: HashMap<u32, String>,
        member_names: HashMap<(u32, u32), String>,
        offsets: HashMap<(u32, u32), u32>,
        array_strides: HashMap<u32, u32>,
        /// Runtime-array type -> its element type.
        runtime_arrays: Vec<(u32, u32)>,
        /// Struct type -> its member count.
        structs: Vec<(u32, usize)>,
    }

    /// A literal string operand: UTF-8, nul-terminated, padded to whole words.
    fn literal_string(words: &[u32]) -> String {
        let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).take_while(|&b| b != 0).collect();
        String::from_utf8(bytes).expect("SPIR-V strings are UTF-8")
    }

    fn parse(words: &[u32]) -> Layouts {
        const OP_NAME: u32 = 5;
        const OP_MEMBER_NAME: u32 = 6;
        const OP_TYPE_RUNTIME_ARRAY: u32 = 29;
        const OP_TYPE_STRUCT: u32 = 30;
        const OP_DECORATE: u32 = 71;
        const OP_MEMBER_DECORATE: u32 = 72;
        const DECORATION_ARRAY_STRIDE: u32 = 6;
        const DECORATION_OFFSET: u32 = 35;
        assert_eq!(words[0], 0x0723_0203, "SPIR-V magic number");
        let mut layouts = Layouts::default();
        let mut at = 5;
        while at < words.len() {
            let count = (words[at] >> 16) as usize;
            assert!(count > 0 && at + count <= words.len(), "malformed instruction at word {at}");
            let operands = &words[at + 1..at + count];
            match words[at] & 0xFFFF {
                OP_NAME => {
                    layouts.names.insert(operands[0], literal_string(&operands[1..]));
                }
                OP_MEMBER_NAME => {
                    layouts.member_names.insert((operands[0], operands[1]), literal_string(&operands[2..]));
                }
                OP_TYPE_RUNTIME_ARRAY => layouts.runtime_arrays.push((operands[0], operands[1])),
                OP_TYPE_STRUCT => layouts.structs.push((operands[0], operands.len() - 1)),
                OP_DECORATE if operands[1] == DECORATION_ARRAY_STRIDE => {
                    layouts.array_strides.insert(operands[0], operands[2]);
                }
                OP_MEMBER_DECORATE if operands[2] == DECORATION_OFFSET => {
                    layouts.offsets.insert((operands[0], operands[1]), operands[3]);
                }
                _ => {}
            }
            at += count;
        }
        layouts
    }

    /// A record's GLSL name, its Rust size, and (GLSL member name, Rust offset) per member.
    type Expected = (&'static str, usize, Vec<(&'static str, usize)>);

    /// Every record as Rust lays it out. `Params`'s `outputs` array is seven GLSL members, one per
    /// `trace::Field`; padding has no GLSL member.
    fn expected() -> Vec<Expected> {
        macro_rules! members {
            ($record:ty: $($field:ident),*) => {
                vec![$((stringify!($field), offset_of!($record, $field))),*]
            };
        }
        let outputs = ["out_t", "out_prim", "out_instance", "out_custom", "out_uv", "out_normal", "out_geometry"];
        let mut params = members!(Params: rays, instances, tlas);
        params.extend(outputs.iter().enumerate().map(|(k, &name)| (name, offset_of!(Params, outputs) + 8 * k)));
        params.extend(members!(Params: scratch, masks, count, bounds, ray_mask));
        vec![
            ("Params", size_of::<Params>(), params),
            (
                "GeometrySource",
                size_of::<GeometrySource>(),
                members!(GeometrySource: vertices, indices, primitive_order, opacity, index_is_u16, vertex_format),
            ),
            (
                "ExactInstance",
                size_of::<ExactInstance>(),
                members!(
                    ExactInstance: rows,
                    vertices,
                    indices,
                    primitive_order,
                    part_offsets,
                    part_count,
                    flags,
                    opacity
                ),
            ),
            (
                "Sensor",
                size_of::<Sensor>(),
                members!(Sensor: origin, axes, kind, columns, rows, pixel_offset, table, tmin64, tmax64, shift),
            ),
            (
                "PointParams",
                size_of::<PointParams>(),
                members!(
                    PointParams: points,
                    distances,
                    hits,
                    nodes,
                    triangles,
                    instances,
                    top_nodes,
                    top_items,
                    spans,
                    edges,
                    order,
                    center,
                    max_distance,
                    count,
                    instance_count
                ),
            ),
            (
                "PackParams",
                size_of::<PackParams>(),
                members!(
                    PackParams: origins,
                    directions,
                    tmin,
                    tmax,
                    packed,
                    advances,
                    frame,
                    t,
                    origin_stride,
                    direction_stride,
                    tmin_stride,
                    tmax_stride,
                    count,
                    first_row,
                    formats,
                    unused,
                    ray_index
                ),
            ),
            (
                "PackFrame",
                size_of::<PackFrame>(),
                members!(
                    PackFrame: shift,
                    bounds_center,
                    radius,
                    far_squared,
                    tmin,
                    tmax,
                    first_invalid,
                    unused
                ),
            ),
            (
                "PointRays",
                size_of::<PointRays>(),
                members!(PointRays: points, order, shift, direction, tmin, tmax, grid),
            ),
            (
                "InsideGridHeader",
                size_of::<InsideGridHeader>(),
                members!(InsideGridHeader: min, inverse_cell, dims, unused, marks),
            ),
            ("BvhNode", size_of::<BvhNode>(), members!(BvhNode: lo, hi, first, count)),
            ("BvhTriangle", size_of::<BvhTriangle>(), members!(BvhTriangle: a, b, c, prim, unused)),
            (
                "BvhInstance",
                size_of::<BvhInstance>(),
                members!(
                    BvhInstance: to_local,
                    to_scene,
                    weights,
                    nodes,
                    triangles,
                    mask,
                    identity,
                    triangle_count,
                    mirrored
                ),
            ),
            (
                "PointOrderParams",
                size_of::<PointOrderParams>(),
                members!(PointOrderParams: points, cells, order, corner, scale, count, pass),
            ),
            (
                "ListParams",
                size_of::<ListParams>(),
                members!(
                    ListParams: counts,
                    sums,
                    lists,
                    offsets,
                    nearest,
                    records,
                    count,
                    max_hits,
                    insertion_limit,
                    run,
                    pass,
                    nearest_hits,
                    room,
                    unused
                ),
            ),
            (
                "ColumnParams",
                size_of::<ColumnParams>(),
                members!(
                    ColumnParams: records,
                    offsets,
                    total,
                    first_ray,
                    ray_index,
                    t,
                    uv,
                    prim,
                    instance,
                    geometry,
                    seen,
                    check,
                    count,
                    max_hits,
                    insertion_limit,
                    unused,
                    offsets_out,
                    base
                ),
            ),
            (
                "SignPointsParams",
                size_of::<SignPointsParams>(),
                members!(
                    SignPointsParams: distances,
                    crossings,
                    cap_winding,
                    unsure,
                    inside_from,
                    outside_below,
                    points,
                    inside,
                    count,
                    unused
                ),
            ),
            (
                "CapWindingParams",
                size_of::<CapWindingParams>(),
                members!(CapWindingParams: cap, origins, counts, winding, shift, count, unused),
            ),
            ("WindingSpan", size_of::<WindingSpan>(), members!(WindingSpan: first, count)),
            ("WindingEdge", size_of::<WindingEdge>(), members!(WindingEdge: a, b)),
            (
                "WindingCapHeader",
                size_of::<WindingCapHeader>(),
                members!(WindingCapHeader: hole_count, mirrored, band, holes, edges),
            ),
            (
                "WindingCapHole",
                size_of::<WindingCapHole>(),
                members!(WindingCapHole: apex, apex_scene, radius, radius_scene, area_scene, first, count),
            ),
            ("WindingCapEdge", size_of::<WindingCapEdge>(), members!(WindingCapEdge: a, b, a_scene, b_scene)),
            ("PointHit", size_of::<PointHit>(), members!(PointHit: position, u, v, instance, prim)),
            ("ExactBest", size_of::<ExactBest>(), members!(ExactBest: t, u, v, instance, prim, custom, geometry)),
            ("HitList", size_of::<HitList>(), members!(HitList: first, capacity)),
            ("FastHit", size_of::<FastHit>(), members!(FastHit: t, u, v, instance, geometry, prim, unused)),
            ("ExactHit", size_of::<ExactHit>(), members!(ExactHit: t, u, v, instance, prim)),
        ]
    }

    /// The member offsets glslc assigned to each record (every declaration with an explicit
    /// layout, in every embedded module), and the stride of arrays of it, match the Rust structs.
    #[test]
    fn shader_records_match_rust_layouts() {
        let expected = expected();
        let mut seen: HashMap<&str, usize> = HashMap::new();
        for (module, bytes) in shaders::ALL {
            let layouts = parse(&shaders::words(bytes));
            for &(id, member_count) in &layouts.structs {
                let Some((name, size, members)) =
                    layouts.names.get(&id).and_then(|n| expected.iter().find(|(record, ..)| record == n))
                else {
                    continue;
                };
                // Declarations without an explicit layout (function-local copies) have no offsets.
                if !layouts.offsets.contains_key(&(id, 0)) {
                    continue;
                }
                *seen.entry(name).or_default() += 1;
                assert_eq!(member_count, members.len(), "{module}: {name} has {member_count} members");
                for index in 0..member_count as u32 {
                    let member = &layouts.member_names[&(id, index)];
                    let offset = layouts.offsets[&(id, index)] as usize;
                    let rust = members.iter().find(|(m, _)| m == member).map(|&(_, offset)| offset);
                    assert_eq!(
                        Some(offset),
                        rust,
                        "{module}: {name}.{member} (member {index}) is at {offset} in GLSL, at {rust:?} in Rust"
                    );
                }
                for &(array, element) in &layouts.runtime_arrays {
                    if element == id {
                        let stride = layouts.array_strides[&array] as usize;
                        assert_eq!(stride, *size, "{module}: arrays of {name} are {stride} bytes apart, Rust's {size}");
                    }
                }
            }
        }
        for (name, ..) in &expected {
            assert!(seen.contains_key(name), "no embedded module lays out {name}: {seen:?}");
        }
    }
}
