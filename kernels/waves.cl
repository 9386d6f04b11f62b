/*
 * The energy-wave pass (SPEC §5.1): for every pixel and every wave, the exact line integral H of
 * the wave's density along the camera ray, in closed form, from the near distance to the opaque
 * depth written by the objects pass. The result is added to the linear image as
 * smoothstep(min(H, c) / c) * colour, and optionally stored unclamped (summed over the waves)
 * as the wave_h AOV. A second kernel, waves_march, integrates the same density by sampling, for
 * comparison.
 *
 * The maths. A ray R(t) = S + t d with unit d and w = S - M (all per-wave scalars below are made
 * by the host, in double, from the eye and the wave; see WAVE_* in common.h). Every piece of the
 * density is 1/sqrt(q(t) + eps^2) with q quadratic in t, and
 *
 *   int dt / sqrt(m^2 t^2 + 2 beta t + gamma + eps^2) = asinh(x(t)) / m,
 *   x(t) = (m^2 t + beta) / sigma,  sigma^2 = m^2 (gamma + eps^2) - beta^2.
 *
 * For the sphere terms m = 1, beta = d.w and sigma^2 = |d x w|^2 + eps^2; for the beam, with
 * n = D x d and w' = w - (w.D) D, m^2 = |n|^2, beta = d.w' and sigma^2 = (n.w')^2 + eps^2 m^2.
 * Both discriminants come from cross products, so nothing cancels when the ray passes close to
 * M or to the axis. A difference asinh(x_b) - asinh(x_a) is formed as log1p(delta) with delta
 * free of cancellation for every sign of x_a and x_b (wave_asinh_span), which is what keeps the
 * float result within about 1e-5 of the exact integral.
 *
 * Each work-item shades a packet of WAVES_PACKET (16) horizontally adjacent pixels in the lanes
 * of a float16, so that PoCL's code is vector code whatever it does with the work-item loop
 * and fills AVX-512's registers: twice the 8 pixels it had at first took about 30% off the pass,
 * which is bound by the number of instructions more than by any one unit. The host lists, for
 * each work-group, the waves that may meet one of its rays (cull_waves in render_waves.c); a
 * packet integrates only those, and skips one whose capsule none of its rays enters. When the
 * pass is the last of an 8-bit frame (WAVES_TONEMAP) it also tone-maps its packets (tonemap.h),
 * and when the objects pass had nothing to draw (WAVES_EMPTY) it starts from the background.
 */
#include "common.h"
#include "fastmath.h"
#include "tonemap.h"

/* A packet's lanes: WAVES_PACKET (common.h; 16, which render_waves.c asserts) pixels of a row,
 * one per vector lane, and the pixel centres relative to its first pixel. The tone map
 * (tonemap.h) works on the same float16 vectors. */
typedef float16 wfloat;
typedef int16 wint;
#define WAVE_LOAD vload16
#define WAVE_STORE vstore16
#define as_wint as_int16
#define as_wfloat as_float16
#define convert_wfloat convert_float16
#define WAVE_LANES                                                                                 \
  ((wfloat)(0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f, 8.5f, 9.5f, 10.5f, 11.5f, 12.5f,       \
            13.5f, 14.5f, 15.5f))

/* Below this m^2 a ray counts as parallel to the axis: rho is then constant along it. At
 * m^2 = 1e-24 rho changes by 1e-12 per unit of distance. */
#define WAVE_PARALLEL 1e-24f

/*
 * log(u) for finite u >= 1, without the builtin log, whose extended-precision reduction and
 * division took a third of the pass (this one takes a tenth): u = 2^e m with m in [sqrt(1/2),
 * sqrt(2)), and log(m) = f - f^2 / 2 + f^3 P(f), f = m - 1, with P of degree 5 (Chebyshev
 * interpolation of (log(1 + f) - f + f^2 / 2) / f^3), within 1e-6 relative. For u in [1,
 * sqrt(2)) f is u - 1 exactly, so log(u) keeps its digits near 1.
 */
