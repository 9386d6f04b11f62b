/*
 * Tests of the energy-wave pass (SPEC §5.1) against an independent reference: the density f of
 * SPEC §5.1 evaluated point by point in double and integrated along each pixel's ray (built in
 * double from SPEC §4's camera) by adaptive Gauss-Kronrod quadrature, over the part of the ray
 * inside the capsule, found by searching the distance to the segment rather than by solving
 * the quadratics the kernel solves. The renderer's wave_h AOV must agree within 1e-4 relative
 * for random waves and cameras and for each degenerate case; an opaque box must end the
 * integral at its depth; the beauty image must gain exactly smoothstep(min(H, c) / c) times the
 * colour; an 8-bit frame, which the waves pass tone-maps itself, must be the tone map of that
 * image.
 * Scenes are built as render_scene_t structs. Exits non-zero on any failure.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "check.h"
#include "pixel_ray.h"
#include "render.h"

#define SIDE 17      /* Odd, so the middle pixel's ray is the camera's forward direction. */
#define MAX_REL 1e-4 /* SPEC §5.1: float32 H within 1e-4 relative of the double quadrature. */

static renderer_t *R;

/* ---- Reference ----------------------------------------------------------------------------- */

/* The wave in double, and the ray it is integrated along. */
typedef struct ref {
  double m[3], d[3], a, b, len, rad, eps;
  ray_t ray;
} ref_t;

static ref_t make_ref(const rwave_t *w, const ray_t *ray) {
  ref_t f;
  double n = 0;
  for (int i = 0; i < 3; i++) {
    f.m[i] = w->center[i];
    f.d[i] = w->direction[i];
    n += f.d[i] * f.d[i];
  }
  for (int i = 0; i < 3; i++)
    f.d[i] /= sqrt(n);
  f.a = w->a, f.b = w->b, f.len = w->length, f.rad = w->radius, f.eps = w->softening;
  f.ray = *ray;
  return f;
}

/* The distance q from the ray's point at 't' to the segment [M, M + L D], and r = |P - M|. */
static double seg_dist(const ref_t *f, double t, double *r) {
  double p[3], e[3];
  for (int i = 0; i < 3; i++)
    p[i] = f->ray.o[i] + t * f->ray.d[i] - f->m[i];
  double s = dot3(p, f->d);
  *r = sqrt(dot3(p, p));
  double along = s <= 0 ? 0 : s >= f->len ? f->len : s;
  for (int i = 0; i < 3; i++)
    e[i] = p[i] - along * f->d[i];
  return sqrt(dot3(e, e));
}

/* SPEC §5.1's density, written as it reads: q is r behind M, the distance to the axis between
 * the planes and the distance to M + L D beyond; zero outside the capsule q <= R. */
static double density(const ref_t *f, double t) {
  double r, q = seg_dist(f, t, &r);
  if (q > f->rad)
    return 0;
  return f->a / sqrt(r * r + f->eps * f->eps) + f->b / sqrt(q * q + f->eps * f->eps);
}

/* One 15-point Kronrod rule on [a, b] with the embedded 7-point Gauss rule's error estimate. */
static double kronrod(const ref_t *f, double a, double b, double *errest) {
  static const double xk[8] = {
      0.991455371120812639, 0.949107912342758525, 0.864864423359769073, 0.741531185599394440,
      0.586087235467691130, 0.405845151377397167, 0.207784955007898468, 0.0};
  static const double wk[8] = {0.022935322010529225, 0.063092092629978553, 0.104790010322250184,
                               0.140653259715525919, 0.169004726639267903, 0.190350578064785410,
                               0.204432940075298892, 0.209482141084727828};
  static const double wg[4] = {0.129484966168869693, 0.279705391489276668, 0.381830050505118945,
                               0.417959183673469388};
  double c = 0.5 * (a + b), h = 0.5 * (b - a);
  double fc = density(f, c), k = wk[7] * fc, g = wg[3] * fc;
  for (int i = 0; i < 7; i++) {
    double s = density(f, c - h * xk[i]) + density(f, c + h * xk[i]);
    k += wk[i] * s;
    if (i % 2 == 1)
      g += wg[i / 2] * s;
  }
  *errest = fabs((k - g) * h);
  return k * h;
}

/* Adaptive bisection until each piece's error estimate is below 'tol' scaled by its share. */
static double adapt(const ref_t *f, double a, double b, double tol, int depth) {
  double err, v = kronrod(f, a, b, &err);
  /* Below 1e-14 of the value the estimate measures rounding, which halving cannot reduce. */
  if (err <= tol || err <= 1e-14 * fabs(v) || depth > 60 || b - a < 1e-14 * (1 + fabs(a)))
    return v;
  double m = 0.5 * (a + b);
  return adapt(f, a, m, tol / 2, depth + 1) + adapt(f, m, b, tol / 2, depth + 1);
}

static int cmp_double(const void *x, const void *y) {
  double a = *(const double *)x, b = *(const double *)y;
  return a < b ? -1 : a > b;
}

