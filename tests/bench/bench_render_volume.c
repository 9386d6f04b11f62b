/*
 * Volume benchmark after paper 002 (seeds/002, §5): its scene of mist around opaque objects
 * with light shafts at 1024x1024 and 32 samples per ray (the paper's best quality, 8 primitives
 * x 4 samples, ran at 43 FPS on a GeForce 7800 GTX), render only (every pass but PNG encoding);
 * then a cloud-sized grid volume (64³ and 128³ voxels of Gaussian blobs, as the cloud pass
 * draws them) at 512x512 with a changing grid every frame, so the light grid and upload are
 * paid each time. The scene is scenes/paper-002.json, built here as structs. Figures are medians
 * of --runs runs (default 11).
 *
 *   bench_render_volume [--runs N] [--device D] [--kernels DIR] [--images DIR]
 *
 * --images DIR renders the documentation's stills into DIR as volume_*.png and exits.
 */
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "render.h"
#include "bench_util.h"

#define MAX_RUNS 101

/* scenes/paper-002.json. */
static robject_t objects[] = {
    {.shape = SHAPE_PLANE, .scale = {1, 1, 1}, .color = {0.35f, 0.35f, 0.35f}},
#define SLAT(z)                                                                                    \
  {                                                                                                \
    .shape = SHAPE_BOX, .position = {0, 4.6f, z}, .scale = {9.5f, 0.25f, 1}, .color = {            \
      0.45f,                                                                                       \
      0.38f,                                                                                       \
      0.3f                                                                                         \
    }                                                                                              \
  }
    SLAT(-3.5f),
    SLAT(-2.1f),
    SLAT(-0.7f),
    SLAT(0.7f),
    SLAT(2.1f),
    SLAT(3.5f),
#undef SLAT
    {.shape = SHAPE_BOX,
     .position = {-1.5f, 1.5f, -1.0f},
     .scale = {0.6f, 3.0f, 0.6f},
     .color = {0.7f, 0.7f, 0.72f}},
    {.shape = SHAPE_SPHERE,
     .position = {1.2f, 1.0f, 0.6f},
     .scale = {2, 2, 2},
     .color = {0.8f, 0.35f, 0.25f}},
    {.shape = SHAPE_BOX,
     .position = {-0.2f, 0.5f, 2.2f},
     .scale = {1, 1, 1},
     .rotation = {0, 30, 0},
     .color = {0.35f, 0.55f, 0.75f}},
};

static rvolume_t mist = {.source = VOLUME_NOISE,
                         .min = {-4.5f, 0, -4},
                         .max = {4.5f, 4.4f, 4},
                         .density = 0.22f,
                         .albedo = {0.85f, 0.85f, 0.88f},
                         .samples = 32,
                         .phase_g = 0.5f,
                         .seed = 7,
                         .noise_scale = 2.5f};

static render_scene_t paper_scene(void) {
  render_scene_t s;
  memset(&s, 0, sizeof s);
  atomic_init(&s.refs, 1);
  s.camera = (rcamera_t){.eye = {7.5f, 2.6f, 9.0f},
                         .target = {0, 1.6f, 0},
                         .up = {0, 1, 0},
                         .fov_y = 50,
                         .near_ = 0.05f,
                         .far_ = 200};
  s.background[0] = 0.02f, s.background[1] = 0.025f, s.background[2] = 0.035f;
  float l[3] = {-0.45f, 1.0f, -0.35f}, n = sqrtf(l[0] * l[0] + l[1] * l[1] + l[2] * l[2]);
  for (int i = 0; i < 3; i++)
    s.light.direction[i] = l[i] / n;
  s.light.color[0] = 1, s.light.color[1] = 0.92f, s.light.color[2] = 0.78f;
  s.light.intensity = 2.2f;
  s.light.ambient = 0.05f;
  s.light.shadow_map = 1024;
  s.objects = objects;
  s.nobjects = sizeof objects / sizeof objects[0];
  s.volumes = &mist;
  s.nvolumes = 1;
  s.tone_map = TONE_ACES;
  return s;
}

/* A cloud-like grid: 'blobs' Gaussian blobs of radius about side/7 in a side³ grid, shifted by
 * 'phase' so every frame's grid differs. */
