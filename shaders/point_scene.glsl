// What the point queries (closest_point.comp, winding.comp) share: the buffers of
// scene::ClosestScene and the f64 maps between the scene's frame and a mesh's. Include after
// records.glsl (with VKRAY_POINT_QUERY defined).
#ifndef VKRAY_POINT_SCENE_GLSL
#define VKRAY_POINT_SCENE_GLSL

layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer Doubles { double v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) writeonly buffer DoubleOut { double v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer Words { uint v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer BvhNodes { BvhNode n[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer BvhTriangles { BvhTriangle t[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer BvhInstances { BvhInstance x[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) writeonly buffer PointHits { PointHit h[]; };

// Affine::point with a map's rows: (the columns times the coordinates, summed in order) plus the
// offset, each operation rounded (glam's).
dvec3 map_point(double m[12], dvec3 v) {
  precise dvec3 r;
  for (int k = 0; k < 3; ++k) {
    precise double c = ((m[4 * k] * v.x + m[4 * k + 1] * v.y) + m[4 * k + 2] * v.z) + m[4 * k + 3];
    r[k] = c;
  }
  return r;
}

// A corner of the mesh's frame in the scene's. Where the map's linear part is the identity the
// products and sums with zero change nothing but the sign of a zero, which no distance sees.
dvec3 corner_in_scene(BvhInstance x, double v[3]) {
  if (x.identity != 0u) {
    precise dvec3 r = dvec3(v[0], v[1], v[2]) + dvec3(x.to_scene[3], x.to_scene[7], x.to_scene[11]);
    return r;
  }
  return map_point(x.to_scene, dvec3(v[0], v[1], v[2]));
}

#endif
