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
  payload.uv = barycentrics;
  resolve_triangle(payload, gl_ObjectToWorldEXT);
}
