/*
 * Tests of the fluid pass (SPEC §5.2: particles as metaballs, P(r) = (1 - r/h)^2, surface at
 * sqrt(sum P) = T) against references computed here in double: a lone particle's sphere of
 * radius h(1 - T) (depth and silhouette); two particles' neck, solved on the mid-plane by
 * bisection; and a random cloud compared pixel by pixel with a brute-force ray march that
 * samples every ray at h/200 and bisects. Then depth testing against an opaque box, the layer
 * switch, and the water's colour. Scenes are render_scene_t structs. Exits non-zero on any
 * failure.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "check.h"
#include "pixel_ray.h"
#include "render.h"

#define H 0.61
#define T 0.765625

static renderer_t *R;
static uint64_t rng = 0x9e3779b97f4a7c15ull;

/* Uniform in [0, 1), xorshift64*. */
static double uniform(void) {
  rng ^= rng >> 12, rng ^= rng << 25, rng ^= rng >> 27;
  return (double)((rng * 0x2545f4914f6cdd1dull) >> 11) / 9007199254740992.0;
}

/* The distance from 'p' to the line of 'r', and the ray parameter of the closest point. */
static double line_distance(const ray_t *r, const float *p, double *along) {
  double w[3] = {p[0] - r->o[0], p[1] - r->o[1], p[2] - r->o[2]};
  double b = dot3(w, r->d), c2 = dot3(w, w) - b * b;
  if (along)
    *along = b;
  return sqrt(c2 > 0 ? c2 : 0);
}

/* A scene with no objects, a grey background and the particles 'pos' (n of them). */
static render_scene_t fluid_scene(const float *pos, uint32_t n, float h) {
  render_scene_t s;
  memset(&s, 0, sizeof s);
  atomic_init(&s.refs, 1);
  s.camera = (rcamera_t){.eye = {0, 0, 3},
                         .target = {0, 0, 0},
                         .up = {0, 1, 0},
                         .fov_y = 10,
                         .near_ = 0.01f,
                         .far_ = 100};
  s.background[0] = 0.3f, s.background[1] = 0.4f, s.background[2] = 0.5f;
  s.light.direction[0] = 0.3f, s.light.direction[1] = 0.9f, s.light.direction[2] = 0.3f;
  s.light.color[0] = s.light.color[1] = s.light.color[2] = 1;
  s.light.intensity = 2;
  s.light.ambient = 0.2f;
  s.tone_map = TONE_NONE;
  s.fluid = (rfluid_t){.count = n,
                       .positions = pos,
                       .h = h,
                       .threshold = (float)T,
                       .color = {0.6f, 0.85f, 0.95f},
                       .ior = 1.33f,
                       .roughness = 0.1f};
  return s;
}

/* Renders and returns the bytes (caller frees), or NULL after reporting the error. */
static void *render(const render_scene_t *s, int w, int h, proto_format_t fmt, aov_t aov,
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
  return rc == 0 ? out.bytes : NULL;
}

static float *render_depth(const render_scene_t *s, int w, int h, unsigned layers) {
  return render(s, w, h, PROTO_FMT_F32, AOV_DEPTH, layers);
}

/* ---- A lone particle ----------------------------------------------------------------------- */

#define SIDE 65 /* Odd, so the middle pixel's ray is the camera's forward direction. */

/*
 * One particle's surface is the sphere of radius h(1 - T) about it: the depth of every pixel
 * well inside the disk equals the sphere's near intersection (within 1e-3 relative; the
 * centre's is |eye - p| - h(1 - T)), pixels whose ray passes closer than h(1 - T) hit and
 * farther miss, except within one pixel's width of the edge.
 */
