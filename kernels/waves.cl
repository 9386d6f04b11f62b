/*
 * The energy-wave pass (SPEC §5.1): for every pixel and every wave, the exact line integral H of
 * the wave's density along the camera ray, in closed form, from the near distance to the opaque
 * depth written by the objects pass. The result is added to the linear image as
 * smoothstep(min(H, c) / c) * colour, and optionally stored unclamped (summed over the waves)
 * as the wave_h AOV. A second kernel, waves_march, integrates the same density by sampling, for comparison.
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
 * Each work-item shades a packet of 8 horizontally adjacent pixels in float8 lanes, like the
 * objects kernel, so that PoCL's code is vector code whatever it does with the work-item loop;
 * a packet skips a wave when none of its rays comes within the wave's bounding sphere.
 */
#include "common.h"

/* The 8 pixel centres of a packet, relative to its first pixel. */
#define WAVE_LANES ((float8)(0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f))

/* Below this m^2 a ray counts as parallel to the axis: rho is then constant along it. At
 * m^2 = 1e-24 rho changes by 1e-12 per unit of distance. */
#define WAVE_PARALLEL 1e-24f

/*
 * The unit camera rays of the packet at pixel (x0, y) of frame 'f', computed exactly as the
 * objects kernel computes them, so the opaque depth belongs to the same rays.
 */
