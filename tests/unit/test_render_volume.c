/*
 * Tests of the volumes pass (SPEC §5.3) against references written from the definitions alone,
 * in double precision, along each pixel's ray built from SPEC §4's camera (pixel_ray.h):
 *
 * - a homogeneous box with albedo 0 before a white background shows exp(-sigma d) per pixel,
 *   d the exact length of the ray inside the box, found by the slab method;
 * - an opaque box inside the volume ends each ray's interval at its surface;
 * - a plate cutting a lit homogeneous volume at a grazing angle: every pixel matches the closed
 *   form of emission-absorption, albedo * ambient * (1 - T) + T * behind, so nothing depends on
 *   where slices would fall, and the values along a row across the cut change only as smoothly
 *   as the exact ones (no stripes);
 * - the shadow map: a thin sheet of medium under an occluder is dark behind it, lit beside it,
 *   and the pixel on the shadow's edge is in between;
 * - a mesh occluder casts the same shadow in the volume as the box it is made of;
 * - the volumes pass at half and a quarter resolution (render.volume_resolution): each pixel a
 *   blend of the exact values of its own kind around it, on the box or off it, and equal to
 *   the documented upsampling rule applied to the exact values of the low pixels;
 * - a coarse and a smooth finer grid volume with zero margins (empty space skipped) against a
 *   fine double-precision march: trilinear density with clamped edges, transmittance towards
 *   the light marched separately, Henyey-Greenstein phase; uniform grids under oblique lights
 *   against the exact light, whichever face its ray leaves by;
 * - the cloud goes through the same code as volumes[].
 * Exits non-zero on any failure.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "check.h"
#include "pixel_ray.h"
#include "render.h"

static renderer_t *R;

/* A scene with the given camera and nothing else: no light, no ambient, no tone map. */
static render_scene_t bare_scene(rcamera_t cam) {
  render_scene_t s;
  memset(&s, 0, sizeof s);
  atomic_init(&s.refs, 1);
  s.camera = cam;
  s.light.direction[1] = 1;
  s.light.color[0] = s.light.color[1] = s.light.color[2] = 1;
  s.light.shadow_map = 512;
  s.tone_map = TONE_NONE;
  return s;
}

/* Renders 'layers' of 's' at w x h as linear RGBA floats (malloc'd), or NULL. */
static float *render_f32(const render_scene_t *s, int w, int h, unsigned layers) {
  render_params_t p = {
      .width = (uint32_t)w, .height = (uint32_t)h, .format = PROTO_FMT_RGBAF32, .layers = layers};
  render_output_t out;
  char err[1024];
  if (renderer_render(R, s, &p, &out, err, sizeof err) != 0) {
    fprintf(stderr, "render: %s\n", err);
    return NULL;
  }
  return (float *)out.bytes;
}

/* The interval [t0, t1] of 'ray' inside the box [lo, hi]; 0 when it misses. */
static int slab(const ray_t *ray, const double lo[3], const double hi[3], double *t0, double *t1) {
  double a = 0, b = INFINITY;
  for (int k = 0; k < 3; k++) {
    if (ray->d[k] == 0) {
      if (ray->o[k] < lo[k] || ray->o[k] > hi[k])
        return 0;
      continue;
    }
    double u = (lo[k] - ray->o[k]) / ray->d[k], v = (hi[k] - ray->o[k]) / ray->d[k];
    a = fmax(a, fmin(u, v));
    b = fmin(b, fmax(u, v));
  }
  *t0 = a, *t1 = b;
  return a < b;
}

static density_grid_t *make_grid(uint32_t nx, uint32_t ny, uint32_t nz) {
  density_grid_t *g = calloc(1, sizeof *g);
  g->dims[0] = nx, g->dims[1] = ny, g->dims[2] = nz;
  g->data = calloc((size_t)nx * ny * nz, sizeof(float));
  atomic_init(&g->refs, 1);
  return g;
}

/* Drops the test's reference; the renderer's cache may hold another and free the grid later. */
static void free_grid(density_grid_t *g) {
  if (atomic_fetch_sub(&g->refs, 1) != 1)
    return;
  free(g->data);
  free(g);
}

static const rcamera_t oblique = {.eye = {3.1f, 2.3f, 4.7f},
                                  .target = {0.1f, 0.4f, -0.2f},
                                  .up = {0, 1, 0},
                                  .fov_y = 40,
                                  .near_ = 0.01f,
                                  .far_ = 100};

/* The homogeneous block of fog of test_transmittance and test_low_resolution (its grid 'g' one
 * voxel of density 1), and the opaque box inside it. */
static rvolume_t fog_block(density_grid_t *g) {
  return (rvolume_t){.source = VOLUME_GRID,
                     .min = {-1, -0.5f, -1.2f},
                     .max = {1.3f, 1.5f, 0.8f},
                     .density = 0.9f,
                     .samples = 7,
                     .grid = g};
}

static const robject_t fog_box = {.shape = SHAPE_BOX,
                                  .position = {0.2f, 0.4f, -0.1f},
                                  .scale = {0.8f, 0.7f, 0.9f},
                                  .color = {0.6f, 0.6f, 0.6f}};

/*
 * The exact value of 'ray' through the fog 'v' onto the box 'box' (NULL: none) lit by ambient 1
 * before a white background: the box's colour or 1, times exp(-density d) for the length d of
 * fog in front of it. '*on' says whether the ray meets the box, '*in_fog' the fog, '*graze'
 * that it only grazes the box's edge (within 1e-3, where float may go either way).
 */
static double fog_exact(const ray_t *ray, const rvolume_t *v, const robject_t *box, int *on,
                        int *in_fog, int *graze) {
  double lo[3], hi[3], blo[3] = {0}, bhi[3] = {0}, t0, t1, b0 = 0, b1 = 0;
  for (int k = 0; k < 3; k++) {
    lo[k] = v->min[k], hi[k] = v->max[k];
    if (box)
      blo[k] = box->position[k] - 0.5 * box->scale[k],
      bhi[k] = box->position[k] + 0.5 * box->scale[k];
  }
  *on = box && slab(ray, blo, bhi, &b0, &b1);
  *graze = *on && b1 - b0 < 1e-3;
  *in_fog = slab(ray, lo, hi, &t0, &t1);
  double end = *on ? b0 : INFINITY, behind = *on ? box->color[0] : 1;
  return *in_fog && t0 < end ? behind * exp(-v->density * (fmin(t1, end) - t0)) : behind;
}

