/*
 * Benchmark of the fluid pass in the set-up of the paper's Table 1 (seed 001): particles on a
 * lattice in layers of 24 x 24, spacing h/2 (0.305 for h = 0.61, so neighbouring metaballs
 * merge into one block of water), stacked to 4096, 16384 and 65536 particles, rendered at
 * 128^2, 256^2 and 512^2 over a floor plane, the camera framing the whole block. Render only:
 * objects + fluid + tone map + readback of RGBA8, the median of --runs frames (default 11)
 * after two of warm-up. Prints a markdown table with the paper's figures beside, and the
 * command line.
 *
 *   bench_render_fluid [--runs N] [--only PARTICLES SIZE] [--device D] [--kernels DIR]
 *                      [--images DIR]
 *
 * --only renders just that row of the table (PARTICLES one of 4096, 16384, 65536; SIZE one of
 * 128, 256, 512).
 *
 * --images DIR renders fluid_block.png (the 4096 block, 512^2) and fluid_drops.png (a splash of
 * random drops over a floor) into DIR and exits.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "render.h"
#include "bench_util.h"

#define MAX_RUNS 101
#define SPACING 0.305f /* h / 2 for the paper's h = 0.61. */

/* The floor under the water. */
static robject_t floor_plane = {
    .shape = SHAPE_PLANE, .scale = {1, 1, 1}, .color = {0.36f, 0.3f, 0.24f}};

/* A scene of 'n' particles at 'pos' over the floor, the camera looking at the centre 'c' from
 * far enough that a sphere of radius 'rad' about it fills the view. */
static render_scene_t scene_for(const float *pos, uint32_t n, const float c[3], float rad) {
  render_scene_t s;
  memset(&s, 0, sizeof s);
  atomic_init(&s.refs, 1);
  float dist = rad / sinf(22.5f * (float)M_PI / 180) * 1.05f;
  float dir[3] = {0.55f, 0.5f, 0.67f};
  float len = sqrtf(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]);
  for (int i = 0; i < 3; i++) {
    s.camera.eye[i] = c[i] + dir[i] / len * dist;
    s.camera.target[i] = c[i];
  }
  s.camera.up[1] = 1;
  s.camera.fov_y = 45;
  s.camera.near_ = 0.05f;
  s.camera.far_ = 1000;
  s.background[0] = 0.42f, s.background[1] = 0.58f, s.background[2] = 0.78f;
  s.light.direction[0] = -0.4f, s.light.direction[1] = 0.8f, s.light.direction[2] = 0.45f;
  s.light.color[0] = 1, s.light.color[1] = 0.96f, s.light.color[2] = 0.9f;
  s.light.intensity = 1.4f;
  s.light.ambient = 0.3f;
  s.objects = &floor_plane;
  s.nobjects = 1;
  s.tone_map = TONE_ACES;
  s.fluid = (rfluid_t){.count = n,
                       .positions = pos,
                       .h = 0.61f,
                       .threshold = 0.765625f,
                       .color = {0.45f, 0.75f, 0.85f},
                       .ior = 1.33f,
                       .roughness = 0.08f};
  return s;
}

/* The first 'n' particles of the stacked 24 x 24 layers, the lowest resting on the floor;
 * writes the block's centre and bounding radius. */
static float *block(uint32_t n, float c[3], float *rad) {
  float *pos = malloc(3 * sizeof(float) * n);
  if (pos == NULL)
    return NULL;
  for (uint32_t i = 0; i < n; i++) {
    uint32_t x = i % 24, z = i / 24 % 24, y = i / 576;
    pos[3 * i] = (x - 11.5f) * SPACING;
    pos[3 * i + 1] = 0.2f + y * SPACING;
    pos[3 * i + 2] = (z - 11.5f) * SPACING;
  }
  float top = 0.2f + ((n - 1) / 576) * SPACING;
  c[0] = 0, c[1] = 0.5f * top, c[2] = 0;
  float half = 11.5f * SPACING + 0.3f;
  *rad = sqrtf(2 * half * half + 0.25f * top * top);
  return pos;
}

