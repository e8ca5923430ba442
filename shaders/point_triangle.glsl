// Point-triangle distance in f64 and f32, shared by the exact tier (contains' on-surface test)
// and closest points: geometry/precision.rs closest_point_on_triangle and geometry/reference.rs
// barycentrics, the same operations in the same order (`precise`: no fused multiply-adds), so
// that the GPU's f64 answers are the CPU's.
#ifndef VKRAY_POINT_TRIANGLE_GLSL
#define VKRAY_POINT_TRIANGLE_GLSL

// glam's DVec3::dot: (x x' + y y') + z z', each product rounded (GLSL's dot may fuse them).
double dot3(dvec3 a, dvec3 b) {
  precise double s = (a.x * b.x + a.y * b.y) + a.z * b.z;
  return s;
}

// geometry/precision.rs length_scale: a power of two that brings m (> 0) within [2^-250, 2^250].
double length_scale(double m) {
  const double BIG = 1.8092513943330656e75lf;    // 2^250
  const double SMALL = 5.527147875260445e-76lf;  // 2^-250
  double s = 1.0;
  if (isinf(m) || isnan(m)) return s;
  while (m * s > BIG) s *= SMALL;
  while (m * s > 0.0 && m * s < SMALL) s *= BIG;
  return s;
}

// n / d for 0 <= n <= d, 0 where d is 0 (precision.rs fraction).
double fraction(double n, double d) {
  precise double r = n / d;
  return d > 0.0 ? r : 0.0;
}

double max_abs3(dvec3 v) {
  dvec3 a = abs(v);
  return max(a.x, max(a.y, a.z));
}

// precision.rs closest_on_segment: the point of (a, b) nearest p (xyz), its squared distance
// scaled by s (w). Only the sum that could fuse is precise (the rest are differences and
// products alone): glslang 2023.2's pass over precise values took minutes over more of them here
// (in every shader that includes exact.glsl). Time glslc after changing it.
dvec4 closest_on_segment(dvec3 p, dvec3 a, dvec3 b, double s) {
  dvec3 e = b - a;
  dvec3 ab = e * s;
  dvec3 ap = (p - a) * s;
  double t = min(fraction(max(dot3(ab, ap), 0.0), dot3(ab, ab)), 1.0);
  precise dvec3 q = a + e * t;
  dvec3 gap = (q - p) * s;
  return dvec4(q, dot3(gap, gap));
}

// precision.rs closest_on_edges: a triangle without area by its edges (the first of equals).
dvec3 closest_on_edges(dvec3 p, dvec3 a, dvec3 b, dvec3 c, double s) {
  dvec4 best = closest_on_segment(p, a, b, s);
  dvec4 other = closest_on_segment(p, b, c, s);
  if (other.w < best.w) best = other;
  other = closest_on_segment(p, c, a, s);
  if (other.w < best.w) best = other;
  return best.xyz;
}

// The point of triangle (a, b, c) closest to p: geometry/precision.rs closest_point_on_triangle
// (Ericson 5.1.5, lengths scaled by a power of two), the same operations in the same order.
dvec3 closest_point_on_triangle(dvec3 p, dvec3 a, dvec3 b, dvec3 c) {
  precise dvec3 ab = b - a;
  precise dvec3 ac = c - a;
  precise dvec3 ap = p - a;
  double s = length_scale(max(max(max_abs3(ab), max_abs3(ac)), max_abs3(ap)));
  // Products by a power of two alone: nothing to fuse (and `precise` here took glslang minutes).
  dvec3 sab = ab * s;
  dvec3 sac = ac * s;
  dvec3 sap = ap * s;
  precise dvec3 n = dvec3(sab.y * sac.z - sab.z * sac.y, sab.z * sac.x - sab.x * sac.z, sab.x * sac.y - sab.y * sac.x);
  if (n == dvec3(0.0)) return closest_on_edges(p, a, b, c, s);
  precise double d1 = dot3(sab, sap);
  precise double d2 = dot3(sac, sap);
  if (d1 <= 0.0 && d2 <= 0.0) return a;
  precise dvec3 bp = (p - b) * s;
  precise double d3 = dot3(sab, bp);
  precise double d4 = dot3(sac, bp);
  if (d3 >= 0.0 && d4 <= d3) return b;
  precise double vc = d1 * d4 - d3 * d2;
  // The points returned are precise too: a + ab * x fused into one rounding would differ from
  // the CPU's two in the last place (issue 34's hostile harness saw it on an H200).
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {
    precise dvec3 q = a + ab * fraction(d1, d1 - d3);
    return q;
  }
  precise dvec3 cp = (p - c) * s;
  precise double d5 = dot3(sab, cp);
  precise double d6 = dot3(sac, cp);
  if (d6 >= 0.0 && d5 <= d6) return c;
  precise double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {
    precise dvec3 q = a + ac * fraction(d2, d2 - d6);
    return q;
  }
  precise double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
    precise dvec3 q = b + (c - b) * fraction(d4 - d3, (d4 - d3) + (d5 - d6));
    return q;
  }
  precise double sum = va + vb + vc;
  if (!(sum > 0.0) || isinf(sum)) return closest_on_edges(p, a, b, c, s);
  precise double denominator = 1.0 / sum;
  precise dvec3 q = a + ab * (vb * denominator) + ac * (vc * denominator);
  return q;
}

