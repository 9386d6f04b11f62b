/*
 * The fluid pass (SPEC §5.2): particles drawn as metaballs. The field of particle j at a point
 * is P_j = s_j^2 with s_j = max(1 - r_j / h, 0); the surface is where I = sqrt(F) - T crosses
 * zero, F = sum of P_j. Each work-item casts one pixel's camera ray through the host's uniform
 * grid (vfx_fluid_t in common.h) with a 3-D DDA, samples the field only in cells whose list is
 * not empty (elsewhere F is exactly zero), and ends the search at the opaque depth. The first
 * crossing is bracketed by a safe step, refined by regula falsi and placed by the linear
 * interpolation of the paper's eq. 5. The hit is shaded as water over the objects' colour and
 * its distance written to the depth buffer, so the passes after it are clipped by the fluid.
 *
 * A ray does divergent work (its own cells, its own number of samples), so the lanes are not
 * pixels but particles: the sums over a cell's list run 8 particles at a time in float8.
 */
#include "common.h"

/* The sum of a float8's lanes. */
static inline float fluid_hsum(float8 v) {
  float4 a = v.lo + v.hi;
  float2 b = a.lo + a.hi;
  return b.x + b.y;
}

/*
 * Bounding the field ahead along the ray. Let x be a point of the ray e + t d (|d| = 1) and
 * r_j, sigma_j = 1 - r_j / h the distance to particle j and its unclamped s_j there. Along the
 * ray, r_j(x + u d) is the norm of an affine function of u, hence convex, so it lies above its
 * tangent: r_j(x + u d) >= r_j - u k_j with k_j = d . (p_j - x) / r_j in [-1, 1] (the cosine
 * between the ray and the direction to the particle). So at u = delta h along the ray,
 *   s_j <= max(sigma_j + delta k_j, 0)  and  F <= G(delta) = sum of max(sigma_j + delta k_j, 0)^2.
 * G is a sum of squares of clamped linear functions, hence convex in delta, so over a whole
 * step [0, D] it never exceeds the larger of G(0) = F and G(D): with both below T^2, F stays
 * below T^2 at every point of the step. G is tangent to F at delta = 0 (its slope there is
 * 2A, A = sum of s_j k_j, exactly F's) and lies above it: a step D with G(D) below T^2 is
 * safe, and as the ray closes in on the surface the longest such step approaches the true
 * distance.
 * (Bounding every k_j by 1 instead, as fluid_step's cruder bound does, cuts the steps near a
 * dense block to a few hundredths of h.)
 */

/* What one pass over a cell's list at x gives the march: F, S = sum of s_j, A = sum of s_j
 * k_j, the nearest particle's sigma_j (-2 when none is within 3h) and G at the steps of
 * 'ladder' (units of h). */
typedef struct {
  float f, s, a, near_sigma;
  float4 g;
} fluid_sums_t;

static inline fluid_sums_t fluid_sums(__global const float *restrict pos, int stride, int first,
                                      int n8, float x, float y, float z, float ux, float uy,
                                      float uz, float inv_h, float4 ladder) {
  float8 f = 0.0f, s = 0.0f, a = 0.0f, near = -2.0f, g0 = 0.0f, g1 = 0.0f, g2 = 0.0f, g3 = 0.0f;
  for (int i = first; i < first + n8; i += 8) {
    float8 px = vload8(0, pos + i) - x, py = vload8(0, pos + stride + i) - y;
    float8 pz = vload8(0, pos + 2 * stride + i) - z;
    float8 r2 = px * px + py * py + pz * pz;
    float8 ir = rsqrt(max(r2, 1e-30f));
    /* sigma_j and k_j; padding entries (FLUID_PAD) get a hugely negative sigma_j. A hair is
     * added to the cosine so that rounding can only lengthen G's reach. */
    float8 sg = 1.0f - r2 * ir * inv_h;
    float8 kp = (px * ux + py * uy + pz * uz) * ir + 1e-3f;
    float8 sj = max(sg, 0.0f);
    f += sj * sj;
    s += sj;
    a += sj * kp;
    near = max(near, sg);
    float8 u0 = max(sg + ladder.x * kp, 0.0f), u1 = max(sg + ladder.y * kp, 0.0f);
    float8 u2 = max(sg + ladder.z * kp, 0.0f), u3 = max(sg + ladder.w * kp, 0.0f);
    g0 += u0 * u0, g1 += u1 * u1, g2 += u2 * u2, g3 += u3 * u3;
  }
  fluid_sums_t r;
  r.f = fluid_hsum(f);
  r.s = fluid_hsum(s);
  r.a = fluid_hsum(a);
  float4 n4 = max(near.lo, near.hi);
  float2 n2 = max(n4.lo, n4.hi);
  r.near_sigma = max(n2.x, n2.y);
  r.g = (float4)(fluid_hsum(g0), fluid_hsum(g1), fluid_hsum(g2), fluid_hsum(g3));
  return r;
}

