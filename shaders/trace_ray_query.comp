#version 460
// Ray-query backend: one invocation traces one ray from a compute shader.
#extension GL_EXT_ray_query : require
#extension GL_EXT_ray_flags_primitive_culling : require
#include "common.glsl"
#include "rays.glsl"
#define HIT_RECORD FastHit
#include "hit_lists.glsl"

layout(local_size_x_id = 2) in;

// The opacity of the query's candidate triangle.
float candidate_opacity(rayQueryEXT query) {
  GeometrySource src = geometry_source(rayQueryGetIntersectionInstanceIdEXT(query, false),
                                       rayQueryGetIntersectionGeometryIndexEXT(query, false));
  return triangle_opacity(src, rayQueryGetIntersectionPrimitiveIndexEXT(query, false));
}

// Every hit (QUERY_ALL): RAY_FLAGS holds NoOpaque, so that each triangle comes here as a
// candidate; each is kept in the ray's list and none is committed. Scenes with spheres do not
// take this path.
void trace_all(uint i, Ray ray) {
  // The storing pass: a ray the counting pass kept whole is done.
  if (list_done(i)) return;
  bool storing = hit_list(i).capacity > 0u;
  int seen = 0;
  rayQueryEXT query;
  rayQueryInitializeEXT(query, accelerationStructureEXT(params.tlas), RAY_FLAGS, ray_cull_mask(i),
                        ray.origin, ray.tmin, ray.direction, ray.tmax);
  while (rayQueryProceedEXT(query)) {
    if (rayQueryGetIntersectionTypeEXT(query, false) != gl_RayQueryCandidateIntersectionTriangleEXT) continue;
    if (!is_solid(candidate_opacity(query))) continue;
    if (!storing) {
      ++seen;
      continue;
    }
    int instance = rayQueryGetIntersectionInstanceIdEXT(query, false);
    int geometry = rayQueryGetIntersectionGeometryIndexEXT(query, false);
    int prim = caller_primitive(geometry_source(instance, geometry), rayQueryGetIntersectionPrimitiveIndexEXT(query, false));
    vec2 uv = rayQueryGetIntersectionBarycentricsEXT(query, false);
    seen = keep_hit(i, seen, FastHit(rayQueryGetIntersectionTEXT(query, false), uv.x, uv.y, instance, geometry, prim, uint[2](0u, 0u)));
  }
  HitCounts(params.out_prim).v[i] = seen;
}

// Transmittance (QUERY_TRANSMIT): RAY_FLAGS holds NoOpaque, so that each triangle comes here; the
// light left is multiplied by 1 - opacity at each, and traversal stops once none is left.
void trace_transmit(uint i, Ray ray) {
  float left = 1.0;
  rayQueryEXT query;
  rayQueryInitializeEXT(query, accelerationStructureEXT(params.tlas), RAY_FLAGS, ray_cull_mask(i),
                        ray.origin, ray.tmin, ray.direction, ray.tmax);
  while (rayQueryProceedEXT(query)) {
    if (rayQueryGetIntersectionTypeEXT(query, false) != gl_RayQueryCandidateIntersectionTriangleEXT) continue;
    left *= 1.0 - candidate_opacity(query);
    if (left == 0.0) rayQueryTerminateEXT(query);
  }
  FloatOut(params.out_t).v[i] = left;
}

void main() {
  uint i = gl_GlobalInvocationID.x;
  if (i >= params.count) return;
  Ray ray = read_ray(i);
  if (QUERY == QUERY_ALL) {
    trace_all(i, ray);
    return;
  }
  if (QUERY == QUERY_TRANSMIT) {
    trace_transmit(i, ray);
    return;
  }

  rayQueryEXT query;
  rayQueryInitializeEXT(query, accelerationStructureEXT(params.tlas), RAY_FLAGS, ray_cull_mask(i),
                        ray.origin, ray.tmin, ray.direction, ray.tmax);
  // Opaque triangles are committed by traversal itself. Where a scene has triangles that are not
  // opaque (opacity, or non-opaque instances: RAY_FLAGS then lacks CULL_NO_OPAQUE), they come here
  // and are committed where their opacity reaches the threshold. For all-opaque scenes this branch
  // is compiled out.
  // Boxes are spheres' (scenes without spheres skip them, gl_RayFlagsSkipAABBEXT): each candidate
  // is tested here and committed at its distance if nearer than the committed hit.
  while (rayQueryProceedEXT(query)) {
    uint candidate = rayQueryGetIntersectionTypeEXT(query, false);
    if ((RAY_FLAGS & gl_RayFlagsCullNoOpaqueEXT) == 0u && candidate == gl_RayQueryCandidateIntersectionTriangleEXT &&
        is_solid(candidate_opacity(query))) {
      rayQueryConfirmIntersectionEXT(query);
    }
    if ((RAY_FLAGS & gl_RayFlagsSkipAABBEXT) == 0u && candidate == gl_RayQueryCandidateIntersectionAABBEXT) {
      bool none = rayQueryGetIntersectionTypeEXT(query, true) == gl_RayQueryCommittedIntersectionNoneEXT;
      float tmax = none ? ray.tmax : rayQueryGetIntersectionTEXT(query, true);
      vec4 sphere = sphere_at(rayQueryGetIntersectionInstanceIdEXT(query, false),
                              rayQueryGetIntersectionGeometryIndexEXT(query, false),
                              rayQueryGetIntersectionPrimitiveIndexEXT(query, false));
      float t = sphere_hit(rayQueryGetIntersectionObjectRayOriginEXT(query, false),
                           rayQueryGetIntersectionObjectRayDirectionEXT(query, false), sphere, ray.tmin, tmax);
      if (t >= 0.0) rayQueryGenerateIntersectionEXT(query, t);
    }
  }

  Hit hit = miss_hit();
  if (rayQueryGetIntersectionTypeEXT(query, true) == gl_RayQueryCommittedIntersectionTriangleEXT) {
    hit.t = rayQueryGetIntersectionTEXT(query, true);
    hit.prim = rayQueryGetIntersectionPrimitiveIndexEXT(query, true);
    hit.instance = rayQueryGetIntersectionInstanceIdEXT(query, true);
    hit.custom = rayQueryGetIntersectionInstanceCustomIndexEXT(query, true);
    hit.geometry = rayQueryGetIntersectionGeometryIndexEXT(query, true);
    hit.uv = rayQueryGetIntersectionBarycentricsEXT(query, true);
    resolve_triangle(hit, rayQueryGetIntersectionObjectToWorldEXT(query, true));
  } else if (rayQueryGetIntersectionTypeEXT(query, true) == gl_RayQueryCommittedIntersectionGeneratedEXT) {
    hit.t = rayQueryGetIntersectionTEXT(query, true);
    hit.prim = rayQueryGetIntersectionPrimitiveIndexEXT(query, true);
    hit.instance = rayQueryGetIntersectionInstanceIdEXT(query, true);
    hit.custom = rayQueryGetIntersectionInstanceCustomIndexEXT(query, true);
    hit.geometry = rayQueryGetIntersectionGeometryIndexEXT(query, true);
    if ((OUTPUTS & OUT_NORMAL) != 0u) {
      hit.normal = sphere_normal(sphere_at(hit.instance, hit.geometry, hit.prim),
                                 rayQueryGetIntersectionObjectRayOriginEXT(query, true),
                                 rayQueryGetIntersectionObjectRayDirectionEXT(query, true), hit.t,
                                 rayQueryGetIntersectionWorldToObjectEXT(query, true));
    }
  }
  store_hit(i, hit);
}
