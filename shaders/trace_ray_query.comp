#version 460
// Ray-query backend: one invocation traces one ray from a compute shader.
#extension GL_EXT_ray_query : require
#extension GL_EXT_ray_flags_primitive_culling : require
#include "common.glsl"

layout(local_size_x_id = 2) in;

void main() {
  uint i = gl_GlobalInvocationID.x;
  if (i >= params.count) return;
  Ray ray = load_ray(i);

  rayQueryEXT query;
  rayQueryInitializeEXT(query, accelerationStructureEXT(params.tlas), RAY_FLAGS, ray_cull_mask(i),
                        ray.origin, ray.tmin, ray.direction, ray.tmax);
  // Opaque triangles are committed by traversal itself. Where a scene has non-opaque instances
  // (RAY_FLAGS then lacks CULL_NO_OPAQUE), their candidates come here and are accepted: vkray has
  // no any-hit programs. For all-opaque scenes this branch is compiled out.
  while (rayQueryProceedEXT(query)) {
    if ((RAY_FLAGS & RAY_FLAG_CULL_NO_OPAQUE) == 0u &&
        rayQueryGetIntersectionTypeEXT(query, false) == gl_RayQueryCandidateIntersectionTriangleEXT) {
      rayQueryConfirmIntersectionEXT(query);
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
  }
  store_hit(i, hit);
}