/* F alone at (x, y, z), as fluid_sums sums it. */
static inline float fluid_field(__global const float *restrict pos, int stride, int first, int n8,
                                float x, float y, float z, float inv_h) {
  float8 f = 0.0f;
  for (int i = first; i < first + n8; i += 8) {
    float8 dx = vload8(0, pos + i) - x;
    float8 dy = vload8(0, pos + stride + i) - y;
    float8 dz = vload8(0, pos + 2 * stride + i) - z;
    float8 sj = max(1.0f - sqrt(dx * dx + dy * dy + dz * dz) * inv_h, 0.0f);
    f += sj * sj;
  }
  return fluid_hsum(f);
}

/* The fixed steps (units of h) at which every sample evaluates G. */
#define FLUID_LADDER ((float4)(0.1f, 0.2f, 0.4f, 0.8f))

/* The longest of the steps 'ladder' whose G in 'g' is below t2, or 0. */
static inline float fluid_best(float4 ladder, float4 g, float t2) {
  float4 ok = select((float4)0.0f, ladder, g < t2);
  return fmax(fmax(ok.x, ok.y), fmax(ok.z, ok.w));
}

/*
 * A safe step (units of h) from the sums 'q' of FLUID_LADDER at the current point; the list
 * holds 'm' particles. Besides the ladder's steps with G below t2 = T^2: no particle reaches
 * within -near_sigma of the point, so a step that long keeps F = 0; and, bounding every k_j by
 * 1, G(delta) <= F + 2 delta S + m delta^2, below t2 for delta < (t2 - F) / (S + sqrt(S^2 + m
 * (t2 - F))) (the positive root, written without cancellation). The longest is safe.
 */
static inline float fluid_step(fluid_sums_t q, float t2, float m) {
  float gap = t2 - q.f;
  float best = fmax(gap / (q.s + sqrt(q.s * q.s + m * gap)), -q.near_sigma);
  return fmax(best, fluid_best(FLUID_LADDER, q.g, t2));
}

/* The outward normal at (x, y, z), -grad F / 2h = sum of s_j (x - p_j) / r_j, not unit. */
static inline float3 fluid_normal(__global const float *restrict pos, int stride, int first, int n8,
                                  float x, float y, float z, float inv_h) {
  float8 gx = 0.0f, gy = 0.0f, gz = 0.0f;
  for (int i = first; i < first + n8; i += 8) {
    float8 dx = x - vload8(0, pos + i);
    float8 dy = y - vload8(0, pos + stride + i);
    float8 dz = z - vload8(0, pos + 2 * stride + i);
    float8 r = sqrt(dx * dx + dy * dy + dz * dz);
    float8 w = max(1.0f - r * inv_h, 0.0f) / max(r, 1e-20f);
    gx += w * dx, gy += w * dy, gz += w * dz;
  }
  return (float3)(fluid_hsum(gx), fluid_hsum(gy), fluid_hsum(gz));
}

/* The tangent's predicted distance to the surface (units of h) under which the march looks
 * FLUID_PAST times as far ahead for the crossing. */
#define FLUID_CLOSE 0.1f
#define FLUID_PAST 1.5f

/*
 * The crossing in [a, b], F(a) = fa < T^2 <= F(b) = fb, refined on I = sqrt(F) - T (close to
 * linear near the surface, exactly so for a lone particle, where sqrt(F) = 1 - r / h) by
 * regula falsi (Illinois) to 'tol', then placed by linear interpolation (the paper's eq. 5).
 */
