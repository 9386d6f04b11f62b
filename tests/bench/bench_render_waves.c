/*
 * Energy-wave benchmark after the thesis (seeds/000, chapter 4): Table 4.2's frame rates at
 * 256x256 and 512x512 for 1, 5 and 10 wave sets (a set is one wave with sphere and beam; eye
 * (0, 0, 300), D = (1, 0, 0), a = 60, b = 30, the sets spread over the view), render-only
 * (every pass but PNG encoding), with only the waves layer and with the objects pass drawing the
 * thesis' two tetrahedra; then the §4.3 comparison with a 120-sample ray march of the same
 * density at 512x512 with 10 sets: its time and its error against the closed form. Figures are
 * medians of --runs runs (default 21), printed as markdown tables beside the thesis' figures
 * (GeForce 9600 GT) with the command line.
 *
 *   bench_render_waves [--runs N] [--device D] [--kernels DIR] [--images DIR]
 *
 * --images DIR renders the thesis' figure set into DIR as waves_*.png and exits.
 */
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "render.h"
#include "bench_util.h"

#define MAX_RUNS 201
#define MAX_SETS 10

/* The thesis' set-up, with this renderer's extra parameters chosen so the glow reads well. */
#define SET_A 60.0f
#define SET_B 30.0f
#define SET_LENGTH 80.0f
#define SET_RADIUS 30.0f
#define SET_EPS 0.3f
#define SET_CLAMP 700.0f

/* The thesis' two tetrahedra (§4.1), at (0, 0, 0) and (10, 0, 250). */
static robject_t tetrahedra[2] = {
    {.shape = SHAPE_TETRAHEDRON,
     .position = {0, -10, 0},
     .scale = {70, 70, 70},
     .rotation = {0, 30, 0},
     .color = {0.55f, 0.6f, 0.7f}},
    {.shape = SHAPE_TETRAHEDRON,
     .position = {10, -4, 250},
     .scale = {14, 14, 14},
     .rotation = {0, 15, 0},
     .color = {0.75f, 0.55f, 0.4f}},
};

static render_scene_t thesis_scene(rwave_t *waves, int n) {
  render_scene_t s;
  memset(&s, 0, sizeof s);
  atomic_init(&s.refs, 1);
  s.camera = (rcamera_t){.eye = {0, 0, 300},
                         .target = {0, 0, 0},
                         .up = {0, 1, 0},
                         .fov_y = 50,
                         .near_ = 0.1f,
                         .far_ = 2000};
  s.background[0] = 0.004f, s.background[1] = 0.005f, s.background[2] = 0.012f;
  s.light.direction[0] = 0.4f, s.light.direction[1] = 0.8f, s.light.direction[2] = 0.45f;
  s.light.color[0] = s.light.color[1] = s.light.color[2] = 1;
  s.light.intensity = 1.6f;
  s.light.ambient = 0.15f;
  s.waves = waves;
  s.nwaves = n;
  s.tone_map = TONE_ACES;
  return s;
}

static rwave_t thesis_wave(float x, float y, float z, float a, float b) {
  rwave_t w = {.center = {x, y, z},
               .direction = {1, 0, 0},
               .a = a,
               .b = b,
               .length = SET_LENGTH,
               .radius = SET_RADIUS,
               .softening = SET_EPS,
               .clamp = SET_CLAMP,
               .color = {0.6f, 1.2f, 2.4f}};
  return w;
}

/* 'n' sets spread over the view: rows of up to two, centred, beams pointing right. */
static void spread_sets(rwave_t *w, int n) {
  int cols = n > 5 ? 2 : 1, rows = (n + cols - 1) / cols;
  for (int i = 0; i < n; i++) {
    int c = i % cols, r = i / cols;
    float x = cols == 1 ? -40.0f : -100.0f + 120.0f * c;
    float y = (rows - 1) * 25.0f - 50.0f * r;
    w[i] = thesis_wave(x, y, 0, SET_A, SET_B);
  }
}

