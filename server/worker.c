/*
 * The render worker thread and its two queues: 'todo' (loop → worker) and 'done' (worker →
 * loop). Both are guarded by one mutex; the worker sleeps on a condition variable and wakes
 * the loop with uv_async_send, which coalesces, so the loop drains every finished job at once.
 */
#include "worker.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "log.h"

struct worker {
  uv_loop_t *loop;
  uv_async_t async;
  uv_thread_t thread;
  uv_mutex_t mu;
  uv_cond_t cv;
  job_t *todo_head, *todo_tail;
  job_t *done_head, *done_tail;
  int depth;
  int max_queue;
  int stop;
  renderer_t *renderer;
};

static uint64_t mono_ns(void) {
  return uv_hrtime();
}

static void push(job_t **head, job_t **tail, job_t *j) {
  j->next = NULL;
  if (*tail)
    (*tail)->next = j;
  else
    *head = j;
  *tail = j;
}

static void worker_main(void *arg) {
  worker_t *w = arg;
  uv_mutex_lock(&w->mu);
  for (;;) {
    while (!w->todo_head && !w->stop)
      uv_cond_wait(&w->cv, &w->mu);
    if (w->stop)
      break;
    job_t *j = w->todo_head;
    w->todo_head = j->next;
    if (!w->todo_head)
      w->todo_tail = NULL;
    w->depth--;
    uv_mutex_unlock(&w->mu);

    j->t_started_ns = mono_ns();
    if (j->has_camera)
      j->params.camera = &j->camera;
    j->code = renderer_render(w->renderer, j->scene, &j->params, &j->out, j->err, sizeof j->err);
    j->t_done_ns = mono_ns();
    render_scene_unref(j->scene);
    j->scene = NULL;

    uv_mutex_lock(&w->mu);
    push(&w->done_head, &w->done_tail, j);
    uv_async_send(&w->async);
  }
  uv_mutex_unlock(&w->mu);
}

/* Runs on the loop thread: hands every finished job to its callback. */
static void on_async(uv_async_t *a) {
  worker_t *w = a->data;
  uv_mutex_lock(&w->mu);
  job_t *j = w->done_head;
  w->done_head = w->done_tail = NULL;
  uv_mutex_unlock(&w->mu);
  while (j) {
    job_t *next = j->next;
    j->done(j);
    j = next;
  }
}

worker_t *worker_start(uv_loop_t *loop, renderer_t *r, int max_queue) {
  worker_t *w = calloc(1, sizeof *w);
  if (!w)
    return NULL;
  w->loop = loop;
  w->renderer = r;
  w->max_queue = max_queue;
  uv_mutex_init(&w->mu);
  uv_cond_init(&w->cv);
  uv_async_init(loop, &w->async, on_async);
  w->async.data = w;
  if (uv_thread_create(&w->thread, worker_main, w) != 0) {
    LOG(LOG_ERROR, "worker", "cannot start the render thread");
    uv_close((uv_handle_t *)&w->async, NULL);
    return NULL;
  }
  return w;
}

int worker_submit(worker_t *w, job_t *j) {
  uv_mutex_lock(&w->mu);
  if (w->depth >= w->max_queue || w->stop) {
    uv_mutex_unlock(&w->mu);
    return -1;
  }
  j->t_queued_ns = mono_ns();
  push(&w->todo_head, &w->todo_tail, j);
  w->depth++;
  uv_cond_signal(&w->cv);
  uv_mutex_unlock(&w->mu);
  return 0;
}

int worker_queue_depth(worker_t *w) {
  uv_mutex_lock(&w->mu);
  int d = w->depth;
  uv_mutex_unlock(&w->mu);
  return d;
}

static void on_async_closed(uv_handle_t *h) {
  worker_t *w = h->data;
  uv_mutex_destroy(&w->mu);
  uv_cond_destroy(&w->cv);
  free(w);
}

void worker_stop(worker_t *w) {
  uv_mutex_lock(&w->mu);
  w->stop = 1;
  job_t *cancelled = w->todo_head;
  w->todo_head = w->todo_tail = NULL;
  w->depth = 0;
  uv_cond_signal(&w->cv);
  uv_mutex_unlock(&w->mu);
  uv_thread_join(&w->thread);

  /* Jobs the worker finished, then jobs it never started, all answered on this thread. */
  on_async(&w->async);
  while (cancelled) {
    job_t *next = cancelled->next;
    render_scene_unref(cancelled->scene);
    cancelled->scene = NULL;
    cancelled->code = PROTO_E_BUSY;
    snprintf(cancelled->err, sizeof cancelled->err, "the server is shutting down");
    cancelled->done(cancelled);
    cancelled = next;
  }
  renderer_destroy(w->renderer);
  w->renderer = NULL;
  uv_close((uv_handle_t *)&w->async, on_async_closed);
}
