/*
 * The render worker thread, the PNG encoder thread, and their queues: 'todo' (loop → worker),
 * 'encode' (worker → encoder) and 'done' (worker or encoder → loop). All are guarded by one
 * mutex; the threads sleep on condition variables and wake the loop with uv_async_send, which
 * coalesces, so the loop drains every finished job at once. PNG encoding runs on its own thread
 * so that a stream of frames overlaps the encoding of one frame with the rendering of the next.
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
  uv_thread_t encoder;
  uv_cond_t encode_cv;
  job_t *todo_head, *todo_tail;
  job_t *encode_head, *encode_tail;
  job_t *done_head, *done_tail;
  int depth;
  int max_queue;
  int stop;        /* The render thread stops. */
  atomic_int halt; /* Set with 'stop', read by running jobs without the lock (job_t.halt). */
  int encode_stop; /* The encoder stops once its queue is empty (set after 'stop' is joined). */
  renderer_t *renderer;
};

static uint64_t mono_ns(void) {
  return uv_hrtime();
}

/* Drops what a job holds for its render: the scene reference and the client's depth buffer. */
static void job_drop_inputs(job_t *j) {
  render_scene_unref(j->scene);
  j->scene = NULL;
  render_depth_free(j->depth);
  j->depth = NULL;
  j->params.depth = NULL;
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
    int encode = 0;
    if (j->run) {
      j->run(w->renderer, j);
    } else {
      if (j->has_camera)
        j->params.camera = &j->camera;
      /* A depth buffer drawn with another camera is reprojected here, off the loop thread
       * (about 5.6 ms at 640x360), and timed as the frame's first pass, "reproject". */
      uint64_t t0 = mono_ns();
      int moved = j->depth_moved && j->depth;
      if (moved && render_depth_reproject(j->depth, &j->depth_camera,
                                          j->has_camera ? &j->camera : &j->scene->camera, j->err,
                                          sizeof j->err) != 0) {
        j->code = PROTO_E_INTERNAL;
      } else {
        double ms = (double)(mono_ns() - t0) / 1e6;
        /* A format with an encoder is rendered to its raw pixels here and encoded by the
         * encoder thread. */
        encode = render_format_get(j->params.format)->encode != NULL;
        j->params.raw = encode;
        j->code =
            renderer_render(w->renderer, j->scene, &j->params, &j->out, j->err, sizeof j->err);
        render_output_t *o = &j->out;
        if (j->code == 0 && moved && o->npasses < RENDER_MAX_PASSES) {
          memmove(&o->passes[1], &o->passes[0], (size_t)o->npasses * sizeof o->passes[0]);
          o->passes[0].name = "reproject";
          o->passes[0].ms = ms;
          o->npasses++;
          o->total_ms += ms;
        }
      }
    }
    j->t_done_ns = mono_ns();
    job_drop_inputs(j);

    uv_mutex_lock(&w->mu);
    if (encode && j->code == 0) {
      push(&w->encode_head, &w->encode_tail, j);
      uv_cond_signal(&w->encode_cv);
      continue;
    }
    push(&w->done_head, &w->done_tail, j);
    uv_async_send(&w->async);
  }
  uv_mutex_unlock(&w->mu);
}

/* Encodes one rendered frame in place with its format's encoder, recording the "encode" pass. */
static void encode_job(job_t *j) {
  j->code = render_output_encode(render_format_get(j->params.format), &j->params, &j->out, j->err,
                                 sizeof j->err);
  j->t_done_ns = mono_ns();
}

/* The encoder thread: runs until stopped and its queue is empty. */
static void encoder_main(void *arg) {
  worker_t *w = arg;
  uv_mutex_lock(&w->mu);
  for (;;) {
    while (!w->encode_head && !w->encode_stop)
      uv_cond_wait(&w->encode_cv, &w->mu);
    job_t *j = w->encode_head;
    if (!j)
      break; /* Stopped, and nothing left to encode. */
    w->encode_head = j->next;
    if (!w->encode_head)
      w->encode_tail = NULL;
    uv_mutex_unlock(&w->mu);
    encode_job(j);
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
  atomic_init(&w->halt, 0);
  w->renderer = r;
  w->max_queue = max_queue;
  uv_mutex_init(&w->mu);
  uv_cond_init(&w->cv);
  uv_cond_init(&w->encode_cv);
  uv_async_init(loop, &w->async, on_async);
  w->async.data = w;
  if (uv_thread_create(&w->thread, worker_main, w) != 0) {
    LOG(LOG_ERROR, "worker", "cannot start the render thread");
    uv_close((uv_handle_t *)&w->async, NULL);
    return NULL;
  }
  if (uv_thread_create(&w->encoder, encoder_main, w) != 0) {
    LOG(LOG_ERROR, "worker", "cannot start the encoder thread");
    uv_mutex_lock(&w->mu);
    w->stop = 1;
    uv_cond_signal(&w->cv);
    uv_mutex_unlock(&w->mu);
    uv_thread_join(&w->thread);
    uv_close((uv_handle_t *)&w->async, NULL);
    return NULL;
  }
  return w;
}

int worker_submit(worker_t *w, job_t *j) {
  uv_mutex_lock(&w->mu);
  if ((w->depth >= w->max_queue && !j->must_run && !j->continues) || w->stop) {
    uv_mutex_unlock(&w->mu);
    return -1;
  }
  j->t_queued_ns = mono_ns();
  j->halt = &w->halt;
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
  uv_cond_destroy(&w->encode_cv);
  free(w);
}

void worker_stop(worker_t *w) {
  uv_mutex_lock(&w->mu);
  w->stop = 1;
  atomic_store(&w->halt, 1);
  job_t *cancelled = w->todo_head;
  w->todo_head = w->todo_tail = NULL;
  w->depth = 0;
  uv_cond_signal(&w->cv);
  uv_mutex_unlock(&w->mu);
  uv_thread_join(&w->thread);
  /* Only now can nothing more reach the encoder; it finishes its queue, then exits. */
  uv_mutex_lock(&w->mu);
  w->encode_stop = 1;
  uv_cond_signal(&w->encode_cv);
  uv_mutex_unlock(&w->mu);
  uv_thread_join(&w->encoder);

  /* Jobs the worker finished, then jobs it never started, all answered on this thread. */
  on_async(&w->async);
  while (cancelled) {
    job_t *next = cancelled->next;
    if (cancelled->must_run) {
      /* The worker thread is gone, so this thread may use the renderer. */
      cancelled->run(w->renderer, cancelled);
    } else {
      cancelled->code = PROTO_E_BUSY;
      snprintf(cancelled->err, sizeof cancelled->err, "the server is shutting down");
    }
    job_drop_inputs(cancelled);
    cancelled->done(cancelled);
    cancelled = next;
  }
  renderer_destroy(w->renderer);
  w->renderer = NULL;
  uv_close((uv_handle_t *)&w->async, on_async_closed);
}