/*
 * H along the reference's ray from 'near' to 'tmax'. The capsule interval comes from the
 * distance to the segment, which is convex along a line: a golden-section search for its
 * minimum, then bisection for where it equals R on either side. The integral is split there,
 * at the planes s = 0 and s = L and at the points nearest M, M + L D and the axis, so that every
 * piece is smooth and each peak of width eps sits at a piece's end.
 */
/* The end of the part of the ray that can reach the capsule, so that searches are bounded. */
static double ray_end(const ref_t *f, double tmax) {
  double w[3];
  for (int i = 0; i < 3; i++)
    w[i] = f->ray.o[i] - f->m[i];
  double end = sqrt(dot3(w, w)) + f->len + f->rad + 1;
  return tmax < end ? tmax : end;
}

/* Where on [near_, tmax] the ray comes nearest the segment (a golden-section search). */
static double nearest_t(const ref_t *f, double near_, double tmax) {
  double r, lo = near_, hi = tmax, g = (sqrt(5.0) - 1) / 2;
  for (int i = 0; i < 200 && hi - lo > 1e-13 * (1 + fabs(lo)); i++) {
    double x1 = hi - g * (hi - lo), x2 = lo + g * (hi - lo);
    if (seg_dist(f, x1, &r) < seg_dist(f, x2, &r))
      hi = x2;
    else
      lo = x1;
  }
  return 0.5 * (lo + hi);
}

static double ref_h(const ref_t *f, double near_, double tmax) {
  double r;
  tmax = ray_end(f, tmax);
  if (!(tmax > near_))
    return 0;
  double tmin = nearest_t(f, near_, tmax);
  if (seg_dist(f, tmin, &r) >= f->rad)
    return 0;
  double in = near_, out = tmax;
  if (seg_dist(f, near_, &r) > f->rad) {
    double a = near_, b = tmin;
    for (int i = 0; i < 200 && b - a > 1e-15 * (1 + fabs(a)); i++) {
      double m = 0.5 * (a + b);
      *(seg_dist(f, m, &r) > f->rad ? &a : &b) = m;
    }
    in = b;
  }
  if (seg_dist(f, tmax, &r) > f->rad) {
    double a = tmin, b = tmax;
    for (int i = 0; i < 200 && b - a > 1e-15 * (1 + fabs(a)); i++) {
      double m = 0.5 * (a + b);
      *(seg_dist(f, m, &r) > f->rad ? &b : &a) = m;
    }
    out = a;
  }

  double w[3], wl[3], k = dot3(f->ray.d, f->d), cuts[8];
  for (int i = 0; i < 3; i++)
    w[i] = f->ray.o[i] - f->m[i], wl[i] = w[i] - f->len * f->d[i];
  int n = 0;
  cuts[n++] = in;
  cuts[n++] = out;
  cuts[n++] = -dot3(f->ray.d, w);
  cuts[n++] = -dot3(f->ray.d, wl);
  if (k != 0) {
    cuts[n++] = -dot3(w, f->d) / k;
    cuts[n++] = (f->len - dot3(w, f->d)) / k;
  }
  if (1 - k * k > 1e-15)
    cuts[n++] = -(dot3(f->ray.d, w) - k * dot3(w, f->d)) / (1 - k * k);
  qsort(cuts, (size_t)n, sizeof cuts[0], cmp_double);
  double sum = 0, prev = in;
  for (int i = 0; i < n; i++) {
    double c = cuts[i] < in ? in : cuts[i] > out ? out : cuts[i];
    if (c > prev)
      sum += adapt(f, prev, c, 1e-13 * (f->a + f->b) * (1 + c - prev), 0);
    prev = c > prev ? c : prev;
  }
  return sum;
}

/* ---- Renderer helpers ---------------------------------------------------------------------- */

static render_scene_t wave_scene(rwave_t *waves, int n, rcamera_t cam) {
  render_scene_t s;
  memset(&s, 0, sizeof s);
  atomic_init(&s.refs, 1);
  s.camera = cam;
  s.light.direction[1] = 1;
  s.light.color[0] = s.light.color[1] = s.light.color[2] = 1;
  s.light.intensity = 1;
  s.light.ambient = 0.2f;
  s.background[0] = 0.05f, s.background[1] = 0.1f, s.background[2] = 0.2f;
  s.waves = waves;
  s.nwaves = n;
  s.tone_map = TONE_NONE;
  return s;
}

/* Renders 's' at 'w' x 'h' as 'aov' in 'fmt' with 'layers'; NULL (reported) on failure. */
static float *render(const render_scene_t *s, int w, int h, aov_t aov, proto_format_t fmt,
                     unsigned layers) {
  render_params_t p = {.width = (uint32_t)w,
                       .height = (uint32_t)h,
                       .format = fmt,
                       .aov = aov,
                       .layers = layers,
                       .png_level = -1};
  render_output_t out;
  char err[1024];
  int rc = renderer_render(R, s, &p, &out, err, sizeof err);
  CHECK(rc == 0, "render failed: %d %s", rc, err);
  return rc == 0 ? (float *)out.bytes : NULL;
}

