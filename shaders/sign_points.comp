#version 460
// The last step of a chunk of signed distances (trace/vulkan/signed_distance.rs) or of `contains`
// (trace/vulkan/inside_points.rs): each point's answer from its sign's ray, by parity or by
// winding number (the crossings' sum plus the cap's), as host_tiers::mark_by_crossings decides on
// the host. Points whose winding number lies within the band about 1/2 get their bit in `unsure`:
// the CPU decides them. Signed distances: each distance negated in place where inside, so that
// only the distances (and a bit a point) travel back, not the crossings and the cap's winding
// numbers (8 bytes a point instead of 20). `contains`: four points an invocation, their answers a
// byte each (1 inside) in one word; a point that is not finite is left to the host (its bit in
// `unsure`), which reports it.
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#define VKRAY_SIGN_POINTS
#include "records.glsl"
#include "points.glsl"

layout(local_size_x_id = 0) in;

layout(buffer_reference, std430, buffer_reference_align = 8) buffer Doubles { double v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Ints { int v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) buffer Bits { uint v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) writeonly buffer Words { uint v[]; };

void mark_unsure(uint i) {
  atomicOr(Bits(sign_params.unsure).v[i >> 5], 1u << (i & 31u));
}

// Whether point i's ray says inside; a point it cannot tell is marked unsure (and not inside).
bool inside_by_ray(uint i) {
  int crossings = Ints(sign_params.crossings).v[i];
  bool on_surface = (crossings & 1) != 0;
  int sum = crossings >> 1;  // arithmetic: the signed sum
  if (sign_params.cap_winding == 0ul) return on_surface || (sum & 1) == 1;
  // One rounding, as the host's f64 sum: no contraction to fuse.
  precise double w = double(sum) + Doubles(sign_params.cap_winding).v[i];
  bool inside = on_surface || w >= sign_params.inside_from;
  // Also where w is NaN.
  if (!inside && !(w < sign_params.outside_below)) mark_unsure(i);
  return inside;
}

void main() {
  uint i = gl_GlobalInvocationID.x;
  if (sign_params.inside == 0ul) {
    if (i >= sign_params.count) return;
    if (inside_by_ray(i)) {
      Doubles distances = Doubles(sign_params.distances);
      distances.v[i] = -distances.v[i];
    }
    return;
  }
  uint first = 4u * i;
  if (first >= sign_params.count) return;
  uint word = 0u;
  for (uint k = 0u; k < 4u && first + k < sign_params.count; ++k) {
    uint p = first + k;
    dvec3 q = load_point(sign_params.points, p);
    if (any(isnan(q)) || any(isinf(q))) {
      mark_unsure(p);
    } else if (inside_by_ray(p)) {
      word |= 1u << (8u * k);
    }
  }
  Words(sign_params.inside).v[i] = word;
}