/* Homogeneous box, albedo 0, white background: exp(-sigma d). Then an opaque box inside. */
static void test_transmittance(void) {
  density_grid_t *g = make_grid(1, 1, 1);
  g->data[0] = 1;
  rvolume_t v = fog_block(g);
  render_scene_t s = bare_scene(oblique);
  s.background[0] = s.background[1] = s.background[2] = 1;
  s.volumes = &v, s.nvolumes = 1;
  const int w = 48, h = 40;
  float *img = render_f32(&s, w, h, LAYER_ALL);
  CHECK(img != NULL, "render failed");
  double worst = 0;
  int inside = 0, on, in_fog, graze;
  for (int y = 0; img && y < h; y++)
    for (int x = 0; x < w; x++) {
      ray_t ray = pixel_ray(&s.camera, w, h, x, y);
      double want = fog_exact(&ray, &v, NULL, &on, &in_fog, &graze);
      inside += in_fog;
      double got = img[4 * (y * w + x)];
      worst = fmax(worst, fabs(got - want));
      CHECK(fabs(got - want) < 2e-5 + 2e-5 * want, "pixel (%d, %d): %.7f, exact exp(-sd) %.7f", x,
            y, got, want);
      CHECK(fabs(img[4 * (y * w + x) + 3] - 1) < 1e-6, "alpha %g", img[4 * (y * w + x) + 3]);
    }
  CHECK(inside > w * h / 4, "only %d pixels see the volume", inside);
  printf("transmittance: %d pixels in the volume, worst error %.2g\n", inside, worst);
  free(img);

  /* Thin segments: many samples of a thin medium make each segment's opacity 1 - exp(-x) tiny,
   * where computing it as 1 minus the exponential loses its digits (up to 2% of the light was
   * lost that way at 1024 samples). More samples may only do as well. */
  v.samples = 1024, v.density = 0.05f;
  img = render_f32(&s, w, h, LAYER_ALL);
  CHECK(img != NULL, "render failed");
  worst = 0;
  for (int y = 0; img && y < h; y++)
    for (int x = 0; x < w; x++) {
      ray_t ray = pixel_ray(&s.camera, w, h, x, y);
      double want = fog_exact(&ray, &v, NULL, &on, &in_fog, &graze);
      double got = img[4 * (y * w + x)], rel = fabs(got - want) / fmax(1 - want, 1e-3);
      worst = fmax(worst, rel);
      CHECK(rel < 2e-4, "1024 samples, pixel (%d, %d): %.7f, exact %.7f", x, y, got, want);
    }
  printf("transmittance at 1024 samples of density 0.05: worst %.2g of the light absorbed\n",
         worst);
  free(img);
  v = fog_block(g);

  /* An opaque box inside the volume, lit only by the ambient term: colour c, seen through the
   * volume from where the ray enters to the box's surface. */
  robject_t box = fog_box;
  s.objects = &box, s.nobjects = 1;
  s.light.intensity = 0;
  s.light.ambient = 1;
  img = render_f32(&s, w, h, LAYER_ALL);
  CHECK(img != NULL, "render failed");
  int hits = 0;
  worst = 0;
  for (int y = 0; img && y < h; y++)
    for (int x = 0; x < w; x++) {
      ray_t ray = pixel_ray(&s.camera, w, h, x, y);
      double want = fog_exact(&ray, &v, &box, &on, &in_fog, &graze);
      /* Pixels whose ray grazes the box's edge may go either way in float: skip them. */
      if (graze)
        continue;
      hits += on;
      double got = img[4 * (y * w + x)];
      worst = fmax(worst, fabs(got - want));
      CHECK(fabs(got - want) < 3e-5, "clipped pixel (%d, %d): %.7f, exact %.7f", x, y, got, want);
    }
  CHECK(hits > 50, "only %d pixels see the box", hits);
  printf("opaque clipping: %d pixels on the box, worst error %.2g\n", hits, worst);
  free(img);
  free_grid(g);
}

/*
 * render.volume_resolution below full: the box inside the homogeneous volume of
 * test_transmittance, its volumes pass at half and a quarter of the frame's size, against the
 * exact transmittance of each full pixel's own ray: every pixel is a blend of the exact values
 * around it of its own kind, so the box's edge pixels show the box through the fog before it,
 * not the fog beside it, and the fog beside the box shows no box.
 */
static void test_low_resolution(void) {
  density_grid_t *g = make_grid(1, 1, 1);
  g->data[0] = 1;
  rvolume_t v = fog_block(g);
  robject_t box = fog_box;
  render_scene_t s = bare_scene(oblique);
  s.background[0] = s.background[1] = s.background[2] = 1;
  s.volumes = &v, s.nvolumes = 1;
  s.objects = &box, s.nobjects = 1;
  s.light.intensity = 0;
  s.light.ambient = 1;
  const int w = 96, h = 80;
  /* The exact image, which pixels are on the box, their opaque depth and transmittance. */
  double *want = malloc(sizeof(double) * w * h), *z = malloc(sizeof(double) * w * h);
  double *trans = malloc(sizeof(double) * w * h);
  int *on = malloc(sizeof(int) * w * h), *grazes = malloc(sizeof(int) * w * h), in_fog;
  double blo[3], bhi[3];
  for (int k = 0; k < 3; k++)
    blo[k] = box.position[k] - 0.5 * box.scale[k], bhi[k] = box.position[k] + 0.5 * box.scale[k];
  for (int y = 0; y < h; y++)
    for (int x = 0; x < w; x++) {
      int i = y * w + x;
      ray_t ray = pixel_ray(&s.camera, w, h, x, y);
      want[i] = fog_exact(&ray, &v, &box, &on[i], &in_fog, &grazes[i]);
      double b0 = s.camera.far_, b1;
      if (on[i])
        slab(&ray, blo, bhi, &b0, &b1);
      z[i] = fmin(b0, s.camera.far_);
      trans[i] = want[i] / (on[i] ? box.color[0] : 1);
    }
  for (int div = 2; div <= 4; div *= 2) {
    s.volume_div = div;
    float *img = render_f32(&s, w, h, LAYER_ALL);
    CHECK(img != NULL, "render at 1/%d failed", div);
    /* Each pixel's value must lie within the exact values of the pixels around it (within
     * div + 1) that are of its kind, on the box or off it, give or take 'slack': a blend of
     * its neighbours, never of the fog beside the box for a pixel on it, or the reverse. */
    const double slack = 0.02;
    double worst = 0, edge = 0;
    int nedge = 0;
    for (int y = 0; img && y < h; y++)
      for (int x = 0; x < w; x++) {
        int i = y * w + x, r = div + 1, box_edge = 0;
        double lo_w = INFINITY, hi_w = -INFINITY;
        for (int dy = -r; dy <= r; dy++)
          for (int dx = -r; dx <= r; dx++) {
            int xx = x + dx, yy = y + dy, n = yy * w + xx;
            if (xx < 0 || yy < 0 || xx >= w || yy >= h)
              continue;
            box_edge |= on[n] != on[i];
            if (on[n] == on[i])
              lo_w = fmin(lo_w, want[n]), hi_w = fmax(hi_w, want[n]);
          }
        double got = img[4 * i], out = fmax(lo_w - got, got - hi_w);
        CHECK(out <= slack, "1/%d: pixel (%d, %d) %s: %.4f outside its kind's %.4f..%.4f", div, x,
              y, on[i] ? "on the box" : "off it", got, lo_w, hi_w);
        worst = fmax(worst, out);
        if (box_edge)
          edge = fmax(edge, fabs(got - want[i])), nedge++;
      }
    CHECK(nedge > 20, "1/%d: only %d pixels beside the box's edge", div, nedge);
    printf("volumes at 1/%d: at most %.4f outside the neighbours' range; %.4f from the exact value "
           "beside the box's edge (%d pixels)\n",
           div, worst, edge, nedge);
    /* The documented rule, applied to the exact values of the low pixels: each low pixel (i, j)
     * is full pixel (d i, d j), up to one past the frame's edge (clamped to it); a pixel blends
     * the transmittance of the four low pixels around it bilinearly over those whose depth is
     * within 5% of its own (weights renormalised), else takes the nearest in depth. Pixels where
     * the 5% test or the box's edge is too close to call in float are left out. */
    int lw = (w - 1) / div + 2, lh = (h - 1) / div + 2, checked = 0;
    double rule_worst = 0;
    for (int y = 0; img && y < h; y++)
      for (int x = 0; x < w; x++) {
        double u = x / (double)div, vv = y / (double)div;
        int i0 = (int)fmin(fmax(floor(u), 0), lw - 1), j0 = (int)fmin(fmax(floor(vv), 0), lh - 1);
        int ii[2] = {i0, i0 + 1 < lw ? i0 + 1 : lw - 1},
            jj[2] = {j0, j0 + 1 < lh ? j0 + 1 : lh - 1};
        double fx = fmin(fmax(u - i0, 0), 1), fy = fmin(fmax(vv - j0, 0), 1);
        double zi = z[y * w + x], tol = 0.05 * zi, sum = 0, acc = 0, best = INFINITY, nearest = 0;
        int doubtful = grazes[y * w + x];
        for (int b = 0; b < 2; b++)
          for (int a = 0; a < 2; a++) {
            int lx = div * ii[a], ly = div * jj[b];
            int n = (ly < h ? ly : h - 1) * w + (lx < w ? lx : w - 1);
            double dz = fabs(z[n] - zi), wgt = (a ? fx : 1 - fx) * (b ? fy : 1 - fy);
            doubtful |= grazes[n] || fabs(dz - tol) < 1e-3 * zi;
            if (dz < best)
              best = dz, nearest = trans[n];
            if (dz <= tol)
              sum += wgt, acc += wgt * trans[n];
          }
        if (doubtful)
          continue;
        double t = sum > 0 ? acc / sum : nearest;
        double ref = t * (on[y * w + x] ? box.color[0] : 1), got = img[4 * (y * w + x)];
        rule_worst = fmax(rule_worst, fabs(got - ref));
        checked++;
        CHECK(fabs(got - ref) < 1e-4, "1/%d: pixel (%d, %d) %s: %.5f, the rule gives %.5f", div, x,
              y, on[y * w + x] ? "on the box" : "off it", got, ref);
      }
    CHECK(checked > w * h * 9 / 10, "1/%d: only %d pixels checked against the rule", div, checked);
    printf("volumes at 1/%d: %d pixels within %.2g of the upsampling rule on exact values\n", div,
           checked, rule_worst);
    free(img);
  }
  free(want);
  free(z);
  free(trans);
  free(on);
  free(grazes);
  free_grid(g);
}