/*
 * The relative error of 'got' against 'want' for a wave of strengths a and b. The denominator
 * has a floor of 1e-3 (a + b), a thousandth of the H of a path of unit length at unit distance:
 * float32 H carries absolute rounding errors of some 1e-7 of its terms, which a relative
 * measure of a vanishing H would magnify without bound (a ray ending just inside the capsule,
 * a wave of a = 0 seen only through its faint rim). Errors below 1e-7 (a + b) are invisible
 * after any clamp.
 */
static double rel_err(double got, double want, double a, double b) {
  return fabs(got - want) / fmax(fabs(want), 1e-3 * (a + b));
}

/*
 * The reference H of one wave for the pixel's ray, as the range [*lo, *hi] that float rounding
 * of the ray allows. The kernel's ray is the pixel's ray rounded to float32, a few 1e-7 off in
 * direction. That is harmless except where the ray grazes the capsule: there the chord, and H,
 * go to zero like the square root of the ray's distance from tangency, so a shift of 1e-6 in a
 * ray of length 10 can change H by 1e-3 of itself. For a ray that passes within 0.02 R of the
 * surface the range spans the reference along the ray turned by 2^-21 (16 float ulps) towards
 * and away from the segment; elsewhere it is the one value.
 */
static void ref_range(const rwave_t *w, const ray_t *ray, double near_, double tmax, double *lo,
                      double *hi) {
  ref_t f = make_ref(w, ray);
  double v = ref_h(&f, near_, tmax);
  *lo = *hi = v;
  double end = ray_end(&f, tmax);
  if (!(end > near_))
    return;
  double r, t = nearest_t(&f, near_, end), q = seg_dist(&f, t, &r);
  if (fabs(q - f.rad) > 0.02 * f.rad)
    return;
  /* e: the unit vector across the ray towards the segment's nearest point. */
  double p[3], e[3], s = 0;
  for (int i = 0; i < 3; i++)
    p[i] = f.ray.o[i] + t * f.ray.d[i] - f.m[i];
  double along = dot3(p, f.d);
  along = along < 0 ? 0 : along > f.len ? f.len : along;
  for (int i = 0; i < 3; i++)
    e[i] = along * f.d[i] - p[i];
  double k = dot3(e, f.ray.d);
  for (int i = 0; i < 3; i++)
    e[i] -= k * f.ray.d[i], s += e[i] * e[i];
  if (!(s > 0))
    return;
  for (int sign = -1; sign <= 1; sign += 2) {
    ref_t g = f;
    double n = 0;
    for (int i = 0; i < 3; i++)
      g.ray.d[i] += sign * ldexp(1, -21) * e[i] / sqrt(s), n += g.ray.d[i] * g.ray.d[i];
    for (int i = 0; i < 3; i++)
      g.ray.d[i] /= sqrt(n);
    double u = ref_h(&g, near_, tmax);
    *lo = fmin(*lo, u), *hi = fmax(*hi, u);
  }
}

typedef struct stats {
  double max_rel;    /* Against the range that the float ray allows (ref_range). */
  double max_strict; /* Against the pixel's own ray, grazing rays included. */
  int pixels, inside, bad;
} stats_t;

/*
 * Compares the wave_h AOV of the scene (one or more waves) with the reference pixel by pixel,
 * each ray ending at 'tmax' (or at the reference box 'box' when not NULL: min and max corners
 * of an axis-aligned opaque box). Accumulates into 'st'.
 */
