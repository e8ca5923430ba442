#version 460
// Closest points on the GPU: one invocation per point searches the reference tier's own
// hierarchies (src/scene/closest.rs uploads them) best first, as ReferenceTracer::closest_point
// does on the CPU: the instances' hierarchy by box distance, each instance's mesh hierarchy by
// box gaps in the mesh's frame weighted per axis (lower bounds of scene distances), the nearer
// child first, boxes farther than the best distance so far skipped. Every triangle is measured
// in the scene's frame with the CPU's operations in the CPU's order (point_triangle.glsl),
// squared distances compared as computed, ties to the lower (instance, triangle): the same
// answer as the CPU's, whatever order the search meets the triangles in. The fast tier measures
// each triangle in f32.
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#define VKRAY_POINT_QUERY
#include "records.glsl"
#include "point_triangle.glsl"
#include "point_scene.glsl"
#include "points.glsl"

layout(local_size_x_id = 0) in;
// 1: measure each triangle in f32 (the fast tier); 0: in f64.
layout(constant_id = 1) const uint DISTANCE_F32 = 0u;

// A median-split hierarchy of n items is about log2(n) deep; the stack holds one pending sibling
// per level: 40 covers 2^32 triangles, 32 the 2^24 instances a scene may hold.
const int MESH_STACK = 40;
const int TOP_STACK = 32;
// The instances' boxes are in the scene's frame: only rounding to allow for.
const double TOP_FACTOR2 = 1.0 - 4e-12;

// The squared length of the gap from the box to p (0 inside): Aabb::distance_to squared. The
// search compares squared bounds with squared distances (no square roots), each bound scaled by
// a factor a hair below 1 (squared): rounding can then never skip a box holding a triangle as
// near as the best.
double box_distance2(BvhNode node, dvec3 p, double scale) {
  dvec3 lo = dvec3(node.lo[0], node.lo[1], node.lo[2]);
  dvec3 hi = dvec3(node.hi[0], node.hi[1], node.hi[2]);
  dvec3 gap = max(max(lo - p, p - hi), dvec3(0.0)) * scale;
  return dot(gap, gap);
}

// As box_distance2, each axis's gap squared weighted (an instance's `weights`: a lower bound of
// the squared scene distance from a local box).
double weighted_box_distance2(BvhNode node, dvec3 p, dvec3 weights, double scale) {
  dvec3 lo = dvec3(node.lo[0], node.lo[1], node.lo[2]);
  dvec3 hi = dvec3(node.hi[0], node.hi[1], node.hi[2]);
  dvec3 gap = max(max(lo - p, p - hi), dvec3(0.0)) * scale;
  return dot(gap * gap, weights);
}

// The search's state: the best squared distance, its triangle (index among all meshes'
// triangles) and instance (-1: none yet), its nearest point, and the reach (the best squared
// distance, or max_distance squared before any: boxes beyond it are skipped). Lengths are
// scaled by `scale` (a power of two: ReferenceTracer::search_scale) before they are squared, so
// that far points and tiny scenes neither overflow nor underflow; `f32`: the fast tier measures
// this point in f32 (the host picks the f64 kernel where coordinates pass 2^30, or all lie within
// 2^-30, whose products f32 cannot hold).
struct Search {
  double scale;
  bool f32;
  double d2;
  double reach2;
  double limit;
  int instance;
  uint prim;
  uint triangle;
  dvec3 q;
};

// Measures one triangle and keeps it where it comes before the best (ClosestHit::is_before).
void measure(inout Search s, dvec3 p, BvhInstance x, int instance, uint triangle) {
  BvhTriangle t = BvhTriangles(point_params.triangles).t[triangle];
  dvec3 a = corner_in_scene(x, t.a);
  dvec3 b = corner_in_scene(x, t.b);
  dvec3 c = corner_in_scene(x, t.c);
  double d2;
  dvec3 q;
  if (s.f32) {
    vec3 qf = closest_point_on_triangle_f32(vec3(p), vec3(a), vec3(b), vec3(c));
    vec3 gap = qf - vec3(p);
    d2 = double(dot(gap, gap));
    q = dvec3(qf);
  } else {
    q = closest_point_on_triangle(p, a, b, c);
    d2 = squared_length((q - p) * s.scale);
  }
  // NaN (a degenerate triangle's) is never kept, as on the CPU.
  if (!(d2 <= s.limit)) return;
  if (s.instance >= 0 &&
      !(d2 < s.d2 || (d2 == s.d2 && (instance < s.instance || (instance == s.instance && t.prim < s.prim)))))
    return;
  s.d2 = d2;
  s.instance = instance;
  s.prim = t.prim;
  s.triangle = triangle;
  s.q = q;
  s.reach2 = d2;
}

