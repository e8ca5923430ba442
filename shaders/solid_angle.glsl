// Signed solid angles of triangles in f64 with an f32 arctangent (GLSL has no f64 one), shared by
// winding.comp (winding numbers over the hierarchy) and the exact tier's winding query (the cap
// that closes a mesh's holes). Include after point_triangle.glsl (dot3).
#ifndef VKRAY_SOLID_ANGLE_GLSL
#define VKRAY_SOLID_ANGLE_GLSL

const double FOUR_PI = 12.566370614359172lf;

// Van Oosterom and Strackee's pair for triangle (a, b, c) seen from the origin (the corners
// relative to the point), from the corners' lengths (|a|, |b|, |c|): tan(Ω / 2) = numerator /
// denominator. (A fan's triangles share their apex: its length is taken once.)
dvec2 solid_angle_pair(dvec3 a, dvec3 b, dvec3 c, dvec3 lengths) {
  double numerator = dot3(a, cross(b, c));
  double denominator = lengths.x * lengths.y * lengths.z + dot3(a, b) * lengths.z + dot3(b, c) * lengths.x +
                       dot3(c, a) * lengths.y;
  return dvec2(numerator, denominator);
}

dvec2 solid_angle_pair(dvec3 a, dvec3 b, dvec3 c) {
  return solid_angle_pair(a, b, c, dvec3(sqrt(dot3(a, a)), sqrt(dot3(b, b)), sqrt(dot3(c, c))));
}

// Whether the point lies on the triangle, or within 1e-10 of its size (the product of its
// corners' lengths) of its inside (|Ω| near 2π), whose solid angle jumps by 4π there: on which
// side f64 puts the point is then uncertain.
bool near_inside(dvec2 pair, double size) {
  return pair.y <= 0.0 && abs(pair.x) <= 1e-10 * size;
}

bool near_inside(dvec3 a, dvec3 b, dvec3 c, dvec2 pair) {
  return near_inside(pair, sqrt(dot3(a, a)) * sqrt(dot3(b, b)) * sqrt(dot3(c, c)));
}

// Twice the signed solid angle from a solid_angle_pair: 2 atan2(numerator, denominator), the
// arctangent in f32 (each term within about 1e-7 of the CPU's f64 one).
double twice_solid_angle(dvec2 pair) {
  double m = max(abs(pair.x), abs(pair.y));
  // atan2(0, 0) is 0 on the CPU (a point on a corner); GLSL leaves it undefined.
  if (m == 0.0) return 0.0;
  // An exact scaling by a power of two brings both into float's range.
  int e;
  frexp(m, e);
  return 2.0 * double(atan(float(ldexp(pair.x, -e)), float(ldexp(pair.y, -e))));
}

// Twice the signed solid angle of triangle (a, b, c) seen from the origin.
double twice_solid_angle(dvec3 a, dvec3 b, dvec3 c) {
  return twice_solid_angle(solid_angle_pair(a, b, c));
}

#endif