static void compare(const render_scene_t *s, unsigned layers, const double *box, const char *what,
                    stats_t *st) {
  float *h = render(s, SIDE, SIDE, AOV_WAVE_H, PROTO_FMT_F32, layers);
  float *depth = box ? render(s, SIDE, SIDE, AOV_DEPTH, PROTO_FMT_F32, LAYER_ALL) : NULL;
  if (h == NULL || (box && depth == NULL)) {
    free(h), free(depth);
    return;
  }
  int bad = 0;
  for (int y = 0; y < SIDE; y++) {
    for (int x = 0; x < SIDE; x++) {
      ray_t ray = pixel_ray(&s->camera, SIDE, SIDE, x, y);
      double tmax = INFINITY;
      if (box) {
        double t0 = -INFINITY, t1 = INFINITY;
        for (int i = 0; i < 3; i++) {
          double ta = (box[i] - ray.o[i]) / ray.d[i], tb = (box[3 + i] - ray.o[i]) / ray.d[i];
          t0 = fmax(t0, fmin(ta, tb));
          t1 = fmin(t1, fmax(ta, tb));
        }
        if (t0 <= t1 && t1 >= s->camera.near_)
          tmax = t0 >= s->camera.near_ ? t0 : t1;
        /* Rays along the box's silhouette may hit in double and miss in float: skip them. */
        double got = depth[y * SIDE + x];
        if (isfinite(tmax) != isfinite(got) || (isfinite(tmax) && fabs(got - tmax) > 1e-3))
          continue;
      }
      double want = 0, wlo = 0, whi = 0, sa = 0, sb = 0;
      int inside = 0;
      for (int i = 0; i < s->nwaves; i++) {
        double lo, hi;
        ref_range(&s->waves[i], &ray, s->camera.near_, tmax, &lo, &hi);
        ref_t f = make_ref(&s->waves[i], &ray);
        double v = ref_h(&f, s->camera.near_, tmax);
        want += v, wlo += lo, whi += hi;
        inside |= v > 0;
        sa += s->waves[i].a, sb += s->waves[i].b;
      }
      double got = h[y * SIDE + x];
      double near_want = got < wlo ? wlo : got > whi ? whi : got;
      double e = rel_err(got, near_want, sa, sb);
      st->max_strict = fmax(st->max_strict, rel_err(got, want, sa, sb));
      st->pixels++;
      st->inside += inside;
      if (e > st->max_rel)
        st->max_rel = e;
      /* Outside every capsule H is exactly zero. */
      int ok = e <= MAX_REL && (want > 0 || got == 0);
      if (!ok && getenv("DIAG")) {
        for (int i = 0; i < s->nwaves; i++) {
          ref_t f = make_ref(&s->waves[i], &ray);
          double best = 1e300, r, bt = 0;
          for (double t = 0; t < 100; t += 1e-3) {
            double q = seg_dist(&f, t, &r);
            if (q < best)
              best = q, bt = t;
          }
          fprintf(stderr, "   wave %d: a %g b %g L %g R %g eps %g  min q %.6g at t %.4g, H %g\n", i,
                  f.a, f.b, f.len, f.rad, f.eps, best, bt, ref_h(&f, s->camera.near_, tmax));
        }
      }
      if (!ok && bad++ < 4)
        fprintf(stderr, "  %s: pixel (%d, %d): H %.9g, reference %.9g (rel %.3g)\n", what, x, y,
                got, want, e);
    }
  }
  st->bad += bad;
  CHECK(bad == 0, "%s: %d pixels differ from the quadrature", what, bad);
  free(h);
  free(depth);
}

/* ---- Tests --------------------------------------------------------------------------------- */

static uint64_t rng = 0x9e3779b97f4a7c15ull;

static double uniform(double lo, double hi) {
  rng ^= rng << 13, rng ^= rng >> 7, rng ^= rng << 17;
  return lo + (hi - lo) * (double)(rng >> 11) / 9007199254740992.0;
}

static void random_unit(float d[3]) {
  double v[3], n;
  do {
    for (int i = 0; i < 3; i++)
      v[i] = uniform(-1, 1);
    n = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  } while (n < 0.1 || n > 1);
  for (int i = 0; i < 3; i++)
    d[i] = (float)(v[i] / n);
}

static rwave_t random_wave(void) {
  rwave_t w = {.a = (float)uniform(0.1, 5),
               .b = (float)uniform(0, 5),
               .length = uniform(0, 1) < 0.2 ? 0.0f : (float)uniform(0, 8),
               .radius = (float)uniform(0.5, 5),
               .softening = (float)exp(uniform(log(0.02), log(1.5))),
               .clamp = 10,
               .color = {1, 1, 1}};
  for (int i = 0; i < 3; i++)
    w.center[i] = (float)uniform(-5, 5);
  random_unit(w.direction);
  return w;
}

/* A camera at 'dist' from a point near the wave's middle, looking at it. */
static rcamera_t camera_at(const rwave_t *w, double dist, double fov) {
  rcamera_t c = {.up = {0, 1, 0}, .fov_y = (float)fov, .near_ = 0.01f, .far_ = 1000};
  float dir[3];
  random_unit(dir);
  double along = uniform(0, w->length);
  for (int i = 0; i < 3; i++) {
    c.target[i] = (float)(w->center[i] + along * w->direction[i] + uniform(-0.5, 0.5));
    c.eye[i] = (float)(c.target[i] + dist * dir[i]);
  }
  return c;
}

static void test_random(void) {
  stats_t st = {0};
  for (int i = 0; i < 60; i++) {
    rwave_t w[3];
    int n = i % 5 == 4 ? 3 : 1;
    for (int k = 0; k < n; k++)
      w[k] = random_wave();
    /* Some cameras start inside the capsule; most look at it from outside. */
    double dist = i % 6 == 5 ? uniform(0, 0.5) * w[0].radius : uniform(1.5, 8) * w[0].radius;
    render_scene_t s = wave_scene(w, n, camera_at(&w[0], dist, uniform(20, 90)));
    char what[64];
    snprintf(what, sizeof what, "random case %d", i);
    compare(&s, LAYER_ALL, NULL, what, &st);
  }
  printf("random waves: %d pixels (%d inside a capsule), max relative error %.3g (%.3g against "
         "the exact pixel ray, grazing rays included)\n",
         st.pixels, st.inside, st.max_rel, st.max_strict);
  CHECK(st.inside > st.pixels / 4, "only %d of %d pixels saw a wave", st.inside, st.pixels);
}

