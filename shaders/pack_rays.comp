#version 460
// Packs one chunk of the caller's rays, read in place in its own layout (float or double arrays,
// any row stride), into the records the trace shaders read: geometry/rays.rs Rays::pack on the
// GPU, with the same f64 operations in the same order (`precise`: no fused multiply-adds). Each
// ray is checked as Rays::is_valid checks it; an invalid one is packed as an empty interval and
// the first such row is kept in PackFrame.first_invalid for the host to report. A ray starting
// far from the scene is advanced towards it in f64 (Frame::advance), and how far is written to
// `advances`; after the trace, the same shader specialized to FINISH adds it back to its t.
// Specialized to EXACT_RAYS, it packs the exact tier's f64 rays instead (Rays::pack_f64: the origin
// moved into the scene's frame in f64, the direction and interval as given; far origins stay,
// the exact tier's traversal starts where the ray enters the scene).
#extension GL_EXT_buffer_reference : require
#extension GL_EXT_shader_explicit_arithmetic_types_int64 : require
#define VKRAY_PACK_RAYS
#include "records.glsl"
#include "point_triangle.glsl"
#include "widen.glsl"

layout(local_size_x_id = 0) in;
// 0: pack the chunk's rays; 1: add each far ray's advance back to its hit distance (a miss stays);
// 2 (EXACT_RAYS): pack the chunk's rays for the exact tier; 3 (FINISH_HITS): add each hit's ray's
// advance back to its distance (all hits' columns, invocation j for hit j).
layout(constant_id = 1) const uint FINISH = 0u;
const uint EXACT_RAYS = 2u;
const uint FINISH_HITS = 3u;

layout(buffer_reference, std430, buffer_reference_align = 4) readonly buffer FloatAt { uint v; };  // f32 bits
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer DoubleAt { double v; };
layout(buffer_reference, std430, buffer_reference_align = 16) writeonly buffer PackedRays { vec4 v[]; };
layout(buffer_reference, std430, buffer_reference_align = 32) writeonly buffer PackedRays64 { dvec4 v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) buffer Advances { double v[]; };
layout(buffer_reference, std430, buffer_reference_align = 4) buffer Distances { float v[]; };
layout(buffer_reference, std430, buffer_reference_align = 8) buffer Frames { PackFrame f; };
layout(buffer_reference, std430, buffer_reference_align = 8) readonly buffer RayIndex { int64_t v[]; };

// Rays::pack's Frame: ADVANCE_STEPS.
const int ADVANCE_STEPS = 24;
const float FLOAT_MAX = 3.4028234663852886e38;

double read_scalar(uint64_t address, bool wide) {
  return wide ? DoubleAt(address).v : widen_f32(FloatAt(address).v);
}

// Row `row` of an array of xyz rows.
dvec3 read_row(uint64_t base, uint stride, bool wide, uint row) {
  uint64_t at = base + uint64_t(row) * uint64_t(stride);
  uint64_t step = wide ? 8ul : 4ul;
  return dvec3(read_scalar(at, wide), read_scalar(at + step, wide), read_scalar(at + 2ul * step, wide));
}

// The next float below / above a non-negative float (f32::next_down / next_up there).
float next_down(float f) { return f == 0.0 ? -uintBitsToFloat(1u) : uintBitsToFloat(floatBitsToUint(f) - 1u); }
float next_up(float f) { return isinf(f) ? f : uintBitsToFloat(floatBitsToUint(f) + 1u); }

// rays.rs round_down_f32 / round_up_f32 (x >= 0): the nearest floats below / above x.
float round_down_f32(double x) {
  float f = float(x);
  return double(f) > x ? next_down(f) : f;
}
float round_up_f32(double x) {
  float f = float(x);
  return double(f) < x ? next_up(f) : f;
}

// rays.rs widened: [tmin, tmax] in f32, one ulp wider at each end, an empty interval kept at 0.
vec2 widened(double tmin, double tmax) {
  float lo = max(next_down(round_down_f32(tmin)), 0.0);
  float hi = tmax == 0.0 ? 0.0 : min(next_up(round_up_f32(tmax)), FLOAT_MAX);
  return vec2(lo, hi);
}

bool finite3(vec3 v) { return !any(isnan(v)) && !any(isinf(v)); }

// Rays::is_valid: a finite origin and direction (as f32), a non-zero direction, 0 <= tmin (finite
// as f32) <= tmax.
bool is_valid(dvec3 origin, dvec3 direction, double tmin, double tmax) {
  vec3 d = vec3(direction);
  return finite3(vec3(origin)) && finite3(d) && any(notEqual(d, vec3(0.0))) && !isnan(tmin) && tmin >= 0.0 &&
         !isinf(float(tmin)) && !isnan(tmax) && tmax >= tmin;
}