static inline wfloat wave_log(wfloat u) {
  wint bits = as_wint(u);
  wint e = (bits >> 23) - 127;
  wfloat m = as_wfloat((bits & 0x007fffff) | 0x3f800000);
  wint big = m > 1.41421356f;
  m = select(m, 0.5f * m, big);
  e -= big; /* big is -1 where true. */
  wfloat f = m - 1.0f, z = f * f;
  wfloat y = fma(f, -0.104905265f, 0.158193884f);
  y = fma(y, f, -0.170016582f);
  y = fma(y, f, 0.199474455f);
  y = fma(y, f, -0.249918395f);
  y = fma(y, f, 0.333336239f);
  wfloat fe = convert_wfloat(e);
  y = fma(y * f, z, fma(fe, -2.12194440e-4f, -0.5f * z));
  return fma(fe, 0.693359375f, f + y);
}

/* 1 / x for finite x >= 1, to within about 2^-14 relative (vrcp14ps alone). */
static inline wfloat wave_recip_est(wfloat x) {
  return native_recip(x);
}

/* sqrt(x) for finite x >= 0, by fast_rsqrt, where it is used; below FLT_MIN (negative x
 * included) it is sqrt(FLT_MIN), about 1e-19, for callers that select it away there. */
static inline wfloat wave_sqrt(wfloat x) {
  x = max(x, FLT_MIN);
  return x * fast_rsqrt(x);
}

/*
 * The unit camera rays of the packet at pixel (x0, y) of frame 'f', as the objects kernel
 * computes them but normalised with the reciprocal square-root estimate: the directions differ
 * by an ulp or so, which moves a ray's end at the opaque depth by some 1e-7 of that depth.
 */
static inline void wave_rays(const vfx_frame_t *f, int x0, int y, wfloat *dx, wfloat *dy,
                             wfloat *dz) {
  wfloat px = (float)x0 + WAVE_LANES;
  float py = y + 0.5f;
  wfloat x = f->base[0] + px * f->step_x[0] + py * f->step_y[0];
  wfloat yv = f->base[1] + px * f->step_x[1] + py * f->step_y[1];
  wfloat z = f->base[2] + px * f->step_x[2] + py * f->step_y[2];
  wfloat il = fast_rsqrt(x * x + yv * yv + z * z);
  *dx = x * il, *dy = yv * il, *dz = z * il;
}

/*
 * (asinh(x_b) - asinh(x_a)) / m for x_a <= x_b, where 'dxm' is (x_b - x_a) / m computed
 * directly from the interval (not from x_b - x_a, which would cancel) and 'inv_m' is 1 / m.
 * The difference is log1p(delta) with delta = g(x_b) / g(x_a) - 1, g(x) = x + sqrt(x^2 + 1):
 *
 *   same signs, p <= q the magnitudes (asinh is odd, so x_a, x_b <= 0 mirrors to 0 <= p <= q):
 *     delta = (q - p) (S_q + S_p + q + p) / ((S_q + S_p) (p + S_p)),  S_x = sqrt(x^2 + 1);
 *   x_a < 0 < x_b, p = -x_a, q = x_b: the sum asinh(q) + asinh(p) = log(g(q) g(p)), and
 *     delta = g(q) g(p) - 1 = q p + q S_p + p S_q + (q^2 + p^2 + q^2 p^2) / (S_q S_p + 1).
 *
 * Every term is non-negative, so neither form loses digits, near zero or far from it. log1p is
 * taken as log(u) + (delta - (u - 1)) / u with u = 1 + delta rounded, the classic correction,
 * and divided by m as a product with 1 / m, which keeps its relative accuracy however small m is.
 */