static void test_degenerate(void) {
  stats_t st = {0};
  rwave_t w = {.center = {0.5f, -0.25f, 1},
               .direction = {0, 0, -1},
               .a = 1,
               .b = 2,
               .length = 6,
               .radius = 1.5f,
               .softening = 0.1f,
               .clamp = 10,
               .color = {1, 1, 1}};
  /* Looking down the axis, the middle ray parallel to it at 0.2 from it, from behind M, and
   * from in front of the far end; then exactly along the axis. */
  rcamera_t c = {.eye = {0.7f, -0.25f, 4},
                 .target = {0.7f, -0.25f, 0},
                 .up = {0, 1, 0},
                 .fov_y = 20,
                 .near_ = 0.01f,
                 .far_ = 100};
  render_scene_t s = wave_scene(&w, 1, c);
  compare(&s, LAYER_ALL, NULL, "parallel to the axis, from behind", &st);
  s.camera.eye[2] = -9, s.camera.target[2] = -5;
  compare(&s, LAYER_ALL, NULL, "parallel to the axis, from beyond", &st);
  s.camera.eye[0] = s.camera.target[0] = 0.5f;
  compare(&s, LAYER_ALL, NULL, "along the axis", &st);

  /* The eye inside the capsule: in the beam, and in the sphere about M. */
  s.camera = c;
  s.camera.eye[0] = 0.9f, s.camera.eye[2] = -2;
  s.camera.target[0] = 3, s.camera.target[1] = 1, s.camera.target[2] = -1;
  compare(&s, LAYER_ALL, NULL, "eye inside the beam", &st);
  s.camera.eye[0] = 0.6f, s.camera.eye[2] = 1.4f;
  compare(&s, LAYER_ALL, NULL, "eye inside the sphere", &st);

  /* L = 0: the beam term is a second sphere term about M. */
  rwave_t w0 = w;
  w0.length = 0;
  s = wave_scene(&w0, 1, c);
  s.camera.eye[0] = 3, s.camera.eye[1] = 1, s.camera.eye[2] = 4;
  s.camera.target[0] = 0.5f, s.camera.target[1] = -0.25f, s.camera.target[2] = 1;
  compare(&s, LAYER_ALL, NULL, "L = 0, middle ray through M", &st);
  {
    /* The same as a wave of sphere strength a + b and no beam. */
    float *h0 = render(&s, SIDE, SIDE, AOV_WAVE_H, PROTO_FMT_F32, LAYER_ALL);
    rwave_t w1 = w0;
    w1.a = w0.a + w0.b, w1.b = 0;
    render_scene_t s1 = s;
    s1.waves = &w1;
    float *h1 = render(&s1, SIDE, SIDE, AOV_WAVE_H, PROTO_FMT_F32, LAYER_ALL);
    double worst = 0;
    for (int i = 0; h0 && h1 && i < SIDE * SIDE; i++)
      worst = fmax(worst, rel_err(h0[i], h1[i], w1.a, 0));
    CHECK(h0 && h1 && worst <= MAX_REL, "L = 0 differs from a sphere of a + b by %.3g", worst);
    free(h0), free(h1);
  }

  /* Rays through M and through the far end with a tiny softening: finite, and exact. */
  rwave_t ws = w;
  ws.softening = 0.005f;
  s = wave_scene(&ws, 1, c);
  s.camera.eye[0] = -3, s.camera.eye[1] = 2, s.camera.eye[2] = 3;
  s.camera.target[0] = 0.5f, s.camera.target[1] = -0.25f, s.camera.target[2] = 1;
  compare(&s, LAYER_ALL, NULL, "middle ray through M", &st);
  float *h = render(&s, SIDE, SIDE, AOV_WAVE_H, PROTO_FMT_F32, LAYER_ALL);
  CHECK(h && isfinite(h[SIDE * SIDE / 2]) && h[SIDE * SIDE / 2] > 0, "H through M: %g",
        h ? h[SIDE * SIDE / 2] : -1.0);
  free(h);
  s.camera.target[2] = -5;
  compare(&s, LAYER_ALL, NULL, "middle ray through M + L D", &st);
  /* A ray crossing the axis between the planes. */
  s.camera.target[2] = -2;
  compare(&s, LAYER_ALL, NULL, "middle ray across the axis", &st);

  /* Rays grazing the capsule: the image spans its silhouette, rays on both sides of it. */
  s = wave_scene(&w, 1, c);
  s.camera.eye[0] = 8, s.camera.eye[2] = -2;
  s.camera.target[0] = 0.5f, s.camera.target[1] = -0.25f + 1.5f, s.camera.target[2] = -2;
  s.camera.fov_y = 2;
  compare(&s, LAYER_ALL, NULL, "grazing the cylinder", &st);
  s.camera.eye[0] = 0.5f, s.camera.eye[1] = 9, s.camera.eye[2] = 1 + 1.5f;
  s.camera.target[0] = 0.5f, s.camera.target[1] = -0.25f, s.camera.target[2] = 1 + 1.5f;
  s.camera.up[1] = 0, s.camera.up[2] = 1;
  compare(&s, LAYER_ALL, NULL, "grazing the sphere about M", &st);

  printf("degenerate cases: %d pixels (%d inside), max relative error %.3g (%.3g against the "
         "exact pixel ray)\n",
         st.pixels, st.inside, st.max_rel, st.max_strict);
}