/* A plate cutting a homogeneous volume at a grazing angle, ambient light only. */
static void test_no_stripes(void) {
  density_grid_t *g = make_grid(1, 1, 1);
  g->data[0] = 1;
  rvolume_t v = {.source = VOLUME_GRID,
                 .min = {-3, -1, -3},
                 .max = {3, 2, 3},
                 .density = 0.45f,
                 .albedo = {0.8f, 0.8f, 0.8f},
                 .samples = 4, /* Few samples: stripes would show at once. */
                 .grid = g};
  /* A plane tilted 10 degrees about x: the rays meet it at very different depths. */
  robject_t plate = {.shape = SHAPE_PLANE,
                     .position = {0, 0.2f, 0},
                     .scale = {1, 1, 1},
                     .rotation = {10, 0, 0},
                     .color = {0.3f, 0.3f, 0.3f}};
  rcamera_t cam = {.eye = {0, 1.2f, 5.5f},
                   .target = {0, 0.3f, 0},
                   .up = {0, 1, 0},
                   .fov_y = 50,
                   .near_ = 0.01f,
                   .far_ = 100};
  render_scene_t s = bare_scene(cam);
  s.light.intensity = 0;
  s.light.ambient = 1;
  s.background[0] = 0.1f;
  s.objects = &plate, s.nobjects = 1;
  s.volumes = &v, s.nvolumes = 1;
  const int w = 64, h = 96;
  float *img = render_f32(&s, w, h, LAYER_ALL);
  CHECK(img != NULL, "render failed");
  /* The plane y = 0 rotated by 10 degrees about x, through (0, 0.2, 0): normal (0, cos, sin). */
  double rad = 10 * M_PI / 180, n[3] = {0, cos(rad), sin(rad)}, p0[3] = {0, 0.2, 0};
  double lo[3], hi[3], worst = 0;
  for (int k = 0; k < 3; k++)
    lo[k] = v.min[k], hi[k] = v.max[k];
  double *want = malloc(sizeof(double) * w * h);
  for (int y = 0; img && y < h; y++)
    for (int x = 0; x < w; x++) {
      ray_t ray = pixel_ray(&cam, w, h, x, y);
      double dn = dot3(ray.d, n), off[3] = {p0[0] - ray.o[0], p0[1] - ray.o[1], p0[2] - ray.o[2]};
      double th = dn != 0 ? dot3(off, n) / dn : INFINITY;
      if (!(th > 0) || th > cam.far_)
        th = INFINITY;
      double behind = th < INFINITY ? plate.color[0] * s.light.ambient : s.background[0];
      double t0, t1, val = behind;
      if (slab(&ray, lo, hi, &t0, &t1) && t0 < th) {
        double tr = exp(-v.density * (fmin(t1, th) - t0));
        val = v.albedo[0] * s.light.ambient * (1 - tr) + tr * behind;
      }
      want[y * w + x] = val;
      double got = img[4 * (y * w + x)];
      worst = fmax(worst, fabs(got - val));
      CHECK(fabs(got - val) < 5e-5, "pixel (%d, %d): %.6f, closed form %.6f", x, y, got, val);
    }
  /* Down the middle column the plate recedes: the steps between neighbours must follow the
   * exact ones, not jump where a sample would cross the plate. */
  double max_step = 0, max_exact = 0;
  for (int y = 1; img && y < h; y++) {
    int x = w / 2;
    double d = fabs(img[4 * (y * w + x)] - img[4 * ((y - 1) * w + x)]);
    double e = fabs(want[y * w + x] - want[(y - 1) * w + x]);
    max_step = fmax(max_step, d), max_exact = fmax(max_exact, e);
  }
  CHECK(max_step <= max_exact + 1e-4, "largest step along the column %.5f, exact %.5f", max_step,
        max_exact);
  printf("no stripes: worst error %.2g, largest step %.4f (exact %.4f)\n", worst, max_step,
         max_exact);
  free(want);
  free(img);
  free_grid(g);
}

