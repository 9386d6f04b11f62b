/*
 * The reclaimer (reclaim.h): a list of blocks and a thread that frees them. Each block is
 * linked through a small node; when the node cannot be allocated, the block is freed on the
 * caller, which is only slower.
 */
#include "reclaim.h"

#include <pthread.h>
#include <stdbool.h>
#include <stdlib.h>

typedef struct reclaim_node {
  struct reclaim_node *next;
  void *block;
} reclaim_node_t;

static pthread_mutex_t g_lock = PTHREAD_MUTEX_INITIALIZER;
static pthread_cond_t g_wake = PTHREAD_COND_INITIALIZER;
static pthread_t g_thread;
static bool g_running, g_stopping;
static reclaim_node_t *g_queue;
static size_t g_handed;

static void *reclaim_main(void *arg) {
  (void)arg;
  pthread_mutex_lock(&g_lock);
  for (;;) {
    while (!g_queue && !g_stopping)
      pthread_cond_wait(&g_wake, &g_lock);
    reclaim_node_t *list = g_queue;
    g_queue = NULL;
    if (!list && g_stopping)
      break;
    pthread_mutex_unlock(&g_lock);
    while (list) {
      reclaim_node_t *next = list->next;
      free(list->block);
      free(list);
      list = next;
    }
    pthread_mutex_lock(&g_lock);
  }
  pthread_mutex_unlock(&g_lock);
  return NULL;
}

int reclaim_start(void) {
  pthread_mutex_lock(&g_lock);
  int rc = 0;
  if (!g_running) {
    g_stopping = false;
    g_handed = 0;
    rc = pthread_create(&g_thread, NULL, reclaim_main, NULL) == 0 ? 0 : -1;
    g_running = rc == 0;
  }
  pthread_mutex_unlock(&g_lock);
  return rc;
}

void reclaim_stop(void) {
  pthread_mutex_lock(&g_lock);
  bool running = g_running;
  g_stopping = true;
  pthread_cond_signal(&g_wake);
  pthread_mutex_unlock(&g_lock);
  if (!running)
    return;
  pthread_join(g_thread, NULL);
  pthread_mutex_lock(&g_lock);
  g_running = false;
  pthread_mutex_unlock(&g_lock);
}

void reclaim_free(void *block, size_t bytes) {
  if (!block)
    return;
  reclaim_node_t *n = bytes >= RECLAIM_MIN_BYTES ? malloc(sizeof *n) : NULL;
  if (n) {
    pthread_mutex_lock(&g_lock);
    if (g_running && !g_stopping) {
      n->block = block;
      n->next = g_queue;
      g_queue = n;
      g_handed++;
      pthread_cond_signal(&g_wake);
      pthread_mutex_unlock(&g_lock);
      return;
    }
    pthread_mutex_unlock(&g_lock);
    free(n);
  }
  free(block);
}

size_t reclaim_handed(void) {
  pthread_mutex_lock(&g_lock);
  size_t n = g_handed;
  pthread_mutex_unlock(&g_lock);
  return n;
}