static int write_file(const char *dir, const char *name, const unsigned char *b, size_t n) {
  char path[4096];
  snprintf(path, sizeof path, "%s/%s", dir, name);
  FILE *f = fopen(path, "wb");
  if (f == NULL || fwrite(b, 1, n, f) != n) {
    fprintf(stderr, "cannot write %s\n", path);
    if (f)
      fclose(f);
    return -1;
  }
  fclose(f);
  printf("wrote %s\n", path);
  return 0;
}

static int render_png(renderer_t *r, const render_scene_t *s, const char *dir, const char *name) {
  render_params_t p = {
      .width = 512, .height = 512, .format = PROTO_FMT_PNG, .layers = LAYER_ALL, .png_level = 9};
  render_output_t out;
  char err[1024];
  if (renderer_render(r, s, &p, &out, err, sizeof err) != 0) {
    fprintf(stderr, "render: %s\n", err);
    return -1;
  }
  int rc = write_file(dir, name, out.bytes, out.nbytes);
  free(out.bytes);
  return rc;
}

static int write_images(renderer_t *r, const char *dir) {
  float c[3], rad;
  float *pos = block(4096, c, &rad);
  if (pos == NULL)
    return -1;
  render_scene_t s = scene_for(pos, 4096, c, rad);
  int rc = render_png(r, &s, dir, "fluid_block.png");
  free(pos);
  if (rc != 0)
    return rc;

  /* A splash: a crown of drops thrown up from a shallow pool, seeded. */
  uint32_t n = 2200;
  pos = malloc(3 * sizeof(float) * n);
  if (pos == NULL)
    return -1;
  uint64_t x = 0x243f6a8885a308d3ull;
  for (uint32_t i = 0; i < n; i++) {
    double u[3];
    for (int k = 0; k < 3; k++) {
      x ^= x >> 12, x ^= x << 25, x ^= x >> 27;
      u[k] = (double)((x * 0x2545f4914f6cdd1dull) >> 11) / 9007199254740992.0;
    }
    if (i < 1500) {
      /* The pool: a disc one or two particles deep. */
      double a = 2 * M_PI * u[0], rr = 3.2 * sqrt(u[1]);
      pos[3 * i] = (float)(rr * cos(a)), pos[3 * i + 2] = (float)(rr * sin(a));
      pos[3 * i + 1] = (float)(0.15 + 0.2 * u[2]);
    } else {
      /* The crown and its drops: thrown outwards and up from a ring, sparser with height. */
      double a = 2 * M_PI * u[0], hgt = 2.6 * u[1] * u[1];
      double rr = 1.3 + 0.35 * hgt + 0.15 * u[2];
      pos[3 * i] = (float)(rr * cos(a)), pos[3 * i + 2] = (float)(rr * sin(a));
      pos[3 * i + 1] = (float)(0.3 + hgt);
    }
  }
  float cd[3] = {0, 0.9f, 0};
  s = scene_for(pos, n, cd, 3.4f);
  s.camera.eye[1] = 3.6f;
  rc = render_png(r, &s, dir, "fluid_drops.png");
  free(pos);
  return rc;
}