/* The passes a render-only frame may report, in the order the renderer runs them. */
static const char *const pass_names[] = {"objects", "waves", "tonemap", "readback"};
#define NPASS (int)(sizeof pass_names / sizeof pass_names[0])

typedef struct timing {
  double total;       /* Median ms of every pass but encoding. */
  double best;        /* The same for the fastest frame. */
  double cpu;         /* Process CPU time per frame, ms: every thread\'s work, whatever the load. */
  double pass[NPASS]; /* Median ms of each of pass_names (0 where a frame has no such pass). */
} timing_t;

/* Renders 's' 'runs' times (after one untimed frame) and takes the medians. */
static int time_frames(renderer_t *r, const render_scene_t *s, const render_params_t *p, int runs,
                       timing_t *t) {
  double tot[MAX_RUNS], pass[NPASS][MAX_RUNS], cpu0 = 0;
  char err[1024];
  for (int i = -1; i < runs; i++) {
    render_output_t out;
    if (renderer_render(r, s, p, &out, err, sizeof err) != 0) {
      fprintf(stderr, "render: %s\n", err);
      return -1;
    }
    free(out.bytes);
    if (i < 0) {
      cpu0 = bench_cpu_ms();
      continue;
    }
    for (int k = 0; k < NPASS; k++)
      pass[k][i] = bench_pass_ms(&out, pass_names[k]);
    tot[i] = 0;
    for (int k = 0; k < out.npasses; k++)
      tot[i] += strcmp(out.passes[k].name, "encode") ? out.passes[k].ms : 0;
  }
  t->cpu = (bench_cpu_ms() - cpu0) / runs;
  t->total = bench_median(tot, runs);
  t->best = tot[0]; /* bench_median() sorted them. */
  for (int k = 0; k < NPASS; k++)
    t->pass[k] = bench_median(pass[k], runs);
  return 0;
}

/* Renders H of 's' at 'side' squared, exactly or by a march of 'samples'; NULL on failure. */
static float *render_h(renderer_t *r, const render_scene_t *s, uint32_t side, int samples,
                       double *ms) {
  render_params_t p = {.width = side,
                       .height = side,
                       .format = PROTO_FMT_F32,
                       .aov = AOV_WAVE_H,
                       .layers = LAYER_WAVES,
                       .march_samples = samples};
  render_output_t out;
  char err[1024];
  if (renderer_render(r, s, &p, &out, err, sizeof err) != 0) {
    fprintf(stderr, "render: %s\n", err);
    return NULL;
  }
  *ms = bench_pass_ms(&out, "waves");
  return (float *)out.bytes;
}

/* ---- Images -------------------------------------------------------------------------------- */

static int write_file(const char *path, const unsigned char *bytes, size_t n) {
  FILE *f = fopen(path, "wb");
  int ok = f && fwrite(bytes, 1, n, f) == n;
  if (f && fclose(f) != 0)
    ok = 0;
  if (!ok)
    fprintf(stderr, "%s: %s\n", path, strerror(errno));
  else
    printf("wrote %s (%zu bytes)\n", path, n);
  return ok ? 0 : -1;
}

static int write_png(renderer_t *r, const render_scene_t *s, unsigned layers, const char *dir,
                     const char *name) {
  render_params_t p = {
      .width = 512, .height = 512, .format = PROTO_FMT_PNG, .layers = layers, .png_level = 9};
  render_output_t out;
  char err[1024], path[4096];
  if (renderer_render(r, s, &p, &out, err, sizeof err) != 0) {
    fprintf(stderr, "render: %s\n", err);
    return -1;
  }
  snprintf(path, sizeof path, "%s/%s", dir, name);
  int rc = write_file(path, out.bytes, out.nbytes);
  free(out.bytes);
  return rc;
}

