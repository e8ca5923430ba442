// The records the host writes and shaders read, each declared once, here. src/gpu/records.rs
// mirrors them as #[repr(C)] structs; its tests compare the member offsets glslc assigns to these
// declarations (read from the compiled SPIR-V, by member name) with the Rust fields' offsets.
// Included by common.glsl after its extensions (64-bit integers). The exact tier's records hold
// doubles: only shaders that use them need shaderFloat64 (glslang emits unused types not at all).
#ifndef VKRAY_RECORDS_GLSL
#define VKRAY_RECORDS_GLSL

// Where the triangles of one geometry live, for the outputs that need them (normal, prim_id).
struct GeometrySource {
  uint64_t vertices;         // float xyz tightly packed; or 4 halves / 4 snorm16 (VERTEX_*)
  uint64_t indices;          // uint32 triples, or uint16 triples packed into words
  uint64_t primitive_order;  // device triangle -> caller's triangle (int32), or 0 if the same
  uint64_t opacity;          // float per device triangle in [0, 1], or 0: every triangle opaque
  uint index_is_u16;
  uint vertex_format;        // VERTEX_F32, VERTEX_F16 or VERTEX_SNORM16 (VertexFormat), or SPHERE_SOURCE
};
const uint VERTEX_F32 = 0u;
const uint VERTEX_F16 = 1u;
const uint VERTEX_SNORM16 = 2u;
const uint SPHERE_SOURCE = 3u;  // `vertices` holds spheres (vec4: centre, radius), no triangles

