// The "exact" precision tier: the f64 watertight ray/triangle test of src/geometry/precision.rs, evaluated
// with the same operations in the same order, for candidates that f32 traversal of conservative
// per-triangle boxes yields. `precise` forbids fused multiply-adds: the two triangles sharing an
// edge must compute exact negations of one edge function, or rays could slip between them.
// Include after common.glsl (which includes records.glsl).

// ExactInstance and ExactBest, the records this tier shares with the host, are in records.glsl.
#include "point_triangle.glsl"
#include "solid_angle.glsl"
#include "points.glsl"
#include "cap.glsl"
layout(buffer_reference, std430, buffer_reference_align = 32) readonly buffer ExactInstances { ExactInstance x[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer Doubles { double v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) writeonly buffer DoubleOut { double v[]; };
layout(buffer_reference, std430, buffer_reference_align = 32) readonly buffer Ray64Buffer { dvec4 v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer PointRaysRecord { PointRays r; };

// One ray in f64, in the scene's frame: origin and tmin, direction and tmax (64 bytes).
struct Ray64 {
  dvec3 origin;
  double tmin;
  dvec3 direction;
  double tmax;
};

// The exact tier's leaner layouts of plain rays (f32, one interval; geometry::rays::RayLayout,
// RAY_SOURCE 3 and 4 as rays.glsl's): a header of 64 bytes (the shift into the scene's frame and
// the interval in f64, then the shared origin in f32), then 6 floats a ray (its origin and
// direction as given, in the world) or 3 (its direction). The origin moves into the scene's
// frame here in f64, as the host moves it (Rays::ray64).
const uint EXACT_FROM_COMPACT = 3u;
const uint EXACT_FROM_DIRECTIONS = 4u;
layout(buffer_reference, std430, buffer_reference_align = 16) readonly buffer ExactRayHeader {
  double shift[3];
  double tmin;
  double tmax;
  double unused;
  uvec4 origin;  // f32 bits: xyz (Rays::pack_exact_compact's shared origin)
};
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer FloatBits { uint v[]; };

// Three f32s (their bits) from `at` of `f`, in f64.
dvec3 widen3(FloatBits f, uint at) {
  return dvec3(widen_f32(f.v[at]), widen_f32(f.v[at + 1u]), widen_f32(f.v[at + 2u]));
}

// The ray (and output row) invocation `launch` serves: itself, or with rays from points in an
// order, the point's own.
uint ray_index(uint launch) {
  if (RAY_SOURCE != RAYS_FROM_POINTS) return launch;
  uint64_t order = PointRaysRecord(params.rays).r.order;
  return order == 0ul ? launch : Words(order).v[launch];
}

layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer InsideGridRecord { InsideGridHeader g; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer GridMarks { uint v[]; };
const uint GRID_INSIDE = 1u;
const uint GRID_UNDECIDED = 2u;

// RAYS_FROM_POINTS with a grid (PointRays.grid): the crossings that give point i the answer of
// its grid cell (one for inside, none for outside: as the winding query counts them, with a cap
// winding number of 0), or -1 where the cell is undecided (or there is no grid). The cell is the
// host's (InsideGrid::mark_rows): the same f64 operations in the same order, so that each point
// reads the cell the host's `contains` reads; a point beyond the grid is outside.
int grid_crossings(uint i) {
  PointRays r = PointRaysRecord(params.rays).r;
  if (r.grid == 0ul) return -1;
  InsideGridHeader g = InsideGridRecord(r.grid).g;
  dvec3 shift = dvec3(packDouble2x32(r.shift[0]), packDouble2x32(r.shift[1]), packDouble2x32(r.shift[2]));
  dvec3 corner = dvec3(packDouble2x32(g.min[0]), packDouble2x32(g.min[1]), packDouble2x32(g.min[2]));
  precise dvec3 q = (load_point(r.points, i) - shift - corner) * packDouble2x32(g.inverse_cell);
  dvec3 dims = dvec3(g.dims[0], g.dims[1], g.dims[2]);
  if (!(all(greaterThanEqual(q, dvec3(0.0))) && all(lessThan(q, dims)))) return 0;
  uint cell = (uint(q.z) * g.dims[1] + uint(q.y)) * g.dims[0] + uint(q.x);
  uint mark = (GridMarks(g.marks).v[cell >> 4u] >> (2u * (cell & 15u))) & 3u;
  return mark == GRID_UNDECIDED ? -1 : (mark == GRID_INSIDE ? CROSSING : 0);
}

Ray64 load_ray64(uint i) {
  if (RAY_SOURCE == RAYS_FROM_SENSOR) {
    // The sensor's f32 ray in the world, moved to the scene's frame in f64 (as the host moves the
    // rays Sensor.rays() returns).
    Sensor s = SensorRecord(params.rays).s;
    Ray r = sensor_ray(i);
    dvec3 shift = dvec3(packDouble2x32(s.shift[0]), packDouble2x32(s.shift[1]), packDouble2x32(s.shift[2]));
    return Ray64(dvec3(r.origin) - shift, packDouble2x32(s.tmin64), dvec3(r.direction), packDouble2x32(s.tmax64));
  }
  if (RAY_SOURCE == RAYS_FROM_POINTS) {
    PointRays r = PointRaysRecord(params.rays).r;
    dvec3 p = load_point(r.points, i);
    dvec3 shift = dvec3(packDouble2x32(r.shift[0]), packDouble2x32(r.shift[1]), packDouble2x32(r.shift[2]));
    dvec3 d = dvec3(packDouble2x32(r.direction[0]), packDouble2x32(r.direction[1]), packDouble2x32(r.direction[2]));
    return Ray64(p - shift, packDouble2x32(r.tmin), d, packDouble2x32(r.tmax));
  }
  if (RAY_SOURCE == EXACT_FROM_COMPACT || RAY_SOURCE == EXACT_FROM_DIRECTIONS) {
    ExactRayHeader h = ExactRayHeader(params.rays);
    FloatBits f = FloatBits(params.rays + 64ul);
    bool shared_origin = RAY_SOURCE == EXACT_FROM_DIRECTIONS;
    uint at = (shared_origin ? 3u : 6u) * i;
    dvec3 o = shared_origin ? dvec3(widen_f32(h.origin.x), widen_f32(h.origin.y), widen_f32(h.origin.z)) : widen3(f, at);
    uint d = shared_origin ? at : at + 3u;
    dvec3 shift = dvec3(h.shift[0], h.shift[1], h.shift[2]);
    return Ray64(o - shift, h.tmin, widen3(f, d), h.tmax);
  }
  Ray64Buffer rays = Ray64Buffer(params.rays);
  dvec4 a = rays.v[2u * i];
  dvec4 b = rays.v[2u * i + 1u];
  return Ray64(a.xyz, a.w, b.xyz, b.w);
}

// Transmittance, pipeline backend: the light left per ray, multiplied by the intersection shader.
layout(buffer_reference, std430, buffer_reference_align = 8) volatile buffer TransmitScratch { double v[]; };

// volatile: the intersection shader's stores must reach the ray generation shader's loads after
// traceRayEXT. A driver that inlines the stages into one function (lavapipe) may otherwise
// forward raygen's initial store straight to its final load, as if the call wrote nothing.
layout(buffer_reference, std430, buffer_reference_align = 8) volatile buffer ExactScratch { ExactBest b[]; };

ExactBest exact_miss() {
  return ExactBest(1.0 / 0.0, 0.0, 0.0, -1, -1, -1, -1);
}

// f32 traversal starts where the ray enters the scene's padded bounds, so that the f32 ray's
// rounding is a few ulps of the scene's size, not of the origin's distance. Returns that distance
// along the ray (f64), or -1 when the ray misses the bounds within [tmin, tmax]. Each slab's
// distance, (bound - origin) / direction, is rounded to a few ulps of itself: from far away (an
// origin 1e20 from a scene of size 2) that is more than the scene, and an entry that overshot
// would start traversal inside the scene, past crossings the f64 test accepts. So the entry is
// moved back by 8 ulps of itself: before the bounds, by about as much as the origin's own
// rounding (which the f64 test shares).
double scene_entry(Ray64 ray) {
  dvec3 lo = dvec3(params.bounds[0], params.bounds[1], params.bounds[2]);
  dvec3 hi = dvec3(params.bounds[3], params.bounds[4], params.bounds[5]);
  dvec3 inv = 1.0 / ray.direction;
  dvec3 t0 = (lo - ray.origin) * inv;
  dvec3 t1 = (hi - ray.origin) * inv;
  // NaN (0 * inf: an origin on a face, moving along it) must not reject: min/max drop NaN.
  dvec3 near = min(t1, t0);
  dvec3 far = max(t1, t0);
  double enter = max(max(ray.tmin, near.x), max(near.y, near.z));
  double leave = min(min(ray.tmax, far.x), min(far.y, far.z));
  // The test is widened by the same rounding: a thin box far away may round to an empty slab.
  // (enter >= tmin >= 0, so scaling moves it back. Keep this shape: `leave + c * abs(leave)`
  // here made glslang 2023.2 take minutes over trace_exact_ray_query.comp. Time glslc after
  // changing it.)
  double backed = enter * (1.0 - 1.7763568394002505e-15lf);  // 8 ulps
  return backed <= leave * (1.0 + 1.7763568394002505e-15lf) ? max(backed, 0.0) : -1.0;
}

// The f32 distance past `entry` to commit for a hit at f64 distance `t`: a little beyond it, so
// that the rounding of t - entry (a few ulps of t: thousands of units from 1e20 away) never lets
// traversal skip a box holding a triangle at the same t (the tie-break wants every one).
float committed_distance(double t, double entry) {
  const double EPSILON = 2.220446049250313e-16lf;
  return float((t - entry) + 8.0 * EPSILON * abs(t)) * (1.0 + 1.0 / 1048576.0);
}

// The f32 ray traversal follows, shifted to start at `entry`, with its interval widened a little:
// boxes are padded and the f64 test judges [tmin, tmax] itself.
struct TraversalRay {
  vec3 origin;
  float tmin;
  vec3 direction;
  float tmax;
};

// The shifted origin is origin + entry * direction in one rounding (fma): near the scene it is
// then within an ulp of its own size of the ray, where a rounded product (entry * direction, to
// an ulp of the origin's distance) could move it sideways off the ray by more than the scene.
TraversalRay traversal_ray(Ray64 ray, double entry) {
  const float FLT_MAX = 3.402823466e38;
  float tmin = float(max(ray.tmin - entry, 0.0)) * (1.0 - 1.0 / 1048576.0);
  float tmax = min(float(ray.tmax - entry) * (1.0 + 1.0 / 1048576.0), FLT_MAX);
  return TraversalRay(vec3(fma(dvec3(entry), ray.direction, ray.origin)), tmin, vec3(ray.direction), tmax);
}

bool owns_edge(dvec2 direction) {
  return direction.y > 0.0 || (direction.y == 0.0 && direction.x > 0.0);
}

// Whether the candidate (t, instance, caller's prim) comes before the best: nearer, then lower ids.
bool is_before(double t, int instance, int prim, ExactBest best, int best_prim) {
  return t < best.t || (t == best.t && (instance < best.instance || (instance == best.instance && prim < best_prim)));
}

// The order of all hits (QUERY_ALL) in the exact tier, as ReferenceHit::is_before.
bool is_before(ExactHit a, ExactHit b) {
  return a.t < b.t || (a.t == b.t && (a.instance < b.instance || (a.instance == b.instance && a.prim < b.prim)));
}

bool is_same(ExactHit a, ExactHit b) {
  return a.t == b.t && a.instance == b.instance && a.prim == b.prim;
}

dvec3 exact_vertex(ExactInstance x, uint index) {
  Doubles d = Doubles(x.vertices);
  return dvec3(d.v[3u * index], d.v[3u * index + 1u], d.v[3u * index + 2u]);
}

// A ray in a mesh's frame, made ready for Woop, Benthin and Wald's watertight test: permuted so
// that z is the dominant axis (kx, ky, kz) and sheared onto +z (sx, sy, sz).
struct ShearedRay {
  dvec3 origin;
  ivec3 axes;
  dvec3 shear;
};

ShearedRay shear_ray(ExactInstance x, Ray64 ray) {
  precise dvec3 o;
  precise dvec3 d;
  for (int r = 0; r < 3; ++r) {
    precise double ox = x.rows[r].x * ray.origin.x + x.rows[r].y * ray.origin.y + x.rows[r].z * ray.origin.z + x.rows[r].w;
    precise double dx = x.rows[r].x * ray.direction.x + x.rows[r].y * ray.direction.y + x.rows[r].z * ray.direction.z;
    o[r] = ox;
    d[r] = dx;
  }
  dvec3 a = abs(d);
  int kz = (a.x >= a.y && a.x >= a.z) ? 0 : (a.y >= a.z ? 1 : 2);
  int kx = (kz + 1) % 3;
  int ky = (kz + 2) % 3;
  if (d[kz] < 0.0) {
    int swap = kx;
    kx = ky;
    ky = swap;
  }
  precise double sx = d[kx] / d[kz];
  precise double sy = d[ky] / d[kz];
  precise double sz = 1.0 / d[kz];
  return ShearedRay(o, ivec3(kx, ky, kz), dvec3(sx, sy, sz));
}

// A corner (mesh frame) relative to the ray's origin, permuted and sheared.
dvec3 sheared_corner(ShearedRay s, dvec3 vertex) {
  precise dvec3 v = vertex - s.origin;
  precise double px = v[s.axes.x] - s.shear.x * v[s.axes.z];
  precise double py = v[s.axes.y] - s.shear.y * v[s.axes.z];
  precise double pz = s.shear.z * v[s.axes.z];
  return dvec3(px, py, pz);
}

// The watertight test of one triangle's sheared corners `p`: false where the ray passes beside
// it, meets it edge-on, or meets only an edge or corner another triangle owns (CLOSED_EDGES 0);
// else its edge functions (`uvw`), their sum `det` (> 0: the ray meets its front, where the mesh
// frame's normal faces the ray) and the hit's distance `t` along the ray. The two triangles that
// share an edge compute exact negations of its edge function (no fused multiply-adds), so a ray
// through the edge meets exactly one of them.
bool watertight(dvec3 p[3], out dvec3 uvw, out double det, out double t) {
  precise double u = p[2].x * p[1].y - p[2].y * p[1].x;
  precise double v = p[0].x * p[2].y - p[0].y * p[2].x;
  precise double w = p[1].x * p[0].y - p[1].y * p[0].x;
  if ((u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0)) return false;
  precise double sum = u + v + w;
  det = sum;
  if (det == 0.0) return false;
  double sign = det > 0.0 ? 1.0 : -1.0;
  if (CLOSED_EDGES == 0u) {
    if (u == 0.0 && !owns_edge(sign * (p[2].xy - p[1].xy))) return false;
    if (v == 0.0 && !owns_edge(sign * (p[0].xy - p[2].xy))) return false;
    if (w == 0.0 && !owns_edge(sign * (p[1].xy - p[0].xy))) return false;
  }
  precise double distance = (u * p[0].z + v * p[1].z + w * p[2].z) / det;
  uvw = dvec3(u, v, w);
  t = distance;
  return true;
}

// The watertight test of device triangle `prim` of `instance` (the ray already in its frame),
// within the ray's interval and the query's culling; on a hit, its t, barycentrics (of vertices
// 1 and 2) and det (its sign: the side met, as `watertight`'s).
bool exact_hit(ShearedRay s, Ray64 ray, int instance, int prim, out double t_hit, out double u_hit, out double v_hit,
               out double det) {
  ExactInstance x = ExactInstances(params.instances).x[instance];
  uvec3 idx = triangle_indices_at(x.indices, 0u, uint(prim));
  dvec3 p[3];
  for (int k = 0; k < 3; ++k) p[k] = sheared_corner(s, exact_vertex(x, idx[k]));
  dvec3 uvw;
  double t;
  if (!watertight(p, uvw, det, t)) return false;
  // Query culling: front is the side the hit's normal points to (see InstanceFlags).
  bool front = (det > 0.0) != ((x.flags & EXACT_FLIP_FACING) != 0u);
  if ((x.flags & EXACT_CULL_DISABLE) == 0u &&
      ((RAY_FLAGS & gl_RayFlagsCullBackFacingTrianglesEXT) != 0u && !front ||
       (RAY_FLAGS & gl_RayFlagsCullFrontFacingTrianglesEXT) != 0u && front)) {
    return false;
  }
  if (!(t >= ray.tmin && t <= ray.tmax)) return false;
  t_hit = t;
  u_hit = uvw.y / det;
  v_hit = uvw.z / det;
  return true;
}

// Runs the watertight test of device triangle `prim` of `instance` within the ray's interval and
// the query's culling; on a hit, its t and barycentrics (of vertices 1 and 2).
bool exact_hit(Ray64 ray, int instance, int prim, out double t_hit, out double u_hit, out double v_hit) {
  double det;
  ShearedRay s = shear_ray(ExactInstances(params.instances).x[instance], ray);
  return exact_hit(s, ray, instance, prim, t_hit, u_hit, v_hit, det);
}

// The opacity of the caller's triangle `caller` (among all parts) of an instance.
float exact_opacity(ExactInstance x, int caller) {
  return x.opacity == 0ul ? 1.0 : Floats(x.opacity).v[caller];
}

// Ray i's exact hit with device triangle `prim` of `instance`, if any and solid, as a stored record.
bool exact_record(Ray64 ray, int instance, int prim, out ExactHit h) {
  double t;
  double u;
  double v;
  if (!exact_hit(ray, instance, prim, t, u, v)) return false;
  ExactInstance x = ExactInstances(params.instances).x[instance];
  int caller = caller_index(x.primitive_order, prim);
  if (!is_solid(exact_opacity(x, caller))) return false;
  h = ExactHit(t, u, v, uint(instance), uint(caller));
  return true;
}

double max_abs(dvec3 v) {
  dvec3 a = abs(v);
  return max(a.x, max(a.y, a.z));
}

// Whether the ray's origin lies on device triangle `prim` of `instance`, to within 8 ulps of the
// coordinates involved: ReferenceTracer::on_surface's test (contains calls such points inside).
// Every triangle whose box holds the origin comes to the shaders as a candidate: traversal of a
// point inside the scene's bounds starts at the point.
bool origin_on_triangle(Ray64 ray, int instance, int prim) {
  const double ON_SURFACE_ULPS = 8.0;
  const double EPSILON = 2.220446049250313e-16lf;
  const double MIN_POSITIVE = 2.2250738585072014e-308lf;
  ExactInstance x = ExactInstances(params.instances).x[instance];
  precise dvec3 p;
  for (int r = 0; r < 3; ++r) {
    precise double coordinate = x.rows[r].x * ray.origin.x + x.rows[r].y * ray.origin.y + x.rows[r].z * ray.origin.z + x.rows[r].w;
    p[r] = coordinate;
  }
  uvec3 idx = triangle_indices_at(x.indices, 0u, uint(prim));
  dvec3 a = exact_vertex(x, idx.x);
  dvec3 b = exact_vertex(x, idx.y);
  dvec3 c = exact_vertex(x, idx.z);
  precise dvec3 gap = closest_point_on_triangle(p, a, b, c) - p;
  double scale = max(max(max_abs(p), max_abs(a)), max(max_abs(b), max_abs(c)));
  return sqrt(dot(gap, gap)) <= ON_SURFACE_ULPS * EPSILON * max(scale, MIN_POSITIVE);
}

// Transmittance: 1 - the opacity of device triangle `prim` of `instance` where the ray crosses
// it, else 1.
double exact_transmit(Ray64 ray, int instance, int prim) {
  double t;
  double u;
  double v;
  if (!exact_hit(ray, instance, prim, t, u, v)) return 1.0;
  ExactInstance x = ExactInstances(params.instances).x[instance];
  return 1.0 - double(exact_opacity(x, caller_index(x.primitive_order, prim)));
}

// Runs the watertight test of device triangle `prim` of `instance`; updates `best` and returns
// true when it is hit (and solid) and comes before `best`.
bool exact_candidate(inout ExactBest best, Ray64 ray, int instance, int prim, int custom, int geometry) {
  double t;
  double bu;
  double bv;
  if (!exact_hit(ray, instance, prim, t, bu, bv)) return false;
  ExactInstance x = ExactInstances(params.instances).x[instance];
  int caller = caller_index(x.primitive_order, prim);
  if (!is_solid(exact_opacity(x, caller))) return false;
  int best_caller = best.prim < 0 ? 0 : caller_index(ExactInstances(params.instances).x[best.instance].primitive_order, best.prim);
  if (best.prim >= 0 && !is_before(t, instance, caller, best, best_caller)) return false;
  best = ExactBest(t, bu, bv, instance, prim, custom, geometry);
  return true;
}

// Writes the requested fields of the best hit: t and uv in f64, the normal from f64 vertices,
// the caller's triangle as (geometry, triangle within that part).
void store_exact(uint i, ExactBest best) {
  bool hit = best.prim >= 0;
  ExactInstance x;
  int caller = -1;
  int geometry = -1;
  vec3 normal = vec3(uintBitsToFloat(0x7fc00000u));
  if (hit) {
    x = ExactInstances(params.instances).x[best.instance];
    caller = caller_index(x.primitive_order, best.prim);
    Words offsets = Words(x.part_offsets);
    geometry = 0;
    while (uint(geometry) + 1u < x.part_count && offsets.v[geometry + 1] <= uint(caller)) ++geometry;
    caller -= int(offsets.v[geometry]);
    if ((OUTPUTS & OUT_NORMAL) != 0u) {
      uvec3 idx = triangle_indices_at(x.indices, 0u, uint(best.prim));
      dvec3 a = exact_vertex(x, idx.x);
      dvec3 n = cross(exact_vertex(x, idx.y) - a, exact_vertex(x, idx.z) - a);
      // The inverse transpose of the mesh-to-scene map is the transpose of its inverse (rows).
      dvec3 world = x.rows[0].xyz * n.x + x.rows[1].xyz * n.y + x.rows[2].xyz * n.z;
      double det = dot(x.rows[0].xyz, cross(x.rows[1].xyz, x.rows[2].xyz));
      normal = vec3(normalize(det < 0.0 ? -world : world));
    }
  }
  double nan = 0.0 / 0.0;
  if ((OUTPUTS & OUT_T) != 0u) DoubleOut(params.out_t).v[i] = hit ? best.t : 1.0 / 0.0;
  if ((OUTPUTS & OUT_PRIM) != 0u) IntOut(params.out_prim).v[i] = caller;
  if ((OUTPUTS & OUT_INSTANCE) != 0u) IntOut(params.out_instance).v[i] = hit ? best.instance : -1;
  if ((OUTPUTS & OUT_CUSTOM) != 0u) IntOut(params.out_custom).v[i] = hit ? best.custom : -1;
  if ((OUTPUTS & OUT_GEOMETRY) != 0u) IntOut(params.out_geometry).v[i] = geometry;
  if ((OUTPUTS & OUT_UV) != 0u) {
    DoubleOut uv = DoubleOut(params.out_uv);
    uv.v[2u * i] = hit ? best.u : nan;
    uv.v[2u * i + 1u] = hit ? best.v : nan;
  }
  if ((OUTPUTS & OUT_NORMAL) != 0u) {
    FloatOut n = FloatOut(params.out_normal);
    n.v[3u * i] = normal.x;
    n.v[3u * i + 1u] = normal.y;
    n.v[3u * i + 2u] = normal.z;
  }
}

// PARITY and WINDING: what device triangle `prim` of `instance` adds to the ray's count (see
// QUERY_PARITY): its crossing, signed by the side met, and whether the origin lies on it.
int exact_crossing(Ray64 ray, int instance, int prim) {
  double t;
  double u;
  double v;
  double det;
  ShearedRay s = shear_ray(ExactInstances(params.instances).x[instance], ray);
  int count = exact_hit(s, ray, instance, prim, t, u, v, det) ? (det > 0.0 ? -CROSSING : CROSSING) : 0;
  return origin_on_triangle(ray, instance, prim) ? count | ON_SURFACE : count;
}

// WINDING: the caps of instance 0 (cap.glsl) at params.scratch.

// Whether the sheared ray may cross the fan of hole `h`: the fan lies within `radius` of its apex,
// and shearing stretches lengths by at most sqrt(1 + sx² + sy²) (both shears are at most 1), so
// its corners' sheared xy lie within that much of the apex's. The margin is far past the rounding
// of the corners (relative 1e-16 of the coordinates), so that no crossing the watertight test
// would find is passed over.
bool may_cross_fan(ShearedRay s, WindingCapHoles holes, uint h) {
  dvec3 apex = dvec3_of(holes.h[h].apex);
  dvec3 c = sheared_corner(s, apex);
  double reach = sqrt(1.0 + s.shear.x * s.shear.x + s.shear.y * s.shear.y) * holes.h[h].radius;
  reach += 1e-6 * reach + 1e-9 * (length(apex) + length(s.origin));
  return dot(c.xy, c.xy) <= reach * reach;
}

// The crossings of the fan of hole `h` from its apex over each of its boundary edges a -> b,
// tested as the mesh's triangles are (the same sheared ray, the boundary's own vertices: a ray
// through a boundary edge meets either the mesh or the fan), as exact_crossing counts them.
int fan_crossings(ShearedRay s, Ray64 ray, WindingCapHoles holes, uint h, WindingCapEdges edges) {
  int count = 0;
  dvec3 p[3];
  p[0] = sheared_corner(s, dvec3_of(holes.h[h].apex));
  uint end = holes.h[h].first + holes.h[h].count;
  for (uint k = holes.h[h].first; k < end; ++k) {
    p[1] = sheared_corner(s, dvec3_of(edges.e[k].a));
    p[2] = sheared_corner(s, dvec3_of(edges.e[k].b));
    dvec3 uvw;
    double det;
    double t;
    if (watertight(p, uvw, det, t) && t >= ray.tmin && t <= ray.tmax) count += det > 0.0 ? -CROSSING : CROSSING;
  }
  return count;
}

// Where a winding query's ray pass leaves each ray's origin for cap_winding.comp: 3 doubles a ray.
layout(buffer_reference, std430, buffer_reference_align = 8) writeonly buffer CapOrigins { double v[]; };

// WINDING, after the mesh's crossings are in `count`: takes away the crossings of the caps from
// it, and leaves the caps' winding number about the origin to cap_winding.comp. The mesh less the
// caps has no boundary: its winding number is the integer count, and the mesh's is that plus the
// caps'. Where no hole's fan needs its solid angle (each bounded by CAP_SKIP_BOUND, and their
// bounds cannot bring the sum within the band about 1/2), the caps' winding number is written as
// 0 here; else as +infinity, for cap_winding.comp, whose workgroups sum each such ray's fans over
// many invocations (one invocation a ray took most of bunny-x16's `contains` on an H200), and the
// origin goes to params.out_uv (rays from points: cap_winding.comp reads the points).
// Keep this shape (the holes' fields read through their buffer reference, one call of
// fan_crossings, the caps added through memory in trace_exact_ray_query.comp): on other shapes,
// glslang 2023.2's pass over precise values took minutes and gigabytes (a budget of bounds shared
// by the holes, struct copies of a hole, or an inout count did). Time glslc after changing it.
int add_cap(uint i, Ray64 ray, int count) {
  WindingCapHead cap = WindingCapHead(params.scratch);
  WindingCapHoles holes = WindingCapHoles(cap.head.holes);
  WindingCapEdges edges = WindingCapEdges(cap.head.edges);
  ShearedRay s = shear_ray(ExactInstances(params.instances).x[0], ray);
  double sign = cap.head.mirrored != 0u ? -1.0 : 1.0;
  bool angles = false;
  double passed_over = 0.0;
  for (uint h = 0u; h < cap.head.hole_count; ++h) {
    double bound = fan_winding_bound(ray.origin, holes, h);
    if (bound > CAP_SKIP_BOUND) {
      angles = true;
    } else {
      passed_over += bound;
    }
    if (may_cross_fan(s, holes, h)) count -= fan_crossings(s, ray, holes, h, edges);
  }
  angles = angles || cap_second_pass(count, 0.0, passed_over, cap.head.band);
  DoubleOut(params.out_t).v[i] = angles ? 1.0 / 0.0 : sign * 0.0 / FOUR_PI;
  if (angles && RAY_SOURCE != RAYS_FROM_POINTS) {
    CapOrigins origins = CapOrigins(params.out_uv);
    origins.v[3u * i] = ray.origin.x;
    origins.v[3u * i + 1u] = ray.origin.y;
    origins.v[3u * i + 2u] = ray.origin.z;
  }
  return count;
}
