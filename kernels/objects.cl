/*
 * The opaque-object pass: casts the camera rays of SPEC §4 against every ellipsoid, convex
 * polyhedron and mesh triangle, shades the nearest hit with Lambert lighting and an exact
 * shadow ray towards the directional light, and writes linear RGBA and the depth.
 *
 * Each work-item traces a packet of 16 horizontally adjacent pixels in float16 lanes. PoCL
 * vectorises a work-group's work-item loop only when the kernel body is straight-line code;
 * a loop over the scene's objects defeats it (measured: the per-pixel version of this kernel
 * ran scalar). With explicit lanes the loops over objects are free to stay loops: object data
 * is uniform, per-lane decisions are selects on 0/-1 masks, and the mesh BVH is traversed by
 * the whole packet, visiting a node when any lane's ray enters it. On a GPU a work-item simply
 * does 16 pixels' work. Sixteen lanes rather than eight (filling AVX-512's registers) took a fifth
 * off the pass for the paper-002 scene's ten objects with shadow rays.
 */
#include "common.h"
#include "ellipsoid.h"

typedef float16 floatv;
typedef int16 intv;

/* The 16 pixel centres of a packet, relative to its first pixel. */
#define LANE_CENTRES                                                                               \
  ((floatv)(0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f, 8.5f, 9.5f, 10.5f, 11.5f, 12.5f,       \
            13.5f, 14.5f, 15.5f))

/*
 * A surface point of an object counts from distance 'tmin' on: of the entry and exit points,
 * the first that is not nearer than 'tmin' is the hit, so a camera inside a box, or one whose
 * near distance cuts a sphere, sees the far side. Returns that distance, or INFINITY.
 */
static inline floatv first_from(floatv t_in, floatv t_out, float tmin, intv hit) {
  floatv t = select(t_out, t_in, t_in >= tmin);
  return select((floatv)INFINITY, t, hit & (t >= tmin));
}

/*
 * Which lanes' rays, from the shared origin along unit directions d, may meet the sphere of
 * radius r whose centre lies at offset w from the origin, at a distance in [0, best]. A cheap
 * test that lets a packet skip objects none of its rays comes near.
 */
static inline intv may_hit(float wx, float wy, float wz, float r, floatv dx, floatv dy, floatv dz,
                           floatv best) {
  floatv cx = wy * dz - wz * dy, cy = wz * dx - wx * dz, cz = wx * dy - wy * dx;
  floatv b = wx * dx + wy * dy + wz * dz;
  intv inside = (intv)(wx * wx + wy * wy + wz * wz <= r * r ? -1 : 0);
  return (cx * cx + cy * cy + cz * cz <= r * r) & ((b >= 0.0f) | inside) & (b - r <= best);
}

/* The same for rays from their own origins along a shared unit direction d, w per lane. */
static inline intv may_block(floatv wx, floatv wy, floatv wz, float r, float dx, float dy,
                             float dz) {
  floatv cx = wy * dz - wz * dy, cy = wz * dx - wx * dz, cz = wx * dy - wy * dx;
  floatv b = wx * dx + wy * dy + wz * dz;
  floatv r2 = r * r;
  return (cx * cx + cy * cy + cz * cz <= r2) & ((b >= 0.0f) | (wx * wx + wy * wy + wz * wz <= r2));
}

/*
 * Closest hit of the packet (eye o, directions d) with the mesh triangles at distances in
 * [tmin, *best). Updates *best, the geometric normal and the mesh index of the lanes that hit.
 * Triangles are double-sided (Moller-Trumbore); the rays share their origin, so the terms in
 * it alone are scalars.
 */