static void fill_cloud(density_grid_t *g, int blobs, double phase) {
  uint32_t n = g->dims[0];
  memset(g->data, 0, (size_t)n * n * n * sizeof(float));
  double r = n / 7.0;
  for (int b = 0; b < blobs; b++) {
    double c[3] = {n * (0.3 + 0.4 * (0.5 + 0.5 * sin(1.7 * b + phase))),
                   n * (0.4 + 0.2 * (0.5 + 0.5 * sin(2.3 * b + 1))),
                   n * (0.3 + 0.4 * (0.5 + 0.5 * cos(1.1 * b)))};
    int lo[3], hi[3];
    for (int k = 0; k < 3; k++) {
      lo[k] = (int)fmax(0, c[k] - 3 * r), hi[k] = (int)fmin(n - 1, c[k] + 3 * r);
    }
    for (int z = lo[2]; z <= hi[2]; z++)
      for (int y = lo[1]; y <= hi[1]; y++)
        for (int x = lo[0]; x <= hi[0]; x++) {
          double d2 = (x - c[0]) * (x - c[0]) + (y - c[1]) * (y - c[1]) + (z - c[2]) * (z - c[2]);
          g->data[((size_t)z * n + y) * n + x] += (float)exp(-d2 / (2 * r * r));
        }
  }
}

static double last_cpu; /* CPU ms of the last render_once. */

static int render_once(renderer_t *r, const render_scene_t *s, uint32_t w, uint32_t h,
                       proto_format_t fmt, double *ms, double *vol_ms, render_output_t *keep) {
  /* PNGs are for the documentation: compressed hard. */
  render_params_t p = {.width = w, .height = h, .format = fmt, .layers = LAYER_ALL, .png_level = 9};
  render_output_t out;
  char err[512];
  double c0 = bench_cpu_ms();
  if (renderer_render(r, s, &p, &out, err, sizeof err) != 0) {
    fprintf(stderr, "render: %s\n", err);
    return -1;
  }
  last_cpu = bench_cpu_ms() - c0;
  double t = 0, v = 0;
  for (int i = 0; i < out.npasses; i++) {
    if (strcmp(out.passes[i].name, "encode") != 0)
      t += out.passes[i].ms;
    if (strcmp(out.passes[i].name, "volumes") == 0)
      v = out.passes[i].ms;
  }
  if (ms)
    *ms = t;
  if (vol_ms)
    *vol_ms = v;
  if (keep)
    *keep = out;
  else
    free(out.bytes);
  return 0;
}

/* Frame times: the medians of a run of renders. */
typedef struct medians {
  double ms, vol, cpu; /* Whole render, volumes pass, process CPU: ms per frame. */
} medians_t;

/* 'runs' renders of 's' at w x h into 'm'; with 'alt', frame i shows the cloud grid alt[i & 1],
 * so that every frame's cloud is new to the renderer. */
static int median_frames(renderer_t *r, render_scene_t *s, uint32_t w, uint32_t h, int runs,
                         density_grid_t *const *alt, medians_t *m) {
  double t[MAX_RUNS], v[MAX_RUNS], c[MAX_RUNS];
  for (int i = 0; i < runs; i++) {
    if (alt)
      s->cloud.grid = alt[i & 1];
    if (render_once(r, s, w, h, PROTO_FMT_RGBA8, &t[i], &v[i], NULL) != 0)
      return -1;
    c[i] = last_cpu;
  }
  m->ms = bench_median(t, runs), m->vol = bench_median(v, runs), m->cpu = bench_median(c, runs);
  return 0;
}

static int write_png(renderer_t *r, const render_scene_t *s, uint32_t w, uint32_t h,
                     const char *dir, const char *name) {
  render_output_t out;
  if (render_once(r, s, w, h, PROTO_FMT_PNG, NULL, NULL, &out) != 0)
    return -1;
  char path[1024];
  snprintf(path, sizeof path, "%s/%s", dir, name);
  FILE *f = fopen(path, "wb");
  int ok = f && fwrite(out.bytes, 1, out.nbytes, f) == out.nbytes;
  if (f)
    fclose(f);
  free(out.bytes);
  if (!ok) {
    fprintf(stderr, "%s: %s\n", path, strerror(errno));
    return -1;
  }
  printf("wrote %s\n", path);
  return 0;
}

