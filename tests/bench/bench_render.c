/*
 * Renderer benchmark: the opaque-object frame of the demo scene at 512x512 and 1024x1024,
 * PNG encoding of those frames, and renderer start-up with a cold and a warm PoCL kernel
 * cache. Every figure is the median of --runs runs (default 11); the cold and warm start-ups
 * run in child processes (this program again, with --child-create) so that nothing compiled
 * in this process helps them. Prints a markdown table and the command line that made it.
 *
 *   bench_render [--runs N] [--device D] [--kernels DIR] [--no-startup] [--write FILE]
 *
 * --write renders the scene at 1024x576 to FILE as a PNG and exits.
 */
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "render.h"
#include "bench_util.h"

#define MAX_RUNS 101

/* The demo scene of scenes/demo.json, by hand: a floor, two spheres, a box and a tetrahedron. */
static robject_t demo_objects[] = {
    {.shape = SHAPE_PLANE, .scale = {1, 1, 1}, .color = {0.42f, 0.44f, 0.48f}},
    {.shape = SHAPE_SPHERE,
     .position = {-1.6f, 0.8f, 0.2f},
     .scale = {1.6f, 1.6f, 1.6f},
     .color = {0.85f, 0.32f, 0.22f}},
    {.shape = SHAPE_BOX,
     .position = {0.7f, 0.55f, -0.6f},
     .scale = {1.1f, 1.1f, 1.1f},
     .rotation = {0, 35, 0},
     .color = {0.25f, 0.5f, 0.8f}},
    {.shape = SHAPE_TETRAHEDRON,
     .position = {2.2f, 0.22f, 0.9f},
     .scale = {1.3f, 1.3f, 1.3f},
     .rotation = {0, 20, 0},
     .color = {0.9f, 0.78f, 0.3f}},
    {.shape = SHAPE_SPHERE,
     .position = {0.2f, 0.3f, 1.5f},
     .scale = {0.6f, 0.6f, 0.6f},
     .color = {0.3f, 0.75f, 0.45f}},
};

static render_scene_t demo_scene = {
    .camera = {.eye = {0, 2.2f, 7.5f},
               .target = {0, 0.7f, 0},
               .up = {0, 1, 0},
               .fov_y = 40,
               .near_ = 0.05f,
               .far_ = 200},
    .background = {0.09f, 0.11f, 0.16f},
    .light = {.direction = {0.55f, 0.75f, 0.35f},
              .color = {1, 0.95f, 0.88f},
              .intensity = 3,
              .ambient = 0.18f,
              .shadow_map = 1024},
    .objects = demo_objects,
    .nobjects = sizeof demo_objects / sizeof demo_objects[0],
    .exposure = 0,
    .tone_map = TONE_ACES,
};

/* Creates a renderer and prints how long it took: the child side of the start-up figures. */
static int child_create(const renderer_opts_t *opts) {
  char err[4096];
  renderer_t *r;
  double t = bench_now_ms();
  if (renderer_create(opts, &r, err, sizeof err) != 0) {
    fprintf(stderr, "renderer_create: %s\n", err);
    return 1;
  }
  printf("%.3f\n", bench_now_ms() - t);
  renderer_destroy(r);
  return 0;
}

/* Runs this program with --child-create and POCL_CACHE_DIR='cache'; returns its time in ms or
 * a negative number on failure. */
static double spawn_create(const char *self, const char *cache, const renderer_opts_t *opts) {
  int fd[2];
  if (pipe(fd) != 0)
    return -1;
  pid_t pid = fork();
  if (pid < 0)
    return -1;
  if (pid == 0) {
    dup2(fd[1], STDOUT_FILENO);
    close(fd[0]), close(fd[1]);
    setenv("POCL_CACHE_DIR", cache, 1);
    const char *argv[8] = {self, "--child-create"};
    int n = 2;
    if (opts->device)
      argv[n++] = "--device", argv[n++] = opts->device;
    if (opts->kernels_dir)
      argv[n++] = "--kernels", argv[n++] = opts->kernels_dir;
    argv[n] = NULL;
    execv(self, (char *const *)argv);
    _exit(127);
  }
  close(fd[1]);
  char buf[64] = {0};
  ssize_t got = read(fd[0], buf, sizeof buf - 1);
  close(fd[0]);
  int status;
  waitpid(pid, &status, 0);
  if (got <= 0 || !WIFEXITED(status) || WEXITSTATUS(status) != 0)
    return -1;
  return atof(buf);
}