/* An opaque box between the eye and the wave ends the integral at its surface. */
static void test_occlusion(void) {
  stats_t st = {0};
  rwave_t w = {.center = {0, 0, 0},
               .direction = {1, 0, 0},
               .a = 2,
               .b = 1,
               .length = 3,
               .radius = 2.5f,
               .softening = 0.2f,
               .clamp = 10,
               .color = {1, 1, 1}};
  rcamera_t c = {.eye = {1, 0.5f, 8},
                 .target = {1, 0, 0},
                 .up = {0, 1, 0},
                 .fov_y = 40,
                 .near_ = 0.01f,
                 .far_ = 100};
  /* The box reaches into the capsule, so some rays end inside it. */
  robject_t box = {.shape = SHAPE_BOX,
                   .position = {0.5f, -0.5f, 1.5f},
                   .scale = {2, 2, 2},
                   .color = {0.5f, 0.5f, 0.5f}};
  double bounds[6] = {-0.5, -1.5, 0.5, 1.5, 0.5, 2.5};
  render_scene_t s = wave_scene(&w, 1, c);
  s.objects = &box;
  s.nobjects = 1;
  compare(&s, LAYER_ALL, bounds, "box cutting the wave", &st);
  /* Without the objects layer nothing is opaque: the whole wave counts. */
  compare(&s, LAYER_WAVES, NULL, "box hidden", &st);
  printf("occlusion: %d pixels, max relative error %.3g\n", st.pixels, st.max_rel);

  /* The box really cut something: H differs between the two. */
  float *cut = render(&s, SIDE, SIDE, AOV_WAVE_H, PROTO_FMT_F32, LAYER_ALL);
  float *whole = render(&s, SIDE, SIDE, AOV_WAVE_H, PROTO_FMT_F32, LAYER_WAVES);
  int less = 0;
  for (int i = 0; cut && whole && i < SIDE * SIDE; i++)
    less += cut[i] < whole[i] * 0.99f;
  CHECK(less > SIDE * SIDE / 10, "the box cut only %d pixels", less);
  free(cut), free(whole);
}

/* The brightness of a wave: smoothstep of min(H, c) / c (kernels/waves.cl, wave_glow). */
static double glow(double h, double c) {
  double t = fmin(h, c) / c;
  return t * t * (3 - 2 * t);
}

/* The beauty image is the objects' image plus glow(H) times the colour, before the tone map;
 * the wave_h AOV sums the waves unclamped. */
static void test_compositing(void) {
  rwave_t w[2] = {{.center = {0, 0, 0},
                   .direction = {1, 0, 0},
                   .a = 1,
                   .b = 0.5f,
                   .length = 2,
                   .radius = 2,
                   .softening = 0.1f,
                   .clamp = 6,
                   .color = {1, 0.5f, 0.25f}},
                  {.center = {0.5f, 0.5f, 0},
                   .direction = {0, 1, 0},
                   .a = 0.5f,
                   .b = 0.5f,
                   .length = 1,
                   .radius = 1.5f,
                   .softening = 0.3f,
                   .clamp = 2,
                   .color = {0.2f, 0.4f, 1}}};
  rcamera_t c = {.eye = {1, 0.5f, 6},
                 .target = {1, 0.3f, 0},
                 .up = {0, 1, 0},
                 .fov_y = 50,
                 .near_ = 0.01f,
                 .far_ = 100};
  robject_t ball = {.shape = SHAPE_SPHERE,
                    .position = {0.3f, 0.2f, -0.5f},
                    .scale = {1.5f, 1.5f, 1.5f},
                    .color = {0.8f, 0.7f, 0.6f}};
  render_scene_t s = wave_scene(w, 2, c);
  s.objects = &ball;
  s.nobjects = 1;
  s.exposure = 0.5f;
  s.tone_map = TONE_ACES;
  float *base = render(&s, SIDE, SIDE, AOV_BEAUTY, PROTO_FMT_RGBAF32, LAYER_OBJECTS);
  float *lit = render(&s, SIDE, SIDE, AOV_BEAUTY, PROTO_FMT_RGBAF32, LAYER_ALL);
  float *both = render(&s, SIDE, SIDE, AOV_WAVE_H, PROTO_FMT_F32, LAYER_ALL);
  float *h[2];
  for (int k = 0; k < 2; k++) {
    render_scene_t one = s;
    one.waves = &w[k], one.nwaves = 1;
    h[k] = render(&one, SIDE, SIDE, AOV_WAVE_H, PROTO_FMT_F32, LAYER_ALL);
  }
  if (!base || !lit || !both || !h[0] || !h[1])
    goto done;
  int bad = 0, clamped = 0, glowing = 0;
  for (int i = 0; i < SIDE * SIDE; i++) {
    double sum = h[0][i] + h[1][i];
    if (fabs(both[i] - sum) > 1e-5 * fmax(sum, 1) && bad++ < 4)
      fprintf(stderr, "  pixel %d: wave_h %.7g, sum of the waves %.7g\n", i, both[i], sum);
    for (int ch = 0; ch < 3; ch++) {
      double want = base[4 * i + ch];
      for (int k = 0; k < 2; k++)
        want += glow(h[k][i], w[k].clamp) * w[k].color[ch];
      if (fabs(lit[4 * i + ch] - want) > 1e-5 * fmax(want, 1) && bad++ < 4)
        fprintf(stderr, "  pixel %d channel %d: %.7g, objects + glow %.7g\n", i, ch,
                lit[4 * i + ch], want);
    }
    clamped += h[0][i] > w[0].clamp;
    glowing += h[0][i] > 0 && h[0][i] < w[0].clamp;
    if (lit[4 * i + 3] != 1.0f && bad++ < 4)
      fprintf(stderr, "  pixel %d: alpha %g over an opaque background\n", i, lit[4 * i + 3]);
  }
  CHECK(bad == 0, "%d beauty values differ from objects + glow(H) * colour", bad);
  CHECK(clamped > 0 && glowing > 0,
        "the test image should hold clamped (%d) and unclamped (%d) "
        "glow",
        clamped, glowing);
done:
  free(base), free(lit), free(both), free(h[0]), free(h[1]);
}

