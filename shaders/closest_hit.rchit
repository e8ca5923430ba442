#version 460
#extension GL_EXT_ray_tracing : require
#include "common.glsl"

layout(location = 0) rayPayloadInEXT Hit payload;
hitAttributeEXT vec2 barycentrics;

void main() {
  payload.t = gl_HitTEXT;
  payload.prim = gl_PrimitiveID;
  payload.instance = gl_InstanceID;
  payload.custom = gl_InstanceCustomIndexEXT;
  payload.geometry = gl_GeometryIndexEXT;
  if (gl_HitKindEXT == SPHERE_HIT_KIND) {
    payload.uv = vec2(uintBitsToFloat(0x7fc00000u));
    if ((OUTPUTS & OUT_NORMAL) != 0u) {
      payload.normal = sphere_normal(sphere_at(gl_InstanceID, gl_GeometryIndexEXT, gl_PrimitiveID), gl_ObjectRayOriginEXT,
                                     gl_ObjectRayDirectionEXT, gl_HitTEXT, gl_WorldToObjectEXT);
    }
    return;
  }
  payload.uv = barycentrics;
  resolve_triangle(payload, gl_ObjectToWorldEXT);
}