#if defined(VKRAY_PACK_RAYS)
// The push constants of pack_rays.comp (records.rs PackParams): where one chunk of the caller's
// rays lies in its own layout (each array by address and byte stride between rows; a stride of 0
// repeats row 0), and where their packed form (Rays::pack's) goes.
layout(push_constant, std430) uniform PackParams {
  uint64_t origins;       // the chunk's first origin: 3 floats, or doubles (PACK_ORIGINS_F64)
  uint64_t directions;    // the chunk's first direction: 3 floats or doubles (PACK_DIRECTIONS_F64)
  uint64_t tmin;          // the chunk's first tmin (float or double), or 0: PackFrame.tmin
  uint64_t tmax;          // the chunk's first tmax, or 0: PackFrame.tmax
  uint64_t packed;        // out: 8 floats per ray, as the trace shaders read them
  uint64_t advances;      // out: double per ray, how far a far ray was moved (0: not moved)
  uint64_t frame;         // PackFrame
  uint64_t t;             // finish: the chunk's hit distances (float per ray), to add `advances` to
  uint origin_stride;     // bytes between rows of each array
  uint direction_stride;
  uint tmin_stride;
  uint tmax_stride;
  uint count;
  uint first_row;         // the chunk's first row among all the rays (for first_invalid)
  uint formats;           // PACK_*_F64 bits
  uint unused;
  uint64_t ray_index;     // finish hits: int64 per hit, its ray among the query's (the chunk's
                          // from first_row), whose advance goes back to the hit's t
} pack_params;
const uint PACK_ORIGINS_F64 = 1u;
const uint PACK_DIRECTIONS_F64 = 2u;
const uint PACK_TMIN_F64 = 4u;
const uint PACK_TMAX_F64 = 8u;
#elif defined(VKRAY_POINT_ORDER)
// The push constants of point_order.comp (records.rs PointOrderParams): the chunk's points (f64
// xyz, world), its cells' counters, the order it writes, the grid's corner and cells per unit
// along each axis (world), the chunk's point count and the pass (POINT_ORDER_*).
layout(push_constant, std430) uniform PointOrderParams {
  uint64_t points;        // as PointParams' (points.glsl)
  uint64_t cells;         // uint per cell: its points' count, then (scanned) its next slot
  uint64_t order;         // uint per point: the points' indices, cell by cell
  double corner[3];
  double scale[3];
  uint count;
  uint pass;
} order_params;
const uint POINT_ORDER_COUNT = 0u;
const uint POINT_ORDER_SCAN = 1u;
const uint POINT_ORDER_SCATTER = 2u;
const uint POINT_ORDER_SCAN_BLOCKS = 3u;
#elif defined(VKRAY_LIST_OFFSETS)
// The push constants of list_offsets.comp (records.rs ListParams): one chunk of an all-hits query,
// from the counting pass's counts to the storing pass's lists and their offsets, in four passes
// (LIST_*) over runs of `run` rays.
layout(push_constant, std430) uniform ListParams {
  uint64_t counts;          // int per ray: the hits the counting pass met
  uint64_t sums;            // uint64 per run: its lists' records, then (scanned) its first record
                            // within its block; then the chunk's records, then whether any ray
                            // needs the storing pass; then per block of runs its records, then
                            // (scanned) its first record
  uint64_t lists;           // out: HitList per ray
  uint64_t offsets;         // out: uint64 per ray, its first record among the chunk's
  uint64_t nearest;         // the counting pass's records: `nearest_hits` per ray, or 0: none kept
  uint64_t records;         // out: the chunk's records (those of rays the counting pass kept whole)
  uint count;               // rays in the chunk
  uint max_hits;            // most hits a list keeps (at most 2^31 - 1)
  uint insertion_limit;     // lists longer than this holding every hit of their ray: HIT_LIST_APPEND
  uint run;                 // rays per run
  uint pass;
  uint nearest_hits;        // records the counting pass kept per ray
  uint room;                // records `records` holds
  uint unused;
} list_params;
const uint LIST_SUMS = 0u;
const uint LIST_SCAN = 1u;
const uint LIST_WRITE = 2u;
const uint LIST_SCAN_BLOCKS = 3u;
#elif defined(VKRAY_HIT_COLUMNS)
// The push constants of hit_columns.comp (records.rs ColumnParams): one stored chunk of an
// all-hits query, its records written out as the answer's columns. Each column's address is 0
// where the caller did not ask for it.
layout(push_constant, std430) uniform ColumnParams {
  uint64_t records;    // the chunk's FastHit or ExactHit records
  uint64_t offsets;    // uint64 per ray: its list's first record among the chunk's
  uint64_t total;      // the chunk's records (one uint64, list_offsets.comp's total)
  uint64_t first_ray;  // the chunk's first ray among the query's
  uint64_t ray_index;  // out: int64 per hit, its ray among the query's
  uint64_t t;          // out: float per hit (double from ExactHit)
  uint64_t uv;         // out: 2 floats per hit (doubles from ExactHit)
  uint64_t prim;       // out: int per hit, the triangle within its geometry
  uint64_t instance;   // out: int per hit
  uint64_t geometry;   // out: int per hit
  uint64_t seen;       // int per ray: the hits the storing pass (or the counting pass) met
  uint64_t check;      // out: one uint, set to 1 where some ray's list is not settled (cleared
                       // by the host's commands)
  uint count;          // rays in the chunk
  uint max_hits;       // hits a ray keeps (at most 2^31 - 1)
  uint insertion_limit;  // lists longer than this are appended to (hit_lists.rs INSERTION_LIMIT)
  uint unused;
  uint64_t offsets_out;  // out, or 0: int64 per ray and one after the last, each list's first hit
                         // among the query's (`base` + the chunk's offset; CUDA's answers)
  uint64_t base;         // the chunk's first hit among the query's
} column_params;
#elif defined(VKRAY_SIGN_POINTS)
// The push constants of sign_points.comp (records.rs SignPointsParams): one chunk of a signed
// distance query, its distances signed in place from its sign's crossings (and cap's winding
// numbers), or of `contains`, its answers written as bytes; the points the GPU cannot tell marked
// for the CPU.
layout(push_constant, std430) uniform SignPointsParams {
  uint64_t distances;    // double per point: in, the distances; out, negated where inside
  uint64_t crossings;    // int per point (Crossings: the sum << 1 | on a surface)
  uint64_t cap_winding;  // double per point, the cap's winding number; or 0: sign by parity
  uint64_t unsure;       // uint per 32 points (cleared by the host): bit i & 31 of word i >> 5 set
                         // where the winding number lies within the band about 1/2 (or is NaN)
  double inside_from;    // winding numbers at least this are inside (1/2 + the band)
  double outside_below;  // winding numbers below this are outside (1/2 - the band)
  uint64_t points;       // contains: the chunk's points (points.glsl, tagged), checked finite
  uint64_t inside;       // contains: a byte per point (1 inside), 4 a word; or 0: signed distances
  uint count;
  uint unused;
} sign_params;
#elif defined(VKRAY_CAP_WINDING)
// The push constants of cap_winding.comp (records.rs CapWindingParams): one chunk of a winding
// query after its ray pass, whose rays' caps' winding numbers it sums.
layout(push_constant, std430) uniform CapWindingParams {
  uint64_t cap;        // the WindingCapHeader (cap.glsl)
  uint64_t origins;    // each ray's origin, as points.glsl reads points (tagged f32 or f64), less `shift`
  uint64_t counts;     // int per ray: its crossings (Crossings), as the ray pass left them
  uint64_t winding;    // double per ray: the caps' winding number; +infinity where this pass sums it
  double shift[3];
  uint count;          // rays in the chunk
  uint unused;
} cap_params;
#elif !defined(VKRAY_POINT_QUERY)
// The push constants of every query (records.rs Params, whose `outputs` array holds out_t ..
// out_geometry in trace::Field order). QUERY_ALL writes no hit fields: out_t points at the
// chunk's FastHit or ExactHit records, out_prim at one int per ray (the hits it met), scratch at
// one HitList per ray (0: none stored, only counted). QUERY_WINDING reads scratch as the cap
// (cap.glsl) and leaves at out_uv the origins cap_winding.comp reads (3 doubles a ray).
layout(push_constant, std430) uniform Params {
  uint64_t rays;
  uint64_t instances;  // InstanceGeometries (fast tier) or ExactInstances (exact tier)
  uint64_t tlas;
  uint64_t out_t;
  uint64_t out_prim;
  uint64_t out_instance;
  uint64_t out_custom;
  uint64_t out_uv;
  uint64_t out_normal;
  uint64_t out_geometry;
  uint64_t scratch;    // exact tier, pipeline backend: ExactBest per ray; QUERY_ALL: HitList per ray
  uint64_t masks;      // one uint cull mask per ray, or 0: every ray uses ray_mask (sensors: the
                       // chunk's first ray; every ray uses ray_mask)
  uint count;
  float bounds[6];     // exact tier: the scene's bounds (min xyz, max xyz), rounded outward
  uint ray_mask;
} params;
#else
// The push constants of closest_point.comp (records.rs PointParams): the chunk's points (f64 xyz,
// world), its outputs, the scene's hierarchies (records below), its frame's offset and the search's
// limit.
layout(push_constant, std430) uniform PointParams {
  uint64_t points;        // xyz per point, tightly packed: f64, or f32 where bit 0 is set (points.glsl)
  uint64_t distances;     // f64 per point: the distance, +inf where nothing is within max_distance
                          // (winding.comp: the largest winding number of any instance)
  uint64_t hits;          // PointHit per point, or 0: only distances asked
  uint64_t nodes;         // BvhNode: every mesh's hierarchy, one after another
  uint64_t triangles;     // BvhTriangle: every mesh's triangles in its leaves' order
  uint64_t instances;     // BvhInstance per instance
  uint64_t top_nodes;     // BvhNode: the hierarchy over the instances' bounds (scene frame)
  uint64_t top_items;     // uint per instance: its index, in the top hierarchy's leaf order
  uint64_t spans;         // winding.comp: WindingSpan per node of `nodes` (0 for closest_point.comp)
  uint64_t edges;         // winding.comp: WindingEdge, every node's boundary
  uint64_t order;         // uint per point: the order to take the points in (point_order.comp),
                          // or 0: as they come
  double center[3];       // world = scene frame + center
  double max_distance;
  uint count;
  uint instance_count;
} point_params;
#endif

