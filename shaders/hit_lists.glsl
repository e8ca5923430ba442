// QUERY_ALL: every hit of a ray is counted, and its nearest `capacity` are kept in its HitList,
// sorted as they arrive (insertion: a list is as long as its ray's hits, which a counting pass
// found, or max_hits). A hit equal to one kept (the same triangle at the same t: traversal may
// report a primitive twice) is dropped, so that the count and the list hold it once. Long lists
// (HIT_LIST_APPEND) are filled in the order met instead, and sorted by the host. The counting
// pass may keep each ray's nearest few (fixed lists); the storing pass then skips the rays they
// held whole (HIT_LIST_DONE).
// Include after common.glsl, with HIT_RECORD defined as the stored record (FastHit, or ExactHit
// after exact.glsl) and `is_before` and `is_same` defined for it.
#ifndef VKRAY_HIT_LISTS_GLSL
#define VKRAY_HIT_LISTS_GLSL

layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer HitLists { HitList l[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) buffer HitRecords { HIT_RECORD h[]; };
// volatile: see ExactScratch in exact.glsl (the pipeline backend counts here across stages).
layout(buffer_reference, std430, buffer_reference_align = 4) volatile buffer HitCounts { int v[]; };

// `scratch` is 0 (only counted), or an odd number (K << 1 | 1: the counting pass keeps each ray's
// nearest K hits in records i * K onwards), or the lists' address.
HitList hit_list(uint i) {
  if (params.scratch == 0ul) return HitList(0u, 0u);
  if ((params.scratch & 1ul) != 0ul) {
    uint k = uint(params.scratch >> 1);
    return HitList(i * k, k);
  }
  return HitLists(params.scratch).l[i];
}

// The counting pass kept ray i's hits whole: the storing pass has nothing to do.
bool list_done(uint i) {
  return params.scratch != 0ul && (params.scratch & 1ul) == 0ul && HitLists(params.scratch).l[i].first == HIT_LIST_DONE;
}

// Ray i met hit h after `seen` others: keeps it if it is among the nearest, and returns the new
// number seen.
int keep_hit(uint i, int seen, HIT_RECORD h) {
  HitList list = hit_list(i);
  HitRecords hits = HitRecords(params.out_t);
  if ((list.capacity & HIT_LIST_APPEND) != 0u) {
    // Insertion would cost the square of the list's length: kept as met, sorted by the host.
    if (uint(seen) < (list.capacity & ~HIT_LIST_APPEND)) hits.h[list.first + uint(seen)] = h;
    return seen + 1;
  }
  uint n = min(uint(seen), list.capacity);
  uint at = n;
  while (at > 0u && is_before(h, hits.h[list.first + at - 1u])) --at;
  if (at > 0u && is_same(h, hits.h[list.first + at - 1u])) return seen;
  if (at < list.capacity) {
    for (uint k = min(n, list.capacity - 1u); k > at; --k) {
      HIT_RECORD moved = hits.h[list.first + k - 1u];
      hits.h[list.first + k] = moved;
    }
    hits.h[list.first + at] = h;
  }
  return seen + 1;
}

#endif