static void remove_tree(const char *dir) {
  char cmd[4200];
  snprintf(cmd, sizeof cmd, "rm -rf '%s'", dir);
  if (system(cmd) != 0)
    fprintf(stderr, "could not remove %s\n", dir);
}

/* Medians of the cold and warm renderer_create times over 'runs' child processes. */
static int bench_startup(const char *self, const renderer_opts_t *opts, int runs, double *cold,
                         double *warm) {
  double c[MAX_RUNS], w[MAX_RUNS];
  char warm_dir[] = "/tmp/volfx-bench-warm-XXXXXX";
  if (mkdtemp(warm_dir) == NULL)
    return -1;
  for (int i = 0; i < runs; i++) {
    char dir[] = "/tmp/volfx-bench-cold-XXXXXX";
    if (mkdtemp(dir) == NULL)
      return -1;
    c[i] = spawn_create(self, dir, opts);
    remove_tree(dir);
    if (c[i] < 0)
      return -1;
  }
  if (spawn_create(self, warm_dir, opts) < 0)
    return -1;
  for (int i = 0; i < runs; i++) {
    if ((w[i] = spawn_create(self, warm_dir, opts)) < 0)
      return -1;
  }
  remove_tree(warm_dir);
  *cold = bench_median(c, runs);
  *warm = bench_median(w, runs);
  return 0;
}

typedef struct frame_times {
  double objects, tonemap, readback, render; /* Medians, ms. */
  double png_fast, png_fast_kb, png6, png6_kb;
} frame_times_t;

/* Renders the demo at 'side' x 'side' 'runs' times and encodes the last frame 'runs' times
 * at each PNG setting. */
static int bench_frame(renderer_t *r, uint32_t side, int runs, frame_times_t *ft) {
  double obj[MAX_RUNS], tm[MAX_RUNS], rb[MAX_RUNS], tot[MAX_RUNS], fast[MAX_RUNS], l6[MAX_RUNS];
  render_params_t p = {.width = side,
                       .height = side,
                       .format = PROTO_FMT_RGBA8,
                       .layers = LAYER_ALL,
                       .png_level = -1};
  render_output_t out = {0};
  char err[1024];
  for (int i = -1; i < runs; i++) {
    free(out.bytes);
    if (renderer_render(r, &demo_scene, &p, &out, err, sizeof err) != 0) {
      fprintf(stderr, "render: %s\n", err);
      return -1;
    }
    if (i < 0)
      continue; /* The first frame at a new size allocates its buffers. */
    obj[i] = bench_pass_ms(&out, "objects");
    tm[i] = bench_pass_ms(&out, "tonemap");
    rb[i] = bench_pass_ms(&out, "readback");
    tot[i] = obj[i] + tm[i] + rb[i];
  }
  size_t n6 = 0, nfast = 0;
  for (int i = 0; i < runs; i++) {
    unsigned char *png;
    double t = bench_now_ms();
    if (encode_png(out.bytes, side, side, -1, &png, &nfast) != 0)
      return -1;
    fast[i] = bench_now_ms() - t;
    free(png);
    t = bench_now_ms();
    if (encode_png(out.bytes, side, side, 6, &png, &n6) != 0)
      return -1;
    l6[i] = bench_now_ms() - t;
    free(png);
  }
  free(out.bytes);
  ft->objects = bench_median(obj, runs);
  ft->tonemap = bench_median(tm, runs);
  ft->readback = bench_median(rb, runs);
  ft->render = bench_median(tot, runs);
  ft->png_fast = bench_median(fast, runs);
  ft->png6 = bench_median(l6, runs);
  ft->png_fast_kb = nfast / 1024.0;
  ft->png6_kb = n6 / 1024.0;
  return 0;
}

/* Renders the demo scene at 1024x576 into a PNG file, one stop darker than the demo's own
 * exposure: at 0 the light floor saturates under ACES and the shading is hard to see. */