/* The documentation's stills. */
static int images(renderer_t *r, const char *dir) {
  render_scene_t s = paper_scene();
  if (write_png(r, &s, 1024, 1024, dir, "volume_mist.png") != 0)
    return -1;
  /* The same with render.antialias 2: smooth edges, and the sub-pixels' interleaved shadow
   * tests smooth the mist's faint rings. */
  render_scene_t smooth = s;
  smooth.antialias = 2;
  if (write_png(r, &smooth, 1024, 1024, dir, "volume_mist_aa2.png") != 0)
    return -1;
  /* Looking up towards the light between the beams: the shafts. */
  render_scene_t shafts = s;
  shafts.camera.eye[0] = 6.5f, shafts.camera.eye[1] = 0.6f, shafts.camera.eye[2] = 6.0f;
  shafts.camera.target[0] = -1.0f, shafts.camera.target[1] = 3.2f, shafts.camera.target[2] = -1.5f;
  if (write_png(r, &shafts, 1024, 1024, dir, "volume_shafts.png") != 0)
    return -1;
  /* The same at render.volume_resolution "half". */
  shafts.volume_div = 2;
  if (write_png(r, &shafts, 1024, 1024, dir, "volume_shafts_half.png") != 0)
    return -1;
  /* A thin plate slicing a uniform block of fog at a grazing angle: slice-based renderers
   * show stripes along the cut; sampling up to the opaque depth shows none. */
  static float one = 1;
  density_grid_t g = {.dims = {1, 1, 1}, .data = &one};
  atomic_init(&g.refs, 1);
  rvolume_t fog = {.source = VOLUME_GRID,
                   .min = {-3, 0, -3},
                   .max = {3, 3, 3},
                   .density = 0.8f,
                   .albedo = {0.8f, 0.85f, 0.9f},
                   .samples = 8,
                   .grid = &g};
  robject_t plate[2] = {
      {.shape = SHAPE_PLANE, .scale = {1, 1, 1}, .color = {0.25f, 0.25f, 0.25f}},
      {.shape = SHAPE_BOX,
       .position = {0, 1.4f, 0},
       .scale = {4.5f, 0.05f, 4.5f},
       .rotation = {12, 0, 8},
       .color = {0.7f, 0.3f, 0.2f}},
  };
  render_scene_t cut = s;
  cut.objects = plate, cut.nobjects = 2;
  cut.volumes = &fog, cut.nvolumes = 1;
  cut.light.intensity = 1.2f;
  cut.camera.eye[0] = 4.5f, cut.camera.eye[1] = 2.8f, cut.camera.eye[2] = 7.5f;
  cut.camera.target[0] = 0, cut.camera.target[1] = 1.2f, cut.camera.target[2] = 0;
  int rc = write_png(r, &cut, 768, 768, dir, "volume_cut.png");
  renderer_destroy(r);
  return rc;
}