/* A thin sheet of medium facing the camera under an occluder from straight above. */
static void test_shadow(void) {
  density_grid_t *g = make_grid(1, 1, 1);
  g->data[0] = 1;
  rvolume_t v = {.source = VOLUME_GRID,
                 .min = {-5, -2, -0.05f},
                 .max = {5, 2, 0.05f},
                 .density = 0.5f,
                 .albedo = {1, 1, 1},
                 .samples = 4,
                 .grid = g};
  /* The camera looks down -z from far away, so rays are almost parallel: the view is 1 unit
   * tall at z = 0 and pixel x's centre lies at world x = (x + 0.5 - w / 2) * pix. The
   * occluder covers x < edge, its edge on the centre of pixel 'e'. */
  const int w = 64, h = 8, e = 40;
  rcamera_t cam = {
      .eye = {0, 0, 200}, .target = {0, 0, 0}, .up = {0, 1, 0}, .near_ = 1, .far_ = 400};
  cam.fov_y = (float)(2 * atan(0.5 / 200) * 180 / M_PI);
  double pix = 1.0 / h;
  double edge = (e + 0.5 - w / 2.0) * pix;
  robject_t occ = {.shape = SHAPE_BOX,
                   .position = {(float)(edge - 50), 3, 0},
                   .scale = {100, 0.2f, 6},
                   .color = {1, 1, 1}};
  render_scene_t s = bare_scene(cam);
  s.light.intensity = 1;
  s.light.ambient = 0;
  s.light.shadow_map = 1024;
  s.objects = &occ, s.nobjects = 1;
  s.volumes = &v, s.nvolumes = 1;
  float *img = render_f32(&s, w, h, LAYER_ALL);
  CHECK(img != NULL, "render failed");
  if (!img) {
    free_grid(g);
    return;
  }
  /* Lit: the light crosses from the sheet's top down to y = 0 through the medium: about
   * exp(-0.5 * 2) of it arrives; the sheet's own opacity is 1 - exp(-0.5 * 0.1). */
  int y = h / 2;
  double a = 1 - exp(-v.density * 0.1);
  double lit = img[4 * (y * w + w - 4)], dark = img[4 * (y * w + 4)], mid = img[4 * (y * w + e)];
  double expect = a * exp(-v.density * 2.0);
  CHECK(fabs(lit - expect) < 0.15 * expect, "lit pixel %.5f, expected about %.5f", lit, expect);
  CHECK(dark < 1e-6, "a pixel behind the occluder shows %.6f", dark);
  CHECK(mid > 0.2 * lit && mid < 0.8 * lit, "the edge pixel %.5f is not between dark and lit %.5f",
        mid, lit);
  /* Across the edge the values rise monotonically (up to the rays' slight divergence). */
  for (int x = 1; x < w; x++)
    CHECK(img[4 * (y * w + x)] >= img[4 * (y * w + x - 1)] - 1e-3 * lit,
          "not monotonic at x = %d: %.7f then %.7f", x, img[4 * (y * w + x - 1)],
          img[4 * (y * w + x)]);
  printf("shadow: dark %.3g, edge %.4f, lit %.4f (expected about %.4f)\n", dark, mid, lit, expect);

  /* The same occluder as a mesh of twelve triangles: the shadow map's mesh traversal finds the
   * box's faces, so the volume shows the same shadow. */
  static const float corner[8][3] = {{-.5f, -.5f, -.5f}, {.5f, -.5f, -.5f}, {.5f, .5f, -.5f},
                                     {-.5f, .5f, -.5f},  {-.5f, -.5f, .5f}, {.5f, -.5f, .5f},
                                     {.5f, .5f, .5f},    {-.5f, .5f, .5f}};
  static const int face[12][3] = {{0, 1, 2}, {0, 2, 3}, {4, 6, 5}, {4, 7, 6}, {0, 4, 5}, {0, 5, 1},
                                  {3, 2, 6}, {3, 6, 7}, {0, 3, 7}, {0, 7, 4}, {1, 5, 6}, {1, 6, 2}};
  /* On the heap: the renderer keeps a reference to a mesh it has drawn. */
  mesh_t *cube = calloc(1, sizeof *cube);
  float *tri = malloc(12 * 9 * sizeof *tri);
  CHECK(cube && tri, "out of memory");
  if (!cube || !tri) {
    free(cube);
    free(tri);
    free(img);
    free_grid(g);
    return;
  }
  for (int t = 0; t < 12; t++)
    for (int k = 0; k < 3; k++)
      memcpy(&tri[9 * t + 3 * k], corner[face[t][k]], sizeof corner[0]);
  cube->ntri = 12;
  cube->tri = tri;
  atomic_init(&cube->refs, 1);
  robject_t as_mesh = occ;
  as_mesh.shape = SHAPE_MESH;
  as_mesh.mesh = cube;
  s.objects = &as_mesh;
  float *img2 = render_f32(&s, w, h, LAYER_ALL);
  CHECK(img2 != NULL, "render of the mesh occluder failed");
  double worst = 0;
  for (int i = 0; img2 && i < w * h; i++)
    worst = fmax(worst, fabs(img2[4 * i] - img[4 * i]));
  CHECK(img2 && worst < 0.02 * lit, "a mesh occluder's shadow differs from its box's by %.6f",
        worst);
  printf("shadow of a mesh: largest difference from the box's %.2g (lit %.4f)\n", worst, lit);
  mesh_unref(cube);
  free(img2);
  free(img);
  free_grid(g);
}

/*
 * A shadow edge slanted across the shadow map's texels: a horizontal sheet of medium lit from
 * straight above through a coarse map (64 texels over the sheet), under an occluder turned
 * 25 degrees about the vertical, seen from straight below. Where each image row crosses half
 * the lit value should lie near a straight line; a single texel per shadow test puts it on a
 * staircase of texel-sized steps (about 4 pixels here).
 */
