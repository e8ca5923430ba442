#version 460
#extension GL_EXT_ray_tracing : require
#include "common.glsl"

layout(location = 0) rayPayloadInEXT Hit payload;

void main() {
  // All hits (QUERY_ALL) ignore every candidate, so traversal always ends here: the payload
  // holds the count.
  if (QUERY == QUERY_CLOSEST) payload = miss_hit();
}
