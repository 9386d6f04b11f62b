/*
 * The reference camera of the render tests, in double precision and written from SPEC §4 alone:
 * pixel (x, y)'s unit ray passes through the pixel centre of an image plane at distance 1 that
 * spans tan(fov_y / 2) * (w / h, 1) about the forward direction, row 0 at the top.
 */
#ifndef VOLFX_TEST_PIXEL_RAY_H
#define VOLFX_TEST_PIXEL_RAY_H

#include <math.h>

#include "render_scene.h"

typedef struct ray {
  double o[3], d[3];
} ray_t;

static inline double dot3(const double *a, const double *b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static inline ray_t pixel_ray(const rcamera_t *c, int w, int h, int x, int y) {
  double fw[3], rt[3], up[3];
  for (int i = 0; i < 3; i++)
    fw[i] = (double)c->target[i] - c->eye[i];
  double n = sqrt(dot3(fw, fw));
  for (int i = 0; i < 3; i++)
    fw[i] /= n;
  rt[0] = fw[1] * c->up[2] - fw[2] * c->up[1];
  rt[1] = fw[2] * c->up[0] - fw[0] * c->up[2];
  rt[2] = fw[0] * c->up[1] - fw[1] * c->up[0];
  n = sqrt(dot3(rt, rt));
  for (int i = 0; i < 3; i++)
    rt[i] /= n;
  up[0] = rt[1] * fw[2] - rt[2] * fw[1];
  up[1] = rt[2] * fw[0] - rt[0] * fw[2];
  up[2] = rt[0] * fw[1] - rt[1] * fw[0];
  double half = tan(c->fov_y * M_PI / 360);
  double u = (2 * (x + 0.5) / w - 1) * half * w / h, v = (1 - 2 * (y + 0.5) / h) * half;
  ray_t r;
  for (int i = 0; i < 3; i++) {
    r.o[i] = c->eye[i];
    r.d[i] = fw[i] + u * rt[i] + v * up[i];
  }
  n = sqrt(dot3(r.d, r.d));
  for (int i = 0; i < 3; i++)
    r.d[i] /= n;
  return r;
}

#endif