static void test_shadow_staircase(void) {
  density_grid_t *g = make_grid(1, 1, 1);
  g->data[0] = 1;
  rvolume_t v = {.source = VOLUME_GRID,
                 .min = {-5, -0.05f, -5},
                 .max = {5, 0.05f, 5},
                 .density = 0.5f,
                 .albedo = {1, 1, 1},
                 .samples = 4,
                 .grid = g};
  const int w = 96, h = 96;
  rcamera_t cam = {.eye = {0, -200, 0}, .target = {0, 0, 0}, .up = {0, 0, 1}, .near_ = 1};
  cam.far_ = 400;
  cam.fov_y = (float)(2 * atan(2.0 / 200) * 180 / M_PI); /* 4 units across. */
  robject_t occ = {.shape = SHAPE_BOX,
                   .position = {-3.0f, 2, 0},
                   .scale = {6, 0.2f, 20},
                   .rotation = {0, 25, 0},
                   .color = {1, 1, 1}};
  render_scene_t s = bare_scene(cam);
  s.light.intensity = 1;
  s.light.ambient = 0;
  s.light.shadow_map = 64;
  s.objects = &occ, s.nobjects = 1;
  s.volumes = &v, s.nvolumes = 1;
  /* The occluder's underside, unlit, adds nothing behind the sheet. */
  float *img = render_f32(&s, w, h, LAYER_ALL);
  CHECK(img != NULL, "render failed");
  double lit = 0, xs[96], ys[96];
  int n = 0;
  for (int i = 0; img && i < w * h; i++)
    lit = fmax(lit, img[4 * i]);
  /* Each row's crossing of half the lit value, between the pixels either side. */
  for (int y = 8; img && y < h - 8; y++) {
    const float *row = img + 4 * y * w;
    for (int x = 1; x < w; x++) {
      double a = row[4 * (x - 1)] - 0.5 * lit, b = row[4 * x] - 0.5 * lit;
      if ((a < 0) != (b < 0)) {
        xs[n] = x - 1 + a / (a - b), ys[n] = y, n++;
        break;
      }
    }
  }
  CHECK(n > 60, "the edge crosses only %d rows", n);
  /* The least-squares line through the crossings, and how far they stray from it. */
  double sy = 0, sx = 0, syy = 0, sxy = 0;
  for (int i = 0; i < n; i++)
    sy += ys[i], sx += xs[i], syy += ys[i] * ys[i], sxy += xs[i] * ys[i];
  double slope = (n * sxy - sx * sy) / (n * syy - sy * sy), icpt = (sx - slope * sy) / n, rms = 0;
  for (int i = 0; i < n; i++)
    rms += pow(xs[i] - (icpt + slope * ys[i]), 2) / n;
  rms = sqrt(rms);
  CHECK(fabs(slope) > 0.3, "the edge is not slanted (slope %.3f)", slope);
  /* One texel per test strays 1.25 pixels (rms); the taps' spread across a texel 0.8. */
  CHECK(rms < 1.0, "the shadow edge strays %.3f pixels from a straight line", rms);
  printf("slanted shadow edge: %d rows within %.3f pixels (rms) of a straight line\n", n, rms);
  free(img);
  free_grid(g);
}

/*
 * Interleaved shadow tests: fog under a slatted roof, a ball inside it, seen across the shafts
 * with few samples per ray. The pixels of each 4 x 4 tile move their shadow tests by different
 * sixteenths of the tests' spacing, so that the error of the tests' steps over shaft edges
 * differs from pixel to pixel instead of drawing rings that follow the depth: against the frame
 * with 16 times the samples, the means of 4 x 4 tiles are much closer than single pixels (with
 * the tests in place in every pixel they were as far). And render.antialias 2 is the mean of
 * the frame drawn twice as large.
 */
static void test_interleaved_shadows(void) {
  density_grid_t *g = make_grid(1, 1, 1);
  g->data[0] = 1;
  rvolume_t v = {.source = VOLUME_GRID,
                 .min = {-2, 0, -2},
                 .max = {2, 2, 2},
                 .density = 0.3f,
                 .albedo = {1, 1, 1},
                 .samples = 16,
                 .grid = g};
  /* A roof over x < 0: one straight shadow edge, a plane through the fog that every ray of the
   * narrow view crosses once, at nearly the same place in its segments as its neighbours. */
  robject_t roof = {.shape = SHAPE_BOX,
                    .position = {-3, 2.6f, 0},
                    .scale = {6, 0.1f, 8},
                    .color = {0.5f, 0.5f, 0.5f}};
  rcamera_t cam = {.eye = {2.5f, 1, 4.5f},
                   .target = {-0.5f, 1, -1},
                   .up = {0, 1, 0},
                   .fov_y = 4,
                   .near_ = 0.05f,
                   .far_ = 100};
  render_scene_t s = bare_scene(cam);
  double l[3] = {-0.35, 1, -0.45}, ln = sqrt(dot3(l, l));
  for (int k = 0; k < 3; k++)
    s.light.direction[k] = (float)(l[k] / ln);
  s.light.intensity = 1;
  s.light.shadow_map = 512;
  s.objects = &roof, s.nobjects = 1;
  s.volumes = &v, s.nvolumes = 1;
  const int w = 64, h = 64;
  float *plain = render_f32(&s, w, h, LAYER_ALL);
  s.antialias = 2;
  float *aa = render_f32(&s, w, h, LAYER_ALL);
  s.antialias = 1;
  float *big = render_f32(&s, 2 * w, 2 * h, LAYER_ALL);
  v.samples = 256;
  float *ref = render_f32(&s, w, h, LAYER_ALL);
  /* The same without the roof: the difference is the shadow's part alone. */
  s.nobjects = 0;
  float *ref0 = render_f32(&s, w, h, LAYER_ALL);
  v.samples = 16;
  float *plain0 = render_f32(&s, w, h, LAYER_ALL);
  s.nobjects = 1;
  CHECK(plain && aa && ref && big && ref0 && plain0, "render failed");
  /* The error of single pixels against the 256-sample frame, and that of the means of 4 x 4
   * tiles: where neighbours make the same error (rings), the tiles' is as large. */
  double e_px = 0, e_tile = 0, off = 0;
  for (int y = 0; plain && ref && ref0 && plain0 && y < h; y++)
    for (int x = 0; x < w; x++) {
      int i = 4 * (y * w + x);
      e_px += pow((plain[i] - plain0[i]) - (ref[i] - ref0[i]), 2);
    }
  for (int ty = 0; plain && ref && ref0 && plain0 && ty < h / 4; ty++)
    for (int tx = 0; tx < w / 4; tx++) {
      double d = 0;
      for (int y = 4 * ty; y < 4 * ty + 4; y++)
        for (int x = 4 * tx; x < 4 * tx + 4; x++)
          d += ((plain[4 * (y * w + x)] - plain0[4 * (y * w + x)]) -
                (ref[4 * (y * w + x)] - ref0[4 * (y * w + x)])) /
               16;
      e_tile += d * d;
    }
  e_px = sqrt(e_px / (w * h)), e_tile = sqrt(e_tile / (w * h / 16));
  CHECK(e_px > 1e-4, "the 16-sample frame shows no shaft error to test (%.2g)", e_px);
  CHECK(e_tile < 0.35 * e_px, "4 x 4 tiles %.5f rms from 256 samples, single pixels %.5f", e_tile,
        e_px);
  /* Antialiasing by n is the mean of the frame drawn n times as large, interleaving included. */
  for (int y = 0; aa && big && y < h; y++)
    for (int x = 0; x < w; x++) {
      double mean = 0;
      for (int sy = 0; sy < 2; sy++)
        for (int sx = 0; sx < 2; sx++)
          mean += big[4 * ((2 * y + sy) * 2 * w + 2 * x + sx)] / 4;
      off = fmax(off, fabs(aa[4 * (y * w + x)] - mean));
    }
  CHECK(off < 1e-5, "antialias 2 is %.2g from the mean of the frame twice as large", off);
  printf("interleaved shadow tests: single pixels %.5f rms from the 256-sample frame, 4 x 4 "
         "tiles %.5f\n",
         e_px, e_tile);
  free(plain), free(plain0), free(ref0);
  free(aa), free(ref), free(big);
  free_grid(g);
}

/* ---- A grid volume against a fine double-precision march --------------------------------- */

typedef struct ref_vol {
  const rvolume_t *v;
  double cell[3];
} ref_vol_t;

/* Trilinear density at world point p, voxel centres at min + (i + 0.5) cell, edges clamped;
 * zero outside the box. */
