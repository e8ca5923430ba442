#version 460
// An all-hits chunk's stored records written out as the answer's columns, on the GPU
// (all_hits.rs, the columns' way): invocation i writes the hits of ray i's list, which
// list_offsets.comp placed from `offsets[i]` and the storing pass (or the counting pass) filled,
// sorted, to its end. The columns index hits among the chunk's, as the records do. The host uses
// these columns only where every list of the chunk is settled (as long as its ray's hits, not
// appended to); it writes the others' from the records. Each invocation checks its rays' lists:
// where every one is settled the host places the chunk's offsets from the hits seen alone, without
// reading back the offsets (8 MB a million rays).
// The records are read as words and their bits copied: no float arithmetic (and no shaderFloat64
// for ExactHit's doubles).
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#define VKRAY_HIT_COLUMNS
#include "records.glsl"

layout(local_size_x_id = 0) in;
// 1: the records are ExactHit (f64 t and uv; prim among all parts of the mesh, which the host
// allows only for one-part meshes, whose geometry is 0); 0: FastHit.
layout(constant_id = 1) const uint EXACT_RECORDS = 0u;

// A record of either tier (FastHit, ExactHit: 32 bytes) as its words.
struct RecordWords {
  uvec4 low;
  uvec4 high;
};
layout(buffer_reference, std430, buffer_reference_align = 16) readonly buffer Records { RecordWords v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer Offsets { uint64_t v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) writeonly buffer Words { uint v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) writeonly buffer Wide { uint64_t v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Seen { int v[]; };

// Hit j (of the chunk's, within 32 bits as the lists' `first` are) of ray `ray`.
void write_hit(uint j, uint64_t ray, RecordWords r) {
  if (column_params.ray_index != 0ul) Wide(column_params.ray_index).v[j] = ray;
  if (EXACT_RECORDS == 1u) {
    // ExactHit: t (words 0-1), u (2-3), v (4-5), instance, prim.
    if (column_params.t != 0ul) Wide(column_params.t).v[j] = packUint2x32(r.low.xy);
    if (column_params.uv != 0ul) {
      Wide uv = Wide(column_params.uv);
      uv.v[2u * j] = packUint2x32(r.low.zw);
      uv.v[2u * j + 1u] = packUint2x32(r.high.xy);
    }
    if (column_params.instance != 0ul) Words(column_params.instance).v[j] = r.high.z;
    if (column_params.prim != 0ul) Words(column_params.prim).v[j] = r.high.w;
    if (column_params.geometry != 0ul) Words(column_params.geometry).v[j] = 0u;
  } else {
    // FastHit: t, u, v, instance, geometry, prim.
    if (column_params.t != 0ul) Words(column_params.t).v[j] = r.low.x;
    if (column_params.uv != 0ul) {
      Words uv = Words(column_params.uv);
      uv.v[2u * j] = r.low.y;
      uv.v[2u * j + 1u] = r.low.z;
    }
    if (column_params.instance != 0ul) Words(column_params.instance).v[j] = r.low.w;
    if (column_params.geometry != 0ul) Words(column_params.geometry).v[j] = r.high.x;
    if (column_params.prim != 0ul) Words(column_params.prim).v[j] = r.high.y;
  }
}

void main() {
  Offsets offsets = Offsets(column_params.offsets);
  Records records = Records(column_params.records);
  uint count = column_params.count;
  // A stride over the rays: a dispatch covers at most maxComputeWorkGroupCount groups.
  uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
  for (uint i = gl_GlobalInvocationID.x; i < count; i += stride) {
    uint first = uint(offsets.v[i]);
    uint end = uint(i + 1u < count ? offsets.v[i + 1u] : Offsets(column_params.total).v[0]);
    uint64_t ray = column_params.first_ray + uint64_t(i);
    for (uint j = first; j < end; ++j) write_hit(j, ray, records.v[j]);
    if (column_params.offsets_out != 0ul) {
      // CUDA rays' answers: the offsets among the query's hits, the last ray's end too.
      Wide(column_params.offsets_out).v[i] = column_params.base + uint64_t(first);
      if (i + 1u == count) Wide(column_params.offsets_out).v[count] = column_params.base + uint64_t(end);
    }
    // Settled: as long as the hits seen, up to max_hits, and not appended to (all_hits.rs
    // `StoredChunk::place` decides the same from the offsets). Every writer writes the same 1.
    uint capacity = end - first;
    uint seen = uint(max(Seen(column_params.seen).v[i], 0));
    bool appended = capacity > column_params.insertion_limit && capacity < column_params.max_hits;
    if (appended || capacity != min(seen, column_params.max_hits)) Words(column_params.check).v[0] = 1u;
  }
}