// Searches one instance's mesh.
void search_instance(inout Search s, dvec3 p, int instance) {
  BvhInstance x = BvhInstances(point_params.instances).x[instance];
  if ((x.mask & 0xFFu) == 0u) return;
  dvec3 local = map_point(x.to_local, p);
  // Local box gaps, weighted per axis, bound world distances from below (gap_weights).
  double factor = (1.0 - 1e-12) * (1.0 - 1e-12);
  dvec3 weights = dvec3(x.weights[0], x.weights[1], x.weights[2]) * factor;
  BvhNodes nodes = BvhNodes(point_params.nodes);
  uint stack[MESH_STACK];
  double bounds[MESH_STACK];
  int n = 0;
  stack[0] = 0u;
  bounds[0] = weighted_box_distance2(nodes.n[x.nodes], local, weights, s.scale);
  n = 1;
  while (n > 0) {
    --n;
    if (bounds[n] > s.reach2) continue;
    BvhNode node = nodes.n[x.nodes + stack[n]];
    if (node.count > 0u) {
      for (uint k = 0u; k < node.count; ++k) measure(s, p, x, instance, x.triangles + node.first + k);
      continue;
    }
    double left = weighted_box_distance2(nodes.n[x.nodes + node.first], local, weights, s.scale);
    double right = weighted_box_distance2(nodes.n[x.nodes + node.first + 1u], local, weights, s.scale);
    // The nearer child is popped first.
    bool left_first = left <= right;
    stack[n] = left_first ? node.first + 1u : node.first;
    bounds[n] = left_first ? right : left;
    stack[n + 1] = left_first ? node.first : node.first + 1u;
    bounds[n + 1] = left_first ? left : right;
    n += 2;
  }
}

void main() {
  uint i = gl_GlobalInvocationID.x;
  if (i >= point_params.count) return;
  // The point this invocation searches (point_order.comp: neighbours in space side by side).
  if (point_params.order != 0ul) i = Words(point_params.order).v[i];
  dvec3 center = dvec3(point_params.center[0], point_params.center[1], point_params.center[2]);
  precise dvec3 p = load_point(point_params.points, i) - center;
  Search s;
  double extent = max_abs3(p);
  if (point_params.instance_count > 0u) {
    BvhNode root = BvhNodes(point_params.top_nodes).n[0];
    extent = max(extent, max(max_abs3(dvec3(root.lo[0], root.lo[1], root.lo[2])), max_abs3(dvec3(root.hi[0], root.hi[1], root.hi[2]))));
  }
  s.scale = length_scale(extent);
  // The host runs this kernel in f32 (DISTANCE_F32) only where every coordinate, the points' and
  // the scene's, lies within 2^±30 of the centre, whose products f32 holds (trace/vulkan/
  // closest_points.rs f32_measurable); a constant, so that the f32 kernel carries no f64 path.
  s.f32 = DISTANCE_F32 != 0u;
  precise double reach = point_params.max_distance * s.scale;
  precise double limit = reach * reach;
  s.limit = limit;
  s.reach2 = limit;
  s.d2 = 0.0;
  s.instance = -1;
  s.prim = 0u;
  s.triangle = 0u;
  s.q = dvec3(0.0);
  if (point_params.instance_count > 0u) {
    BvhNodes top = BvhNodes(point_params.top_nodes);
    Words items = Words(point_params.top_items);
    uint stack[TOP_STACK];
    double bounds[TOP_STACK];
    stack[0] = 0u;
    bounds[0] = box_distance2(top.n[0], p, s.scale) * TOP_FACTOR2;
    int n = 1;
    while (n > 0) {
      --n;
      if (bounds[n] > s.reach2) continue;
      BvhNode node = top.n[stack[n]];
      if (node.count > 0u) {
        for (uint k = 0u; k < node.count; ++k) search_instance(s, p, int(items.v[node.first + k]));
        continue;
      }
      double left = box_distance2(top.n[node.first], p, s.scale) * TOP_FACTOR2;
      double right = box_distance2(top.n[node.first + 1u], p, s.scale) * TOP_FACTOR2;
      bool left_first = left <= right;
      stack[n] = left_first ? node.first + 1u : node.first;
      bounds[n] = left_first ? right : left;
      stack[n + 1] = left_first ? node.first : node.first + 1u;
      bounds[n + 1] = left_first ? left : right;
      n += 2;
    }
  }
  bool found = s.instance >= 0;
  double distance = s.f32 ? double(sqrt(float(s.d2))) : sqrt(s.d2) / s.scale;
  DoubleOut(point_params.distances).v[i] = found ? distance : 1.0 / 0.0;
  if (point_params.hits == 0ul) return;
  double nan = 0.0 / 0.0;
  PointHit hit = PointHit(double[3](nan, nan, nan), nan, nan, -1, 0u);
  if (found) {
    BvhInstance x = BvhInstances(point_params.instances).x[s.instance];
    BvhTriangle t = BvhTriangles(point_params.triangles).t[s.triangle];
    dvec3 a = corner_in_scene(x, t.a);
    dvec3 b = corner_in_scene(x, t.b);
    dvec3 c = corner_in_scene(x, t.c);
    dvec2 uv;
    if (s.f32) {
      uv = dvec2(barycentrics_f32(vec3(s.q), vec3(a), vec3(b), vec3(c)));
    } else {
      uv = barycentrics_of(s.q, a, b, c);
    }
    precise dvec3 world = s.q + center;
    hit = PointHit(double[3](world.x, world.y, world.z), uv.x, uv.y, s.instance, s.prim);
  }
  PointHits(point_params.hits).h[i] = hit;
}