static inline wfloat wave_asinh_span(wfloat xa, wfloat xb, wfloat dxm, wfloat m, wfloat inv_m) {
  wfloat p = min(fabs(xa), fabs(xb)), q = max(fabs(xa), fabs(xb));
  wfloat p2 = fma(p, p, 1.0f), q2 = fma(q, q, 1.0f);
  wfloat sp = p2 * fast_rsqrt(p2), sq = q2 * fast_rsqrt(q2);
  wint same = (xa >= 0.0f) | (xb <= 0.0f);
  wfloat ssum = sq + sp, spq = fma(sq, sp, 1.0f);
  wfloat num =
      select(fma(q * p + q * sp + p * sq, spq, fma(q * q, p2, p * p)), dxm * (ssum + q + p), same);
  wfloat den = select(spq, ssum * (p + sp), same);
  /* z is delta / m for the same-sign form (dxm carries the 1 / m) and delta otherwise. */
  wfloat z = fast_div(num, den);
  wfloat delta = select(z, z * m, same);
  /* log1p(delta) = log(u) - ((u - 1) - delta) / u for u = 1 + delta rounded: the correction is
   * under an ulp of u, so the reciprocal estimate is ample for it. */
  wfloat u = 1.0f + delta;
  wfloat l = fma((delta - (u - 1.0f)), wave_recip_est(u), wave_log(u));
  return l * inv_m;
}

/*
 * The sphere-like integral of 1/sqrt(r^2 + eps^2) over [ta, tb] (ta <= tb), where
 * r^2 + eps^2 = (t + beta)^2 + delta2 for the lane: m = 1, x(t) = (t + beta) / sqrt(delta2).
 */
static inline wfloat wave_sphere_span(wfloat ta, wfloat tb, wfloat beta, wfloat inv_delta) {
  wfloat xa = (ta + beta) * inv_delta, xb = (tb + beta) * inv_delta;
  return wave_asinh_span(xa, xb, (tb - ta) * inv_delta, (wfloat)1.0f, (wfloat)1.0f);
}

/* What wave_setup works out for the packet's rays and one wave, per lane. */
typedef struct wave_ray {
  wfloat bm, v2;            /* d.w and |d x w|^2: r^2 = (t + bm)^2 + v2. */
  wfloat bl, vl2;           /* The same about M + L D. */
  wfloat m2, c, bp;         /* rho^2 = m2 t^2 + 2 bp t + |w'|^2; c^2 = m2 |w'|^2 - bp^2. */
  wfloat k;                 /* d.D, so s = s0 + k t; never zero (a tiny k of the right sign). */
  wfloat t0, tl;            /* Where s = 0 and s = L. */
  wfloat slab_in, slab_out; /* [min, max] of t0 and tl. */
  wfloat lo, hi;            /* The interval to integrate; lo = hi = 0 for a miss. */
  wint par;                 /* The ray is parallel to the axis (m2 below WAVE_PARALLEL). */
} wave_ray_t;

/*
 * Sets up wave 'wv' for the packet's unit rays d from the eye: the quantities of wave_ray_t and
 * the interval [lo, hi] of each ray inside the capsule, from 'near_' up to 'tmax'.
 */