static void test_lone(void) {
  static const float p[3] = {0.05f, -0.03f, 0.02f};
  render_scene_t s = fluid_scene(p, 1, (float)H);
  s.camera.target[0] = p[0], s.camera.target[1] = p[1], s.camera.target[2] = p[2];
  float *d = render_depth(&s, SIDE, SIDE, LAYER_ALL);
  if (d == NULL)
    return;
  double rad = H * (1 - T), dist = 0;
  for (int i = 0; i < 3; i++)
    dist += ((double)s.camera.eye[i] - p[i]) * ((double)s.camera.eye[i] - p[i]);
  dist = sqrt(dist);
  double centre = d[(SIDE / 2) * SIDE + SIDE / 2], want = dist - rad;
  CHECK(fabs(centre - want) <= 1e-3 * want, "centre depth %.7f, want %.7f", centre, want);
  /* One pixel spans this much across at the particle's distance. */
  double pixel = 2 * tan(s.camera.fov_y * M_PI / 360) / SIDE * dist;
  int hits = 0, bad = 0, bad_depth = 0;
  for (int y = 0; y < SIDE; y++) {
    for (int x = 0; x < SIDE; x++) {
      ray_t r = pixel_ray(&s.camera, SIDE, SIDE, x, y);
      double along, miss = line_distance(&r, p, &along);
      float got = d[y * SIDE + x];
      int hit = isfinite(got);
      hits += hit;
      if (miss < rad - pixel || miss > rad + pixel)
        bad += hit != (miss < rad);
      if (hit && miss < 0.9 * rad) {
        double t = along - sqrt(rad * rad - miss * miss);
        bad_depth += !(fabs(got - t) <= 1e-3 * t);
      }
    }
  }
  double disk = M_PI * (rad / pixel) * (rad / pixel);
  CHECK(bad == 0, "%d pixels on the wrong side of the silhouette", bad);
  CHECK(bad_depth == 0, "%d pixels off the sphere's depth", bad_depth);
  CHECK(fabs(hits - disk) < 2 * M_PI * rad / pixel + 4, "%d pixels hit, the disk covers %.1f", hits,
        disk);
  free(d);
}

/* ---- Two particles ------------------------------------------------------------------------- */

/* The field of 'n' particles at 'q' in double, sum of (1 - r/h)^2 over r < h. */
static double field(const float *pos, int n, double h, const double q[3]) {
  double f = 0;
  for (int j = 0; j < n; j++) {
    double dx = q[0] - pos[3 * j], dy = q[1] - pos[3 * j + 1], dz = q[2] - pos[3 * j + 2];
    double r = sqrt(dx * dx + dy * dy + dz * dz);
    if (r < h)
      f += (1 - r / h) * (1 - r / h);
  }
  return f;
}

/*
 * Two particles 0.4 apart on the x axis merge (their field at the midpoint is above T^2). On
 * the mid-plane the surface is a circle about the axis whose radius rho is solved here along
 * the line x = 0, z = 0 by bisection in double. The camera looks along -z at the midpoint, so
 * the middle pixel sees the neck at depth |eye| - rho, and the middle column's rays, which stay
 * in the mid-plane, hit exactly when they pass closer than rho to the axis.
 */
static void test_neck(void) {
  static const float p[6] = {-0.2f, 0, 0, 0.2f, 0, 0};
  double lo = 0, hi = H;
  for (int i = 0; i < 200; i++) {
    double mid = 0.5 * (lo + hi), q[3] = {0, mid, 0};
    if (sqrt(field(p, 2, H, q)) >= T)
      lo = mid;
    else
      hi = mid;
  }
  double rho = lo;
  render_scene_t s = fluid_scene(p, 2, (float)H);
  float *d = render_depth(&s, SIDE, SIDE, LAYER_ALL);
  if (d == NULL)
    return;
  double got = 3 - d[(SIDE / 2) * SIDE + SIDE / 2];
  CHECK(rho > 0.05 && fabs(got - rho) <= 2e-4, "neck radius %.6f, solved %.6f", got, rho);
  double pixel = 2 * tan(s.camera.fov_y * M_PI / 360) / SIDE * 3;
  int bad = 0, hits = 0;
  static const float axis[3] = {0, 0, 0};
  for (int y = 0; y < SIDE; y++) {
    ray_t r = pixel_ray(&s.camera, SIDE, SIDE, SIDE / 2, y);
    double miss = line_distance(&r, axis, NULL);
    int hit = isfinite(d[y * SIDE + SIDE / 2]);
    hits += hit;
    if (fabs(miss - rho) > pixel)
      bad += hit != (miss < rho);
  }
  CHECK(bad == 0 && hits > 4, "%d pixels of the middle column wrong (%d hit)", bad, hits);
  free(d);
}

/* ---- No holes ------------------------------------------------------------------------------ */

#define CLOUD 500
#define CW 64
#define GRAZE 1e-4 /* |I| below which a ray counts as grazing the surface (see test_cloud). */

/*
 * The reference for one ray: samples I = sqrt(F) - T every h/200 from the near distance to
 * past the last particle (F is zero beyond), over the particles within h of the ray's line,
 * and bisects the first sign change to 1e-12. Returns the distance or INFINITY, and in
 * '*peak' the largest I over the first run of samples inside the fluid (the first hit) or, on
 * a miss, over the whole ray.
 */