static double ref_density(const ref_vol_t *rv, const double p[3]) {
  const rvolume_t *v = rv->v;
  const density_grid_t *g = v->grid;
  double c[3], f[3];
  int i0[3], i1[3];
  for (int k = 0; k < 3; k++) {
    if (p[k] < v->min[k] || p[k] > v->max[k])
      return 0;
    c[k] = (p[k] - v->min[k]) / rv->cell[k] - 0.5;
    c[k] = fmin(fmax(c[k], 0), g->dims[k] - 1.0);
    i0[k] = (int)floor(c[k]);
    i1[k] = i0[k] + 1 < (int)g->dims[k] ? i0[k] + 1 : i0[k];
    f[k] = c[k] - i0[k];
  }
  double r = 0;
  for (int k = 0; k < 8; k++) {
    int x = k & 1 ? i1[0] : i0[0], y = k & 2 ? i1[1] : i0[1], z = k & 4 ? i1[2] : i0[2];
    double wgt = (k & 1 ? f[0] : 1 - f[0]) * (k & 2 ? f[1] : 1 - f[1]) * (k & 4 ? f[2] : 1 - f[2]);
    r += wgt * g->data[((size_t)z * g->dims[1] + y) * g->dims[0] + x];
  }
  return r;
}

/* Transmittance from p towards the light l through the volume, marched finely. */
static double ref_light(const ref_vol_t *rv, const double p[3], const double l[3]) {
  double lo[3], hi[3], t0, t1;
  for (int k = 0; k < 3; k++)
    lo[k] = rv->v->min[k], hi[k] = rv->v->max[k];
  ray_t ray = {{p[0], p[1], p[2]}, {l[0], l[1], l[2]}};
  if (!slab(&ray, lo, hi, &t0, &t1))
    return 1;
  int n = 400;
  double tau = 0, dt = (t1 - t0) / n;
  for (int i = 0; i < n; i++) {
    double t = t0 + (i + 0.5) * dt, q[3] = {p[0] + t * l[0], p[1] + t * l[1], p[2] + t * l[2]};
    tau += rv->v->density * ref_density(rv, q) * dt;
  }
  return exp(-tau);
}

/*
 * Renders 's' (one grid volume 'rv', lit by s->light) at w x h and checks every pixel against a
 * fine double-precision march with the transmittance towards the light marched separately
 * (ref_light), to 'tol' of the brightest scattering and on average to 'tol_mean' of it.
 */
static void check_direct(const char *what, render_scene_t *s, const ref_vol_t *rv, int w, int h,
                         double tol, double tol_mean) {
  const rvolume_t *v = rv->v;
  double l[3] = {s->light.direction[0], s->light.direction[1], s->light.direction[2]};
  float *img = render_f32(s, w, h, LAYER_ALL);
  CHECK(img != NULL, "render failed");
  double lo[3], hi[3], worst = 0, peak = 0;
  for (int k = 0; k < 3; k++)
    lo[k] = v->min[k], hi[k] = v->max[k];
  double gg = v->phase_g;
  double *err_img = calloc(3 * w * h, sizeof(double));
  for (int y = 0; img && y < h; y++)
    for (int x = 0; x < w; x++) {
      ray_t ray = pixel_ray(&s->camera, w, h, x, y);
      double t0, t1, c[3] = {0, 0, 0}, tr = 1;
      if (slab(&ray, lo, hi, &t0, &t1)) {
        double cos_th = dot3(ray.d, l);
        double hg = 1 + gg * gg - 2 * gg * cos_th, phase = (1 - gg * gg) / (hg * sqrt(hg));
        int n = 1500;
        double dt = (t1 - t0) / n;
        for (int i = 0; i < n; i++) {
          double t = t0 + (i + 0.5) * dt;
          double p[3] = {ray.o[0] + t * ray.d[0], ray.o[1] + t * ray.d[1], ray.o[2] + t * ray.d[2]};
          double sig = v->density * ref_density(rv, p);
          if (sig <= 0)
            continue;
          double a = 1 - exp(-sig * dt), tl = ref_light(rv, p, l);
          for (int k = 0; k < 3; k++)
            c[k] += tr * a * v->albedo[k] *
                    (s->light.color[k] * s->light.intensity * tl * phase + s->light.ambient);
          tr *= 1 - a;
        }
      }
      for (int k = 0; k < 3; k++) {
        double want = c[k] + tr * s->background[k], got = img[4 * (y * w + x) + k];
        peak = fmax(peak, c[k]);
        worst = fmax(worst, fabs(got - want));
        err_img[3 * (y * w + x) + k] = fabs(got - want);
      }
    }
  double mean = 0;
  for (int i = 0; img && i < 3 * w * h; i++) {
    CHECK(err_img[i] < tol * peak, "%s: pixel %d channel %d off by %.4f (brightest %.4f)", what,
          i / 3, i % 3, err_img[i], peak);
    mean += err_img[i] / (3 * w * h);
  }
  free(err_img);
  CHECK(mean < tol_mean * peak, "%s: the direct term is off by %.4f on average (brightest %.4f)",
        what, mean, peak);
  printf("%s grid vs reference: worst error %.4f, mean %.4f (brightest scattering %.3f)\n", what,
         worst, mean, peak);
  CHECK(peak > 0.2, "%s: the volume hardly shows (%.3f)", what, peak);
  free(img);
}