static void mesh_closest(__global const float *restrict nodes, __global const float *restrict tris,
                         float ox, float oy, float oz, floatv dx, floatv dy, floatv dz, float tmin,
                         floatv *best, floatv *nx, floatv *ny, floatv *nz, intv *mesh) {
  floatv ix = 1.0f / dx, iy = 1.0f / dy, iz = 1.0f / dz;
  int stack[BVH_MAX_DEPTH];
  int sp = 0, node = 0;
  for (;;) {
    __global const float *n = nodes + node * NODE_STRIDE;
    int count = as_int(n[NODE_COUNT]), first = as_int(n[NODE_FIRST]);
    if (count > 0) {
      for (int i = first; i < first + count; i++) {
        __global const float *tr = tris + i * TRI_STRIDE;
        float e1x = tr[3], e1y = tr[4], e1z = tr[5];
        float e2x = tr[6], e2y = tr[7], e2z = tr[8];
        float sx = ox - tr[0], sy = oy - tr[1], sz = oz - tr[2];
        float qx = sy * e1z - sz * e1y, qy = sz * e1x - sx * e1z, qz = sx * e1y - sy * e1x;
        floatv px = dy * e2z - dz * e2y, py = dz * e2x - dx * e2z, pz = dx * e2y - dy * e2x;
        floatv inv = 1.0f / (e1x * px + e1y * py + e1z * pz);
        floatv u = (sx * px + sy * py + sz * pz) * inv;
        floatv v = (dx * qx + dy * qy + dz * qz) * inv;
        floatv t = (e2x * qx + e2y * qy + e2z * qz) * inv;
        /* A degenerate triangle gives NaNs, which fail every comparison. */
        intv hit = (u >= 0.0f) & (v >= 0.0f) & (u + v <= 1.0f) & (t >= tmin) & (t < *best);
        *best = select(*best, t, hit);
        *nx = select(*nx, (floatv)(e1y * e2z - e1z * e2y), hit);
        *ny = select(*ny, (floatv)(e1z * e2x - e1x * e2z), hit);
        *nz = select(*nz, (floatv)(e1x * e2y - e1y * e2x), hit);
        *mesh = select(*mesh, (intv)as_int(tr[TRI_COLOR]), hit);
      }
    } else {
      /* Enter the child that some lane reaches first; keep the other if any lane reaches it. */
      int child[2] = {node + 1, first};
      float near[2];
      for (int k = 0; k < 2; k++) {
        __global const float *c = nodes + child[k] * NODE_STRIDE;
        floatv t0x = (c[0] - ox) * ix, t1x = (c[3] - ox) * ix;
        floatv t0y = (c[1] - oy) * iy, t1y = (c[4] - oy) * iy;
        floatv t0z = (c[2] - oz) * iz, t1z = (c[5] - oz) * iz;
        floatv lo = fmax(fmax(fmin(t0x, t1x), fmin(t0y, t1y)), fmax(fmin(t0z, t1z), tmin));
        floatv hi = fmin(fmin(fmax(t0x, t1x), fmax(t0y, t1y)), fmin(fmax(t0z, t1z), *best));
        near[k] = lanes_fmin(select((floatv)INFINITY, lo, lo <= hi));
      }
      int first_child = near[1] < near[0];
      float t_first = near[first_child], t_second = near[!first_child];
      if (t_first < INFINITY) {
        if (t_second < INFINITY)
          stack[sp++] = child[!first_child];
        node = child[first_child];
        continue;
      }
    }
    if (sp == 0)
      return;
    node = stack[--sp];
  }
}

/*
 * Which lanes of 'active' meet a mesh triangle at a distance above zero along the shared
 * direction d from their own origins o: the shadow rays. Returns a 0/-1 mask.
 */