float fraction_f32(float n, float d) {
  return d > 0.0 ? n / d : 0.0;
}

vec4 closest_on_segment_f32(vec3 p, vec3 a, vec3 b, float s) {
  vec3 e = b - a;
  float t = min(fraction_f32(max(dot(e * s, (p - a) * s), 0.0), dot(e * s, e * s)), 1.0);
  vec3 q = a + e * t;
  vec3 gap = (q - p) * s;
  return vec4(q, dot(gap, gap));
}

vec3 closest_on_edges_f32(vec3 p, vec3 a, vec3 b, vec3 c, float s) {
  vec4 best = closest_on_segment_f32(p, a, b, s);
  vec4 other = closest_on_segment_f32(p, b, c, s);
  if (other.w < best.w) best = other;
  other = closest_on_segment_f32(p, c, a, s);
  if (other.w < best.w) best = other;
  return best.xyz;
}

// The fast tier of closest points: Ericson's closest point (as above) in f32.
vec3 closest_point_on_triangle_f32(vec3 p, vec3 a, vec3 b, vec3 c) {
  vec3 ab = b - a;
  vec3 ac = c - a;
  vec3 ap = p - a;
  // No scaling: the host runs the f32 kernel only where every length lies within 2^±30 (its
  // products of four stay finite in f32), and the f64 kernel elsewhere (closest_points.rs
  // f32_measurable); a data-dependent loop here cost the f32 kernel 5x its speed on an H200.
  const float s = 1.0;
  vec3 sab = ab * s;
  vec3 sac = ac * s;
  if (cross(sab, sac) == vec3(0.0)) return closest_on_edges_f32(p, a, b, c, s);
  vec3 sap = ap * s;
  float d1 = dot(sab, sap);
  float d2 = dot(sac, sap);
  if (d1 <= 0.0 && d2 <= 0.0) return a;
  vec3 bp = (p - b) * s;
  float d3 = dot(sab, bp);
  float d4 = dot(sac, bp);
  if (d3 >= 0.0 && d4 <= d3) return b;
  float vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) return a + ab * fraction_f32(d1, d1 - d3);
  vec3 cp = (p - c) * s;
  float d5 = dot(sab, cp);
  float d6 = dot(sac, cp);
  if (d6 >= 0.0 && d5 <= d6) return c;
  float vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) return a + ac * fraction_f32(d2, d2 - d6);
  float va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) return b + (c - b) * fraction_f32(d4 - d3, (d4 - d3) + (d5 - d6));
  float sum = va + vb + vc;
  if (!(sum > 0.0) || isinf(sum)) return closest_on_edges_f32(p, a, b, c, s);
  float denominator = 1.0 / sum;
  return a + ab * (vb * denominator) + ac * (vc * denominator);
}

vec2 barycentrics_f32(vec3 q, vec3 a, vec3 b, vec3 c) {
  vec3 e1 = b - a;
  vec3 e2 = c - a;
  vec3 w = q - a;
  float d11 = dot(e1, e1);
  float d12 = dot(e1, e2);
  float d22 = dot(e2, e2);
  float det = d11 * d22 - d12 * d12;
  if (det == 0.0) return vec2(0.0);
  return vec2(d22 * dot(w, e1) - d12 * dot(w, e2), d11 * dot(w, e2) - d12 * dot(w, e1)) / det;
}

double squared_length(dvec3 v) {
  precise double s = (v.x * v.x + v.y * v.y) + v.z * v.z;
  return s;
}

// The barycentrics (of b and c) of a point q of triangle (a, b, c): geometry/reference.rs
// `barycentrics`, the same operations in the same order.
dvec2 barycentrics_of(dvec3 q, dvec3 a, dvec3 b, dvec3 c) {
  precise dvec3 e1 = b - a;
  precise dvec3 e2 = c - a;
  precise dvec3 w = q - a;
  precise double d11 = (e1.x * e1.x + e1.y * e1.y) + e1.z * e1.z;
  precise double d12 = (e1.x * e2.x + e1.y * e2.y) + e1.z * e2.z;
  precise double d22 = (e2.x * e2.x + e2.y * e2.y) + e2.z * e2.z;
  precise double dw1 = (w.x * e1.x + w.y * e1.y) + w.z * e1.z;
  precise double dw2 = (w.x * e2.x + w.y * e2.y) + w.z * e2.z;
  precise double det = d11 * d22 - d12 * d12;
  if (det == 0.0) return dvec2(0.0);
  precise double u = (d22 * dw1 - d12 * dw2) / det;
  precise double v = (d11 * dw2 - d12 * dw1) / det;
  return dvec2(u, v);
}

#endif
