/*
 * The tone-map pass: linear RGBA floats to 8-bit sRGB RGBA (the arithmetic is in tonemap.h).
 * A work-item converts TONEMAP_PACKET pixels, loaded as float16 vectors of four RGBA pixels and
 * regrouped into one float16 per channel, so that the code is vector code whatever PoCL does
 * with its work-item loop: loads and stores are whole vectors rather than gathers and byte
 * scatters, the operator is chosen once per work-item, and no lane is spent on alpha's sRGB
 * curve. The waves pass does the same itself when it is the frame's last pass.
 */
#include "tonemap.h"

/*
 * TONEMAP_PACKET pixels per work-item, over the whole padded buffer as a 2-D range of its pitch
 * / TONEMAP_PACKET by its rows, so there is no bounds test; 'scale' is 2^exposure.
 */
__kernel void tonemap(__global const float *restrict linear, __global uchar *restrict out,
                      float scale, int op) {
  size_t i = (get_global_id(1) * get_global_size(0) + get_global_id(0)) * TONEMAP_PACKET;
  for (int k = 0; k < TONEMAP_PACKET / 16; k++) {
    float16 r, g, b, a;
    tone_load16(linear + 4 * (i + 16 * k), &r, &g, &b, &a);
    tone_store16(out + 4 * (i + 16 * k), tone_colour(r, scale, op), tone_colour(g, scale, op),
                 tone_colour(b, scale, op), tone_alpha(a));
  }
}

/* ---- Anti-aliasing (render.antialias) ------------------------------------------------------ */

/*
 * Splits the 16 pixels of 'row' at x = (x0 + k) n + sx, k = 0 .. 15 (clamped to the rendered
 * width 'hi_w'), into one float16 per channel: one sample of each of 16 output pixels.
 */
static void resolve_load16(__global const float *restrict row, int x0, int n, int sx, int hi_w,
                           float16 *r, float16 *g, float16 *b, float16 *a) {
  float4 p[16];
  for (int k = 0; k < 16; k++)
    p[k] = vload4(min((x0 + k) * n + sx, hi_w - 1), row);
  float16 v0 = (float16)(p[0], p[1], p[2], p[3]), v1 = (float16)(p[4], p[5], p[6], p[7]);
  float16 v2 = (float16)(p[8], p[9], p[10], p[11]), v3 = (float16)(p[12], p[13], p[14], p[15]);
  *r = (float16)(v0.s048c, v1.s048c, v2.s048c, v3.s048c);
  *g = (float16)(v0.s159d, v1.s159d, v2.s159d, v3.s159d);
  *b = (float16)(v0.s26ae, v1.s26ae, v2.s26ae, v3.s26ae);
  *a = (float16)(v0.s37bf, v1.s37bf, v2.s37bf, v3.s37bf);
}

/*
 * The frame was rendered at n times its width and height into 'linear' ('pitch' pixels a row,
 * 'hi_w' of them drawn). Each work-item makes 16 output pixels of a row, at (16 global x,
 * global y), each from its n x n samples; the range is rounded up to whole work-groups, so
 * work-items past 'out_pitch' or row 'out_h' do nothing: resolve_tonemap averages the samples after
 * the operator and before the sRGB encoding (as a display would blend them), into 8-bit RGBA rows
 * of 'out_pitch' pixels; resolve_linear averages the linear values, into float RGBA rows.
 */
__kernel void resolve_tonemap(__global const float *restrict linear, int pitch, int hi_w, int n,
                              __global uchar *restrict out, int out_pitch, int out_h, float scale,
                              int op) {
  int x0 = 16 * get_global_id(0), y = get_global_id(1);
  if (x0 >= out_pitch || y >= out_h)
    return;
  float16 sr = 0.0f, sg = 0.0f, sb = 0.0f, sa = 0.0f;
  for (int sy = 0; sy < n; sy++)
    for (int sx = 0; sx < n; sx++) {
      float16 r, g, b, a;
      resolve_load16(linear + 4 * (size_t)(y * n + sy) * pitch, x0, n, sx, hi_w, &r, &g, &b, &a);
      sr += tone_op(r * scale, op), sg += tone_op(g * scale, op), sb += tone_op(b * scale, op);
      sa += a;
    }
  float inv = 1.0f / (float)(n * n);
  tone_store16(out + 4 * ((size_t)y * out_pitch + x0),
               convert_int16(tone_srgb(sr * inv) * 255.0f + 0.5f),
               convert_int16(tone_srgb(sg * inv) * 255.0f + 0.5f),
               convert_int16(tone_srgb(sb * inv) * 255.0f + 0.5f), tone_alpha(sa * inv));
}

/* Writes four pixels, one float4 per channel, to 'o' in RGBA order. */
static void resolve_store4(float4 r, float4 g, float4 b, float4 a, __global float *restrict o) {
  vstore16((float16)(r.s0, g.s0, b.s0, a.s0, r.s1, g.s1, b.s1, a.s1, r.s2, g.s2, b.s2, a.s2, r.s3,
                     g.s3, b.s3, a.s3),
           0, o);
}

__kernel void resolve_linear(__global const float *restrict linear, int pitch, int hi_w, int n,
                             __global float *restrict out, int out_pitch, int out_h) {
  int x0 = 16 * get_global_id(0), y = get_global_id(1);
  if (x0 >= out_pitch || y >= out_h)
    return;
  float16 s[4] = {0.0f, 0.0f, 0.0f, 0.0f};
  for (int sy = 0; sy < n; sy++)
    for (int sx = 0; sx < n; sx++) {
      float16 c[4];
      resolve_load16(linear + 4 * (size_t)(y * n + sy) * pitch, x0, n, sx, hi_w, &c[0], &c[1],
                     &c[2], &c[3]);
      for (int k = 0; k < 4; k++)
        s[k] += c[k];
    }
  float inv = 1.0f / (float)(n * n);
  float16 r = s[0] * inv, g = s[1] * inv, b = s[2] * inv, a = s[3] * inv;
  __global float *o = out + 4 * ((size_t)y * out_pitch + x0);
  resolve_store4(r.lo.lo, g.lo.lo, b.lo.lo, a.lo.lo, o);
  resolve_store4(r.lo.hi, g.lo.hi, b.lo.hi, a.lo.hi, o + 16);
  resolve_store4(r.hi.lo, g.hi.lo, b.hi.lo, a.hi.lo, o + 32);
  resolve_store4(r.hi.hi, g.hi.hi, b.hi.hi, a.hi.hi, o + 48);
}