static inline wave_ray_t wave_setup(__global const float *restrict wv, float near_, wfloat tmax,
                                    wfloat dx, wfloat dy, wfloat dz) {
  wave_ray_t w;
  float wx = wv[WAVE_W], wy = wv[WAVE_W + 1], wz = wv[WAVE_W + 2];
  float ax = wv[WAVE_D], ay = wv[WAVE_D + 1], az = wv[WAVE_D + 2];
  float px = wv[WAVE_WP], py = wv[WAVE_WP + 1], pz = wv[WAVE_WP + 2];
  float s0 = wv[WAVE_S0], len = wv[WAVE_L], r2 = wv[WAVE_R2];

  /* Sphere around M: v = d x w. */
  w.bm = dx * wx + dy * wy + dz * wz;
  wfloat vx = dy * wz - dz * wy, vy = dz * wx - dx * wz, vz = dx * wy - dy * wx;
  w.v2 = vx * vx + vy * vy + vz * vz;
  /* The axis: n = D x d; about M + L D, d x (w - L D) = v + L n. */
  wfloat nx = ay * dz - az * dy, ny = az * dx - ax * dz, nz = ax * dy - ay * dx;
  wfloat k = dx * ax + dy * ay + dz * az;
  wfloat vlx = fma(len, nx, vx), vly = fma(len, ny, vy), vlz = fma(len, nz, vz);
  w.vl2 = vlx * vlx + vly * vly + vlz * vlz;
  w.bl = fma(-len, k, w.bm);
  w.m2 = nx * nx + ny * ny + nz * nz;
  w.c = nx * px + ny * py + nz * pz;
  w.bp = dx * px + dy * py + dz * pz;
  w.par = w.m2 < WAVE_PARALLEL;

  /* A ray in a plane s = const gets a tiny k of the right sign: its crossings move far away, to
   * the side that puts the whole ray in the right region. */
  w.k = select(k, select((wfloat)1e-30f, (wfloat)-1e-30f, k < 0.0f), fabs(k) < 1e-30f);
  wfloat ik = fast_div((wfloat)1.0f, w.k);
  w.t0 = -s0 * ik;
  w.tl = (len - s0) * ik;
  w.slab_in = min(w.t0, w.tl);
  w.slab_out = max(w.t0, w.tl);

  /* The capsule is convex, so its interval is the hull of those of its three pieces: the two
   * end spheres and the cylinder between the planes. */
  wfloat dm = r2 - w.v2, dl = r2 - w.vl2;
  wfloat sm = wave_sqrt(dm), sl = wave_sqrt(dl);
  wfloat in = select((wfloat)INFINITY, -w.bm - sm, dm >= 0.0f);
  wfloat out = select((wfloat)-INFINITY, -w.bm + sm, dm >= 0.0f);
  in = select(in, min(in, -w.bl - sl), dl >= 0.0f);
  out = select(out, max(out, -w.bl + sl), dl >= 0.0f);
  wfloat dc = w.m2 * r2 - w.c * w.c;
  wfloat sc = wave_sqrt(dc), im2 = fast_div((wfloat)1.0f, max(w.m2, WAVE_PARALLEL));
  wfloat cyl_in = select((-w.bp - sc) * im2, (wfloat)-INFINITY, w.par);
  wfloat cyl_out = select((-w.bp + sc) * im2, (wfloat)INFINITY, w.par);
  wint cyl = select(dc >= 0.0f, (wint)(wv[WAVE_GP] < r2 ? -1 : 0), w.par);
  wfloat cin = max(cyl_in, w.slab_in), cout = min(cyl_out, w.slab_out);
  cyl &= cin <= cout;
  in = select(in, min(in, cin), cyl);
  out = select(out, max(out, cout), cyl);

  wfloat lo = max(in, near_), hi = min(out, tmax);
  wint hit = lo < hi;
  w.lo = select((wfloat)0.0f, lo, hit);
  w.hi = select((wfloat)0.0f, hi, hit);
  return w;
}

/*
 * H / |Q| of wave 'wv' along the rays set up in 'w' (the rays are unit, so this is H), in
 * closed form: the sphere term over [lo, hi]; the beam term as the sphere term about M where
 * s <= 0, the distance to the axis between the planes and the distance to M + L D where s >= L.
 * Zero where a ray misses the capsule.
 */