/* ACES (Narkowicz) and the sRGB curve, as kernels/tonemap.cl applies them. */
static unsigned char tone_byte(float x) {
  x = x > 0 ? x : 0;
  double y = (x * (2.51 * x + 0.03)) / (x * (2.43 * x + 0.59) + 0.14);
  y = y < 1 ? y : 1;
  y = y <= 0.0031308 ? 12.92 * y : 1.055 * pow(y, 1 / 2.4) - 0.055;
  return (unsigned char)(y * 255 + 0.5);
}

/*
 * The thesis' "hidden surface off" (Figs. 4.8-4.13, left): the glow drawn over the objects
 * whatever their depth. The renderer always ends a ray at the opaque depth, so this picture is
 * composed here: the objects alone plus the glow of the waves alone (over a black background,
 * so that it adds nothing else), tone mapped as the renderer does.
 */
static int write_hidden_off(renderer_t *r, const render_scene_t *s, const char *dir) {
  render_params_t p = {
      .width = 512, .height = 512, .format = PROTO_FMT_RGBAF32, .layers = LAYER_OBJECTS};
  render_output_t objs, glow;
  char err[1024], path[4096];
  render_scene_t black = *s;
  memset(black.background, 0, sizeof black.background);
  if (renderer_render(r, s, &p, &objs, err, sizeof err) != 0) {
    fprintf(stderr, "render: %s\n", err);
    return -1;
  }
  p.layers = LAYER_WAVES;
  if (renderer_render(r, &black, &p, &glow, err, sizeof err) != 0) {
    fprintf(stderr, "render: %s\n", err);
    free(objs.bytes);
    return -1;
  }
  const float *a = (const float *)objs.bytes, *b = (const float *)glow.bytes;
  size_t npix = 512 * 512;
  unsigned char *rgba = malloc(4 * npix), *png = NULL;
  size_t npng = 0;
  int rc = -1;
  if (rgba) {
    float scale = exp2f(s->exposure);
    for (size_t i = 0; i < npix; i++) {
      for (int c = 0; c < 3; c++)
        rgba[4 * i + c] = tone_byte((a[4 * i + c] + b[4 * i + c]) * scale);
      rgba[4 * i + 3] = 255;
    }
    if (encode_png(rgba, 512, 512, 9, &png, &npng) == 0) {
      snprintf(path, sizeof path, "%s/waves_hidden_off.png", dir);
      rc = write_file(path, png, npng);
    }
  }
  free(png);
  free(rgba);
  free(objs.bytes);
  free(glow.bytes);
  return rc;
}

/* The thesis' figure set (Figs. 4.1-4.6 and 4.9), one wave at the centre of the view unless
 * said otherwise; the beam runs out of the view to the right as the thesis' does. */
static int write_images(renderer_t *r, const char *dir) {
  struct {
    const char *name;
    float a, b;
  } figs[] = {
      {"waves_sphere.png", 60, 0},  {"waves_beam.png", 0, 60},    {"waves_both.png", 60, 30},
      {"waves_a_high.png", 90, 30}, {"waves_b_high.png", 60, 50},
  };
  for (size_t i = 0; i < sizeof figs / sizeof figs[0]; i++) {
    rwave_t w = thesis_wave(-30, 0, 0, figs[i].a, figs[i].b);
    w.length = 200;
    render_scene_t s = thesis_scene(&w, 1);
    if (write_png(r, &s, LAYER_ALL, dir, figs[i].name) != 0)
      return -1;
  }
  /* Fig. 4.9: M at z = 160, between the tetrahedra; the near one hides part of the glow. */
  rwave_t w = thesis_wave(-20, 0, 160, SET_A, SET_B);
  render_scene_t s = thesis_scene(&w, 1);
  s.objects = tetrahedra;
  s.nobjects = 2;
  if (write_png(r, &s, LAYER_ALL, dir, "waves_hidden_on.png") != 0)
    return -1;
  if (write_hidden_off(r, &s, dir) != 0)
    return -1;
  rwave_t sets[MAX_SETS];
  spread_sets(sets, MAX_SETS);
  s = thesis_scene(sets, MAX_SETS);
  return write_png(r, &s, LAYER_ALL, dir, "waves_sets10.png");
}

