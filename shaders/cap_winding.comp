#version 460
// The caps' winding numbers of a winding query's rays (QUERY_WINDING, exact.glsl add_cap), after
// its ray pass counted their crossings: a workgroup a ray, its invocations sharing each hole's
// fan (cap.glsl fan_angles), its partial sums added in one order (the same answers every run).
// The ray pass takes one invocation a ray, and a ray near a large hole sums hundreds of its fan's
// triangles: one invocation each took 6.5–8 ms of bunny-x16's 28.6k-point `contains` on an H200
// (892 edges a point in too few warps to hide their latency). The holes' first and second passes
// are add_cap's of before: holes whose bound is at most CAP_SKIP_BOUND are summed only where the
// first pass leaves the winding number within reach of the band about 1/2.
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#define VKRAY_CAP_WINDING
#include "records.glsl"
#include "point_triangle.glsl"
#include "solid_angle.glsl"
#include "points.glsl"
#include "cap.glsl"

layout(local_size_x_id = 0) in;

layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer CapCounts { int v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) buffer CapWindings { double v[]; };

shared double partial_sums[gl_WorkGroupSize.x];
shared uint partial_unsure[gl_WorkGroupSize.x];

// The sum over the workgroup's invocations of `part`, in the invocations' order, and whether any
// is unsure. Every invocation calls it (it waits at barriers) and gets the same answer.
double workgroup_sum(double part, bool unsure, out bool any_unsure) {
  uint lane = gl_LocalInvocationID.x;
  barrier();  // the last call's reads are done
  partial_sums[lane] = part;
  partial_unsure[lane] = unsure ? 1u : 0u;
  barrier();
  double sum = 0.0;
  uint flags = 0u;
  for (uint k = 0u; k < gl_WorkGroupSize.x; ++k) {
    sum += partial_sums[k];
    flags |= partial_unsure[k];
  }
  any_unsure = flags != 0u;
  return sum;
}

void main() {
  WindingCapHead cap = WindingCapHead(cap_params.cap);
  WindingCapHoles holes = WindingCapHoles(cap.head.holes);
  WindingCapEdges edges = WindingCapEdges(cap.head.edges);
  CapWindings winding = CapWindings(cap_params.winding);
  double sign = cap.head.mirrored != 0u ? -1.0 : 1.0;
  dvec3 shift = dvec3(cap_params.shift[0], cap_params.shift[1], cap_params.shift[2]);
  uint lane = gl_LocalInvocationID.x;
  for (uint i = gl_WorkGroupID.x; i < cap_params.count; i += gl_NumWorkGroups.x) {
    // The same value for the whole workgroup: it goes on or not together.
    if (winding.v[i] != 1.0 / 0.0) continue;
    precise dvec3 origin = load_point(cap_params.origins, i) - shift;
    int count = CapCounts(cap_params.counts).v[i];
    double part = 0.0;
    bool unsure = false;
    double passed_over = 0.0;
    for (int pass = 0; pass < 2; ++pass) {
      if (pass == 1) {
        bool any_unsure;
        double first = sign * workgroup_sum(part, unsure, any_unsure) / FOUR_PI;
        if (!cap_second_pass(count, first, passed_over, cap.head.band)) break;
      }
      for (uint h = 0u; h < cap.head.hole_count; ++h) {
        double bound = fan_winding_bound(origin, holes, h);
        bool angles = pass == 0 ? bound > CAP_SKIP_BOUND : bound <= CAP_SKIP_BOUND;
        if (pass == 0 && !angles) passed_over += bound;
        if (angles) {
          FanAngles fan = fan_angles(origin, holes, h, edges, lane, gl_WorkGroupSize.x);
          part += fan.twice_angle;
          unsure = unsure || fan.unsure;
        }
      }
    }
    bool any_unsure;
    double sum = workgroup_sum(part, unsure, any_unsure);
    if (lane == 0u) winding.v[i] = any_unsure ? 0.0 / 0.0 : sign * sum / FOUR_PI;
  }
}