static float fluid_refine(__global const float *restrict pos, const vfx_fluid_t *fl, int first,
                          int n8, float ex, float ey, float ez, float dx, float dy, float dz,
                          float a, float b, float fa, float fb) {
  float ga = sqrt(fa) - fl->threshold, gb = sqrt(fb) - fl->threshold;
  int side = 0;
  for (int k = 0; k < 40 && b - a > fl->tol; k++) {
    float c = a + (b - a) * (ga / (ga - gb));
    if (!(c > a && c < b))
      c = 0.5f * (a + b);
    float gc = sqrt(fluid_field(pos, fl->stride, first, n8, ex + c * dx, ey + c * dy, ez + c * dz,
                                fl->inv_h)) -
               fl->threshold;
    if (gc >= 0.0f) {
      b = c, gb = gc;
      if (side == 1)
        ga *= 0.5f;
      side = 1;
    } else {
      a = c, ga = gc;
      if (side == -1)
        gb *= 0.5f;
      side = -1;
    }
  }
  float w = ga / (ga - gb);
  return a + (b - a) * (w >= 0.0f && w <= 1.0f ? w : 0.5f);
}

/* The march's last sample in the cell it left, kept for the cell it enters: its t (negative
 * when there is none), F there, and that cell's list. */
typedef struct {
  float t, f;
  int first, n8;
} fluid_prev_t;

/*
 * Searches the ray e + t d over [ta, tb], inside one cell whose list ('first', 'n8' padded
 * entries, 'm' real ones) holds every particle that reaches it, for the first t with
 * F >= T^2. Returns that t, or INFINITY. 'prev' carries the last sample of the cell before
 * (used when F >= T^2 already at ta) and comes back with the list the hit lies in, or with
 * this cell's last sample when a step reaches tb and 'last' is 0.
 *
 * The march only takes steps over which G, and so F, provably stays below T^2: no point of
 * the surface, however thin the sheet, lies strictly inside a step, so nothing is skipped and
 * no sample count is capped. Each sample takes fluid_step's step (the longest of G's ladder
 * below T^2, the reach of the nearest particle, or the cruder bound), so the remaining
 * distance shrinks several-fold per sample. Once G's tangent, which reaches T^2 at
 * delta_lin = (T^2 - F) / 2A, puts the surface closer than FLUID_CLOSE h, one field sample
 * FLUID_PAST times as far ahead is tried: if it lies inside, the crossing is bracketed at once.
 * That look can only end the march on a crossing, never carry it past one, so it cannot make
 * a hole; at worst, when a sliver of fluid thinner than the look lies in front of the
 * surface, the refinement may settle on the surface just behind the sliver. Near a tangent of
 * the surface the safe step still shrinks, so it has a floor, 'min_step' (h / 2000): a floor
 * step can pass over only a piece of the ray shorter than it that is inside the fluid, i.e. a
 * graze of the surface whose chord is under h / 2000, far below a pixel at any distance we
 * render. The crossing is refined by fluid_refine.
 */
