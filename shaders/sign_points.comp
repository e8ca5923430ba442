#version 460
// The last step of a signed distance chunk (trace/signed.rs): each point's distance negated in
// place where its sign's ray says inside, by parity or by winding number (the crossings' sum plus
// the cap's), as tiers::mark_by_crossings decides on the host. Points whose winding number lies
// within the band about 1/2 keep their distance and get their bit in `unsure`: the CPU decides
// them. So only the distances (and a bit a point) travel back, not the crossings and the cap's
// winding numbers (8 bytes a point instead of 20).
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#define VKRAY_SIGN_POINTS
#include "records.glsl"

layout(local_size_x_id = 0) in;

layout(buffer_reference, std430, buffer_reference_align = 8) buffer Doubles { double v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Ints { int v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) buffer Bits { uint v[]; };

void main() {
  uint i = gl_GlobalInvocationID.x;
  if (i >= sign_params.count) return;
  int crossings = Ints(sign_params.crossings).v[i];
  bool on_surface = (crossings & 1) != 0;
  int sum = crossings >> 1;  // arithmetic: the signed sum
  bool inside;
  if (sign_params.cap_winding == 0ul) {
    inside = on_surface || (sum & 1) == 1;
  } else {
    // One rounding, as the host's f64 sum: no contraction to fuse.
    precise double w = double(sum) + Doubles(sign_params.cap_winding).v[i];
    inside = on_surface || w >= sign_params.inside_from;
    // Also where w is NaN.
    if (!inside && !(w < sign_params.outside_below)) {
      atomicOr(Bits(sign_params.unsure).v[i >> 5], 1u << (i & 31u));
    }
  }
  if (inside) {
    Doubles distances = Doubles(sign_params.distances);
    distances.v[i] = -distances.v[i];
  }
}