static intv mesh_any(__global const float *restrict nodes, __global const float *restrict tris,
                     floatv ox, floatv oy, floatv oz, float dx, float dy, float dz, intv active) {
  float ix = 1.0f / dx, iy = 1.0f / dy, iz = 1.0f / dz;
  intv blocked = (intv)0;
  int stack[BVH_MAX_DEPTH];
  int sp = 0, node = 0;
  for (;;) {
    __global const float *n = nodes + node * NODE_STRIDE;
    floatv lo, hi;
    node_span16(n, ox, oy, oz, ix, iy, iz, &lo, &hi);
    lo = fmax(lo, 0.0f);
    if (any((lo <= hi) & active & ~blocked)) {
      int count = as_int(n[NODE_COUNT]), first = as_int(n[NODE_FIRST]);
      if (count == 0) {
        stack[sp++] = first;
        node++;
        continue;
      }
      for (int i = first; i < first + count; i++) {
        intv inside;
        floatv t = tri_line16(tris + i * TRI_STRIDE, ox, oy, oz, dx, dy, dz, &inside);
        blocked |= inside & (t > 0.0f);
      }
      if (!any(active & ~blocked))
        return blocked;
    }
    if (sp == 0)
      return blocked;
    node = stack[--sp];
  }
}

/*
 * One packet of 16 pixels per work-item, at pixel (16 * global x, global y). The range covers
 * the padded buffers exactly (pitch and rows of vfx_frame_t), so nothing tests bounds; pixels
 * of the padding are computed and never read. 'linear' receives RGBA floats (alpha 1 on
 * objects, f.bg[3] elsewhere) and 'depth' the hit distance or +INFINITY.
 */
