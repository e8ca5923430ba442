// f32 rays in the leaner layouts of the rays buffer (geometry::rays::RayLayout), for the shaders
// that read f32 rays (raygen.rgen, trace_ray_query.comp): `read_ray` is `load_ray` (common.glsl)
// with them. Its own header, common.glsl untouched: glslang's time over the exact tier's shaders,
// which include common.glsl, went from 0.1 s to minutes with two more constants or one more
// function there (its propagation of `precise`, which exact.glsl uses throughout, is sensitive
// to the whole tree).
#ifndef VKRAY_RAYS_GLSL
#define VKRAY_RAYS_GLSL

// RAY_SOURCE's leaner layouts (trace::variants): after a header of 8 floats (the shared origin at
// 0..2 for RAYS_FROM_DIRECTIONS, tmin at 3, tmax at 7), 6 floats a ray (origin, direction;
// RAYS_FROM_COMPACT) or 3 (its direction; RAYS_FROM_DIRECTIONS).
const uint RAYS_FROM_COMPACT = 3u;
const uint RAYS_FROM_DIRECTIONS = 4u;

Ray read_ray(uint i) {
  if (RAY_SOURCE != RAYS_FROM_COMPACT && RAY_SOURCE != RAYS_FROM_DIRECTIONS) return load_ray(i);
  Floats f = Floats(params.rays);
  bool shared_origin = RAY_SOURCE == RAYS_FROM_DIRECTIONS;
  uint at = 8u + (shared_origin ? 3u : 6u) * i;
  uint o = shared_origin ? 0u : at;
  uint d = shared_origin ? at : at + 3u;
  return Ray(vec3(f.v[o], f.v[o + 1u], f.v[o + 2u]), f.v[3], vec3(f.v[d], f.v[d + 1u], f.v[d + 2u]), f.v[7]);
}

#endif
