/* Host-side loops over a few threads (parallel.h). */
#include "parallel.h"

#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <unistd.h>

int par_parts(size_t work, size_t min_work) {
  long cpus = sysconf(_SC_NPROCESSORS_ONLN);
  int n = cpus < 1 ? 1 : cpus > PAR_MAX ? PAR_MAX : (int)cpus;
  return work < min_work ? 1 : n;
}

/* A started thread's part, held until every thread has started (gate 1) or one could not
 * (gate -1: the thread returns without running it). */
typedef struct held {
  void *(*fn)(void *);
  void *arg;
  atomic_int *gate;
} held_t;

static void *run_held(void *arg) {
  held_t *h = arg;
  int g;
  while ((g = atomic_load_explicit(h->gate, memory_order_acquire)) == 0)
    sched_yield();
  if (g > 0)
    h->fn(h->arg);
  return NULL;
}

int par_run_together(void *(*fn)(void *), void *parts, size_t size, int n) {
  pthread_t th[PAR_MAX];
  held_t held[PAR_MAX];
  atomic_int gate = 0;
  char *p = parts;
  if (n > PAR_MAX)
    n = PAR_MAX;
  int started = 1;
  for (; started < n; started++) {
    held[started] = (held_t){fn, p + (size_t)started * size, &gate};
    if (pthread_create(&th[started], NULL, run_held, &held[started]) != 0)
      break;
  }
  int all = started == n;
  atomic_store_explicit(&gate, all ? 1 : -1, memory_order_release);
  if (all)
    fn(p);
  for (int i = 1; i < started; i++)
    pthread_join(th[i], NULL);
  return all ? 0 : -1;
}

void par_run(void *(*fn)(void *), void *parts, size_t size, int n) {
  if (n > 1 && par_run_together(fn, parts, size, n) == 0)
    return;
  for (int i = 0; i < n; i++)
    fn((char *)parts + (size_t)i * size);
}
