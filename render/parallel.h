/*
 * Host-side loops over a few threads and the CPU's vector width: the cloud automaton and its
 * density (sim_cloud.c), the light sweep and the packing of volume grids (render_volume.c).
 * Each is a few milliseconds of work on one core for grids from about 64³ up, worth a thread
 * per core (the machines volfxd runs on have a handful), not a pool.
 */
#ifndef VOLFX_PARALLEL_H
#define VOLFX_PARALLEL_H

#include <stddef.h>

/* The hot host loops are built for AVX-512, AVX2 and the baseline, picked at load time (GCC's
 * function multi-versioning; not under ASan, which does not support it). */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) &&                             \
    !defined(__SANITIZE_ADDRESS__)
#define PAR_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define PAR_CLONES
#endif

/* Most threads a split uses, the caller's included. */
#define PAR_MAX 4

/* How many parts to split 'work' units into: the online cores up to PAR_MAX, and one when
 * 'work' is below 'min_work' (a thread costs tens of microseconds to start). */
int par_parts(size_t work, size_t min_work);

/* Runs fn(parts + i * size) for i in [0, n) at the same time: parts 1 .. n-1 on threads of
 * their own, part 0 on the caller, so parts may wait for each other. Returns 0 when all are
 * done, or -1 having run none of them when a thread could not be started. */
int par_run_together(void *(*fn)(void *), void *parts, size_t size, int n);

/* The same for parts that do not wait for each other: when threads cannot be started, they run
 * one after another on the caller. Returns when all are done. */
void par_run(void *(*fn)(void *), void *parts, size_t size, int n);

#endif