// A query's frame for pack_rays.comp (records.rs PackFrame, rays.rs Frame): the shift into the
// scene's frame, the sphere bounding the scene in it, how far out rays are advanced, the interval
// of rays without per-ray bounds; and the first invalid ray the shader met (host-visible).
struct PackFrame {
  double shift[3];
  double bounds_center[3];
  double radius;
  double far_squared;
  double tmin;
  double tmax;
  uint first_invalid;     // the first invalid row, or 0xFFFFFFFF (atomicMin)
  uint unused;
};

// Closest points: one node of a bounding-volume hierarchy (geometry/reference.rs Bvh): f64
// bounds, and a leaf's first item and count, or an inner node's left child (the right follows)
// and 0. Indices count from the node's own hierarchy (BvhInstance.nodes). 56 bytes.
struct BvhNode {
  double lo[3];
  double hi[3];
  uint first;
  uint count;
};

// Closest points: one triangle of a mesh in its frame (f64 corners), in its hierarchy's leaf
// order, and its index among all parts of the mesh. 80 bytes.
struct BvhTriangle {
  double a[3];
  double b[3];
  double c[3];
  uint prim;
  uint unused;
};

// Closest points, per instance: the f64 maps between the scene's frame and the mesh's (rows of
// 3x4: xyz linear, w offset), the weights per local axis that turn the mesh's box gaps squared into
// lower bounds of squared scene distances (geometry/reference.rs gap_weights), where its mesh's nodes and
// triangles start, its mask, whether to_scene's linear part is the identity, its mesh's
// triangle count, and whether to_scene mirrors (its determinant is negative). 240 bytes.
struct BvhInstance {
  double to_local[12];
  double to_scene[12];
  double weights[3];
  uint nodes;
  uint triangles;
  uint mask;
  uint identity;
  uint triangle_count;
  uint mirrored;
};