static inline void wave_rays(const vfx_frame_t *f, int x0, int y, float8 *dx, float8 *dy,
                             float8 *dz) {
  float8 px = (float)x0 + WAVE_LANES;
  float py = y + 0.5f;
  float8 x = f->base[0] + px * f->step_x[0] + py * f->step_y[0];
  float8 yv = f->base[1] + px * f->step_x[1] + py * f->step_y[1];
  float8 z = f->base[2] + px * f->step_x[2] + py * f->step_y[2];
  float8 il = 1.0f / sqrt(x * x + yv * yv + z * z);
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
 * taken as log(u) * delta / (u - 1) with u = 1 + delta, the classic exact correction, which
 * also yields the quotient by m without dividing a small log by a small m.
 */
static inline float8 wave_asinh_span(float8 xa, float8 xb, float8 dxm, float8 m, float8 inv_m) {
  float8 p = min(fabs(xa), fabs(xb)), q = max(fabs(xa), fabs(xb));
  float8 sp = sqrt(fma(p, p, 1.0f)), sq = sqrt(fma(q, q, 1.0f));
  int8 same = (xa >= 0.0f) | (xb <= 0.0f);
  float8 ssum = sq + sp, spq = fma(sq, sp, 1.0f);
  float8 num = select(fma(q * p + q * sp + p * sq, spq, fma(q * q, fma(p, p, 1.0f), p * p)),
                      dxm * (ssum + q + p), same);
  float8 den = select(spq, ssum * (p + sp), same);
  /* z is delta / m for the same-sign form (dxm carries the 1 / m) and delta otherwise. */
  float8 z = num / den;
  float8 delta = select(z, z * m, same), dm = select(z * inv_m, z, same);
  float8 u = 1.0f + delta;
  float8 l = select(log(u) / (u - 1.0f), (float8)1.0f, u == 1.0f);
  return l * dm;
}

/*
 * The sphere-like integral of 1/sqrt(r^2 + eps^2) over [ta, tb] (ta <= tb), where
 * r^2 + eps^2 = (t + beta)^2 + delta2 for the lane: m = 1, x(t) = (t + beta) / sqrt(delta2).
 */
static inline float8 wave_sphere_span(float8 ta, float8 tb, float8 beta, float8 inv_delta) {
  float8 xa = (ta + beta) * inv_delta, xb = (tb + beta) * inv_delta;
  return wave_asinh_span(xa, xb, (tb - ta) * inv_delta, (float8)1.0f, (float8)1.0f);
}

/* What wave_setup works out for the packet's rays and one wave, per lane. */
typedef struct wave_ray {
  float8 bm, v2;            /* d.w and |d x w|^2: r^2 = (t + bm)^2 + v2. */
  float8 bl, vl2;           /* The same about M + L D. */
  float8 m2, c, bp;         /* rho^2 = m2 t^2 + 2 bp t + |w'|^2; c^2 = m2 |w'|^2 - bp^2. */
  float8 k;                 /* d.D, so s = s0 + k t; never zero (a tiny k of the right sign). */
  float8 t0, tl;            /* Where s = 0 and s = L. */
  float8 slab_in, slab_out; /* [min, max] of t0 and tl. */
  float8 lo, hi;            /* The interval to integrate; lo = hi = 0 for a miss. */
  int8 par;                 /* The ray is parallel to the axis (m2 below WAVE_PARALLEL). */
} wave_ray_t;

/*
 * Sets up wave 'wv' for the packet's unit rays d from the eye: the quantities of wave_ray_t and
 * the interval [lo, hi] of each ray inside the capsule, from 'near_' up to 'tmax'.
 */
static inline wave_ray_t wave_setup(__global const float *restrict wv, float near_, float8 tmax,
                                    float8 dx, float8 dy, float8 dz) {
  wave_ray_t w;
  float wx = wv[WAVE_W], wy = wv[WAVE_W + 1], wz = wv[WAVE_W + 2];
  float ax = wv[WAVE_D], ay = wv[WAVE_D + 1], az = wv[WAVE_D + 2];
  float px = wv[WAVE_WP], py = wv[WAVE_WP + 1], pz = wv[WAVE_WP + 2];
  float s0 = wv[WAVE_S0], len = wv[WAVE_L], r2 = wv[WAVE_R2];

  /* Sphere around M: v = d x w. */
  w.bm = dx * wx + dy * wy + dz * wz;
  float8 vx = dy * wz - dz * wy, vy = dz * wx - dx * wz, vz = dx * wy - dy * wx;
  w.v2 = vx * vx + vy * vy + vz * vz;
  /* The axis: n = D x d; about M + L D, d x (w - L D) = v + L n. */
  float8 nx = ay * dz - az * dy, ny = az * dx - ax * dz, nz = ax * dy - ay * dx;
  float8 k = dx * ax + dy * ay + dz * az;
  float8 vlx = fma(len, nx, vx), vly = fma(len, ny, vy), vlz = fma(len, nz, vz);
  w.vl2 = vlx * vlx + vly * vly + vlz * vlz;
  w.bl = fma(-len, k, w.bm);
  w.m2 = nx * nx + ny * ny + nz * nz;
  w.c = nx * px + ny * py + nz * pz;
  w.bp = dx * px + dy * py + dz * pz;
  w.par = w.m2 < WAVE_PARALLEL;

  /* A ray in a plane s = const gets a tiny k of the right sign: its crossings move far away, to
   * the side that puts the whole ray in the right region. */
  w.k = select(k, select((float8)1e-30f, (float8)-1e-30f, k < 0.0f), fabs(k) < 1e-30f);
  float8 ik = 1.0f / w.k;
  w.t0 = -s0 * ik;
  w.tl = (len - s0) * ik;
  w.slab_in = min(w.t0, w.tl);
  w.slab_out = max(w.t0, w.tl);

  /* The capsule is convex, so its interval is the hull of those of its three pieces: the two
   * end spheres and the cylinder between the planes. */
  float8 dm = r2 - w.v2, dl = r2 - w.vl2;
  float8 sm = sqrt(max(dm, 0.0f)), sl = sqrt(max(dl, 0.0f));
  float8 in = select((float8)INFINITY, -w.bm - sm, dm >= 0.0f);
  float8 out = select((float8)-INFINITY, -w.bm + sm, dm >= 0.0f);
  in = select(in, min(in, -w.bl - sl), dl >= 0.0f);
  out = select(out, max(out, -w.bl + sl), dl >= 0.0f);
  float8 dc = w.m2 * r2 - w.c * w.c;
  float8 sc = sqrt(max(dc, 0.0f)), im2 = 1.0f / w.m2;
  float8 cyl_in = select((-w.bp - sc) * im2, (float8)-INFINITY, w.par);
  float8 cyl_out = select((-w.bp + sc) * im2, (float8)INFINITY, w.par);
  int8 cyl = select(dc >= 0.0f, (int8)(wv[WAVE_GP] < r2 ? -1 : 0), w.par);
  float8 cin = max(cyl_in, w.slab_in), cout = min(cyl_out, w.slab_out);
  cyl &= cin <= cout;
  in = select(in, min(in, cin), cyl);
  out = select(out, max(out, cout), cyl);

  float8 lo = max(in, near_), hi = min(out, tmax);
  int8 hit = lo < hi;
  w.lo = select((float8)0.0f, lo, hit);
  w.hi = select((float8)0.0f, hi, hit);
  return w;
}

/*
 * H / |Q| of wave 'wv' along the rays set up in 'w' (the rays are unit, so this is H), in
 * closed form: the sphere term over [lo, hi]; the beam term as the sphere term about M where
 * s <= 0, the distance to the axis between the planes and the distance to M + L D where s >= L.
 * Zero where a ray misses the capsule.
 */
static inline float8 wave_exact(__global const float *restrict wv, const wave_ray_t *w) {
  float a = wv[WAVE_A], b = wv[WAVE_B], eps2 = wv[WAVE_EPS2];
  /* The region s <= 0 is the part of [lo, hi] before t0 for k > 0 and after it for k < 0. */
  float8 mid = clamp(w->t0, w->lo, w->hi);
  float8 inv_d = rsqrt(w->v2 + eps2);
  int8 ahead = w->k > 0.0f;
  float8 first = wave_sphere_span(w->lo, mid, w->bm, inv_d);
  float8 second = wave_sphere_span(mid, w->hi, w->bm, inv_d);
  float8 h = first * select((float8)a, (float8)(a + b), ahead) +
             second * select((float8)(a + b), (float8)a, ahead);
  if (b == 0.0f)
    return h;

  float8 ma = clamp(w->slab_in, w->lo, w->hi), mb = clamp(w->slab_out, w->lo, w->hi);
  if (any(mb > ma)) {
    float8 inv_s = rsqrt(fma(w->c, w->c, eps2 * w->m2)), inv_m = rsqrt(w->m2);
    float8 m = w->m2 * inv_m;
    float8 xa = fma(w->m2, ma, w->bp) * inv_s, xb = fma(w->m2, mb, w->bp) * inv_s;
    float8 beam = wave_asinh_span(xa, xb, (mb - ma) * m * inv_s, m, inv_m);
    /* Parallel to the axis, rho is the constant |w'|. */
    float8 flat = (mb - ma) * rsqrt((float8)(wv[WAVE_GP] + eps2));
    h += b * select(beam, flat, w->par);
  }

  float8 fa = clamp(select(w->lo, w->tl, ahead), w->lo, w->hi);
  float8 fb = clamp(select(w->tl, w->hi, ahead), w->lo, w->hi);
  if (any(fb > fa))
    h += b * wave_sphere_span(fa, fb, w->bl, rsqrt(w->vl2 + eps2));
  return h;
}

/*
 * The same integral by the midpoint rule with 'n' samples evenly spaced over [lo, hi]: the ray
 * march of the thesis' §4.3, given the exact interval so that only the sampling differs.
 */
static inline float8 wave_march(__global const float *restrict wv, const wave_ray_t *w, int n) {
  float a = wv[WAVE_A], b = wv[WAVE_B], eps2 = wv[WAVE_EPS2], s0 = wv[WAVE_S0];
  float len = wv[WAVE_L], gp = wv[WAVE_GP];
  float8 dt = (w->hi - w->lo) / (float)n;
  float8 sum = 0.0f;
  for (int i = 0; i < n; i++) {
    float8 t = fma((float8)(i + 0.5f), dt, w->lo);
    float8 r2 = (t + w->bm) * (t + w->bm) + w->v2;
    float8 rl2 = (t + w->bl) * (t + w->bl) + w->vl2;
    float8 rho2 = max(fma(fma(w->m2, t, 2.0f * w->bp), t, gp), 0.0f);
    float8 s = fma(w->k, t, s0);
    float8 q2 = select(select(rho2, rl2, s >= len), r2, s <= 0.0f);
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
static inline float8 wave_glow(float8 h, __global const float *wv) {
  float8 t = min(h, wv[WAVE_CLAMP]) * wv[WAVE_INV_CLAMP];
  return t * t * fma(-2.0f, t, 3.0f);
}

/*
 * Adds the waves to the packet's pixel at buffer offset 'o': H summed into hout (when mode has
 * WAVES_STORE_H) and the clamped glow into the linear RGBA (when mode has WAVES_ADD).
 */
static inline void wave_store(__global float *restrict linear, __global float *restrict hout,
                              int mode, int o, float8 hsum, float8 gr, float8 gg, float8 gb,
                              int touched) {
  if (mode & WAVES_STORE_H)
    vstore8(hsum, 0, hout + o);
  if (!(mode & WAVES_ADD) || !touched)
    return;
  /* The glow is light, so it is added to the colour; alpha becomes at least its strength, so
   * that glow over a transparent background shows. */
  float8 ga = min(max(max(gr, gg), gb), 1.0f);
  const float ni = -INFINITY;
  float16 p0 = vload16(0, linear + 4 * o), p1 = vload16(0, linear + 4 * o + 16);
  p0 += (float16)(gr.s0, gg.s0, gb.s0, 0.0f, gr.s1, gg.s1, gb.s1, 0.0f, gr.s2, gg.s2, gb.s2, 0.0f,
                  gr.s3, gg.s3, gb.s3, 0.0f);
  p1 += (float16)(gr.s4, gg.s4, gb.s4, 0.0f, gr.s5, gg.s5, gb.s5, 0.0f, gr.s6, gg.s6, gb.s6, 0.0f,
                  gr.s7, gg.s7, gb.s7, 0.0f);
  p0 = max(p0,
           (float16)(ni, ni, ni, ga.s0, ni, ni, ni, ga.s1, ni, ni, ni, ga.s2, ni, ni, ni, ga.s3));
  p1 = max(p1,
           (float16)(ni, ni, ni, ga.s4, ni, ni, ni, ga.s5, ni, ni, ni, ga.s6, ni, ni, ni, ga.s7));
  vstore16(p0, 0, linear + 4 * o);
  vstore16(p1, 0, linear + 4 * o + 16);
}

/*
 * Whether some ray of the packet may pass through wave 'wv' between 'near_' and 'tmax': the
 * test against the wave's bounding sphere, about the middle of its axis.
 */
static inline int wave_in_view(__global const float *restrict wv, float near_, float8 tmax,
                               float8 dx, float8 dy, float8 dz) {
  float cx = wv[WAVE_BOUND], cy = wv[WAVE_BOUND + 1], cz = wv[WAVE_BOUND + 2];
  float rb = wv[WAVE_BOUND + 3];
  float8 ux = dy * cz - dz * cy, uy = dz * cx - dx * cz, uz = dx * cy - dy * cx;
  float8 tc = -(dx * cx + dy * cy + dz * cz);
  return any((ux * ux + uy * uy + uz * uz <= rb * rb) & (tc + rb >= near_) & (tc - rb <= tmax));
}

/*
 * The planes that bound a packet's rays, for wave_in_packet. The 8 rays of a packet lie in one
 * plane through the eye (they differ only along step_x): its unit normal 'n', and the unit
 * normals 'e0' and 'e7' of the planes through the first and the last ray, perpendicular to it,
 * facing the other rays.
 */
typedef struct wave_wedge {
  float3 n, e0, e7;
} wave_wedge_t;

static inline wave_wedge_t wave_packet_wedge(const vfx_frame_t *f, int x0, int y) {
  float3 sx = (float3)(f->step_x[0], f->step_x[1], f->step_x[2]);
  float3 a0 = (float3)(f->base[0], f->base[1], f->base[2]) + (x0 + 0.5f) * sx +
              (y + 0.5f) * (float3)(f->step_y[0], f->step_y[1], f->step_y[2]);
  float3 a7 = a0 + 7.0f * sx;
  wave_wedge_t w;
  w.n = normalize(cross(a0, sx));
  w.e0 = normalize(cross(w.n, a0));
  w.e7 = normalize(cross(a7, w.n));
  w.e0 = dot(w.e0, a7) < 0.0f ? -w.e0 : w.e0;
  w.e7 = dot(w.e7, a0) < 0.0f ? -w.e7 : w.e7;
  return w;
}

/*
 * Whether wave 'wv' may meet a ray of the packet bounded by 'g': the capsule is out of reach
 * when both ends of its segment lie farther than R from the packet's plane on the same side,
 * or farther than R outside one of the side planes. Exact for the plane, conservative at the
 * wedge's edges, and all scalar work: most packets skip most waves here.
 */
static inline int wave_in_packet(__global const float *restrict wv, const wave_wedge_t *g) {
  float3 w = (float3)(wv[WAVE_W], wv[WAVE_W + 1], wv[WAVE_W + 2]);
  float3 d = (float3)(wv[WAVE_D], wv[WAVE_D + 1], wv[WAVE_D + 2]);
  float len = wv[WAVE_L], r = wv[WAVE_RADIUS];
  /* Signed distances of M and M + L D, whose offsets from the eye are -w and L D - w. */
  float pm = -dot(g->n, w), pl = pm + len * dot(g->n, d);
  float am = -dot(g->e0, w), al = am + len * dot(g->e0, d);
  float bm = -dot(g->e7, w), bl = bm + len * dot(g->e7, d);
  return !((pm > r && pl > r) || (pm < -r && pl < -r) || (am < -r && al < -r) ||
           (bm < -r && bl < -r));
}

/*
 * One packet of 8 pixels per work-item, at pixel (8 * global x, global y), over the padded
 * buffers of the objects pass: 'depth' ends every ray (+INFINITY where nothing opaque was hit);
 * 'waves' holds 'nwaves' records of WAVE_STRIDE floats made for this frame's eye. 'mode' is a
 * set of WAVES_* bits; 'hout' receives the summed unclamped H when it asks for it. Each wave
 * adds wave_glow(H) times its colour to the linear RGB: its full colour where H >= c, fading
 * smoothly to nothing as H falls to 0.
 */
__kernel void waves(vfx_frame_t f, __global const float *restrict waves, int nwaves,
                    __global const float *restrict depth, __global float *restrict linear,
                    __global float *restrict hout, int mode) {
  int x0 = 8 * get_global_id(0), y = get_global_id(1);
  int o = y * f.pitch + x0;
  float8 dx, dy, dz;
  wave_rays(&f, x0, y, &dx, &dy, &dz);
  float8 tmax = vload8(0, depth + o);
  wave_wedge_t g = wave_packet_wedge(&f, x0, y);
  float8 hsum = 0.0f, gr = 0.0f, gg = 0.0f, gb = 0.0f;
  int touched = 0;
  for (int i = 0; i < nwaves; i++) {
    __global const float *wv = waves + i * WAVE_STRIDE;
    if (!wave_in_packet(wv, &g) || !wave_in_view(wv, f.near_, tmax, dx, dy, dz))
      continue;
    wave_ray_t w = wave_setup(wv, f.near_, tmax, dx, dy, dz);
    if (!any(w.hi > w.lo))
      continue;
    float8 h = wave_exact(wv, &w);
    float8 g = wave_glow(h, wv);
    hsum += h;
    gr = fma(g, wv[WAVE_COLOR], gr);
    gg = fma(g, wv[WAVE_COLOR + 1], gg);
    gb = fma(g, wv[WAVE_COLOR + 2], gb);
    touched = 1;
  }
  wave_store(linear, hout, mode, o, hsum, gr, gg, gb, touched);
}

/* The waves kernel with the closed form replaced by a ray march of 'samples' samples per wave
 * and ray (wave_march); for comparisons, never used to render a frame. */
__kernel void waves_march(vfx_frame_t f, __global const float *restrict waves, int nwaves,
                          __global const float *restrict depth, __global float *restrict linear,
                          __global float *restrict hout, int mode, int samples) {
  int x0 = 8 * get_global_id(0), y = get_global_id(1);
  int o = y * f.pitch + x0;
  float8 dx, dy, dz;
  wave_rays(&f, x0, y, &dx, &dy, &dz);
  float8 tmax = vload8(0, depth + o);
  wave_wedge_t g = wave_packet_wedge(&f, x0, y);
  float8 hsum = 0.0f, gr = 0.0f, gg = 0.0f, gb = 0.0f;
  int touched = 0;
  for (int i = 0; i < nwaves; i++) {
    __global const float *wv = waves + i * WAVE_STRIDE;
    if (!wave_in_packet(wv, &g) || !wave_in_view(wv, f.near_, tmax, dx, dy, dz))
      continue;
    wave_ray_t w = wave_setup(wv, f.near_, tmax, dx, dy, dz);
    if (!any(w.hi > w.lo))
      continue;
    float8 h = wave_march(wv, &w, samples);
    float8 g = wave_glow(h, wv);
    hsum += h;
    gr = fma(g, wv[WAVE_COLOR], gr);
    gg = fma(g, wv[WAVE_COLOR + 1], gg);
    gb = fma(g, wv[WAVE_COLOR + 2], gb);
    touched = 1;
  }
  wave_store(linear, hout, mode, o, hsum, gr, gg, gb, touched);
}
