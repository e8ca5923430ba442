// The points a point query reads (the `points` of PointParams, PointOrderParams and PointRays):
// xyz per point, f64, or f32 where the address's bit 0 is set (trace/vulkan/closest_points.rs
// POINTS_F32_TAG: f32 points travel as the caller gave them, half the bytes of f64), widened
// here, exactly (subnormals too: widen.glsl). Include after enabling GL_EXT_buffer_reference and
// 64-bit integers.
#ifndef VKRAY_POINTS_GLSL
#define VKRAY_POINTS_GLSL

#include "widen.glsl"

layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer PointsF32 { uint v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer PointsF64 { double v[]; };

// Point i of the points at `points` (tagged), in f64.
dvec3 load_point(uint64_t points, uint i) {
  uint64_t base = points & ~1ul;
  dvec3 p;
  if ((points & 1ul) != 0ul) {
    PointsF32 f = PointsF32(base);
    p = dvec3(widen_f32(f.v[3u * i]), widen_f32(f.v[3u * i + 1u]), widen_f32(f.v[3u * i + 2u]));
  } else {
    PointsF64 d = PointsF64(base);
    p = dvec3(d.v[3u * i], d.v[3u * i + 1u], d.v[3u * i + 2u]);
  }
  return p;
}

#endif