static float fluid_search(__global const float *restrict pos, const vfx_fluid_t *fl, int first,
                          int n8, int m, float ex, float ey, float ez, float dx, float dy, float dz,
                          float ta, float tb, int last, fluid_prev_t *prev) {
  float t2 = fl->threshold * fl->threshold, inv_h = fl->inv_h;
  fluid_sums_t q = fluid_sums(pos, fl->stride, first, n8, ex + ta * dx, ey + ta * dy, ez + ta * dz,
                              dx, dy, dz, inv_h, FLUID_LADDER);
  if (q.f >= t2) {
    /* The crossing lies in the previous cell's last step, whose list covers that step. */
    if (prev->t >= 0.0f && prev->t < ta)
      return fluid_refine(pos, fl, prev->first, prev->n8, ex, ey, ez, dx, dy, dz, prev->t, ta,
                          prev->f, q.f);
    prev->first = first, prev->n8 = n8;
    return ta;
  }
  prev->first = first, prev->n8 = n8;
  float fm = (float)m;
  while (ta < tb) {
    float f = q.f;
    float step = fluid_step(q, t2, fm);
    float lin = q.a > 0.0f ? (t2 - f) / (2.0f * q.a) : INFINITY;
    if (lin < FLUID_CLOSE && ta + FLUID_PAST * lin * fl->h < tb) {
      /* Close in front of the surface: a look just past the tangent's crossing. Inside there,
       * the bracket is refined; otherwise it was a graze and the march goes on. */
      float ts = ta + FLUID_PAST * lin * fl->h;
      float fs =
          fluid_field(pos, fl->stride, first, n8, ex + ts * dx, ey + ts * dy, ez + ts * dz, inv_h);
      if (fs >= t2)
        return fluid_refine(pos, fl, first, n8, ex, ey, ez, dx, dy, dz, ta, ts, f, fs);
    }
    float tn = ta + fmax(step * fl->h, fl->min_step);
    if (tn >= tb && !last) {
      /* The step is safe to the cell's end; the next cell's first sample, at that end, decides
       * whether the crossing lies there. */
      prev->t = ta, prev->f = f;
      return INFINITY;
    }
    tn = fmin(tn, tb);
    q = fluid_sums(pos, fl->stride, first, n8, ex + tn * dx, ey + tn * dy, ez + tn * dz, dx, dy, dz,
                   inv_h, FLUID_LADDER);
    if (q.f >= t2)
      return fluid_refine(pos, fl, first, n8, ex, ey, ez, dx, dy, dz, ta, tn, f, q.f);
    ta = tn;
  }
  prev->t = -1.0f;
  return INFINITY;
}

/*
 * One pixel per work-item over the padded image the objects pass set up. Reads the opaque
 * colour and depth there; where the fluid's surface is nearer, writes the water's colour to
 * 'linear' and its distance to 'depth'.
 */