__kernel void objects(vfx_frame_t f, __global const float *restrict objs,
                      __global const float *restrict nodes, __global const float *restrict tris,
                      __global float *restrict linear, __global float *restrict depth) {
  int x0 = 16 * get_global_id(0), y = get_global_id(1);

  float ex = f.eye[0], ey = f.eye[1], ez = f.eye[2];
  floatv px = (float)x0 + LANE_CENTRES;
  float py = y + 0.5f;
  floatv dx = f.base[0] + px * f.step_x[0] + py * f.step_y[0];
  floatv dy = f.base[1] + px * f.step_x[1] + py * f.step_y[1];
  floatv dz = f.base[2] + px * f.step_x[2] + py * f.step_y[2];
  floatv il = 1.0f / sqrt(dx * dx + dy * dy + dz * dz);
  dx *= il, dy *= il, dz *= il;

  floatv best = INFINITY, nx = 0.0f, ny = 0.0f, nz = 0.0f, cr = 0.0f, cg = 0.0f, cb = 0.0f;

  /* Ellipsoids: the ray in object space meets the sphere |p| = 0.5. The discriminant is written
   * as a r^2 - |q x o|^2, which does not cancel for distant spheres. */
  for (int i = 0; i < f.nsph; i++) {
    __global const float *s = objs + i * SPH_STRIDE;
    __global const float *m = s + SPH_MINV;
    float wx = ex - s[0], wy = ey - s[1], wz = ez - s[2];
    if (!any(may_hit(-wx, -wy, -wz, s[SPH_RADIUS], dx, dy, dz, best)))
      continue;
    float ox = m[0] * wx + m[1] * wy + m[2] * wz;
    float oy = m[3] * wx + m[4] * wy + m[5] * wz;
    float oz = m[6] * wx + m[7] * wy + m[8] * wz;
    floatv qx = m[0] * dx + m[1] * dy + m[2] * dz;
    floatv qy = m[3] * dx + m[4] * dy + m[5] * dz;
    floatv qz = m[6] * dx + m[7] * dy + m[8] * dz;
    floatv a = qx * qx + qy * qy + qz * qz;
    floatv b = qx * ox + qy * oy + qz * oz;
    floatv cx = qy * oz - qz * oy, cy = qz * ox - qx * oz, cz = qx * oy - qy * ox;
    floatv disc = 0.25f * a - (cx * cx + cy * cy + cz * cz);
    floatv sq = sqrt(fmax(disc, 0.0f));
    floatv ia = 1.0f / a;
    floatv t = first_from((-b - sq) * ia, (-b + sq) * ia, f.near_, disc >= 0.0f);
    intv take = (t <= f.far_) & (t < best);
    /* The object-space normal is the hit point; M^T carries it to world space. */
    floatv hx = ox + t * qx, hy = oy + t * qy, hz = oz + t * qz;
    best = select(best, t, take);
    nx = select(nx, m[0] * hx + m[3] * hy + m[6] * hz, take);
    ny = select(ny, m[1] * hx + m[4] * hy + m[7] * hz, take);
    nz = select(nz, m[2] * hx + m[5] * hy + m[8] * hz, take);
    cr = select(cr, (floatv)s[SPH_COLOR], take);
    cg = select(cg, (floatv)s[SPH_COLOR + 1], take);
    cb = select(cb, (floatv)s[SPH_COLOR + 2], take);
  }

  /* Convex polyhedra: the ray is inside between the last entering and the first leaving
   * boundary plane. */
  for (int i = 0; i < f.nconv; i++) {
    __global const float *c = objs + f.conv_off + i * CONV_STRIDE;
    __global const float *bs = c + CONV_BOUND;
    if (!any(may_hit(bs[0] - ex, bs[1] - ey, bs[2] - ez, bs[3], dx, dy, dz, best)))
      continue;
    floatv tin = -INFINITY, tout = INFINITY;
    floatv inx = 0.0f, iny = 0.0f, inz = 0.0f, onx = 0.0f, ony = 0.0f, onz = 0.0f;
    intv miss = 0;
    int np = as_int(c[CONV_NPLANES]);
    for (int k = 0; k < np; k++) {
      float pnx = c[4 * k], pny = c[4 * k + 1], pnz = c[4 * k + 2];
      float num = c[4 * k + 3] - (pnx * ex + pny * ey + pnz * ez);
      floatv den = pnx * dx + pny * dy + pnz * dz;
      floatv t = num / den;
      intv enter = (den < 0.0f) & (t > tin);
      intv leave = (den > 0.0f) & (t < tout);
      /* The eye is outside this half-space: a ray parallel to its plane never enters. */
      if (num < 0.0f)
        miss |= den == 0.0f;
      tin = select(tin, t, enter);
      inx = select(inx, (floatv)pnx, enter);
      iny = select(iny, (floatv)pny, enter);
      inz = select(inz, (floatv)pnz, enter);
      tout = select(tout, t, leave);
      onx = select(onx, (floatv)pnx, leave);
      ony = select(ony, (floatv)pny, leave);
      onz = select(onz, (floatv)pnz, leave);
    }
    floatv t = first_from(tin, tout, f.near_, ~miss & (tin <= tout));
    intv take = (t <= f.far_) & (t < best);
    intv front = tin >= f.near_;
    best = select(best, t, take);
    nx = select(nx, select(onx, inx, front), take);
    ny = select(ny, select(ony, iny, front), take);
    nz = select(nz, select(onz, inz, front), take);
    cr = select(cr, (floatv)c[CONV_COLOR], take);
    cg = select(cg, (floatv)c[CONV_COLOR + 1], take);
    cb = select(cb, (floatv)c[CONV_COLOR + 2], take);
  }

  if (f.ntri > 0) {
    /* Hits exactly at the far distance count, as for the other shapes. */
    floatv mesh_best = fmin(best, nextafter(f.far_, INFINITY));
    intv mesh = -1;
    mesh_closest(nodes, tris, ex, ey, ez, dx, dy, dz, f.near_, &mesh_best, &nx, &ny, &nz, &mesh);
    intv took = mesh >= 0;
    best = select(best, mesh_best, took);
    /* Gather the lanes' mesh colours through private arrays, which allow indexing by lane. */
    int at[16];
    float r8[16], g8[16], b8[16];
    vstore16(f.mesh_off + 3 * max(mesh, 0), 0, at);
    for (int l = 0; l < 16; l++) {
      r8[l] = objs[at[l]];
      g8[l] = objs[at[l] + 1];
      b8[l] = objs[at[l] + 2];
    }
    cr = select(cr, vload16(0, r8), took);
    cg = select(cg, vload16(0, g8), took);
    cb = select(cb, vload16(0, b8), took);
  }

  /* Shading: the normal is turned towards the viewer, so every surface is lit on the side it
   * is seen from. */
  intv hit = best < INFINITY;
  floatv nl = 1.0f / sqrt(nx * nx + ny * ny + nz * nz);
  floatv flip = select((floatv)nl, -nl, nx * dx + ny * dy + nz * dz > 0.0f);
  nx *= flip, ny *= flip, nz *= flip;
  float lx = f.light_dir[0], ly = f.light_dir[1], lz = f.light_dir[2];
  floatv ndl = fmax(nx * lx + ny * ly + nz * lz, 0.0f);
  floatv th = select((floatv)0.0f, best, hit);
  floatv bias = SHADOW_BIAS * (1.0f + th);
  floatv sx = ex + th * dx + bias * nx, sy = ey + th * dy + bias * ny,
         sz = ez + th * dz + bias * nz;

  /* Shadow rays towards the light from the lit side of every hit, with the same tests as
   * above; now the direction is shared and the origins differ. */
  intv lit = hit & (ndl > 0.0f);
  for (int i = 0; i < f.nsph && any(lit); i++) {
    __global const float *s = objs + i * SPH_STRIDE;
    floatv wx = sx - s[0], wy = sy - s[1], wz = sz - s[2];
    if (!any(lit & may_block(-wx, -wy, -wz, s[SPH_RADIUS], lx, ly, lz)))
      continue;
    float a;
    floatv b, disc = ellipsoid_disc(s + SPH_MINV, wx, wy, wz, lx, ly, lz, &a, &b);
    /* The far root (-b + sqrt(disc)) / a is ahead exactly when b < 0 or b^2 < disc. */
    lit &= ~((disc >= 0.0f) & ((b < 0.0f) | (b * b < disc)));
  }
  for (int i = 0; i < f.nconv && any(lit); i++) {
    __global const float *c = objs + f.conv_off + i * CONV_STRIDE;
    __global const float *bs = c + CONV_BOUND;
    if (!any(lit & may_block(bs[0] - sx, bs[1] - sy, bs[2] - sz, bs[3], lx, ly, lz)))
      continue;
    floatv tin, tout;
    intv miss = convex_span16(c, sx, sy, sz, lx, ly, lz, &tin, &tout);
    lit &= ~(~miss & (tin <= tout) & (tout > 0.0f));
  }
  if (f.ntri > 0 && any(lit))
    lit &= ~mesh_any(nodes, tris, sx, sy, sz, lx, ly, lz, lit);

  floatv direct = select((floatv)0.0f, ndl, lit);
  floatv r = select((floatv)f.bg[0], cr * (f.light_rgb[0] * direct + f.ambient), hit);
  floatv g = select((floatv)f.bg[1], cg * (f.light_rgb[1] * direct + f.ambient), hit);
  floatv b = select((floatv)f.bg[2], cb * (f.light_rgb[2] * direct + f.ambient), hit);
  floatv a = select((floatv)f.bg[3], (floatv)1.0f, hit);

  int o = y * f.pitch + x0;
  vstore16(best, 0, depth + o);
  vstore16((float16)(r.s0, g.s0, b.s0, a.s0, r.s1, g.s1, b.s1, a.s1, r.s2, g.s2, b.s2, a.s2, r.s3,
                     g.s3, b.s3, a.s3),
           0, linear + 4 * o);
  vstore16((float16)(r.s4, g.s4, b.s4, a.s4, r.s5, g.s5, b.s5, a.s5, r.s6, g.s6, b.s6, a.s6, r.s7,
                     g.s7, b.s7, a.s7),
           0, linear + 4 * o + 16);
  vstore16((float16)(r.s8, g.s8, b.s8, a.s8, r.s9, g.s9, b.s9, a.s9, r.sa, g.sa, b.sa, a.sa, r.sb,
                     g.sb, b.sb, a.sb),
           0, linear + 4 * o + 32);
  vstore16((float16)(r.sc, g.sc, b.sc, a.sc, r.sd, g.sd, b.sd, a.sd, r.se, g.se, b.se, a.se, r.sf,
                     g.sf, b.sf, a.sf),
           0, linear + 4 * o + 48);
}
