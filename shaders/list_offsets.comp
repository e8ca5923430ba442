#version 460
// The storing pass's lists from the counting pass's counts, on the GPU (all_hits.rs): ray i keeps
// min(count, max_hits) records, from the sum of those of the rays before it in its chunk. The
// host reads only the total (to size the records) and, with the hits, the offsets.
//   LIST_SUMS: invocation j sums the records of the rays of run j.
//   LIST_SCAN_BLOCKS: workgroup b turns the sums of its block of runs (BLOCK_STRETCH a thread)
//     into each run's first record within the block, and writes the block's records after the
//     runs'. (One workgroup scanning every run, a stretch of 256 a thread for a million rays, took
//     most of this kernel's 0.19 ms on an H200.)
//   LIST_SCAN: one workgroup turns the blocks' records into each block's first record (each
//     thread scans a stretch of blocks, the stretches' sums are scanned in shared memory), and
//     writes the total after the last run.
//   LIST_WRITE: invocation j writes the lists and offsets of run j's rays from its first record
//     (its block's first and its own within the block).
//     Where the counting pass kept each ray's nearest hits, a ray it kept whole (all its hits, or
//     its nearest max_hits) has them copied into place and its list marked HIT_LIST_DONE; any
//     other ray sets the flag after the total: the storing pass must trace it.
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#define VKRAY_LIST_OFFSETS
#include "records.glsl"

layout(local_size_x_id = 0) in;

layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Counts { int v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) buffer Sums { uint64_t v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) writeonly buffer Lists { HitList l[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) writeonly buffer Offsets { uint64_t v[]; };
// A hit record of either tier (FastHit, ExactHit: 32 bytes), copied as it is.
struct AnyHit {
  uvec4 low;
  uvec4 high;
};
layout(buffer_reference, std430, buffer_reference_align = 16) buffer Records { AnyHit v[]; };

shared uint64_t partial[gl_WorkGroupSize.x];

// The hits the counting pass met on ray i.
uint met_hits(uint i) {
  return uint(max(Counts(list_params.counts).v[i], 0));
}

// Whether a list of `capacity` records is appended to (sorted by the host): long, and holding
// every hit of its ray (hit_lists.rs `appends`).
bool appended(uint capacity) {
  return capacity > list_params.insertion_limit && capacity < list_params.max_hits;
}

// The records ray i keeps. With fixed lists, the counting pass counts a hit met twice once where
// it kept it; an appended list counts every hit the storing pass meets: it has room for as many
// repeats as the counting pass kept hits (the host drops them).
uint kept(uint i) {
  uint capacity = min(met_hits(i), list_params.max_hits);
  if (list_params.nearest != 0ul && appended(capacity)) {
    capacity = min(capacity + list_params.nearest_hits, list_params.max_hits);
  }
  return capacity;
}

uint runs() {
  return (list_params.count + list_params.run - 1u) / list_params.run;
}

// Runs each thread of LIST_SCAN_BLOCKS sums (hit_lists.rs BLOCK_STRETCH).
const uint BLOCK_STRETCH = 4u;

uint block_runs() {
  return gl_WorkGroupSize.x * BLOCK_STRETCH;
}

uint blocks() {
  return (runs() + block_runs() - 1u) / block_runs();
}

// Where block b's records (then its first record) lie among the sums: after the runs', the
// chunk's total and the storing flag.
uint block_at(uint b) {
  return runs() + 2u + b;
}

void sum_run(uint j) {
  uint first = j * list_params.run;
  uint last = min(first + list_params.run, list_params.count);
  uint64_t sum = 0ul;
  for (uint i = first; i < last; ++i) sum += uint64_t(kept(i));
  Sums(list_params.sums).v[j] = sum;
}

// The values v[first..last) (a stretch of thread t's, `sum` in all) turned into each one's first
// record, from the stretches before t's in this workgroup; returns the workgroup's total.
uint64_t scan_stretches(Sums sums, uint first, uint last, uint64_t sum) {
  uint threads = gl_WorkGroupSize.x;
  uint t = gl_LocalInvocationID.x;
  partial[t] = sum;
  barrier();
  for (uint step = 1u; step < threads; step <<= 1) {
    uint64_t add = t >= step ? partial[t - step] : 0ul;
    barrier();
    partial[t] += add;
    barrier();
  }
  uint64_t at = partial[t] - sum;
  for (uint j = first; j < last; ++j) {
    uint64_t records = sums.v[j];
    sums.v[j] = at;
    at += records;
  }
  return partial[threads - 1u];
}

void scan_block(uint b) {
  Sums sums = Sums(list_params.sums);
  uint first = min(b * block_runs() + gl_LocalInvocationID.x * BLOCK_STRETCH, runs());
  uint last = min(first + BLOCK_STRETCH, runs());
  uint64_t sum = 0ul;
  for (uint j = first; j < last; ++j) sum += sums.v[j];
  uint64_t total = scan_stretches(sums, first, last, sum);
  if (gl_LocalInvocationID.x == 0u) sums.v[block_at(b)] = total;
}

void scan_blocks() {
  Sums sums = Sums(list_params.sums);
  uint threads = gl_WorkGroupSize.x;
  uint stretch = (blocks() + threads - 1u) / threads;
  uint first = min(gl_LocalInvocationID.x * stretch, blocks());
  uint last = min(first + stretch, blocks());
  uint64_t sum = 0ul;
  for (uint b = first; b < last; ++b) sum += sums.v[block_at(b)];
  uint64_t total = scan_stretches(sums, block_at(first), block_at(last), sum);
  if (gl_LocalInvocationID.x == 0u) {
    sums.v[runs()] = total;
    sums.v[runs() + 1u] = 0ul;
  }
}

// Ray i's hits as the counting pass kept them (`kept` of them, its nearest), into place from `at`.
void copy_nearest(uint i, uint kept, uint64_t at) {
  Records nearest = Records(list_params.nearest);
  Records records = Records(list_params.records);
  // Both within 32 bits: the nearest records hold at most 8 per ray of a chunk, and `at` lies
  // within the room, which a list's `first` indexes.
  uint from = i * list_params.nearest_hits;
  for (uint k = 0u; k < kept; ++k) records.v[uint(at) + k] = nearest.v[from + k];
}

void write_run(uint j) {
  uint first = j * list_params.run;
  uint last = min(first + list_params.run, list_params.count);
  Sums sums = Sums(list_params.sums);
  uint64_t at = sums.v[block_at(j / block_runs())] + sums.v[j];
  Lists lists = Lists(list_params.lists);
  Offsets offsets = Offsets(list_params.offsets);
  bool storing = false;
  uint k_nearest = list_params.nearest != 0ul ? list_params.nearest_hits : 0u;
  for (uint i = first; i < last; ++i) {
    uint capacity = kept(i);
    uint met = met_hits(i);
    // Kept whole by the counting pass: every hit it met, or the nearest max_hits of them.
    bool whole = capacity <= k_nearest && (met <= k_nearest || list_params.max_hits <= k_nearest);
    // Only lists the host will keep are read by the storing pass: their `first` fits 32 bits
    // (the copies, those that fit the records' room).
    if (whole && at + uint64_t(capacity) <= uint64_t(list_params.room)) {
      copy_nearest(i, capacity, at);
      lists.l[i] = HitList(HIT_LIST_DONE, capacity);
    } else {
      lists.l[i] = HitList(uint(at), capacity | (appended(capacity) ? HIT_LIST_APPEND : 0u));
      storing = true;
    }
    offsets.v[i] = at;
    at += uint64_t(capacity);
  }
  // Every writer writes the same 1.
  if (storing) Sums(list_params.sums).v[runs() + 1u] = 1ul;
}

void main() {
  if (list_params.pass == LIST_SCAN_BLOCKS) {
    scan_block(gl_WorkGroupID.x);
    return;
  }
  if (list_params.pass == LIST_SCAN) {
    scan_blocks();
    return;
  }
  uint j = gl_GlobalInvocationID.x;
  if (j >= runs()) return;
  if (list_params.pass == LIST_SUMS) {
    sum_run(j);
  } else {
    write_run(j);
  }
}