int main(int argc, char **argv) {
  int runs = 11;
  renderer_opts_t opts = {0};
  const char *img = NULL;
  for (int i = 1; i < argc; i++) {
    if (strcmp(argv[i], "--runs") == 0 && i + 1 < argc)
      runs = atoi(argv[++i]);
    else if (strcmp(argv[i], "--device") == 0 && i + 1 < argc)
      opts.device = argv[++i];
    else if (strcmp(argv[i], "--kernels") == 0 && i + 1 < argc)
      opts.kernels_dir = argv[++i];
    else if (strcmp(argv[i], "--images") == 0 && i + 1 < argc)
      img = argv[++i];
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
  renderer_t *r;
  char err[4096];
  if (renderer_create(&opts, &r, err, sizeof err) != 0) {
    fprintf(stderr, "renderer_create: %s\n", err);
    return 1;
  }
  if (img)
    return images(r, img) == 0 ? 0 : 1;

  /* The paper's scene. The first frame bakes the noise and renders the shadow map; later
   * frames of the still scene reuse both, as a game's would. */
  render_scene_t s = paper_scene();
  double first_ms, first_vol;
  if (render_once(r, &s, 1024, 1024, PROTO_FMT_RGBA8, &first_ms, &first_vol, NULL) != 0)
    return 1;
  medians_t paper, low[2];
  if (median_frames(r, &s, 1024, 1024, runs, NULL, &paper) != 0)
    return 1;
  /* The same at render.volume_resolution "half" and "quarter". */
  for (int q = 0; q < 2; q++) {
    s.volume_div = 2 << q;
    if (median_frames(r, &s, 1024, 1024, runs, NULL, &low[q]) != 0)
      return 1;
  }
  s.volume_div = 1;

  /* Cloud-sized grids, a new grid every frame. */
  medians_t fresh[2], still[2];
  uint32_t sides[2] = {64, 128};
  for (int c = 0; c < 2; c++) {
    uint32_t dims[3] = {sides[c], sides[c], sides[c]};
    density_grid_t *g[2];
    for (int k = 0; k < 2; k++) {
      g[k] = calloc(1, sizeof *g[k]);
      g[k]->data = malloc((size_t)dims[0] * dims[1] * dims[2] * sizeof(float));
      memcpy(g[k]->dims, dims, sizeof dims);
      atomic_init(&g[k]->refs, 1);
      fill_cloud(g[k], 12, k);
    }
    render_scene_t cs;
    memset(&cs, 0, sizeof cs);
    atomic_init(&cs.refs, 1);
    cs.camera = (rcamera_t){.eye = {0, 0.5f, 3.2f},
                            .target = {0, 0.5f, 0},
                            .up = {0, 1, 0},
                            .fov_y = 45,
                            .near_ = 0.05f,
                            .far_ = 100};
    cs.background[0] = 0.35f, cs.background[1] = 0.5f, cs.background[2] = 0.8f;
    cs.light = s.light;
    cs.light.ambient = 0.25f;
    cs.cloud = (rvolume_t){.source = VOLUME_GRID,
                           .min = {-1, -0.5f, -1},
                           .max = {1, 1.5f, 1},
                           .density = 6,
                           .albedo = {0.95f, 0.95f, 0.95f},
                           .samples = 64,
                           .phase_g = 0.3f};
    cs.tone_map = TONE_ACES;
    /* Alternating grids, then the same grid every frame: the kernel alone. */
    if (median_frames(r, &cs, 512, 512, runs, g, &fresh[c]) != 0 ||
        median_frames(r, &cs, 512, 512, runs, NULL, &still[c]) != 0)
      return 1;
    renderer_destroy(r);
    if (renderer_create(&opts, &r, err, sizeof err) != 0) {
      fprintf(stderr, "renderer_create: %s\n", err);
      return 1;
    }
    for (int k = 0; k < 2; k++) {
      free(g[k]->data);
      free(g[k]);
    }
  }
  renderer_destroy(r);

  printf("Paper 002: GeForce 7800 GTX, DirectX 9, 1024² (16-bit float frame buffer), shadow map "
         "256² from a point light.\n\n");
  printf(
      "| scene | size | samples per ray | paper FPS | ours: FPS (ms per frame) | ratio | volumes "
      "pass ms | CPU ms per frame |\n");
  printf("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n");
  printf("| mist + 10 objects + shafts (shadow map 1024²) | 1024² | 32 | 43 (8 primitives x 4 "
         "samples) | %.1f (%.1f) | %.2fx | %.1f | %.0f |\n",
         1000 / paper.ms, paper.ms, 1000 / paper.ms / 43, paper.vol, paper.cpu);
  printf("| same, first frame (noise baked, shadow map rendered) | 1024² | 32 | | %.1f (%.1f) | "
         "| %.1f | |\n",
         1000 / first_ms, first_ms, first_vol);
  for (int q = 0; q < 2; q++)
    printf(
        "| same, volumes pass at %s resolution (%d² rays) | 1024² | 32 | | %.1f (%.1f) | %.2fx | "
        "%.1f | %.0f |\n",
        q ? "quarter" : "half", 1024 >> (q + 1), 1000 / low[q].ms, low[q].ms, 1000 / low[q].ms / 43,
        low[q].vol, low[q].cpu);
  for (int c = 0; c < 2; c++) {
    printf("| cloud grid %u³, new every frame | 512² | 64 | | %.1f (%.1f) | | %.1f | %.0f |\n",
           sides[c], 1000 / fresh[c].ms, fresh[c].ms, fresh[c].vol, fresh[c].cpu);
    printf("| cloud grid %u³, unchanged | 512² | 64 | | %.1f (%.1f) | | %.1f | %.0f |\n", sides[c],
           1000 / still[c].ms, still[c].ms, still[c].vol, still[c].cpu);
  }
  printf("\nMedians of %d runs; render only (no PNG encoding). CPU ms: the process's CPU time "
         "per frame over all threads (on an idle 2-core machine the wall time is about half of "
         "it). Command:",
         runs);
  for (int i = 0; i < argc; i++)
    printf(" %s", argv[i]);
  printf("\n");
  return 0;
}
