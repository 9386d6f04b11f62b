/*
 * The game-depth pass: a client's depth buffer (the game's own picture, drawn with the frame's
 * camera) joined into the depth the objects pass wrote, so that every later pass stops its
 * rays at the game's geometry as it does at the objects'.
 */
#include "common.h"

/*
 * One drawn pixel per work-item, over the padded buffers; pixels past the drawn width or height
 * do nothing. 'z' holds the client's view-space depths (distance along the view axis, +INFINITY
 * for none), 'zw' of them a row, one per output pixel; the frame is drawn 'n' times larger each
 * way, so drawn pixel (x, y) takes output pixel (x / n, y / n). A view-space depth z lies at
 * distance z / cos along a ray at angle acos(cos) to the view axis, which is the direction
 * through the image plane's centre.
 */
__kernel void game_depth(vfx_frame_t f, int n, __global const float *restrict z, int zw,
                         __global float *restrict depth) {
  int x = get_global_id(0), y = get_global_id(1);
  if (x >= f.width || y >= f.height)
    return;
  float px = x + 0.5f, py = y + 0.5f, hx = 0.5f * f.width, hy = 0.5f * f.height;
  float3 base = (float3)(f.base[0], f.base[1], f.base[2]);
  float3 sx = (float3)(f.step_x[0], f.step_x[1], f.step_x[2]);
  float3 sy = (float3)(f.step_y[0], f.step_y[1], f.step_y[2]);
  float3 d = base + px * sx + py * sy, axis = base + hx * sx + hy * sy;
  float cosv = dot(d, axis) / (length(d) * length(axis));
  float t = z[(y / n) * zw + x / n] / cosv;
  int o = y * f.pitch + x;
  depth[o] = fmin(depth[o], t);
}