static inline wfloat wave_exact(__global const float *restrict wv, const wave_ray_t *w) {
  float a = wv[WAVE_A], b = wv[WAVE_B], eps2 = wv[WAVE_EPS2];
  /* The region s <= 0 is the part of [lo, hi] before t0 for k > 0 and after it for k < 0. */
  wfloat mid = clamp(w->t0, w->lo, w->hi);
  wfloat inv_d = fast_rsqrt(w->v2 + eps2);
  wint ahead = w->k > 0.0f;
  /* Each side is skipped when it is empty for the whole packet, as inside the beam's body. */
  wfloat h = 0.0f;
  if (any(mid > w->lo))
    h = wave_sphere_span(w->lo, mid, w->bm, inv_d) * select((wfloat)a, (wfloat)(a + b), ahead);
  if (any(w->hi > mid))
    h += wave_sphere_span(mid, w->hi, w->bm, inv_d) * select((wfloat)(a + b), (wfloat)a, ahead);
  if (b == 0.0f)
    return h;

  wfloat ma = clamp(w->slab_in, w->lo, w->hi), mb = clamp(w->slab_out, w->lo, w->hi);
  if (any(mb > ma)) {
    wfloat inv_s = fast_rsqrt(max(fma(w->c, w->c, eps2 * w->m2), FLT_MIN));
    wfloat inv_m = fast_rsqrt(max(w->m2, FLT_MIN));
    wfloat m = w->m2 * inv_m;
    wfloat xa = fma(w->m2, ma, w->bp) * inv_s, xb = fma(w->m2, mb, w->bp) * inv_s;
    wfloat beam = wave_asinh_span(xa, xb, (mb - ma) * m * inv_s, m, inv_m);
    /* Parallel to the axis, rho is the constant |w'|. */
    wfloat flat = (mb - ma) * rsqrt(wv[WAVE_GP] + eps2);
    h += b * select(beam, flat, w->par);
  }

  wfloat fa = clamp(select(w->lo, w->tl, ahead), w->lo, w->hi);
  wfloat fb = clamp(select(w->tl, w->hi, ahead), w->lo, w->hi);
  if (any(fb > fa))
    h += b * wave_sphere_span(fa, fb, w->bl, fast_rsqrt(w->vl2 + eps2));
  return h;
}

/*
 * The same integral by the midpoint rule with 'n' samples evenly spaced over [lo, hi]: the ray
 * march of the thesis' §4.3, given the exact interval so that only the sampling differs.
 */
static inline wfloat wave_march(__global const float *restrict wv, const wave_ray_t *w, int n) {
  float a = wv[WAVE_A], b = wv[WAVE_B], eps2 = wv[WAVE_EPS2], s0 = wv[WAVE_S0];
  float len = wv[WAVE_L], gp = wv[WAVE_GP];
  wfloat dt = (w->hi - w->lo) / (float)n;
  wfloat sum = 0.0f;
  for (int i = 0; i < n; i++) {
    wfloat t = fma((wfloat)(i + 0.5f), dt, w->lo);
    wfloat r2 = (t + w->bm) * (t + w->bm) + w->v2;
    wfloat rl2 = (t + w->bl) * (t + w->bl) + w->vl2;
    wfloat rho2 = max(fma(fma(w->m2, t, 2.0f * w->bp), t, gp), 0.0f);
    wfloat s = fma(w->k, t, s0);
    wfloat q2 = select(select(rho2, rl2, s >= len), r2, s <= 0.0f);
    sum += a * rsqrt(r2 + eps2) + b * rsqrt(q2 + eps2);
  }
  return sum * dt;
}

/*
 * The brightness a wave gives for its integral 'h': t = min(h, c) / c through smoothstep,
 * 3t² - 2t³. The thesis shows H clamped at c as brightness (eq. 2.12, §2.2.4); a linear map
 * of it outlines the capsule, because H rises like the square root of the distance from the
 * capsule's surface, and outlines the clamp, because the slope stops dead at c. Smoothstep's
 * zero slope at both ends turns the first into a soft halo and the second into a smooth core.
 */
static inline wfloat wave_glow(wfloat h, __global const float *wv) {
  wfloat t = min(h, wv[WAVE_CLAMP]) * wv[WAVE_INV_CLAMP];
  return t * t * fma(-2.0f, t, 3.0f);
}

