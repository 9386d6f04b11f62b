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