static void test_grid_reference(void) {
  /* A 7x6x5 grid whose outer layer is empty, random inside. */
  density_grid_t *g = make_grid(7, 6, 5);
  uint64_t seed = 12345;
  for (uint32_t z = 1; z < 4; z++)
    for (uint32_t y = 1; y < 5; y++)
      for (uint32_t x = 1; x < 6; x++) {
        seed = seed * 6364136223846793005ull + 1442695040888963407ull;
        g->data[(z * 6 + y) * 7 + x] = (float)((seed >> 40) / (double)(1 << 24)) * 1.5f;
      }
  rvolume_t v = {.source = VOLUME_GRID,
                 .min = {-1.2f, -0.4f, -0.9f},
                 .max = {1.0f, 1.1f, 0.7f},
                 .density = 2.2f,
                 .albedo = {0.9f, 0.7f, 0.5f},
                 .samples = 256,
                 .phase_g = 0.3f,
                 .grid = g};
  ref_vol_t rv = {.v = &v};
  for (int k = 0; k < 3; k++)
    rv.cell[k] = ((double)v.max[k] - v.min[k]) / g->dims[k];
  render_scene_t s = bare_scene(oblique);
  s.background[0] = 0.2f, s.background[1] = 0.3f, s.background[2] = 0.4f;
  double l[3] = {0.3, 0.9, 0.2}, ln = sqrt(dot3(l, l));
  for (int k = 0; k < 3; k++)
    l[k] /= ln, s.light.direction[k] = (float)l[k];
  s.light.intensity = 1.5f;
  s.light.ambient = 0.25f;
  s.volumes = &v, s.nvolumes = 1;
  /* The light grid holds the transmittance towards the light at voxel centres only, swept slice
   * by slice, and this grid has 7x6x5 voxels: the direct term is checked to 8.5% of the
   * brightest scattering, and on average to 0.2% (the ambient-only case below is checked
   * tightly); a smooth 21x18x15 grid below to 3% and 0.1%. */
  const int w = 32, h = 24;
  check_direct("7x6x5", &s, &rv, w, h, 0.085, 0.002);
  double lo[3], hi[3];
  for (int k = 0; k < 3; k++)
    lo[k] = v.min[k], hi[k] = v.max[k];
  float *img;

  /* With the light off, only the ambient term: the light grid plays no part and the march must
   * match the reference closely. */
  s.light.intensity = 0;
  img = render_f32(&s, w, h, LAYER_ALL);
  CHECK(img != NULL, "render failed");
  double worst0 = 0;
  for (int y = 0; img && y < h; y++)
    for (int x = 0; x < w; x++) {
      ray_t ray = pixel_ray(&s.camera, w, h, x, y);
      double t0, t1, tau = 0;
      if (slab(&ray, lo, hi, &t0, &t1)) {
        int n = 4000;
        double dt = (t1 - t0) / n;
        for (int i = 0; i < n; i++) {
          double t = t0 + (i + 0.5) * dt;
          double p[3] = {ray.o[0] + t * ray.d[0], ray.o[1] + t * ray.d[1], ray.o[2] + t * ray.d[2]};
          tau += v.density * ref_density(&rv, p) * dt;
        }
      }
      /* Emission-absorption with a constant source: albedo * ambient * (1 - T) + T * bg. */
      double tr = exp(-tau);
      for (int k = 0; k < 3; k++) {
        double want = v.albedo[k] * s.light.ambient * (1 - tr) + tr * s.background[k];
        double got = img[4 * (y * w + x) + k];
        worst0 = fmax(worst0, fabs(got - want));
        CHECK(fabs(got - want) < 2e-3, "ambient pixel (%d, %d) channel %d: %.5f, reference %.5f", x,
              y, k, got, want);
      }
    }
  printf("grid vs reference, ambient only: worst error %.2g\n", worst0);
  free(img);

  /* The cloud is drawn by the same code: the same grid as the cloud gives the same image. */
  s.light.intensity = 1.5f;
  float *as_vol = render_f32(&s, w, h, LAYER_OBJECTS | LAYER_VOLUMES);
  s.volumes = NULL, s.nvolumes = 0;
  s.cloud = v;
  float *as_cloud = render_f32(&s, w, h, LAYER_OBJECTS | LAYER_CLOUD);
  float *off = render_f32(&s, w, h, LAYER_OBJECTS);
  CHECK(as_vol && as_cloud && off, "render failed");
  if (as_vol && as_cloud && off) {
    CHECK(memcmp(as_vol, as_cloud, sizeof(float) * 4 * w * h) == 0,
          "the cloud renders differently from the same volume");
    int bg = 1;
    for (int i = 0; i < w * h; i++)
      bg &= off[4 * i] == s.background[0];
    CHECK(bg, "without the cloud layer the cloud still shows");
  }
  free(as_vol);
  free(as_cloud);
  free(off);
  free_grid(g);

  /* A smooth 21x18x15 grid, empty outer layer, in the same box and light: finer voxels light
   * it closer to the reference (a sweep that read the wrong slice's extinction passed the
   * uniform grids of test_light_grid_oblique, and fails here). */
  const uint32_t nx = 21, ny = 18, nz = 15;
  g = make_grid(nx, ny, nz);
  for (uint32_t z = 1; z + 1 < nz; z++)
    for (uint32_t y = 1; y + 1 < ny; y++)
      for (uint32_t x = 1; x + 1 < nx; x++)
        g->data[(z * ny + y) * nx + x] =
            0.75f + 0.7f * sinf(0.9f * x + 0.4f * y) * cosf(0.7f * z - 0.5f * y);
  s.cloud.grid = NULL;
  v.grid = g;
  s.volumes = &v, s.nvolumes = 1;
  for (int k = 0; k < 3; k++)
    rv.cell[k] = ((double)v.max[k] - v.min[k]) / g->dims[k];
  check_direct("21x18x15", &s, &rv, w, h, 0.03, 0.001);
  free_grid(g);
}

/* Procedural noise: the same seed gives the same image, another seed another. */
static void test_noise(void) {
  rvolume_t v = {.source = VOLUME_NOISE,
                 .min = {-1, -0.5f, -1},
                 .max = {1, 1.5f, 1},
                 .density = 1.5f,
                 .albedo = {0.9f, 0.9f, 0.9f},
                 .samples = 16,
                 .seed = 3,
                 .noise_scale = 0.7f};
  render_scene_t s = bare_scene(oblique);
  s.light.intensity = 1;
  s.light.ambient = 0.2f;
  s.volumes = &v, s.nvolumes = 1;
  const int w = 32, h = 24;
  float *a = render_f32(&s, w, h, LAYER_ALL);
  float *b = render_f32(&s, w, h, LAYER_ALL);
  v.seed = 4;
  float *c = render_f32(&s, w, h, LAYER_ALL);
  CHECK(a && b && c, "render failed");
  if (a && b && c) {
    CHECK(memcmp(a, b, sizeof(float) * 4 * w * h) == 0, "the same seed renders differently");
    CHECK(memcmp(a, c, sizeof(float) * 4 * w * h) != 0, "another seed renders the same");
    double sum = 0;
    for (int i = 0; i < w * h; i++)
      sum += a[4 * i];
    CHECK(sum > 0.5, "the noise volume hardly shows (%.3f)", sum);
  }
  free(a);
  free(b);
  free(c);
}

/* ---- The light sweep of a grid large enough to run on two threads ------------------------- */

/*
 * A homogeneous box lit straight from above: the light grid then holds exactly
 * exp(-sigma (top - y)) at every voxel centre (the trapezoid rule is exact for a constant),
 * so the frame, with no ambient and an isotropic phase, is the sum over the kernel's own
 * samples of tr * (1 - exp(-sigma dt)) * T(p), T interpolated linearly in y between those
 * centre values and extended linearly from the two outer ones over the last half-voxels. The grid
 * has more voxels than SWEEP_THREAD_MIN (render_volume.c), so the sweep runs on two threads; a race
 * between them would show as a wrong or a changing frame.
 */