int main(int argc, char **argv) {
  int runs = 11;
  const char *images = NULL;
  long only_n = 0, only_side = 0;
  renderer_opts_t opts = {0};
  for (int i = 1; i < argc; i++) {
    if (strcmp(argv[i], "--runs") == 0 && i + 1 < argc)
      runs = atoi(argv[++i]);
    else if (strcmp(argv[i], "--device") == 0 && i + 1 < argc)
      opts.device = argv[++i];
    else if (strcmp(argv[i], "--kernels") == 0 && i + 1 < argc)
      opts.kernels_dir = argv[++i];
    else if (strcmp(argv[i], "--only") == 0 && i + 2 < argc)
      only_n = atol(argv[i + 1]), only_side = atol(argv[i + 2]), i += 2;
    else if (strcmp(argv[i], "--images") == 0 && i + 1 < argc)
      images = argv[++i];
    else {
      fprintf(stderr,
              "usage: %s [--runs N] [--only PARTICLES SIZE] [--device D] [--kernels DIR] "
              "[--images DIR]\n",
              argv[0]);
      return 2;
    }
  }
  runs = runs < 11 ? 11 : runs > MAX_RUNS ? MAX_RUNS : runs;
  renderer_t *r;
  char err[8192];
  if (renderer_create(&opts, &r, err, sizeof err) != 0) {
    fprintf(stderr, "renderer_create: %s\n", err);
    return 1;
  }
  if (images) {
    int rc = write_images(r, images);
    renderer_destroy(r);
    return rc != 0;
  }

  static const uint32_t counts[3] = {4096, 16384, 65536};
  static const int sides[3] = {128, 256, 512};
  /* The paper's Table 1 (GeForce 8800 GTX), fps; 0 where it gives none. */
  static const double paper[3][3] = {{0, 0, 0}, {35, 21, 7}, {11, 10, 3}};
  double fps[3][3], fluid_ms[3][3];
  for (int c = 0; c < 3; c++) {
    if (only_n && only_n != counts[c])
      continue;
    float centre[3], rad;
    float *pos = block(counts[c], centre, &rad);
    if (pos == NULL)
      return 1;
    render_scene_t s = scene_for(pos, counts[c], centre, rad);
    for (int k = 0; k < 3; k++) {
      if (only_side && only_side != sides[k])
        continue;
      render_params_t p = {.width = (uint32_t)sides[k],
                           .height = (uint32_t)sides[k],
                           .format = PROTO_FMT_RGBA8,
                           .layers = LAYER_ALL};
      double total[MAX_RUNS], pass[MAX_RUNS];
      for (int i = -2; i < runs; i++) {
        render_output_t out;
        if (renderer_render(r, &s, &p, &out, err, sizeof err) != 0) {
          fprintf(stderr, "render: %s\n", err);
          return 1;
        }
        free(out.bytes);
        if (i < 0)
          continue;
        total[i] = out.total_ms;
        pass[i] = 0;
        for (int j = 0; j < out.npasses; j++) {
          if (strcmp(out.passes[j].name, "fluid") == 0)
            pass[i] = out.passes[j].ms;
        }
      }
      qsort(total, (size_t)runs, sizeof(double), bench_cmp_double);
      qsort(pass, (size_t)runs, sizeof(double), bench_cmp_double);
      fps[c][k] = 1000 / total[runs / 2];
      fluid_ms[c][k] = pass[runs / 2];
    }
    free(pos);
  }
  printf("Fluid render (objects + fluid + tonemap + readback, RGBA8) on %s; 24x24 layers, "
         "spacing h/2; median of %d frames.\n\n",
         renderer_device_name(r), runs);
  printf("| particles | size | fps (volfx) | fluid pass ms | fps (paper, 8800 GTX) |\n");
  printf("| --- | --- | --- | --- | --- |\n");
  for (int k = 0; k < 3; k++) {
    for (int c = 0; c < 3; c++) {
      if ((only_n && only_n != counts[c]) || (only_side && only_side != sides[k]))
        continue;
      char ref[16] = "-";
      if (paper[k][c] > 0)
        snprintf(ref, sizeof ref, "%.0f", paper[k][c]);
      printf("| %u | %d² | %.1f | %.2f | %s |\n", counts[c], sides[k], fps[c][k], fluid_ms[c][k],
             ref);
    }
  }
  printf("\nCommand:");
  for (int i = 0; i < argc; i++)
    printf(" %s", argv[i]);
  printf("\n");
  renderer_destroy(r);
  return 0;
}
