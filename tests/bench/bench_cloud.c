/*
 * The cloud automaton and its density pass (SPEC §5.4, paper 003) at 64³, 128³ and 256³: one
 * Kuromiya step, one Dobashi step and the density of the metaballs (radius 9 voxels at 64³,
 * scaled with the grid), each the median of several runs, on a cloud grown from the default
 * seeding until about a third of the cells are cloud. The paper drew a 64³ cloud at 33.33 FPS
 * (PentiumIII 550 MHz with a VolumePro 500 board), which leaves 30 ms per frame for
 * everything; it gives no time for the automaton alone.
 *
 *   bench_cloud [runs]
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "sim_cloud.h"
#include "bench_util.h"

static size_t count_cld(const cloud_cells_t *c) {
  size_t n = 0, words = (size_t)c->words * c->n[1] * c->n[2];
  for (size_t i = 0; i < words; i++)
    n += (size_t)__builtin_popcountll(c->cld[i]);
  return n;
}

int main(int argc, char **argv) {
  int runs = argc > 1 ? atoi(argv[1]) : 9;
  if (runs < 1 || runs > 1000)
    runs = 9;
  printf("# cloud automaton and density, median of %d runs (ms)\n", runs);
  printf("%-6s %8s %10s %10s %10s %12s %8s %14s\n", "grid", "cld", "kuromiya", "dobashi", "density",
         "density cpu", "radius", "step+density");
  const uint32_t sides[] = {64, 128, 256};
  for (int s = 0; s < 3; s++) {
    uint32_t n = sides[s], dims[3] = {n, n, n};
    cloud_params_t k = {.rules = CLOUD_KUROMIYA, .seed = 1};
    cloud_params_t d = {.rules = CLOUD_DOBASHI,
                        .p_ext = 0.001,
                        .p_hum = 0.005,
                        .p_act = 0.0005,
                        .wind = 0.5,
                        .seed = 1};
    cloud_cells_t *a = cloud_cells_new(dims), *b = cloud_cells_new(dims);
    float *dens = malloc(sizeof(float) * n * n * n);
    if (!a || !b || !dens) {
      fprintf(stderr, "out of memory\n");
      return 1;
    }
    cloud_cells_seed(a, &k, 0.6, 0.0005);
    /* Grow until about a third of the cells are cloud (or growth stops). */
    size_t total = (size_t)n * n * n;
    for (int i = 0; i < 4 * (int)n && count_cld(a) < total / 3; i++) {
      cloud_step(a, b, &k);
      cloud_cells_t *t = a;
      a = b;
      b = t;
    }
    size_t cld = count_cld(a);
    double radius = 9.0 * n / 64;
    double tk[1000], td[1000], tz[1000], tc[1000];
    for (int r = 0; r < runs; r++) {
      double t0 = bench_now_ms();
      cloud_step(a, b, &k);
      double t1 = bench_now_ms();
      cloud_step(a, b, &d);
      double t2 = bench_now_ms(), c2 = bench_cpu_ms();
      cloud_density(a, radius, dens);
      double t3 = bench_now_ms();
      tc[r] = bench_cpu_ms() - c2;
      tk[r] = t1 - t0;
      td[r] = t2 - t1;
      tz[r] = t3 - t2;
    }
    double mk = bench_median(tk, runs), md = bench_median(td, runs), mz = bench_median(tz, runs);
    printf("%-6u %7.1f%% %10.3f %10.3f %10.2f %12.2f %8.1f %14.2f\n", n, 100.0 * cld / total, mk,
           md, mz, bench_median(tc, runs), radius, mk + mz);
    cloud_cells_unref(a);
    cloud_cells_unref(b);
    free(dens);
  }
  printf("# paper 003: 64^3, metaball radius 9, 33.33 FPS drawn on a VolumePro 500 "
         "(30 ms per frame for everything)\n");
  return 0;
}
