#version 460
// The order to search a chunk of points in: cell by cell of a grid over the scene's bounds, the
// cells along a Morton curve (a counting sort in three passes). Neighbouring invocations then
// search neighbouring points, which walk the same nodes of the hierarchies: points as random as
// a box's uniform samples search about twice as fast (docs/benchmarks.md). The answers do not
// depend on the order (each point's search is its own; its results go to its own row).
//   POINT_ORDER_COUNT: each point adds one to its cell's count (cells cleared by the host).
//   POINT_ORDER_SCAN: one workgroup turns the counts into each cell's first slot.
//   POINT_ORDER_SCATTER: each point takes the next slot of its cell.
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#define VKRAY_POINT_ORDER
#include "records.glsl"
#include "points.glsl"

layout(local_size_x_id = 0) in;
// Cells per axis: a power of two, at most 1024 (trace/closest.rs ORDER_GRID).
layout(constant_id = 1) const uint GRID = 32u;

layout(buffer_reference, std430, buffer_reference_align = 4) buffer Counters { uint v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) writeonly buffer Order { uint v[]; };

shared uint partial[gl_WorkGroupSize.x];

// The low 10 bits of x spread to every third bit.
uint spread(uint x) {
  x &= 0x3FFu;
  x = (x | (x << 16)) & 0x030000FFu;
  x = (x | (x << 8)) & 0x0300F00Fu;
  x = (x | (x << 4)) & 0x030C30C3u;
  return (x | (x << 2)) & 0x09249249u;
}

// Point i's cell along the Morton curve; points outside the grid (or NaN) go to its border.
uint cell_of(uint i) {
  dvec3 p = load_point(order_params.points, i);
  dvec3 corner = dvec3(order_params.corner[0], order_params.corner[1], order_params.corner[2]);
  dvec3 scale = dvec3(order_params.scale[0], order_params.scale[1], order_params.scale[2]);
  dvec3 g = (p - corner) * scale;
  uvec3 c;
  for (int k = 0; k < 3; ++k) {
    // Written so that NaN lands in cell 0.
    c[k] = g[k] > 0.0 ? uint(min(g[k], double(GRID - 1u))) : 0u;
  }
  return spread(c.x) | (spread(c.y) << 1) | (spread(c.z) << 2);
}

// Exclusive prefix sums of the cells' counts, by one workgroup: each thread sums a run of cells,
// the runs' sums are scanned in shared memory, and each thread writes its run's first slots.
void scan() {
  Counters cells = Counters(order_params.cells);
  uint threads = gl_WorkGroupSize.x;
  uint run = (GRID * GRID * GRID + threads - 1u) / threads;
  uint t = gl_LocalInvocationID.x;
  uint first = t * run;
  uint last = min(first + run, GRID * GRID * GRID);
  uint sum = 0u;
  for (uint k = first; k < last; ++k) sum += cells.v[k];
  partial[t] = sum;
  barrier();
  for (uint step = 1u; step < threads; step <<= 1) {
    uint add = t >= step ? partial[t - step] : 0u;
    barrier();
    partial[t] += add;
    barrier();
  }
  uint slot = partial[t] - sum;
  for (uint k = first; k < last; ++k) {
    uint count = cells.v[k];
    cells.v[k] = slot;
    slot += count;
  }
}

void main() {
  if (order_params.pass == POINT_ORDER_SCAN) {
    scan();
    return;
  }
  uint i = gl_GlobalInvocationID.x;
  if (i >= order_params.count) return;
  Counters cells = Counters(order_params.cells);
  uint slot = atomicAdd(cells.v[cell_of(i)], 1u);
  if (order_params.pass == POINT_ORDER_SCATTER) Order(order_params.order).v[slot] = i;
}
