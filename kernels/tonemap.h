/*
 * The tone map's arithmetic, shared by the tone-map pass (tonemap.cl) and the waves pass, which
 * tone-maps its packets itself when it is the frame's last pass (waves.cl, WAVES_TONEMAP). Both
 * work on float16 vectors and apply the same operations lane by lane, so they produce the same
 * bytes: each colour channel is scaled by 2^exposure, compressed by the scene's operator and
 * encoded with the sRGB transfer function; alpha is only clamped and quantised.
 */
#ifndef VOLFX_KERNELS_TONEMAP_H
#define VOLFX_KERNELS_TONEMAP_H

#include "common.h"
#include "fastmath.h"

/*
 * The sRGB encoding of 'x' in [0, 1]. Above the linear toe, 1.055 x^(1/2.4) - 0.055 is a
 * polynomial of degree 5 in s = x^(1/4) (Chebyshev interpolation over [0.0031308, 1]), within
 * 1e-5 of it, under 0.3% of an 8-bit step; s is two reciprocal square roots. pow() would not
 * vectorise, and this takes a third of the time of the square roots it replaced.
 */
static inline float16 tone_srgb(float16 x) {
  float16 s = fast_rsqrt(fast_rsqrt(max(x, 0.0031308f)));
  float16 p = fma(s, -0.0627589896f, 0.272752255f);
  p = fma(p, s, -0.557555676f);
  p = fma(p, s, 1.24421394f);
  p = fma(p, s, 0.164974004f);
  p = fma(p, s, -0.0616297051f);
  return select(p, 12.92f * x, x <= 0.0031308f);
}

/*
 * Applies the operator 'op' (TONE_OP_*) to exposed linear values; the results are in [0, 1].
 * Values are first clamped to 1e18, where every operator gives 1 already, so that nothing
 * overflows and fast_div never sees an infinity.
 */
static inline float16 tone_op(float16 x, int op) {
  x = clamp(x, 0.0f, 1e18f);
  if (op == TONE_OP_REINHARD)
    x = fast_div(x, 1.0f + x);
  else if (op == TONE_OP_ACES) /* Narkowicz's fit of the ACES filmic curve, as it is. */
    x = fast_div(x * (2.51f * x + 0.03f), x * (2.43f * x + 0.59f) + 0.14f);
  return min(x, 1.0f);
}

/* The 8-bit value, as an int per lane, of the linear colour channel 'x' scaled by 'scale'. */
static inline int16 tone_colour(float16 x, float scale, int op) {
  return convert_int16(tone_srgb(tone_op(x * scale, op)) * 255.0f + 0.5f);
}

/* The 8-bit value, as an int per lane, of the alpha 'a'. */
static inline int16 tone_alpha(float16 a) {
  return convert_int16(clamp(a, 0.0f, 1.0f) * 255.0f + 0.5f);
}

/* Writes the 8-bit RGBA of 16 pixels to 'out' (64 bytes) from one int16 per channel. */
static inline void tone_store16(__global uchar *restrict out, int16 r, int16 g, int16 b, int16 a) {
#ifdef __ENDIAN_LITTLE__
  vstore16(as_uint16(r | (g << 8) | (b << 16) | (a << 24)), 0, (__global uint *)out);
#else
  for (int k = 0; k < 4; k++) {
    int4 rk = k == 0 ? r.lo.lo : k == 1 ? r.lo.hi : k == 2 ? r.hi.lo : r.hi.hi;
    int4 gk = k == 0 ? g.lo.lo : k == 1 ? g.lo.hi : k == 2 ? g.hi.lo : g.hi.hi;
    int4 bk = k == 0 ? b.lo.lo : k == 1 ? b.lo.hi : k == 2 ? b.hi.lo : b.hi.hi;
    int4 ak = k == 0 ? a.lo.lo : k == 1 ? a.lo.hi : k == 2 ? a.hi.lo : a.hi.hi;
    vstore16(convert_uchar16((int16)(rk.s0, gk.s0, bk.s0, ak.s0, rk.s1, gk.s1, bk.s1, ak.s1, rk.s2,
                                     gk.s2, bk.s2, ak.s2, rk.s3, gk.s3, bk.s3, ak.s3)),
             0, out + 16 * k);
  }
#endif
}

/* Splits 16 RGBA pixels at 'p' (64 floats) into one float16 per channel. */
static inline void tone_load16(__global const float *restrict p, float16 *r, float16 *g, float16 *b,
                               float16 *a) {
  float16 v0 = vload16(0, p), v1 = vload16(1, p), v2 = vload16(2, p), v3 = vload16(3, p);
  *r = (float16)(v0.s048c, v1.s048c, v2.s048c, v3.s048c);
  *g = (float16)(v0.s159d, v1.s159d, v2.s159d, v3.s159d);
  *b = (float16)(v0.s26ae, v1.s26ae, v2.s26ae, v3.s26ae);
  *a = (float16)(v0.s37bf, v1.s37bf, v2.s37bf, v3.s37bf);
}

#endif
