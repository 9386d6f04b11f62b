/*
 * The reclaimer (reclaim.h): a list of the big blocks dropped, newest first and within the
 * store's bounds, from which reclaim_alloc can take one back, and a thread that frees those
 * older than RECLAIM_KEEP_MS and those pushed past the bounds. Each block is linked through a small
 * node; when the node cannot be allocated, the block is freed on the caller, which is only slower.
 *
 * Under AddressSanitizer a kept block is poisoned, so that a use after its free is still
 * reported, and unpoisoned when it is taken back.
 */
#include "reclaim.h"

#include <pthread.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdlib.h>
#include <time.h>

#if defined(__SANITIZE_ADDRESS__)
#include <sanitizer/asan_interface.h>
#define KEPT_POISON(p, n) ASAN_POISON_MEMORY_REGION(p, n)
#define KEPT_UNPOISON(p, n) ASAN_UNPOISON_MEMORY_REGION(p, n)
#else
#define KEPT_POISON(p, n) ((void)(p), (void)(n))
#define KEPT_UNPOISON(p, n) ((void)(p), (void)(n))
#endif

typedef struct reclaim_node {
  struct reclaim_node *next;
  void *block;
  size_t bytes;
  uint64_t dropped_ms; /* CLOCK_MONOTONIC, when reclaim_free took it. */
} reclaim_node_t;

static pthread_mutex_t g_lock = PTHREAD_MUTEX_INITIALIZER;
static pthread_cond_t g_wake;
static pthread_t g_thread;
static bool g_running, g_stopping;
static reclaim_node_t *g_kept; /* Newest first, within the bounds. */
static reclaim_node_t *g_due;  /* To be freed by the thread. */
static size_t g_kept_count, g_kept_bytes;
static size_t g_handed, g_reused;

static uint64_t now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (uint64_t)ts.tv_sec * 1000 + (uint64_t)ts.tv_nsec / 1000000;
}

/* Moves the kept blocks past the bounds, or older than 'now' allows (all when the reclaimer
 * stops), to the list to free. g_lock held. */
static void trim(uint64_t now) {
  reclaim_node_t **at = &g_kept;
  size_t count = 0, bytes = 0;
  /* Newest first: once one block is past a bound, all older ones are too. */
  while (*at && !g_stopping) {
    reclaim_node_t *k = *at;
    if (count + 1 > RECLAIM_KEEP_BLOCKS || bytes + k->bytes > RECLAIM_KEEP_BYTES ||
        now - k->dropped_ms >= RECLAIM_KEEP_MS)
      break;
    count++, bytes += k->bytes;
    at = &k->next;
  }
  reclaim_node_t *old = *at;
  *at = NULL;
  g_kept_count = count, g_kept_bytes = bytes;
  while (old) {
    reclaim_node_t *next = old->next;
    old->next = g_due;
    g_due = old;
    old = next;
  }
}

/* Milliseconds from 'now' until the oldest kept block falls due, or 0 when none is kept. */
static uint64_t next_due(uint64_t now) {
  for (reclaim_node_t *k = g_kept; k; k = k->next)
    if (!k->next)
      return k->dropped_ms + RECLAIM_KEEP_MS > now ? k->dropped_ms + RECLAIM_KEEP_MS - now : 1;
  return 0;
}

static void free_list(reclaim_node_t *list) {
  while (list) {
    reclaim_node_t *next = list->next;
    KEPT_UNPOISON(list->block, list->bytes);
    free(list->block);
    free(list);
    list = next;
  }
}

static void *reclaim_main(void *arg) {
  (void)arg;
  pthread_mutex_lock(&g_lock);
  for (;;) {
    uint64_t now = now_ms();
    trim(now);
    if (g_due) {
      reclaim_node_t *due = g_due;
      g_due = NULL;
      pthread_mutex_unlock(&g_lock);
      free_list(due);
      pthread_mutex_lock(&g_lock);
      continue;
    }
    if (g_stopping)
      break;
    uint64_t wait_ms = next_due(now);
    if (wait_ms == 0) {
      pthread_cond_wait(&g_wake, &g_lock);
    } else {
      struct timespec ts;
      clock_gettime(CLOCK_MONOTONIC, &ts);
      uint64_t ns = (uint64_t)ts.tv_nsec + (wait_ms % 1000) * 1000000;
      ts.tv_sec += (time_t)(wait_ms / 1000 + ns / 1000000000);
      ts.tv_nsec = (long)(ns % 1000000000);
      pthread_cond_timedwait(&g_wake, &g_lock, &ts);
    }
  }
  pthread_mutex_unlock(&g_lock);
  return NULL;
}

