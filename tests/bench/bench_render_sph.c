/*
 * Benchmark of one SPH simulation step (server/sim_fluid.c) at dt = 1/60 s for 4096, 16384 and
 * 65536 particles: a block of water settled on the floor of a tank that fits it across, so
 * every particle has its full share of neighbours. Prints a markdown table: the median of
 * 'steps' timed steps after warm-up, the substeps each step took, and the time per substep.
 *
 *   build-sph/bin/bench_render_sph [steps]      (default 15, at least 11)
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "cl_device.h"
#include "sim_fluid.h"
#include "bench_util.h"

int main(int argc, char **argv) {
  int steps = argc > 1 ? atoi(argv[1]) : 15;
  if (steps < 11)
    steps = 11;
  static cl_dev_t dev;
  char err[8192];
  if (cl_dev_open(&dev, NULL, err, sizeof err) != 0 ||
      cl_dev_build(&dev, NULL, "-cl-std=CL1.2 -cl-mad-enable -cl-no-signed-zeros", err,
                   sizeof err) != 0) {
    fprintf(stderr, "OpenCL device: %s\n", err);
    return 1;
  }
  static const int sizes[][3] = {{16, 16, 16}, {32, 16, 32}, {64, 16, 64}};
  printf("SPH step at dt = 1/60 s on %s; median of %d steps after 20 of warm-up.\n\n",
         dev.device_name, steps);
  printf("| particles | ms per step (median) | fastest | substeps | ms per substep | target |\n");
  printf("| --- | --- | --- | --- | --- | --- |\n");
  for (size_t c = 0; c < sizeof sizes / sizeof sizes[0]; c++) {
    int nx = sizes[c][0], ny = sizes[c][1], nz = sizes[c][2];
    uint32_t n = (uint32_t)(nx * ny * nz);
    fluid_params_t p;
    fluid_params_default(&p);
    float dx = p.h / 2;
    p.bounds_min[0] = p.bounds_min[1] = p.bounds_min[2] = 0;
    p.bounds_max[0] = nx * dx, p.bounds_max[1] = 2 * ny * dx, p.bounds_max[2] = nz * dx;
    p.max_particles = n;
    float *pos = malloc(3 * sizeof(float) * n);
    uint32_t k = 0;
    for (int z = 0; z < nz; z++) {
      for (int y = 0; y < ny; y++) {
        for (int x = 0; x < nx; x++, k++) {
          pos[3 * k] = (x + 0.5f) * dx, pos[3 * k + 1] = (y + 0.5f) * dx;
          pos[3 * k + 2] = (z + 0.5f) * dx;
        }
      }
    }
    fluid_sim_t *s = fluid_sim_create(&dev, &p, err, sizeof err);
    if (s == NULL || fluid_sim_set_particles(s, pos, NULL, n, err, sizeof err) != 0) {
      fprintf(stderr, "%s\n", err);
      return 1;
    }
    for (int i = 0; i < 20; i++)
      fluid_sim_step(s, 1.0 / 60, err, sizeof err);
    double *ms = malloc(sizeof(double) * steps);
    int sub = 0;
    for (int i = 0; i < steps; i++) {
      double t0 = bench_now_ms();
      if (fluid_sim_step(s, 1.0 / 60, err, sizeof err) != 0) {
        fprintf(stderr, "%s\n", err);
        return 1;
      }
      ms[i] = bench_now_ms() - t0;
      sub += fluid_sim_last_substeps(s);
    }
    qsort(ms, steps, sizeof(double), bench_cmp_double);
    double med = ms[steps / 2], per = (double)sub / steps;
    printf("| %u | %.2f | %.2f | %.1f | %.2f | %s |\n", n, med, ms[0], per, med / per,
           n == 16384 ? "<= 8 ms per step" : "");
    free(ms);
    free(pos);
    fluid_sim_destroy(s);
  }
  printf("\nCommand: %s %d\n", argv[0], steps);
  cl_dev_close(&dev);
  return 0;
}