// Winding numbers (geometry/winding.rs): where a node's boundary lies among the WindingEdges
// (absolute indices), or count 0xFFFFFFFF where the node keeps none (its children or its
// triangles are summed). 8 bytes.
struct WindingSpan {
  uint first;
  uint count;
};

// Winding numbers: one oriented boundary edge of a node's triangles, in the mesh's frame (f64).
// 48 bytes.
struct WindingEdge {
  double a[3];
  double b[3];
};

// The exact tier's winding query (trace::Query::Winding, one instance): the caps that close its
// mesh's holes, one fan per hole from the hole's apex over its boundary edges (geometry/winding.rs
// boundary_loops over the hierarchy's root's boundary), each corner in the mesh's frame (the
// crossing test's, the vertices' own f64 values) and in the scene's (the solid angles'). A
// WindingCapHeader; its holes and edges follow it in one buffer, at the addresses it holds.
// 32 bytes.
struct WindingCapHeader {
  uint hole_count;
  uint mirrored;          // the instance mirrors: its winding number is the negated sum
  double band;            // winding numbers within this of 1/2 go to the CPU (the host's band)
  uint64_t holes;         // hole_count WindingCapHoles
  uint64_t edges;         // every hole's WindingCapEdges, each hole's together
};

// One hole's cap: the fan from `apex` over edges first .. first + count; every point of the fan
// lies within `radius` of the apex (mesh frame; `radius_scene` in the scene's), and its
// triangles' areas (scene frame) sum to `area_scene`. 80 bytes.
struct WindingCapHole {
  double apex[3];
  double apex_scene[3];
  double radius;
  double radius_scene;
  double area_scene;
  uint first;
  uint count;
};

// One boundary edge a -> b of the cap's mesh. 96 bytes.
struct WindingCapEdge {
  double a[3];
  double b[3];
  double a_scene[3];
  double b_scene[3];
};

// Closest points: the nearest surface point of one point (world, f64), the barycentrics (of
// vertices 1 and 2) of that point on its triangle, the instance and the triangle among all parts
// of its mesh (instance -1: none within max_distance). 48 bytes.
struct PointHit {
  double position[3];
  double u;
  double v;
  int instance;
  uint prim;
};

// The exact tier, per instance: the f64 map from the scene's frame to the mesh's (rows: xyz
// linear, w offset), and where the mesh's f64 vertices and boxed triangles live. Triangles are
// counted among all parts of the mesh; `part_offsets` splits them back into (geometry, triangle
// within it). 160 bytes (the dvec4s' 32-byte alignment).
struct ExactInstance {
  dvec4 rows[3];
  uint64_t vertices;         // f64 xyz per vertex, all parts
  uint64_t indices;          // uint32 corner triples, in box order
  uint64_t primitive_order;  // box -> caller's triangle among all parts, or 0 if the same
  uint64_t part_offsets;     // uint32: first triangle of each part, then the total
  uint part_count;
  uint flags;                // EXACT_CULL_DISABLE | EXACT_FLIP_FACING
  uint64_t opacity;          // float per caller's triangle among all parts, or 0: all opaque
};
const uint EXACT_CULL_DISABLE = 1u;  // query culling does not apply to this instance
const uint EXACT_FLIP_FACING = 2u;   // front is the side opposite the object-space normal

// The exact tier's best hit so far: t and barycentrics in f64, the device's triangle index
// (prim < 0: none).
struct ExactBest {
  double t;
  double u;
  double v;
  int instance;
  int prim;
  int custom;
  int geometry;
};

// QUERY_ALL: where ray i keeps its nearest hits, sorted: `capacity` records from `first` among
// the chunk's records (hit_lists.glsl). HIT_LIST_APPEND in `capacity`: the list is long (and as
// long as the ray's hits): they are appended as they come, and the host sorts them.
struct HitList {
  uint first;
  uint capacity;
};
const uint HIT_LIST_APPEND = 0x80000000u;
// `first` of a ray whose hits the counting pass kept whole (list_offsets.comp copied them into
// place): the storing pass skips it.
const uint HIT_LIST_DONE = 0xFFFFFFFFu;

