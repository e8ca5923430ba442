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

// The point of triangle (a, b, c) closest to p: geometry/precision.rs closest_point_on_triangle
// (Ericson 5.1.5), the same operations in the same order.
dvec3 closest_point_on_triangle(dvec3 p, dvec3 a, dvec3 b, dvec3 c) {
  precise dvec3 ab = b - a;
  precise dvec3 ac = c - a;
  precise dvec3 ap = p - a;
  precise double d1 = dot3(ab, ap);
  precise double d2 = dot3(ac, ap);
  if (d1 <= 0.0 && d2 <= 0.0) return a;
  precise dvec3 bp = p - b;
  precise double d3 = dot3(ab, bp);
  precise double d4 = dot3(ac, bp);
  if (d3 >= 0.0 && d4 <= d3) return b;
  precise double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) return a + ab * (d1 / (d1 - d3));
  precise dvec3 cp = p - c;
  precise double d5 = dot3(ab, cp);
  precise double d6 = dot3(ac, cp);
  if (d6 >= 0.0 && d5 <= d6) return c;
  precise double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) return a + ac * (d2 / (d2 - d6));
  precise double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
  precise double denominator = 1.0 / (va + vb + vc);
  return a + ab * (vb * denominator) + ac * (vc * denominator);
}

// The fast tier of closest points: Ericson's closest point (as above) in f32.
vec3 closest_point_on_triangle_f32(vec3 p, vec3 a, vec3 b, vec3 c) {
  vec3 ab = b - a;
  vec3 ac = c - a;
  vec3 ap = p - a;
  float d1 = dot(ab, ap);
  float d2 = dot(ac, ap);
  if (d1 <= 0.0 && d2 <= 0.0) return a;
  vec3 bp = p - b;
  float d3 = dot(ab, bp);
  float d4 = dot(ac, bp);
  if (d3 >= 0.0 && d4 <= d3) return b;
  float vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) return a + ab * (d1 / (d1 - d3));
  vec3 cp = p - c;
  float d5 = dot(ab, cp);
  float d6 = dot(ac, cp);
  if (d6 >= 0.0 && d5 <= d6) return c;
  float vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) return a + ac * (d2 / (d2 - d6));
  float va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
  float denominator = 1.0 / (va + vb + vc);
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