// chunks.rs unpack: t + advance in f64, rounded to f32, where the ray hit something.
void finish(uint i) {
  double advanced = Advances(pack_params.advances).v[i];
  if (advanced == 0.0) return;
  Distances t = Distances(pack_params.t);
  float hit = t.v[i];
  if (!isinf(hit) && !isnan(hit)) t.v[i] = float(double(hit) + advanced);
}

// `finish` for hit j of an all-hits chunk's columns: its ray's advance, from the hit's ray index.
void finish_hit(uint j) {
  uint ray = uint(RayIndex(pack_params.ray_index).v[j] - int64_t(pack_params.first_row));
  double advanced = Advances(pack_params.advances).v[ray];
  if (advanced == 0.0) return;
  Distances t = Distances(pack_params.t);
  t.v[j] = float(double(t.v[j]) + advanced);
}

void main() {
  uint i = gl_GlobalInvocationID.x;
  if (i >= pack_params.count) return;
  if (FINISH == 1u) {
    finish(i);
    return;
  }
  if (FINISH == FINISH_HITS) {
    finish_hit(i);
    return;
  }
  Frames frames = Frames(pack_params.frame);
  PackFrame frame = frames.f;
  dvec3 shift = dvec3(frame.shift[0], frame.shift[1], frame.shift[2]);
  dvec3 center = dvec3(frame.bounds_center[0], frame.bounds_center[1], frame.bounds_center[2]);
  uint formats = pack_params.formats;
  dvec3 world = read_row(pack_params.origins, pack_params.origin_stride, (formats & PACK_ORIGINS_F64) != 0u, i);
  dvec3 d = read_row(pack_params.directions, pack_params.direction_stride, (formats & PACK_DIRECTIONS_F64) != 0u, i);
  double tmin = pack_params.tmin == 0ul ? frame.tmin
      : read_scalar(pack_params.tmin + uint64_t(i) * uint64_t(pack_params.tmin_stride), (formats & PACK_TMIN_F64) != 0u);
  double tmax = pack_params.tmax == 0ul ? frame.tmax
      : read_scalar(pack_params.tmax + uint64_t(i) * uint64_t(pack_params.tmax_stride), (formats & PACK_TMAX_F64) != 0u);
  precise dvec3 origin = world - shift;
  if (FINISH == EXACT_RAYS) {
    PackedRays64 rays64 = PackedRays64(pack_params.packed);
    if (is_valid(world, d, tmin, tmax)) {
      rays64.v[2u * i] = dvec4(origin, tmin);
      rays64.v[2u * i + 1u] = dvec4(d, tmax);
    } else {
      // An empty interval (tmin above tmax): the ray enters nothing and is answered as a miss.
      atomicMin(frames.f.first_invalid, pack_params.first_row + i);
      rays64.v[2u * i] = dvec4(0.0, 0.0, 0.0, 1.0);
      rays64.v[2u * i + 1u] = dvec4(1.0, 0.0, 0.0, 0.0);
    }
    return;
  }
  double advanced = 0.0;
  vec2 interval;
  if (!is_valid(world, d, tmin, tmax)) {
    atomicMin(frames.f.first_invalid, pack_params.first_row + i);
    interval = vec2(0.0);
  } else {
    precise dvec3 offset = origin - center;
    if (dot3(offset, offset) <= frame.far_squared) {
      interval = widened(tmin, tmax);
    } else {
      // Frame::advance: aim twice the radius short of the sphere's nearest approach, and step
      // again from there until the step is small.
      double d2 = dot3(d, d);
      precise double back_off = 2.0 * frame.radius / sqrt(d2);
      bool never = false;
      for (int step = 0; step < ADVANCE_STEPS; step++) {
        precise double t = -dot3(origin - center, d) / d2 - back_off;
        if (step == 0 && t <= 0.0) {
          never = true;
          break;
        }
        origin += t * d;
        advanced += t;
        if (abs(t) <= 1e-3 * back_off) break;
      }
      if (never || tmax < advanced) {
        interval = vec2(0.0);
        advanced = 0.0;
      } else {
        interval = widened(max(tmin - advanced, 0.0), tmax - advanced);
      }
    }
  }
  vec3 o = vec3(origin);
  PackedRays packed = PackedRays(pack_params.packed);
  packed.v[2u * i] = vec4(o, interval.x);
  packed.v[2u * i + 1u] = vec4(vec3(d), interval.y);
  Advances(pack_params.advances).v[i] = advanced;
}