static double reference(const ray_t *r, const float *pos, int n, double h, double near_,
                        double *peak) {
  static float near_pos[3 * CLOUD];
  int m = 0;
  double tmax = near_;
  for (int j = 0; j < n; j++) {
    double along;
    if (line_distance(r, pos + 3 * j, &along) < h) {
      memcpy(near_pos + 3 * m++, pos + 3 * j, 3 * sizeof(float));
      tmax = fmax(tmax, along + h);
    }
  }
  double step = h / 200, prev_t = near_, prev_i = -T, hit = INFINITY;
  *peak = -T;
  for (long k = 0;; k++) {
    double t = near_ + k * step;
    if (t > tmax + step)
      break;
    double q[3] = {r->o[0] + t * r->d[0], r->o[1] + t * r->d[1], r->o[2] + t * r->d[2]};
    double i = sqrt(field(near_pos, m, h, q)) - T;
    if (isfinite(hit) && i < 0)
      break;
    *peak = fmax(*peak, i);
    if (!isfinite(hit) && i >= 0) {
      double a = prev_t, b = t;
      for (int it = 0; it < 60 && b - a > 1e-12; it++) {
        double c = 0.5 * (a + b);
        double qc[3] = {r->o[0] + c * r->d[0], r->o[1] + c * r->d[1], r->o[2] + c * r->d[2]};
        if (sqrt(field(near_pos, m, h, qc)) - T >= 0)
          b = c;
        else
          a = c;
      }
      hit = k == 0 ? t : 0.5 * (a + b);
    }
    prev_t = t, prev_i = i;
  }
  (void)prev_i;
  return hit;
}

/*
 * 500 random particles in a cube of side 2 with h = 0.25 (about one particle per h^3, so the
 * surface has blobs, necks and thin bridges) at 64x64, against the reference pixel by pixel:
 * hit or miss, and the depth within 1e-3 relative. A ray may disagree only where it grazes
 * the surface: the reference's sampling itself cannot see a graze shorter than h/200 (whose
 * I peaks far below GRAZE: I rises by about |grad I| = 1/h times the depth of penetration,
 * c^2 / 8 rho for a chord c on a surface of curvature radius rho), and the renderer's floor
 * step is h/2000. Such rays are counted, allowed, and must be rare.
 */
static void test_cloud(void) {
  static float pos[3 * CLOUD];
  for (int i = 0; i < 3 * CLOUD; i++)
    pos[i] = (float)(2 * uniform() - 1);
  double h = 0.25;
  render_scene_t s = fluid_scene(pos, CLOUD, (float)h);
  s.camera = (rcamera_t){.eye = {0.7f, 1.1f, 4.2f},
                         .target = {0, 0, 0},
                         .up = {0, 1, 0},
                         .fov_y = 36,
                         .near_ = 0.5f,
                         .far_ = 100};
  float *d = render_depth(&s, CW, CW, LAYER_ALL);
  if (d == NULL)
    return;
  int hits = 0, wrong = 0, grazes = 0;
  for (int y = 0; y < CW; y++) {
    for (int x = 0; x < CW; x++) {
      ray_t r = pixel_ray(&s.camera, CW, CW, x, y);
      double peak, want = reference(&r, pos, CLOUD, h, s.camera.near_, &peak);
      double got = d[y * CW + x];
      int agree =
          isfinite(want) ? isfinite(got) && fabs(got - want) <= 1e-3 * want : !isfinite(got);
      hits += isfinite(want);
      if (!agree && fabs(peak) < GRAZE)
        grazes++;
      else if (!agree) {
        wrong++;
        if (wrong <= 5)
          fprintf(stderr, "pixel (%d, %d): depth %.6f, reference %.6f (peak I %.2e)\n", x, y, got,
                  want, peak);
      }
    }
  }
  printf("cloud: %d of %d rays hit; %d disagree, %d of them grazing\n", hits, CW * CW,
         wrong + grazes, grazes);
  CHECK(hits > CW * CW / 4 && hits < CW * CW, "%d hits: the cloud should cover part of the view",
        hits);
  CHECK(wrong == 0, "%d rays disagree with the reference without grazing", wrong);
  CHECK(grazes <= CW * CW / 200, "%d grazing rays disagree", grazes);
  free(d);
}

/* ---- Depth test, layers, colour ------------------------------------------------------------ */

/*
 * A box between the camera and a clump of particles hides the left of it: the full depth is
 * the nearer of the box alone and the fluid alone, exactly, and the beauty image equals the
 * box-only image wherever the box is in front.
 */
