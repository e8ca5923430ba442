// The cap that closes a mesh's holes for the winding query (scene::WindingCap: a WindingCapHeader,
// its holes and their edges in one buffer), as the exact tier's ray pass (exact.glsl add_cap: the
// cap's crossings) and cap_winding.comp (its solid angles) read it. Include after records.glsl and
// solid_angle.glsl.
#ifndef VKRAY_CAP_GLSL
#define VKRAY_CAP_GLSL

layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer WindingCapHead {
  WindingCapHeader head;
};
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer WindingCapHoles {
  WindingCapHole h[];
};
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer WindingCapEdges {
  WindingCapEdge e[];
};

dvec3 dvec3_of(double v[3]) {
  return dvec3(v[0], v[1], v[2]);
}

// A hole's winding number whose bound (below) is at most this is not summed at first: the bounds
// of those passed over are summed instead, and only where they could move the winding number
// into the band about 1/2 is it summed after all. Most points' winding numbers lie near 0 or 1:
// with up to 5 holes passed over (0.4), those never are.
const double CAP_SKIP_BOUND = 0.08;

// A bound on the size of hole `h`'s winding number about `origin`: each point of the fan lies at
// least (distance to the apex - radius) from it, so each triangle's solid angle is at most its
// area over that squared (the integrand of the solid angle is at most 1 / r²). 1e300 where the
// origin lies within the radius (not a constant infinity: records.glsl PointRays).
// `precise`: the ray pass and cap_winding.comp must class each hole alike (summed, or passed over).
double fan_winding_bound(dvec3 origin, WindingCapHoles holes, uint h) {
  precise double gap = length(dvec3_of(holes.h[h].apex_scene) - origin) - holes.h[h].radius_scene;
  precise double bound = holes.h[h].area_scene / (FOUR_PI * gap * gap);
  return gap > 0.0 ? bound : 1e300lf;
}

// Whether the caps' winding number about a ray's origin needs a second pass over the holes it
// passed over at first (their bounds summing to `passed_over`): the ray's count (Crossings: its
// crossings << 1, bit 0 set where the origin lies on a surface) and the first pass's winding
// number `first` (signed as the instance mirrors) could then lie within the band about 1/2.
bool cap_second_pass(int count, double first, double passed_over, double band) {
  double near_half = abs(double(count >> 1) + first - 0.5);
  return passed_over != 0.0 && (count & 1) == 0 && near_half <= band + passed_over;
}

// What some of one hole's fan adds to a winding number (fan_angles).
struct FanAngles {
  double twice_angle;  // twice the solid angle of its triangles about the origin
  bool unsure;         // the origin lies within rounding of one of them
};

// The triangles of hole `h`'s fan from its apex over edges first + lane, first + lane + lanes ...
// (a workgroup's `lanes` invocations share the fan), seen from `origin` (scene frame).
FanAngles fan_angles(dvec3 origin, WindingCapHoles holes, uint h, WindingCapEdges edges, uint lane, uint lanes) {
  FanAngles fan = FanAngles(0.0, false);
  dvec3 apex = dvec3_of(holes.h[h].apex_scene) - origin;
  // The apex's length, shared by the fan's triangles: two square roots an edge rather than six.
  double apex_length = sqrt(dot3(apex, apex));
  uint end = holes.h[h].first + holes.h[h].count;
  for (uint k = holes.h[h].first + lane; k < end; k += lanes) {
    dvec3 a = dvec3_of(edges.e[k].a_scene) - origin;
    dvec3 b = dvec3_of(edges.e[k].b_scene) - origin;
    dvec3 lengths = dvec3(apex_length, sqrt(dot3(a, a)), sqrt(dot3(b, b)));
    dvec2 pair = solid_angle_pair(apex, a, b, lengths);
    fan.unsure = fan.unsure || near_inside(pair, lengths.x * lengths.y * lengths.z);
    fan.twice_angle += twice_solid_angle(pair);
  }
  return fan;
}

#endif
