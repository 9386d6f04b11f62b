/*
 * The tone-map pass: linear RGBA floats to 8-bit sRGB RGBA. Each colour channel is scaled by
 * 2^exposure, compressed by the scene's operator and encoded with the sRGB transfer function;
 * alpha is only quantised. A work-item converts TONEMAP_PACKET pixels held as float16 vectors
 * of four RGBA pixels, so that the code is vector code whatever PoCL does with its work-item
 * loop: loads and stores are whole vectors rather than gathers and byte scatters, the
 * operator is chosen once per work-item, and the sRGB power is a fit in square roots instead
 * of pow(), which PoCL cannot vectorise.
 */
#include "common.h"

/*
 * The sRGB encoding of 'x' in [0, 1]. Above the linear toe, 1.055 x^(1/2.4) - 0.055 is
 * replaced by a least-squares fit in x^(1/2), x^(1/4), x^(1/8) and x over [0.0031308, 1]; its
 * largest error is 7e-5, under 2% of an 8-bit step.
 */
static inline float16 srgb_encode(float16 x) {
  float16 s2 = sqrt(x), s4 = sqrt(s2), s8 = sqrt(s4);
  float16 fit =
      0.65468921f * s2 + 0.68884282f * s4 - 0.31928467f * s8 - 0.020600825f * x - 0.0037168936f;
  return select(fit, 12.92f * x, x <= 0.0031308f);
}

/* Applies the operator 'op' (TONE_OP_*) to exposed linear values; the results are in [0, 1]. */
static inline float16 tone(float16 x, int op) {
  x = max(x, 0.0f);
  if (op == TONE_OP_REINHARD)
    x = x / (1.0f + x);
  else if (op == TONE_OP_ACES) /* Narkowicz's fit of the ACES filmic curve, as it is. */
    x = (x * (2.51f * x + 0.03f)) / (x * (2.43f * x + 0.59f) + 0.14f);
  return min(x, 1.0f);
}

/*
 * TONEMAP_PACKET pixels per work-item, over the whole padded buffer as a 2-D range of its pitch
 * / TONEMAP_PACKET by its rows, so there is no bounds test; 'scale' is 2^exposure.
 */
__kernel void tonemap(__global const float *restrict linear, __global uchar *restrict out,
                      float scale, int op) {
  size_t i = (get_global_id(1) * get_global_size(0) + get_global_id(0)) * TONEMAP_PACKET;
  const int16 alpha = (int16)(0, 0, 0, -1, 0, 0, 0, -1, 0, 0, 0, -1, 0, 0, 0, -1);
  for (int k = 0; k < TONEMAP_PACKET / 4; k++) {
    float16 v = vload16(0, linear + 4 * i + 16 * k);
    float16 y = select(srgb_encode(tone(v * scale, op)), clamp(v, 0.0f, 1.0f), alpha);
    vstore16(convert_uchar16(y * 255.0f + 0.5f), 0, out + 4 * i + 16 * k);
  }
}