// One stored hit of the fast tier: f32 t and barycentrics (of vertices 1 and 2), the caller's
// triangle within its geometry. Ordered by (t, instance, geometry, prim). 32 bytes, as ExactHit:
// the host turns each into the CPU tracer's record in place.
struct FastHit {
  float t;
  float u;
  float v;
  int instance;
  int geometry;
  int prim;
  uint unused[2];
};

// One stored hit of the exact tier: f64 t and barycentrics, the caller's triangle among all parts
// of the mesh (src/geometry/reference.rs ReferenceHit). Ordered by (t, instance, prim).
struct ExactHit {
  double t;
  double u;
  double v;
  uint instance;
  uint prim;
};

// A sensor whose rays the shaders generate (RAY_SOURCE = RAYS_FROM_SENSOR): `params.rays` points
// at it, and `params.masks` holds the chunk's first ray (such rays share one mask). Every value is the host's f64
// rounded once to f32, and the shaders combine them in f32 without fused multiply-adds in the
// order python/vkray/sensors.py documents, so that `Sensor.rays()` holds the same rays bit for
// bit. Pinhole: direction a px + (b py + c) with a, b, c = axes (Open3D's order); orthographic: origin
// (origin + U px) + V py with U, V = axes[0], axes[1], direction axes[2]; lidar: direction R l,
// l from the cos/sin table of channel (row) and step (column), R's rows in axes. Pixel (px, py)
// is (column, row) + pixel_offset. In the fast tier the origin is in the scene's frame already;
// in the exact tier it is in the world's, and `shift` (f64 bits) moves it to the scene's frame.
struct Sensor {
  vec4 origin;      // xyz; w: the fast tier's tmin (rounded down to f32, as uploaded rays are)
  vec4 axes[3];     // xyz each; axes[0].w: the fast tier's tmax (rounded up)
  uint kind;        // SENSOR_PINHOLE, SENSOR_ORTHOGRAPHIC or SENSOR_LIDAR
  uint columns;     // image width, or lidar steps
  uint rows;        // image height, or lidar channels (rays run row by row)
  float pixel_offset;
  uint64_t table;   // lidar: (cos, sin) of each step's azimuth, then of each channel's elevation
  uvec2 tmin64;     // the exact tier's interval, f64 bits
  uvec2 tmax64;
  uvec2 shift[3];   // the exact tier: the scene frame's offset, f64 bits
};
// Rays cast from points (RAY_SOURCE = RAYS_FROM_POINTS: the sign of a signed distance): ray i
// starts at point i of `points` (f64 xyz, the world's, as the closest-point search reads them)
// moved into the scene's frame by `shift`, runs along `direction` (the scene's frame) over
// [tmin, tmax]. `params.rays` points at it. records.rs PointRays. The interval comes from the
// host: with a constant infinity (1.0 / 0.0) for tmax, the H100's rays met nothing. With an
// `order` (point_order.comp's, for the search), invocation k casts the ray of point order[k] and
// writes its outputs to that point's row: neighbours in space trace side by side. With a `grid`
// (PARITY and WINDING), a point whose cell the grid decides casts no ray (exact.glsl
// grid_crossings).
struct PointRays {
  uint64_t points;      // as PointParams' (points.glsl)
  uint64_t order;       // uint per point, or 0: as they come
  uvec2 shift[3];       // f64 bits: scene frame = world - shift
  uvec2 direction[3];   // f64 bits (trace::tiers::PARITY_DIRECTION)
  uvec2 tmin;           // f64 bits
  uvec2 tmax;
  uint64_t grid;        // an InsideGridHeader, or 0: every point casts its ray
};

// The scene's inside grid (scene::InsideGrid) on the device: each cell's answer (GRID_OUTSIDE 0,
// GRID_INSIDE 1, GRID_UNDECIDED 2), two bits a cell (cell i in bits 2(i % 4) of byte i / 4) at
// `marks`, the grid's corner and cells per unit in the scene's frame. 56 bytes.
struct InsideGridHeader {
  uvec2 min[3];         // f64 bits
  uvec2 inverse_cell;   // f64 bits
  uint dims[3];
  uint unused;
  uint64_t marks;
};

const uint SENSOR_PINHOLE = 1u;
const uint SENSOR_ORTHOGRAPHIC = 2u;
const uint SENSOR_LIDAR = 3u;

#endif
