// An f32's value in f64 from its bits, exactly, subnormals included: a GPU's conversion may flush
// a subnormal input to zero (Vulkan asks no DenormPreserve of it, and the H200 flushes them),
// where the host's widening keeps it. For the f32 values the f64 paths read (points, the exact
// tier's rays, CUDA rays), so that they equal the host's bit for bit.
#ifndef VKRAY_WIDEN_GLSL
#define VKRAY_WIDEN_GLSL

double widen_f32(uint bits) {
  uint significand = bits & 0x007FFFFFu;
  // Normal, zero, infinite or NaN: the conversion is exact. Subnormal: its significand times
  // 2^-149, a normal f64. (Selected, not branched: branches here multiplied glslc's time on the
  // exact tier's shaders a hundredfold.)
  double converted = double(uintBitsToFloat(bits & 0x7FFFFFFFu));
  double subnormal = ldexp(double(significand), -149);
  double magnitude = ((bits & 0x7F800000u) == 0u && significand != 0u) ? subnormal : converted;
  return (bits & 0x80000000u) != 0u ? -magnitude : magnitude;
}

#endif
