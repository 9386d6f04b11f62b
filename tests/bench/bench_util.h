/*
 * What the C benchmarks share: clocks in milliseconds and the median of a set of runs. Header
 * only (every bench_*.c here is a program of its own). With render.h included first, also the
 * time of one pass of a render.
 */
#ifndef VOLFX_BENCH_UTIL_H
#define VOLFX_BENCH_UTIL_H

#include <stdlib.h>
#include <string.h>
#include <time.h>

/* Wall-clock milliseconds (monotonic). */
static inline double bench_now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec / 1e6;
}

/* CPU milliseconds of the whole process, all threads. */
static inline double bench_cpu_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec / 1e6;
}

/* For qsort: ascending doubles. */
static inline int bench_cmp_double(const void *a, const void *b) {
  double x = *(const double *)a, y = *(const double *)b;
  return (x > y) - (x < y);
}

/* The median of v[0 .. n) (n >= 1), which is sorted in place. */
static inline double bench_median(double *v, int n) {
  qsort(v, (size_t)n, sizeof *v, bench_cmp_double);
  return n % 2 ? v[n / 2] : (v[n / 2 - 1] + v[n / 2]) / 2;
}

#ifdef VOLFX_RENDER_H
/* Milliseconds of the pass 'name' of a render, 0 when it did not run. */
static inline double bench_pass_ms(const render_output_t *out, const char *name) {
  for (int i = 0; i < out->npasses; i++)
    if (strcmp(out->passes[i].name, name) == 0)
      return out->passes[i].ms;
  return 0;
}
#endif

#endif