__kernel void fluid(vfx_frame_t f, vfx_fluid_t fl, __global const int *restrict cells,
                    __global const float *restrict pos, __global float *restrict linear,
                    __global float *restrict depth) {
  int x = get_global_id(0), y = get_global_id(1);
  int o = y * f.pitch + x;
  float ex = f.eye[0], ey = f.eye[1], ez = f.eye[2];
  float px = x + 0.5f, py = y + 0.5f;
  float dx = f.base[0] + px * f.step_x[0] + py * f.step_y[0];
  float dy = f.base[1] + px * f.step_x[1] + py * f.step_y[1];
  float dz = f.base[2] + px * f.step_x[2] + py * f.step_y[2];
  float il = 1.0f / sqrt(dx * dx + dy * dy + dz * dz);
  dx *= il, dy *= il, dz *= il;

  /* The part of [near, min(opaque depth, far)] inside the grid's box. */
  float opaque = depth[o];
  float ix = 1.0f / dx, iy = 1.0f / dy, iz = 1.0f / dz;
  float t0x = (fl.box_min[0] - ex) * ix, t1x = (fl.box_max[0] - ex) * ix;
  float t0y = (fl.box_min[1] - ey) * iy, t1y = (fl.box_max[1] - ey) * iy;
  float t0z = (fl.box_min[2] - ez) * iz, t1z = (fl.box_max[2] - ez) * iz;
  float t = fmax(fmax(fmin(t0x, t1x), fmin(t0y, t1y)), fmax(fmin(t0z, t1z), f.near_));
  float tend =
      fmin(fmin(fmax(t0x, t1x), fmax(t0y, t1y)), fmin(fmax(t0z, t1z), fmin(opaque, f.far_)));
  if (!(t <= tend))
    return;

  /* 3-D DDA from the cell holding the entry point. */
  float cx = (ex + t * dx - fl.origin[0]) * fl.inv_cell;
  float cy = (ey + t * dy - fl.origin[1]) * fl.inv_cell;
  float cz = (ez + t * dz - fl.origin[2]) * fl.inv_cell;
  int kx = clamp((int)floor(cx), 0, fl.dims[0] - 1);
  int ky = clamp((int)floor(cy), 0, fl.dims[1] - 1);
  int kz = clamp((int)floor(cz), 0, fl.dims[2] - 1);
  int sx = dx > 0.0f ? 1 : -1, sy = dy > 0.0f ? 1 : -1, sz = dz > 0.0f ? 1 : -1;
  float tdx = fabs(fl.cell * ix), tdy = fabs(fl.cell * iy), tdz = fabs(fl.cell * iz);
  float nx = (fl.origin[0] + (kx + (sx > 0)) * fl.cell - ex) * ix;
  float ny = (fl.origin[1] + (ky + (sy > 0)) * fl.cell - ey) * iy;
  float nz = (fl.origin[2] + (kz + (sz > 0)) * fl.cell - ez) * iz;
  if (dx == 0.0f)
    nx = INFINITY;
  if (dy == 0.0f)
    ny = INFINITY;
  if (dz == 0.0f)
    nz = INFINITY;

  float hit = INFINITY;
  fluid_prev_t prev = {-1.0f, 0.0f, 0, 0};
  for (;;) {
    float tb = fmin(fmin(nx, ny), fmin(nz, tend));
    int c = (kz * fl.dims[1] + ky) * fl.dims[0] + kx;
    int m = cells[2 * c + 1];
    if (m > 0 && tb >= t) {
      hit = fluid_search(pos, &fl, cells[2 * c], (m + 7) & ~7, m, ex, ey, ez, dx, dy, dz, t, tb,
                         tb >= tend, &prev);
      if (hit < INFINITY)
        break;
    } else {
      /* F is 0 all over an empty cell, so nothing carries across it. */
      prev.t = -1.0f;
    }
    if (tb >= tend)
      break;
    t = fmax(t, tb);
    if (nx <= ny && nx <= nz)
      kx += sx, nx += tdx;
    else if (ny <= nz)
      ky += sy, ny += tdy;
    else
      kz += sz, nz += tdz;
    if ((uint)kx >= (uint)fl.dims[0] || (uint)ky >= (uint)fl.dims[1] ||
        (uint)kz >= (uint)fl.dims[2])
      break;
  }
  if (!(hit < INFINITY))
    return;

  /* Water: Schlick's Fresnel mixes the reflected background (brighter towards the zenith, as
   * a sky would be; the scene has no environment map) with the transmitted colour behind,
   * tinted; a Blinn-Phong highlight of the light sits on top. */
  float hx = ex + hit * dx, hy = ey + hit * dy, hz = ez + hit * dz;
  float3 n = fluid_normal(pos, fl.stride, prev.first, prev.n8, hx, hy, hz, fl.inv_h);
  float nl = length(n);
  n = nl > 0.0f ? n / nl : (float3)(-dx, -dy, -dz);
  float3 d = (float3)(dx, dy, dz), v = -d;
  float cosv = dot(n, v);
  if (cosv < 0.0f)
    n = -n, cosv = -cosv;
  float k = 1.0f - cosv, k2 = k * k;
  float fr = fl.f0 + (1.0f - fl.f0) * k2 * k2 * k;
  float3 r = d + 2.0f * cosv * n;
  float sky = 0.7f + 0.6f * clamp(r.y, 0.0f, 1.0f);
  float3 l = (float3)(f.light_dir[0], f.light_dir[1], f.light_dir[2]);
  float3 lrgb = (float3)(f.light_rgb[0], f.light_rgb[1], f.light_rgb[2]);
  float3 hv = l + v;
  float hl = length(hv);
  float nh = hl > 0.0f ? fmax(dot(n, hv) / hl, 0.0f) : 0.0f;
  float spec = dot(n, l) > 0.0f
                   ? native_exp2(fl.shininess * native_log2(nh)) * (fl.shininess + 8.0f) * 0.0398f
                   : 0.0f;
  /* Absorption as through water reaching back to the opaque surface behind, at most 3h of it
   * (we do not trace the exit point): thin sheets over the floor stay clear, deep water and
   * drops against the sky take the tint's full colour. */
  float4 behind = vload4(o, linear);
  float depth_h = clamp((fmin(opaque, hit + 3.0f * fl.h) - hit) * fl.inv_h, 0.35f, 3.0f);
  float3 tint = native_exp2(depth_h * native_log2((float3)(fl.color[0], fl.color[1], fl.color[2])));
  float3 bg = (float3)(f.bg[0], f.bg[1], f.bg[2]);
  float3 col = fr * (bg * sky + spec * lrgb) + (1.0f - fr) * tint * behind.xyz;
  vstore4((float4)(col, 1.0f), o, linear);
  depth[o] = hit;
}