/* The 8-bit value of linear 'x' under 'op' and the exact sRGB curve, in double. */
static int ref_byte(double x, tone_map_t op) {
  x = fmax(x, 0);
  if (op == TONE_REINHARD)
    x = x / (1 + x);
  else if (op == TONE_ACES)
    x = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14);
  x = fmin(x, 1);
  x = x <= 0.0031308 ? 12.92 * x : 1.055 * pow(x, 1 / 2.4) - 0.055;
  return (int)floor(x * 255 + 0.5);
}

/* Renders an 8-bit frame of 's' with 'layers'; the bytes (NULL, reported, on failure) and in
 * 'names' the passes it reported, comma-separated. */
static unsigned char *render_rgba8(const render_scene_t *s, int w, int h, unsigned layers,
                                   char *names, size_t len) {
  render_params_t p = {.width = (uint32_t)w,
                       .height = (uint32_t)h,
                       .format = PROTO_FMT_RGBA8,
                       .layers = layers,
                       .png_level = -1};
  render_output_t out;
  char err[1024];
  int rc = renderer_render(R, s, &p, &out, err, sizeof err);
  CHECK(rc == 0, "render failed: %d %s", rc, err);
  names[0] = '\0';
  for (int i = 0; rc == 0 && i < out.npasses; i++)
    snprintf(names + strlen(names), len - strlen(names), "%s%s", i ? "," : "", out.passes[i].name);
  return rc == 0 ? out.bytes : NULL;
}

/*
 * An 8-bit frame with waves is tone-mapped by the waves pass itself (no "tonemap" pass), and
 * without objects to draw the objects kernel does not run; the bytes must still be the tone
 * map of the linear frame (rgbaf32, which keeps the separate passes) for every operator, with
 * and without objects, over an opaque and a transparent background, on a frame whose width
 * leaves padding. A frame whose waves are all unusable is exactly the background of the
 * separate tone-map pass.
 */