/* Adds the glow 'r', 'g', 'b' of 4 pixels to their linear RGBA at 'p'; alpha is left as it is. */
static inline void wave_add4(__global float *restrict p, float4 r, float4 g, float4 b) {
  float16 v = vload16(0, p);
  v += (float16)(r.s0, g.s0, b.s0, 0.0f, r.s1, g.s1, b.s1, 0.0f, r.s2, g.s2, b.s2, 0.0f, r.s3, g.s3,
                 b.s3, 0.0f);
  vstore16(v, 0, p);
}

/*
 * Adds the waves to the packet's pixels at buffer offset 'o': H summed into hout (when mode has
 * WAVES_STORE_H), the clamped glow into the linear RGBA (WAVES_ADD), or the glow added to the
 * linear RGBA and the sum tone-mapped into 'rgba8' (WAVES_TONEMAP), every packet, touched or
 * not, since this replaces the tone-map pass. With WAVES_EMPTY the linear colour is the
 * background's, which the objects pass did not write.
 */
static inline void wave_store(const vfx_frame_t *f, __global float *restrict linear,
                              __global float *restrict hout, __global uchar *restrict rgba8,
                              int mode, int o, wfloat hsum, wfloat gr, wfloat gg, wfloat gb,
                              int touched, float scale, int op) {
  if (mode & WAVES_STORE_H)
    WAVE_STORE(hsum, 0, hout + o);
  /* The glow is emitted light that hides nothing behind it: it is added to the colour and leaves
   * alpha (the coverage) alone, so that over a transparent background the premultiplied pixel
   * composites as glow added to whatever lies behind. */
  if (mode & WAVES_TONEMAP) {
    if ((mode & WAVES_EMPTY) && !touched) {
      /* The background alone: its four channels through one tone map, for the same bytes. */
      int16 c = tone_colour((float16)(f->bg[0], f->bg[1], f->bg[2], 0.0f, 0.0f, 0.0f, 0.0f, 0.0f,
                                      0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f),
                            scale, op);
      tone_store16(rgba8 + 4 * o, (int16)c.s0, (int16)c.s1, (int16)c.s2,
                   tone_alpha((float16)f->bg[3]));
      return;
    }
    wfloat r = f->bg[0], g = f->bg[1], b = f->bg[2], a = f->bg[3];
    if (!(mode & WAVES_EMPTY))
      tone_load16(linear + 4 * o, &r, &g, &b, &a);
    tone_store16(rgba8 + 4 * o, tone_colour(r + gr, scale, op), tone_colour(g + gg, scale, op),
                 tone_colour(b + gb, scale, op), tone_alpha(a));
    return;
  }
  if (!(mode & WAVES_ADD) || !touched)
    return;
  wave_add4(linear + 4 * o, gr.lo.lo, gg.lo.lo, gb.lo.lo);
  wave_add4(linear + 4 * o + 16, gr.lo.hi, gg.lo.hi, gb.lo.hi);
  wave_add4(linear + 4 * o + 32, gr.hi.lo, gg.hi.lo, gb.hi.lo);
  wave_add4(linear + 4 * o + 48, gr.hi.hi, gg.hi.hi, gb.hi.hi);
}

/*
 * One packet of WAVES_PACKET pixels per work-item, at pixel (WAVES_PACKET * global x, global y),
 * over the padded buffers of the objects pass: 'depth' ends every ray (+INFINITY where nothing
 * opaque was hit), and so does the camera's far distance; 'waves' holds 'nwaves' records of
 * WAVE_STRIDE floats made for this frame's eye, and 'lists', for work-group g (numbered row by
 * row), the number of waves to draw at (nwaves + 1) g and their indices after it. 'mode' is a set
 * of WAVES_* bits; 'hout' receives the summed unclamped H when it asks for it; 'rgba8', 'scale'
 * (2^exposure) and 'op' (TONE_OP_*) serve WAVES_TONEMAP, and with WAVES_EMPTY 'depth' and 'linear'
 * are not read. Each wave adds wave_glow(H) times its colour to the linear RGB: its full colour
 * where H >= c, fading smoothly to nothing as H falls to 0.
 */