int reclaim_start(void) {
  pthread_mutex_lock(&g_lock);
  int rc = 0;
  if (!g_running) {
    pthread_condattr_t attr;
    rc = pthread_condattr_init(&attr) == 0 &&
                 pthread_condattr_setclock(&attr, CLOCK_MONOTONIC) == 0 &&
                 pthread_cond_init(&g_wake, &attr) == 0
             ? 0
             : -1;
    pthread_condattr_destroy(&attr);
    g_stopping = false;
    g_handed = g_reused = 0;
    if (rc == 0 && pthread_create(&g_thread, NULL, reclaim_main, NULL) != 0) {
      pthread_cond_destroy(&g_wake);
      rc = -1;
    }
    g_running = rc == 0;
  }
  pthread_mutex_unlock(&g_lock);
  return rc;
}

void reclaim_stop(void) {
  pthread_mutex_lock(&g_lock);
  bool running = g_running;
  g_stopping = true;
  if (running)
    pthread_cond_signal(&g_wake);
  pthread_mutex_unlock(&g_lock);
  if (!running)
    return;
  pthread_join(g_thread, NULL);
  pthread_mutex_lock(&g_lock);
  g_running = false;
  pthread_cond_destroy(&g_wake);
  pthread_mutex_unlock(&g_lock);
}

void reclaim_free(void *block, size_t bytes) {
  if (!block)
    return;
  reclaim_node_t *n = bytes >= RECLAIM_MIN_BYTES ? malloc(sizeof *n) : NULL;
  if (n) {
    pthread_mutex_lock(&g_lock);
    if (g_running && !g_stopping) {
      KEPT_POISON(block, bytes);
      *n = (reclaim_node_t){.next = g_kept, .block = block, .bytes = bytes, .dropped_ms = now_ms()};
      g_kept = n;
      g_kept_count++, g_kept_bytes += bytes;
      g_handed++;
      /* Past the bounds, the oldest go at once. Else the thread need not wake unless this is
       * the only block kept: it waits for the oldest's time. */
      int over = g_kept_count > RECLAIM_KEEP_BLOCKS || g_kept_bytes > RECLAIM_KEEP_BYTES;
      if (over)
        trim(n->dropped_ms);
      if (over || g_kept_count == 1)
        pthread_cond_signal(&g_wake);
      pthread_mutex_unlock(&g_lock);
      return;
    }
    pthread_mutex_unlock(&g_lock);
    free(n);
  }
  free(block);
}

void *reclaim_alloc(size_t bytes) {
  if (bytes >= RECLAIM_MIN_BYTES) {
    pthread_mutex_lock(&g_lock);
    for (reclaim_node_t **at = &g_kept; *at; at = &(*at)->next) {
      reclaim_node_t *k = *at;
      if (k->bytes != bytes)
        continue;
      *at = k->next;
      g_kept_count--, g_kept_bytes -= bytes;
      g_reused++;
      pthread_mutex_unlock(&g_lock);
      void *block = k->block;
      free(k);
      KEPT_UNPOISON(block, bytes);
      return block;
    }
    pthread_mutex_unlock(&g_lock);
  }
  return malloc(bytes);
}

size_t reclaim_handed(void) {
  pthread_mutex_lock(&g_lock);
  size_t n = g_handed;
  pthread_mutex_unlock(&g_lock);
  return n;
}

size_t reclaim_reused(void) {
  pthread_mutex_lock(&g_lock);
  size_t n = g_reused;
  pthread_mutex_unlock(&g_lock);
  return n;
}

size_t reclaim_kept_bytes(void) {
  pthread_mutex_lock(&g_lock);
  size_t n = g_kept_bytes;
  pthread_mutex_unlock(&g_lock);
  return n;
}