static void test_light_sweep_threads(void) {
  const uint32_t nx = 70, ny = 66, nz = 64;
  density_grid_t *g = make_grid(nx, ny, nz);
  for (size_t i = 0; i < (size_t)nx * ny * nz; i++)
    g->data[i] = 1;
  rvolume_t v = {.source = VOLUME_GRID,
                 .min = {-1, -1, -1},
                 .max = {1, 1.2f, 1},
                 .density = 1.3f,
                 .albedo = {1, 1, 1},
                 .samples = 40,
                 .grid = g};
  render_scene_t s = bare_scene(oblique);
  s.light.intensity = 1;
  s.volumes = &v, s.nvolumes = 1;
  const int w = 40, h = 32;
  float *img = render_f32(&s, w, h, LAYER_ALL), *again = render_f32(&s, w, h, LAYER_ALL);
  CHECK(img && again, "render failed");
  if (img && again)
    CHECK(memcmp(img, again, sizeof(float) * 4 * w * h) == 0, "the same frame renders twice alike");
  double lo[3], hi[3], worst = 0, peak = 0;
  for (int k = 0; k < 3; k++)
    lo[k] = v.min[k], hi[k] = v.max[k];
  double cell = (hi[1] - lo[1]) / ny, sigma = v.density;
  for (int y = 0; img && y < h; y++)
    for (int x = 0; x < w; x++) {
      ray_t ray = pixel_ray(&s.camera, w, h, x, y);
      double t0, t1, want = 0, tr = 1;
      if (slab(&ray, lo, hi, &t0, &t1)) {
        int n = v.samples;
        double dt = (t1 - t0) / n, a = 1 - exp(-sigma * dt);
        for (int i = 0; i < n; i++) {
          double py = ray.o[1] + (t0 + (i + 0.5) * dt) * ray.d[1];
          double c = fmin(fmax((py - lo[1]) / cell - 0.5, -0.5), ny - 0.5);
          int j0 = (int)fmin(fmax(c, 0), ny - 2.0), j1 = j0 + 1;
          double f = c - j0;
          double l0 = exp(-sigma * (hi[1] - (lo[1] + (j0 + 0.5) * cell)));
          double l1 = exp(-sigma * (hi[1] - (lo[1] + (j1 + 0.5) * cell)));
          want += tr * a * fmin(fmax(l0 + f * (l1 - l0), 0), 1);
          tr *= 1 - a;
        }
      }
      double got = img[4 * (y * w + x)];
      peak = fmax(peak, want);
      worst = fmax(worst, fabs(got - want));
      CHECK(fabs(got - want) < 2e-4, "pixel (%d, %d): %.6f, reference %.6f", x, y, got, want);
    }
  CHECK(peak > 0.3, "the volume hardly shows (%.3f)", peak);
  printf("light sweep on two threads: worst error %.2g (brightest %.3f)\n", worst, peak);
  free(img);
  free(again);
  free_grid(g);
}

/*
 * A uniform 32³ grid lit from oblique directions, ambient 0, isotropic phase: against single
 * scattering with the exact transmittance towards the light, exp(-sigma d) for the distance d
 * to where the light's ray leaves the box, through whichever face: 0.35-0.45% off on average,
 * the worst pixels (rays through a sliver along the box's edges) 6-7% (protocol.md). (Holding
 * the light of the outer voxel centres over the last half-voxel, as the density is, gave
 * 0.7-0.8% and 9-12%.)
 * (The sweep once let a ray that leaves through a side face run on along the outer column of
 * voxels to the far face: up to 79% too dark there; carrying the transmittance from slice to
 * slice, interpolated in each, left up to 18% where the exit changes face.)
 */
static void test_light_grid_oblique(void) {
  const uint32_t n = 32;
  density_grid_t *g = make_grid(n, n, n);
  for (size_t i = 0; i < (size_t)n * n * n; i++)
    g->data[i] = 1;
  rvolume_t v = {.source = VOLUME_GRID,
                 .min = {-1, 0, -1},
                 .max = {1, 2, 1},
                 .density = 0.8f,
                 .albedo = {1, 1, 1},
                 .samples = 128,
                 .grid = g};
  rcamera_t cam = {.eye = {0.3f, 1.2f, 6},
                   .target = {0, 1, 0},
                   .up = {0, 1, 0},
                   .fov_y = 40,
                   .near_ = 0.05f,
                   .far_ = 100};
  render_scene_t s = bare_scene(cam);
  s.light.intensity = 1;
  s.volumes = &v, s.nvolumes = 1;
  const double dirs[][3] = {{0.3, 1, 0}, {0, 1, 0.4}, {0.3, 1, -0.4}, {-0.9, 0.5, 0.3}};
  double lo[3], hi[3];
  for (int k = 0; k < 3; k++)
    lo[k] = v.min[k], hi[k] = v.max[k];
  const int w = 48, h = 48;
  for (int d = 0; d < 4; d++) {
    double l[3], ln = sqrt(dot3(dirs[d], dirs[d]));
    for (int k = 0; k < 3; k++)
      l[k] = dirs[d][k] / ln, s.light.direction[k] = (float)l[k];
    float *img = render_f32(&s, w, h, LAYER_ALL);
    CHECK(img != NULL, "render failed");
    double worst = 0, peak = 0, sum = 0;
    int count = 0;
    for (int y = 0; img && y < h; y++)
      for (int x = 0; x < w; x++) {
        ray_t ray = pixel_ray(&s.camera, w, h, x, y);
        double t0, t1, want = 0, tr = 1;
        if (slab(&ray, lo, hi, &t0, &t1)) {
          int m = 2000;
          double dt = (t1 - t0) / m, a = 1 - exp(-v.density * dt);
          for (int i = 0; i < m; i++) {
            double t = t0 + (i + 0.5) * dt, e0, e1;
            ray_t up = {{ray.o[0] + t * ray.d[0], ray.o[1] + t * ray.d[1], ray.o[2] + t * ray.d[2]},
                        {l[0], l[1], l[2]}};
            double exit = slab(&up, lo, hi, &e0, &e1) ? e1 : 0;
            want += tr * a * exp(-v.density * exit);
            tr *= 1 - a;
          }
        }
        double got = img[4 * (y * w + x)], rel = fabs(got - want) / fmax(want, 1e-3);
        peak = fmax(peak, want);
        worst = fmax(worst, rel);
        if (want > 1e-3)
          sum += rel, count++;
        CHECK(rel < 0.08, "light [%.1f, %.1f, %.1f]: pixel (%d, %d) %.5f, exact %.5f", dirs[d][0],
              dirs[d][1], dirs[d][2], x, y, got, want);
      }
    CHECK(peak > 0.2, "the volume hardly shows (%.3f)", peak);
    CHECK(count > 0 && sum / count < 0.006, "light [%.1f, %.1f, %.1f]: mean error %.2f%%",
          dirs[d][0], dirs[d][1], dirs[d][2], count ? 100 * sum / count : 0.0);
    printf("uniform 32³ lit from [%.1f, %.1f, %.1f]: worst %.2f%% from the exact light, mean "
           "%.2f%% over %d pixels\n",
           dirs[d][0], dirs[d][1], dirs[d][2], 100 * worst, count ? 100 * sum / count : 0.0, count);
    free(img);
  }
  free_grid(g);
}

int main(void) {
  char err[8192];
  if (renderer_create(NULL, &R, err, sizeof err) != 0) {
    fprintf(stderr, "renderer_create: %s\n", err);
    return 1;
  }
  test_transmittance();
  test_no_stripes();
  test_shadow();
  test_shadow_staircase();
  test_interleaved_shadows();
  test_low_resolution();
  test_grid_reference();
  test_light_sweep_threads();
  test_light_grid_oblique();
  test_noise();
  renderer_destroy(R);
  printf("%d checks, %d failed\n", checks, failures);
  return failures != 0;
}