__kernel void waves(vfx_frame_t f, __global const float *restrict waves, int nwaves,
                    __global const int *restrict lists, __global const float *restrict depth,
                    __global float *restrict linear, __global float *restrict hout, int mode,
                    __global uchar *restrict rgba8, float scale, int op) {
  int x0 = WAVES_PACKET * get_global_id(0), y = get_global_id(1);
  int o = y * f.pitch + x0;
  wfloat dx, dy, dz;
  wave_rays(&f, x0, y, &dx, &dy, &dz);
  /* Nothing is drawn beyond the camera's far distance, glow included. */
  wfloat tmax = fmin(mode & WAVES_EMPTY ? (wfloat)INFINITY : WAVE_LOAD(0, depth + o), f.far_);
  wfloat hsum = 0.0f, gr = 0.0f, gg = 0.0f, gb = 0.0f;
  int touched = 0;
  __global const int *list =
      lists + (get_group_id(1) * get_num_groups(0) + get_group_id(0)) * (nwaves + 1);
  for (int j = 0, count = list[0]; j < count; j++) {
    __global const float *wv = waves + list[1 + j] * WAVE_STRIDE;
    wave_ray_t w = wave_setup(wv, f.near_, tmax, dx, dy, dz);
    if (!any(w.hi > w.lo))
      continue;
    wfloat h = wave_exact(wv, &w);
    wfloat g = wave_glow(h, wv);
    hsum += h;
    gr = fma(g, wv[WAVE_COLOR], gr);
    gg = fma(g, wv[WAVE_COLOR + 1], gg);
    gb = fma(g, wv[WAVE_COLOR + 2], gb);
    touched = 1;
  }
  wave_store(&f, linear, hout, rgba8, mode, o, hsum, gr, gg, gb, touched, scale, op);
}

/* The waves kernel with the closed form replaced by a ray march of 'samples' samples per wave
 * and ray (wave_march); for comparisons, never used to render a frame. */
__kernel void waves_march(vfx_frame_t f, __global const float *restrict waves, int nwaves,
                          __global const int *restrict lists, __global const float *restrict depth,
                          __global float *restrict linear, __global float *restrict hout, int mode,
                          __global uchar *restrict rgba8, float scale, int op, int samples) {
  int x0 = WAVES_PACKET * get_global_id(0), y = get_global_id(1);
  int o = y * f.pitch + x0;
  wfloat dx, dy, dz;
  wave_rays(&f, x0, y, &dx, &dy, &dz);
  /* Nothing is drawn beyond the camera's far distance, glow included. */
  wfloat tmax = fmin(mode & WAVES_EMPTY ? (wfloat)INFINITY : WAVE_LOAD(0, depth + o), f.far_);
  wfloat hsum = 0.0f, gr = 0.0f, gg = 0.0f, gb = 0.0f;
  int touched = 0;
  __global const int *list =
      lists + (get_group_id(1) * get_num_groups(0) + get_group_id(0)) * (nwaves + 1);
  for (int j = 0, count = list[0]; j < count; j++) {
    __global const float *wv = waves + list[1 + j] * WAVE_STRIDE;
    wave_ray_t w = wave_setup(wv, f.near_, tmax, dx, dy, dz);
    if (!any(w.hi > w.lo))
      continue;
    wfloat h = wave_march(wv, &w, samples);
    wfloat g = wave_glow(h, wv);
    hsum += h;
    gr = fma(g, wv[WAVE_COLOR], gr);
    gg = fma(g, wv[WAVE_COLOR + 1], gg);
    gb = fma(g, wv[WAVE_COLOR + 2], gb);
    touched = 1;
  }
  wave_store(&f, linear, hout, rgba8, mode, o, hsum, gr, gg, gb, touched, scale, op);
}
