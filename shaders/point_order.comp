#version 460
// The order to search a chunk of points in: cell by cell of a grid over the scene's bounds, the
// cells along a Morton curve (a counting sort in three passes). Neighbouring invocations then
// search neighbouring points, which walk the same nodes of the hierarchies: points as random as
// a box's uniform samples search about twice as fast (docs/benchmarks.md). The answers do not
// depend on the order (each point's search is its own; its results go to its own row).
//   POINT_ORDER_COUNT: each point adds one to its cell's count (cells cleared by the host).
//   POINT_ORDER_SCAN: each workgroup turns its block's counts into each cell's first slot in the
//     block, and writes the block's total after the cells.
//   POINT_ORDER_SCAN_BLOCKS: one workgroup turns the blocks' totals into each block's first slot.
//   POINT_ORDER_SCATTER: each point takes the next slot of its cell, after its block's.
// (One workgroup scanning all 64^3 cells took most of the order's 0.6 ms on an H200.)
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

// Cells one workgroup of POINT_ORDER_SCAN scans: a stretch of CELLS_PER_THREAD a thread.
const uint CELLS_PER_THREAD = 16u;
const uint BLOCK = CELLS_PER_THREAD * gl_WorkGroupSize.x;
const uint CELLS = GRID * GRID * GRID;

// Exclusive prefix sums of the `count` counters from `base`, by one workgroup: each thread sums a
// stretch, the stretches' sums are scanned in shared memory, and each thread writes its stretch's
// sums; returns the counters' total.
uint scan_range(Counters cells, uint base, uint count) {
  uint threads = gl_WorkGroupSize.x;
  uint run = (count + threads - 1u) / threads;
  uint t = gl_LocalInvocationID.x;
  uint first = min(t * run, count);
  uint last = min(first + run, count);
  uint sum = 0u;
  for (uint k = first; k < last; ++k) sum += cells.v[base + k];
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
    uint count_k = cells.v[base + k];
    cells.v[base + k] = slot;
    slot += count_k;
  }
  return partial[threads - 1u];
}

void main() {
  Counters cells = Counters(order_params.cells);
  if (order_params.pass == POINT_ORDER_SCAN) {
    // Workgroup w: the cells of block w, its total after every cell (at CELLS + w).
    uint w = gl_WorkGroupID.x;
    uint total = scan_range(cells, w * BLOCK, min(BLOCK, CELLS - w * BLOCK));
    if (gl_LocalInvocationID.x == 0u) cells.v[CELLS + w] = total;
    return;
  }
  if (order_params.pass == POINT_ORDER_SCAN_BLOCKS) {
    scan_range(cells, CELLS, (CELLS + BLOCK - 1u) / BLOCK);
    return;
  }
  uint i = gl_GlobalInvocationID.x;
  if (i >= order_params.count) return;
  uint cell = cell_of(i);
  uint slot = atomicAdd(cells.v[cell], 1u);
  if (order_params.pass == POINT_ORDER_SCATTER) Order(order_params.order).v[cells.v[CELLS + cell / BLOCK] + slot] = i;
}
