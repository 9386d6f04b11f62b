/*
 * The tone-map pass: linear RGBA floats to 8-bit sRGB RGBA. Each colour channel is scaled by
 * 2^exposure, compressed by the scene's operator and encoded with the sRGB transfer function;
 * alpha is only quantised. The kernel is straight-line scalar code so that PoCL vectorises
 * its work-item loop: the operator is chosen with selects, and the sRGB power is a fit in
 * square roots instead of pow(), which PoCL cannot vectorise.
 */
#include "common.h"

/*
 * The sRGB encoding of 'x' in [0, 1]. Above the linear toe, 1.055 x^(1/2.4) - 0.055 is
 * replaced by a least-squares fit in x^(1/2), x^(1/4), x^(1/8) and x over [0.0031308, 1]; its
 * largest error is 7e-5, under 2% of an 8-bit step.
 */
static inline float srgb_encode(float x) {
  float s2 = sqrt(x), s4 = sqrt(s2), s8 = sqrt(s4);
  float fit =
      0.65468921f * s2 + 0.68884282f * s4 - 0.31928467f * s8 - 0.020600825f * x - 0.0037168936f;
  return x <= 0.0031308f ? 12.92f * x : fit;
}

/* Applies the operator 'op' (TONE_OP_*) to an exposed linear value; the result is in [0, 1]. */
static inline float tone(float x, int op) {
  x = fmax(x, 0.0f);
  float reinhard = x / (1.0f + x);
  /* Narkowicz's fit of the ACES filmic curve, applied to the exposed value as it is. */
  float aces = (x * (2.51f * x + 0.03f)) / (x * (2.43f * x + 0.59f) + 0.14f);
  float y = op == TONE_OP_REINHARD ? reinhard : op == TONE_OP_ACES ? aces : x;
  return fmin(y, 1.0f);
}

static inline uchar quantise(float y) {
  return (uchar)(clamp(y, 0.0f, 1.0f) * 255.0f + 0.5f);
}

/*
 * One pixel per work-item over the whole padded buffer, as a 2-D range of its pitch by its
 * rows, so there is no bounds test; 'scale' is 2^exposure. (A 1-D range of the same pixels
 * made PoCL compile a second variant of the kernel for large frames.)
 */
__kernel void tonemap(__global const float *restrict linear, __global uchar *restrict out,
                      float scale, int op) {
  int i = get_global_id(1) * get_global_size(0) + get_global_id(0);
  float r = linear[4 * i], g = linear[4 * i + 1], b = linear[4 * i + 2], a = linear[4 * i + 3];
  out[4 * i] = quantise(srgb_encode(tone(r * scale, op)));
  out[4 * i + 1] = quantise(srgb_encode(tone(g * scale, op)));
  out[4 * i + 2] = quantise(srgb_encode(tone(b * scale, op)));
  out[4 * i + 3] = quantise(a);
}