/* ---- Main ---------------------------------------------------------------------------------- */

int main(int argc, char **argv) {
  renderer_opts_t opts = {0};
  int runs = 21;
  const char *images = NULL;
  for (int i = 1; i < argc; i++) {
    if (strcmp(argv[i], "--runs") == 0 && i + 1 < argc)
      runs = atoi(argv[++i]);
    else if (strcmp(argv[i], "--device") == 0 && i + 1 < argc)
      opts.device = argv[++i];
    else if (strcmp(argv[i], "--kernels") == 0 && i + 1 < argc)
      opts.kernels_dir = argv[++i];
    else if (strcmp(argv[i], "--images") == 0 && i + 1 < argc)
      images = argv[++i];
    else {
      fprintf(stderr, "usage: %s [--runs N] [--device D] [--kernels DIR] [--images DIR]\n",
              argv[0]);
      return 2;
    }
  }
  if (runs < 1 || runs > MAX_RUNS) {
    fprintf(stderr, "--runs must lie in [1, %d]\n", MAX_RUNS);
    return 2;
  }
  char err[8192];
  renderer_t *r;
  if (renderer_create(&opts, &r, err, sizeof err) != 0) {
    fprintf(stderr, "renderer_create: %s\n", err);
    return 1;
  }
  if (images) {
    int rc = write_images(r, images);
    renderer_destroy(r);
    return rc != 0;
  }

  /* Table 4.2. */
  static const int set_counts[3] = {1, 5, 10};
  static const uint32_t sides[2] = {256, 512};
  static const double thesis_fps[3][2] = {{105, 27}, {90, 23}, {65, 17}};
  timing_t tw[3][2], to[3][2];
  for (int i = 0; i < 3; i++) {
    rwave_t sets[MAX_SETS];
    spread_sets(sets, set_counts[i]);
    render_scene_t s = thesis_scene(sets, set_counts[i]);
    for (int j = 0; j < 2; j++) {
      render_params_t p = {.width = sides[j],
                           .height = sides[j],
                           .format = PROTO_FMT_RGBA8,
                           .layers = LAYER_WAVES,
                           .png_level = -1};
      s.objects = NULL, s.nobjects = 0;
      if (time_frames(r, &s, &p, runs, &tw[i][j]) != 0)
        return 1;
      p.layers = LAYER_ALL;
      s.objects = tetrahedra, s.nobjects = 2;
      if (time_frames(r, &s, &p, runs, &to[i][j]) != 0)
        return 1;
    }
  }

  /* §4.3: the march against the closed form, 512x512, 10 sets. */
  rwave_t sets[MAX_SETS];
  spread_sets(sets, MAX_SETS);
  render_scene_t s = thesis_scene(sets, MAX_SETS);
  double exact_ms[MAX_RUNS], march_ms[MAX_RUNS], ms;
  float *exact = NULL, *march = NULL;
  for (int i = -1; i < runs; i++) {
    free(exact), free(march);
    exact = render_h(r, &s, 512, 0, &ms);
    if (i >= 0)
      exact_ms[i] = ms;
    march = render_h(r, &s, 512, 120, &ms);
    if (i >= 0)
      march_ms[i] = ms;
    if (exact == NULL || march == NULL)
      return 1;
  }
  /* Errors over the pixels whose rays meet a wave, relative to the exact H, with a floor of 1%
   * of the clamp so that the faint rims do not dominate the mean. */
  double max_rel = 0, sum_rel = 0, max_vis = 0;
  long n = 0;
  for (int i = 0; i < 512 * 512; i++) {
    if (!(exact[i] > 0))
      continue;
    double e = fabs(march[i] - exact[i]) / fmax(exact[i], 0.01 * SET_CLAMP);
    max_rel = fmax(max_rel, e);
    sum_rel += e;
    double shown = fabs(fmin(march[i], SET_CLAMP) - fmin(exact[i], SET_CLAMP)) / SET_CLAMP;
    max_vis = fmax(max_vis, shown);
    n++;
  }
  free(exact), free(march);
  double t_exact = bench_median(exact_ms, runs), t_march = bench_median(march_ms, runs);

  printf("Device: %s / %s. Thesis: GeForce 9600 GT, Core 2 Duo 3.0 GHz (Table 4.1).\n",
         renderer_platform_name(r), renderer_device_name(r));
  printf("Set-up: eye (0, 0, 300) looking at the origin, fov_y 50; a set is one wave, D = (1, 0, "
         "0), a = %g, b = %g, L = %g, R = %g, eps = %g, c = %g; the sets in rows of two. "
         "Render-only: every pass but PNG encoding (objects, waves, tonemap, rgba8 readback). "
         "Medians of %d runs.\n\n",
         SET_A, SET_B, SET_LENGTH, SET_RADIUS, SET_EPS, SET_CLAMP, runs);
  printf("| sets | size | thesis FPS | waves only: FPS (ms) | ratio | waves pass ms | "
         "with objects: FPS (ms) | ratio |\n");
  printf("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n");
  for (int i = 0; i < 3; i++) {
    for (int j = 0; j < 2; j++) {
      printf("| %d | %u² | %.0f | %.0f (%.2f) | %.1fx | %.2f | %.0f (%.2f) | %.1fx |\n",
             set_counts[i], sides[j], thesis_fps[i][j], 1000 / tw[i][j].total, tw[i][j].total,
             1000 / tw[i][j].total / thesis_fps[i][j], tw[i][j].pass[1], 1000 / to[i][j].total,
             to[i][j].total, 1000 / to[i][j].total / thesis_fps[i][j]);
    }
  }
  printf("\nWhere a frame's time goes, median ms of each pass (waves only / with objects; 0: "
         "no such pass), the fastest frame's total, and the CPU time per frame of every thread\n"
         "together, which the load of the machine does not inflate (two cores: ideal FPS = 2000 / "
         "CPU ms):\n\n| sets | size |");
  for (int k = 0; k < NPASS; k++)
    printf(" %s |", pass_names[k]);
  printf(" fastest frame | CPU ms per frame |\n| ---: | ---: | ---: | ---: |");
  for (int k = 0; k < NPASS; k++)
    printf(" ---: |");
  printf("\n");
  for (int i = 0; i < 3; i++) {
    for (int j = 0; j < 2; j++) {
      printf("| %d | %u² |", set_counts[i], sides[j]);
      for (int k = 0; k < NPASS; k++)
        printf(" %.2f / %.2f |", tw[i][j].pass[k], to[i][j].pass[k]);
      printf(" %.2f / %.2f | %.2f / %.2f |\n", tw[i][j].best, to[i][j].best, tw[i][j].cpu,
             to[i][j].cpu);
    }
  }
  printf("\n§4.3, 512², 10 sets, waves pass only (H as f32):\n\n");
  printf("| method | ms | relative error of H: max | mean | max error shown (min(H, c) / c) |\n");
  printf("| --- | ---: | ---: | ---: | ---: |\n");
  printf("| closed form (this) | %.2f | reference | reference | reference |\n", t_exact);
  printf("| ray march, 120 samples per wave and ray over the same interval | %.2f | %.3g | %.3g | "
         "%.3g |\n",
         t_march, max_rel, n ? sum_rel / n : 0.0, max_vis);
  printf("\n%ld pixels meet a wave. Command:", n);
  for (int i = 0; i < argc; i++)
    printf(" %s", argv[i]);
  printf("\n");
  renderer_destroy(r);
  return 0;
}
