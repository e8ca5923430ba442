#version 460
// The generalized winding number of each instance about each point (Jacobson et al. 2013: the
// sum of its triangles' signed solid angles over 4π, each by Van Oosterom and Strackee's
// formula; a mirroring instance's sum negated), as geometry/winding.rs computes it on the CPU:
// over the mesh's hierarchy, a node whose box the point lies well outside adding the fan from its
// box's centre over its boundary edges instead of its triangles (exact: the same sum), where it
// keeps one (WindingSpan), one invocation per point. The vectors, the triple product and the
// denominator are f64, the arctangent f32 (GLSL has no f64 one) of the pair scaled by a power of
// two: each term is within about 1e-7 of the CPU's, and no point sums more terms than its mesh
// has triangles, so the sum over N triangles is within N · 2e-7 of the CPU's; the host decides
// points that near 1/2 on the CPU. Writes the largest winding number of any instance (0 for an
// empty scene).
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#define VKRAY_POINT_QUERY
#include "records.glsl"
#include "point_triangle.glsl"
#include "point_scene.glsl"
#include "solid_angle.glsl"
#include "points.glsl"

layout(local_size_x_id = 0) in;
// geometry/winding.rs CAP_MARGIN_DIVISOR: a node's boundary stands in for its triangles where the
// point lies outside its box grown by its largest side over this.
layout(constant_id = 2) const uint CAP_MARGIN_DIVISOR = 8u;

layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer WindingSpans { WindingSpan s[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer WindingEdges { WindingEdge e[]; };

const uint NO_CAP = 0xFFFFFFFFu;
// One pending sibling per level of a median-split hierarchy: 40 covers 2^32 triangles.
const int STACK = 40;

// geometry/winding.rs beyond_margin: whether p lies outside the node's box grown by its largest
// side over CAP_MARGIN_DIVISOR.
bool beyond_margin(dvec3 lo, dvec3 hi, dvec3 p) {
  dvec3 extent = max(hi - lo, dvec3(0.0));
  dvec3 margin = dvec3(max(max(extent.x, extent.y), extent.z) / double(CAP_MARGIN_DIVISOR));
  return any(lessThan(p, lo - margin)) || any(greaterThan(p, hi + margin));
}

// Twice the solid angles of one instance's triangles about p, summed over its hierarchy.
double instance_sum(BvhInstance x, dvec3 p) {
  BvhNodes nodes = BvhNodes(point_params.nodes);
  BvhTriangles triangles = BvhTriangles(point_params.triangles);
  WindingSpans spans = WindingSpans(point_params.spans);
  WindingEdges edges = WindingEdges(point_params.edges);
  dvec3 local = map_point(x.to_local, p);
  double sum = 0.0;
  uint stack[STACK];
  int n = 0;
  if (x.triangle_count > 0u) stack[n++] = 0u;
  while (n > 0) {
    uint i = stack[--n];
    BvhNode node = nodes.n[x.nodes + i];
    WindingSpan span = spans.s[x.nodes + i];
    dvec3 lo = dvec3(node.lo[0], node.lo[1], node.lo[2]);
    dvec3 hi = dvec3(node.hi[0], node.hi[1], node.hi[2]);
    if (span.count != NO_CAP && beyond_margin(lo, hi, local)) {
      dvec3 c = 0.5 * (lo + hi);
      dvec3 apex = corner_in_scene(x, double[3](c.x, c.y, c.z)) - p;
      for (uint k = 0u; k < span.count; ++k) {
        WindingEdge edge = edges.e[span.first + k];
        sum += twice_solid_angle(apex, corner_in_scene(x, edge.a) - p, corner_in_scene(x, edge.b) - p);
      }
    } else if (node.count > 0u) {
      for (uint k = 0u; k < node.count; ++k) {
        BvhTriangle t = triangles.t[x.triangles + node.first + k];
        sum += twice_solid_angle(corner_in_scene(x, t.a) - p, corner_in_scene(x, t.b) - p,
                                 corner_in_scene(x, t.c) - p);
      }
    } else {
      stack[n++] = node.first + 1u;
      stack[n++] = node.first;
    }
  }
  return sum;
}

void main() {
  uint i = gl_GlobalInvocationID.x;
  if (i >= point_params.count) return;
  // The point this invocation searches (point_order.comp: neighbours in space side by side).
  if (point_params.order != 0ul) i = Words(point_params.order).v[i];
  dvec3 center = dvec3(point_params.center[0], point_params.center[1], point_params.center[2]);
  precise dvec3 p = load_point(point_params.points, i) - center;
  BvhInstances instances = BvhInstances(point_params.instances);
  double largest = point_params.instance_count > 0u ? -1.0 / 0.0 : 0.0;
  for (uint k = 0u; k < point_params.instance_count; ++k) {
    BvhInstance x = instances.x[k];
    double w = instance_sum(x, p) / FOUR_PI;
    largest = max(largest, x.mirrored != 0u ? -w : w);
  }
  DoubleOut(point_params.distances).v[i] = largest;
}