static void test_fused_tonemap(void) {
  enum { FW = 75, FH = 41 };
  rwave_t w[2] = {{.center = {0, 0, 0},
                   .direction = {1, 0, 0},
                   .a = 1,
                   .b = 0.5f,
                   .length = 2,
                   .radius = 2,
                   .softening = 0.1f,
                   .clamp = 6,
                   .color = {1, 0.5f, 0.25f}},
                  {.center = {0.5f, 0.5f, 0},
                   .direction = {0, 1, 0},
                   .a = 0.5f,
                   .b = 0.5f,
                   .length = 1,
                   .radius = 1.5f,
                   .softening = 0.3f,
                   .clamp = 2,
                   .color = {0.2f, 0.4f, 1}}};
  rcamera_t c = {.eye = {1, 0.5f, 6},
                 .target = {1, 0.3f, 0},
                 .up = {0, 1, 0},
                 .fov_y = 50,
                 .near_ = 0.01f,
                 .far_ = 100};
  robject_t ball = {.shape = SHAPE_SPHERE,
                    .position = {0.3f, 0.2f, -0.5f},
                    .scale = {1.5f, 1.5f, 1.5f},
                    .color = {0.8f, 0.7f, 0.6f}};
  tone_map_t ops[3] = {TONE_NONE, TONE_REINHARD, TONE_ACES};
  float exposures[3] = {-0.5f, 0.7f, 0};
  char names[256];
  for (int k = 0; k < 3; k++) {
    for (int objs = 0; objs < 2; objs++) {
      render_scene_t s = wave_scene(w, 2, c);
      s.objects = objs ? &ball : NULL;
      s.nobjects = objs;
      s.tone_map = ops[k];
      s.exposure = exposures[k];
      s.transparent_background = k == 1;
      float *lin = render(&s, FW, FH, AOV_BEAUTY, PROTO_FMT_RGBAF32, LAYER_ALL);
      unsigned char *px = render_rgba8(&s, FW, FH, LAYER_ALL, names, sizeof names);
      CHECK(px == NULL || strcmp(names, "objects,waves,readback") == 0,
            "8-bit frame with waves has passes %s", names);
      if (lin && px) {
        int off = 0, worst = 0, glowing = 0;
        double scale = pow(2, s.exposure);
        for (int i = 0; i < FW * FH * 4; i++) {
          int want = i % 4 == 3 ? (int)floor(fmin(fmax(lin[i], 0), 1) * 255 + 0.5)
                                : ref_byte(lin[i] * scale, s.tone_map);
          int d = abs(want - px[i]);
          off += d != 0;
          worst = d > worst ? d : worst;
          glowing += !objs && i % 4 != 3 && px[i - i % 4 + 3] == 0 && px[i] > 0;
        }
        CHECK(worst <= 1 && off < FW * FH * 4 / 100,
              "tone map %d, objects %d: %d bytes off the linear frame's, worst by %d", k, objs, off,
              worst);
        /* Glow hides nothing: over a transparent background it is colour at alpha 0, which
         * composites as light added to what lies behind (premultiplied). */
        CHECK(k != 1 || objs || glowing > 0, "glow over a transparent background keeps alpha 0");
      }
      free(lin);
      free(px);
    }
  }

  /* Unusable waves (the kernel is given none): the fused pass is only the tone map. */
  rwave_t bad = w[0];
  bad.radius = 0;
  render_scene_t s = wave_scene(&bad, 1, c);
  s.tone_map = TONE_ACES;
  s.exposure = 0.3f;
  char names_bg[256];
  unsigned char *fused = render_rgba8(&s, FW, FH, LAYER_ALL, names, sizeof names);
  unsigned char *plain = render_rgba8(&s, FW, FH, LAYER_OBJECTS, names_bg, sizeof names_bg);
  CHECK(fused == NULL || strcmp(names, "objects,tonemap,readback") == 0,
        "frame without usable waves has passes %s", names);
  CHECK(plain == NULL || strcmp(names_bg, "objects,tonemap,readback") == 0,
        "frame without waves has passes %s", names_bg);
  CHECK(fused && plain && memcmp(fused, plain, 4 * FW * FH) == 0,
        "background tone-mapped in the waves pass differs from the tone-map pass");
  free(fused);
  free(plain);
}

/* The ray march of the bench converges to the closed form. */
static void test_march(void) {
  rwave_t w = {.center = {0, 0, 0},
               .direction = {1, 0, 0},
               .a = 1,
               .b = 1,
               .length = 2,
               .radius = 2,
               .softening = 0.5f,
               .clamp = 10,
               .color = {1, 1, 1}};
  rcamera_t c = {.eye = {1, 1, 6},
                 .target = {1, 0, 0},
                 .up = {0, 1, 0},
                 .fov_y = 40,
                 .near_ = 0.01f,
                 .far_ = 100};
  render_scene_t s = wave_scene(&w, 1, c);
  float *exact = render(&s, SIDE, SIDE, AOV_WAVE_H, PROTO_FMT_F32, LAYER_ALL);
  render_params_t p = {.width = SIDE,
                       .height = SIDE,
                       .format = PROTO_FMT_F32,
                       .aov = AOV_WAVE_H,
                       .layers = LAYER_ALL,
                       .march_samples = 4000};
  render_output_t out;
  char err[1024];
  int rc = renderer_render(R, &s, &p, &out, err, sizeof err);
  CHECK(rc == 0, "march: %s", err);
  if (rc == 0 && exact) {
    const float *m = (const float *)out.bytes;
    double worst = 0;
    for (int i = 0; i < SIDE * SIDE; i++)
      worst = fmax(worst, rel_err(m[i], exact[i], w.a, w.b));
    CHECK(worst < 1e-3, "4000-sample march differs from the closed form by %.3g", worst);
    free(out.bytes);
  }
  free(exact);
}

int main(void) {
  char err[8192];
  /* VOLFX_TEST_SEED picks other random cases; the default keeps runs repeatable. */
  const char *seed = getenv("VOLFX_TEST_SEED");
  if (seed && strtoull(seed, NULL, 0) != 0)
    rng = strtoull(seed, NULL, 0);
  if (renderer_create(NULL, &R, err, sizeof err) != 0) {
    fprintf(stderr, "renderer_create: %s\n", err);
    return 1;
  }
  test_random();
  test_degenerate();
  test_occlusion();
  test_compositing();
  test_fused_tonemap();
  test_march();
  renderer_destroy(R);
  printf("%d checks, %d failed\n", checks, failures);
  return failures != 0;
}
