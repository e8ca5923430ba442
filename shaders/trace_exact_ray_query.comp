#version 460
// Ray-query backend, "exact" tier: f32 traversal of per-triangle boxes, every candidate decided
// by the f64 watertight test (shaders/exact.glsl).
#extension GL_EXT_ray_query : require
#include "common.glsl"
#include "exact.glsl"
#define HIT_RECORD ExactHit
#include "hit_lists.glsl"

layout(local_size_x_id = 2) in;

void main() {
  uint i = gl_GlobalInvocationID.x;
  if (i >= params.count) return;
  i = ray_index(i);
  // The storing pass of all hits: a ray the counting pass kept whole is done.
  if (QUERY == QUERY_ALL && list_done(i)) return;
  // A point the scene's inside grid decides casts no ray.
  if (RAY_SOURCE == RAYS_FROM_POINTS && (QUERY == QUERY_PARITY || QUERY == QUERY_WINDING)) {
    int decided = grid_crossings(i);
    if (decided >= 0) {
      HitCounts(params.out_prim).v[i] = decided;
      if (QUERY == QUERY_WINDING) DoubleOut(params.out_t).v[i] = 0.0;
      return;
    }
  }
  Ray64 ray = load_ray64(i);
  ExactBest best = exact_miss();
  int seen = 0;
  double left = 1.0;
  double entry = scene_entry(ray);
  if (entry >= 0.0) {
    TraversalRay r = traversal_ray(ray, entry);
    rayQueryEXT query;
    rayQueryInitializeEXT(query, accelerationStructureEXT(params.tlas), RAY_FLAGS, ray_cull_mask(i), r.origin, r.tmin,
                          r.direction, r.tmax);
    float committed = r.tmax;
    while (rayQueryProceedEXT(query)) {
      if (rayQueryGetIntersectionTypeEXT(query, false) != gl_RayQueryCandidateIntersectionAABBEXT) continue;
      int instance = rayQueryGetIntersectionInstanceIdEXT(query, false);
      int prim = rayQueryGetIntersectionPrimitiveIndexEXT(query, false);
      if (QUERY == QUERY_TRANSMIT) {
        left *= exact_transmit(ray, instance, prim);
        if (left == 0.0) rayQueryTerminateEXT(query);
      } else if (QUERY == QUERY_ALL) {
        // Every box's triangle is tested once per instance and none is committed: each crossing
        // the f64 test accepts is met once.
        ExactHit h;
        if (exact_record(ray, instance, prim, h)) seen = keep_hit(i, seen, h);
      } else if (QUERY == QUERY_PARITY || QUERY == QUERY_WINDING) {
        int count = exact_crossing(ray, instance, prim);
        seen = (seen + (count & ~ON_SURFACE)) | (count & ON_SURFACE);
      } else if (exact_candidate(best, ray, instance, prim, rayQueryGetIntersectionInstanceCustomIndexEXT(query, false),
                                 rayQueryGetIntersectionGeometryIndexEXT(query, false))) {
        // Commit in f32 too, so that traversal skips boxes beyond the best hit.
        committed = clamp(committed_distance(best.t, entry), r.tmin, committed);
        rayQueryGenerateIntersectionEXT(query, committed);
        if ((RAY_FLAGS & gl_RayFlagsTerminateOnFirstHitEXT) != 0u) rayQueryTerminateEXT(query);
      }
    }
  }
  if (QUERY == QUERY_ALL || QUERY == QUERY_PARITY || QUERY == QUERY_WINDING) {
    HitCounts(params.out_prim).v[i] = seen;
  } else if (QUERY == QUERY_TRANSMIT) {
    DoubleOut(params.out_t).v[i] = left;
  } else {
    store_exact(i, best);
  }
  // The caps add to the crossings through memory, as raygen_exact.rgen's do: taking `seen` as it
  // is, glslang's pass over precise values took minutes and gigabytes.
  if (QUERY == QUERY_WINDING) {
    HitCounts counts = HitCounts(params.out_prim);
    counts.v[i] = add_cap(i, ray, counts.v[i]);
  }
}
