#version 460
// The generalized winding number of each instance about each point (Jacobson et al. 2013: the
// sum of its triangles' signed solid angles over 4π, each by Van Oosterom and Strackee's
// formula; a mirroring instance's sum negated), as geometry's CPU `winding_number` computes it,
// one invocation per point over every triangle (all invocations read the same triangle at once).
// The vectors, the triple product and the denominator are f64, the arctangent f32 (GLSL has no
// f64 one) of the pair scaled by a power of two: each term is within about 1e-7 of the CPU's, so
// the sum over N triangles is within N · 2e-7 of it; the host decides points that near 1/2 on
// the CPU. Writes the largest winding number of any instance (0 for an empty scene).
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#define VKRAY_POINT_QUERY
#include "records.glsl"
#include "point_triangle.glsl"
#include "point_scene.glsl"

layout(local_size_x_id = 0) in;

const double FOUR_PI = 12.566370614359172lf;

// Twice the signed solid angle of triangle (a, b, c) seen from the origin (the corners relative
// to the point): 2 atan2(a · (b × c), |a||b||c| + (a·b)|c| + (b·c)|a| + (c·a)|b|).
double twice_solid_angle(dvec3 a, dvec3 b, dvec3 c) {
  double la = sqrt(dot3(a, a));
  double lb = sqrt(dot3(b, b));
  double lc = sqrt(dot3(c, c));
  double numerator = dot3(a, cross(b, c));
  double denominator = la * lb * lc + dot3(a, b) * lc + dot3(b, c) * la + dot3(c, a) * lb;
  double m = max(abs(numerator), abs(denominator));
  // atan2(0, 0) is 0 on the CPU (a point on a corner); GLSL leaves it undefined.
  if (m == 0.0) return 0.0;
  // An exact scaling by a power of two brings both into float's range.
  int e;
  frexp(m, e);
  return 2.0 * double(atan(float(ldexp(numerator, -e)), float(ldexp(denominator, -e))));
}

void main() {
  uint i = gl_GlobalInvocationID.x;
  if (i >= point_params.count) return;
  Doubles points = Doubles(point_params.points);
  dvec3 center = dvec3(point_params.center[0], point_params.center[1], point_params.center[2]);
  precise dvec3 p = dvec3(points.v[3u * i], points.v[3u * i + 1u], points.v[3u * i + 2u]) - center;
  BvhInstances instances = BvhInstances(point_params.instances);
  BvhTriangles triangles = BvhTriangles(point_params.triangles);
  double largest = point_params.instance_count > 0u ? -1.0 / 0.0 : 0.0;
  for (uint k = 0u; k < point_params.instance_count; ++k) {
    BvhInstance x = instances.x[k];
    double sum = 0.0;
    for (uint t = 0u; t < x.triangle_count; ++t) {
      BvhTriangle tri = triangles.t[x.triangles + t];
      sum += twice_solid_angle(corner_in_scene(x, tri.a) - p, corner_in_scene(x, tri.b) - p,
                               corner_in_scene(x, tri.c) - p);
    }
    double w = sum / FOUR_PI;
    largest = max(largest, x.mirrored != 0u ? -w : w);
  }
  DoubleOut(point_params.distances).v[i] = largest;
}