static int write_image(renderer_t *r, const char *path) {
  render_scene_t scene = demo_scene;
  scene.exposure -= 1;
  render_params_t p = {
      .width = 1024, .height = 576, .format = PROTO_FMT_PNG, .layers = LAYER_ALL, .png_level = 9};
  render_output_t out;
  char err[1024];
  if (renderer_render(r, &scene, &p, &out, err, sizeof err) != 0) {
    fprintf(stderr, "render: %s\n", err);
    return 1;
  }
  FILE *f = fopen(path, "wb");
  int ok = f && fwrite(out.bytes, 1, out.nbytes, f) == out.nbytes;
  if (f && fclose(f) != 0)
    ok = 0;
  free(out.bytes);
  if (!ok) {
    fprintf(stderr, "%s: %s\n", path, strerror(errno));
    return 1;
  }
  printf("wrote %s (%zu bytes)\n", path, out.nbytes);
  return 0;
}

int main(int argc, char **argv) {
  renderer_opts_t opts = {0};
  int runs = 11, startup = 1, child = 0;
  const char *write = NULL;
  for (int i = 1; i < argc; i++) {
    if (strcmp(argv[i], "--runs") == 0 && i + 1 < argc)
      runs = atoi(argv[++i]);
    else if (strcmp(argv[i], "--device") == 0 && i + 1 < argc)
      opts.device = argv[++i];
    else if (strcmp(argv[i], "--kernels") == 0 && i + 1 < argc)
      opts.kernels_dir = argv[++i];
    else if (strcmp(argv[i], "--write") == 0 && i + 1 < argc)
      write = argv[++i];
    else if (strcmp(argv[i], "--no-startup") == 0)
      startup = 0;
    else if (strcmp(argv[i], "--child-create") == 0)
      child = 1;
    else {
      fprintf(stderr,
              "usage: %s [--runs N] [--device D] [--kernels DIR] [--no-startup] "
              "[--write FILE]\n",
              argv[0]);
      return 2;
    }
  }
  if (child)
    return child_create(&opts);
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
  if (write) {
    int rc = write_image(r, write);
    renderer_destroy(r);
    return rc;
  }

  frame_times_t f512, f1024;
  if (bench_frame(r, 512, runs, &f512) != 0 || bench_frame(r, 1024, runs, &f1024) != 0) {
    renderer_destroy(r);
    return 1;
  }
  char device[300];
  snprintf(device, sizeof device, "%s / %s", renderer_platform_name(r), renderer_device_name(r));
  renderer_destroy(r);

  double cold = 0, warm = 0;
  if (startup) {
    /* /proc/self/exe, so the children run this very binary whatever argv[0] says. */
    char self[4096];
    ssize_t n = readlink("/proc/self/exe", self, sizeof self - 1);
    if (n <= 0) {
      fprintf(stderr, "cannot find this program's path\n");
      return 1;
    }
    self[n] = '\0';
    if (bench_startup(self, &opts, runs, &cold, &warm) != 0) {
      fprintf(stderr, "start-up measurement failed\n");
      return 1;
    }
  }

  printf("Device: %s. Scene: scenes/demo.json (a floor plane, 2 spheres, a box, a tetrahedron, "
         "a directional light).\n"
         "Medians of %d runs, ms.\n\n",
         device, runs);
  printf("| measure | 512x512 | 1024x1024 |\n| --- | ---: | ---: |\n");
  printf("| render (objects + tonemap + readback) | %.2f | %.2f |\n", f512.render, f1024.render);
  printf("| - objects pass | %.2f | %.2f |\n", f512.objects, f1024.objects);
  printf("| - tonemap pass | %.2f | %.2f |\n", f512.tonemap, f1024.tonemap);
  printf("| - readback (rgba8) | %.2f | %.2f |\n", f512.readback, f1024.readback);
  printf("| PNG encode, fast default (zlib 1, no filter) | %.2f (%.0f KiB) | %.2f (%.0f KiB) |\n",
         f512.png_fast, f512.png_fast_kb, f1024.png_fast, f1024.png_fast_kb);
  printf("| PNG encode, level 6 (default filters) | %.2f (%.0f KiB) | %.2f (%.0f KiB) |\n",
         f512.png6, f512.png6_kb, f1024.png6, f1024.png6_kb);
  if (startup) {
    printf("\n| renderer_create | ms |\n| --- | ---: |\n");
    printf("| cold (empty POCL_CACHE_DIR) | %.1f |\n| warm (cache filled) | %.1f |\n", cold, warm);
  }
  printf("\nCommand:");
  for (int i = 0; i < argc; i++)
    printf(" %s", argv[i]);
  printf("\n");
  return 0;
}
