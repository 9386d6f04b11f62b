/*
 * The ellipsoid test shared by the objects pass's shadow rays (objects.cl) and the volumes
 * pass's shadow map (volume.cl): lines from 16 origins along one shared direction against an
 * ellipsoid record (SPH_* of common.h), whose matrix takes world offsets to the object space
 * where the ellipsoid is the sphere |p| = 0.5.
 */
#ifndef VOLFX_KERNELS_ELLIPSOID_H
#define VOLFX_KERNELS_ELLIPSOID_H

#include "common.h"

/*
 * For the lines o + t d, with o at offsets (wx, wy, wz) from the centre and d the unit (dx, dy,
 * dz), the roots of the object-space quadratic a t^2 + 2 b t + |o|^2 - 0.25 lie at
 * (-b +- sqrt(disc)) / a. Returns disc, written as a r^2 - |q x o|^2, which does not cancel for
 * distant ellipsoids; the lines miss where it is negative. Sets *a and *b.
 */
static inline float16 ellipsoid_disc(__global const float *m, float16 wx, float16 wy, float16 wz,
                                     float dx, float dy, float dz, float *a, float16 *b) {
  float16 ox = m[0] * wx + m[1] * wy + m[2] * wz;
  float16 oy = m[3] * wx + m[4] * wy + m[5] * wz;
  float16 oz = m[6] * wx + m[7] * wy + m[8] * wz;
  float qx = m[0] * dx + m[1] * dy + m[2] * dz;
  float qy = m[3] * dx + m[4] * dy + m[5] * dz;
  float qz = m[6] * dx + m[7] * dy + m[8] * dz;
  *a = qx * qx + qy * qy + qz * qz;
  *b = qx * ox + qy * oy + qz * oz;
  float16 cx = qy * oz - qz * oy, cy = qz * ox - qx * oz, cz = qx * oy - qy * ox;
  return 0.25f * *a - (cx * cx + cy * cy + cz * cz);
}

#endif