static void test_depth_test(void) {
  static float p[3 * 7];
  for (int i = 0; i < 7; i++)
    p[3 * i] = 0.12f * (i - 3), p[3 * i + 1] = 0.05f * (i % 2), p[3 * i + 2] = 0;
  render_scene_t s = fluid_scene(p, 7, (float)H);
  s.camera.fov_y = 25;
  robject_t box = {.shape = SHAPE_BOX,
                   .position = {-0.5f, 0, 0.8f},
                   .scale = {1, 1, 0.2f},
                   .color = {0.8f, 0.3f, 0.2f}};
  s.objects = &box;
  s.nobjects = 1;
  float *all = render_depth(&s, SIDE, SIDE, LAYER_ALL);
  float *obj = render_depth(&s, SIDE, SIDE, LAYER_ALL & ~LAYER_FLUID);
  float *flu = render_depth(&s, SIDE, SIDE, LAYER_ALL & ~LAYER_OBJECTS);
  float *img = render(&s, SIDE, SIDE, PROTO_FMT_RGBAF32, AOV_BEAUTY, LAYER_ALL);
  float *img_obj = render(&s, SIDE, SIDE, PROTO_FMT_RGBAF32, AOV_BEAUTY, LAYER_ALL & ~LAYER_FLUID);
  if (all && obj && flu && img && img_obj) {
    int bad = 0, front = 0, behind = 0, bad_rgb = 0;
    for (int i = 0; i < SIDE * SIDE; i++) {
      float want = fminf(obj[i], flu[i]);
      bad += !(all[i] == want);
      if (obj[i] < flu[i] && isfinite(flu[i])) {
        front++;
        bad_rgb += memcmp(img + 4 * i, img_obj + 4 * i, 4 * sizeof(float)) != 0;
      }
      behind += flu[i] < obj[i];
    }
    CHECK(bad == 0, "%d pixels' depth is not the nearer of box and fluid", bad);
    CHECK(front > 20 && behind > 20, "box hides %d fluid pixels, fluid seen at %d", front, behind);
    CHECK(bad_rgb == 0, "%d pixels behind the box changed colour", bad_rgb);
  }
  free(all), free(obj), free(flu), free(img), free(img_obj);
}

/*
 * Without LAYER_FLUID the frame is exactly that of the scene without particles; with it, a
 * pixel on the fluid differs from the background and, being water over the background, is
 * neither black nor opaque grey.
 */
static void test_layers_and_colour(void) {
  static const float p[6] = {-0.05f, 0, 0, 0.05f, 0.02f, 0};
  render_scene_t s = fluid_scene(p, 2, (float)H);
  render_scene_t none = s;
  none.fluid.count = 0;
  unsigned layers = LAYER_ALL & ~LAYER_FLUID;
  float *a = render(&s, SIDE, SIDE, PROTO_FMT_RGBAF32, AOV_BEAUTY, layers);
  float *b = render(&none, SIDE, SIDE, PROTO_FMT_RGBAF32, AOV_BEAUTY, LAYER_ALL);
  float *da = render_depth(&s, SIDE, SIDE, layers);
  float *c = render(&s, SIDE, SIDE, PROTO_FMT_RGBAF32, AOV_BEAUTY, LAYER_ALL);
  if (a && b && da && c) {
    CHECK(memcmp(a, b, (size_t)SIDE * SIDE * 4 * sizeof(float)) == 0,
          "fluid drawn without LAYER_FLUID");
    int finite = 0;
    for (int i = 0; i < SIDE * SIDE; i++)
      finite += isfinite(da[i]);
    CHECK(finite == 0, "%d depth pixels without LAYER_FLUID", finite);
    const float *m = c + 4 * ((SIDE / 2) * SIDE + SIDE / 2), *bg = b;
    double diff = fabs(m[0] - bg[0]) + fabs(m[1] - bg[1]) + fabs(m[2] - bg[2]);
    CHECK(diff > 0.02 && m[0] > 0 && m[3] == 1, "fluid pixel %.3f %.3f %.3f vs background", m[0],
          m[1], m[2]);
    /* Transmission tinted towards blue-green over a background of the same hue order. */
    CHECK(m[2] > m[0], "fluid pixel %.3f %.3f %.3f is not tinted", m[0], m[1], m[2]);
  }
  free(a), free(b), free(da), free(c);
}

int main(void) {
  char err[8192];
  const char *seed = getenv("VOLFX_TEST_SEED");
  if (seed && strtoull(seed, NULL, 0) != 0)
    rng = strtoull(seed, NULL, 0);
  if (renderer_create(NULL, &R, err, sizeof err) != 0) {
    fprintf(stderr, "renderer_create: %s\n", err);
    return 1;
  }
  test_lone();
  test_neck();
  test_cloud();
  test_depth_test();
  test_layers_and_colour();
  renderer_destroy(R);
  printf("%d checks, %d failed\n", checks, failures);
  return failures != 0;
}
