/*
 * The render worker: one thread that owns the renderer (and so the OpenCL queue) and runs
 * render jobs in order. Jobs are submitted from the loop thread; each finished job's 'done'
 * callback runs back on the loop thread, woken by a uv_async handle. The loop never waits on
 * the worker.
 */
#ifndef VOLFX_WORKER_H
#define VOLFX_WORKER_H

#include <stdatomic.h>
#include <uv.h>

#include "render.h"

typedef struct job job_t;
typedef struct worker worker_t;

struct job {
  job_t *next;
  render_scene_t *scene; /* A reference, dropped by the worker when the job is done. */
  render_params_t params;
  rcamera_t camera; /* Used when 'has_camera'; params.camera points here. */
  int has_camera;
  render_depth_t *depth;  /* The client's depth buffer, owned; params.depth points here. Freed
                             with the scene reference (render_job_release, or the worker). */
  rcamera_t depth_camera; /* When 'depth_moved': the camera 'depth' was drawn with, whose view the
                             worker reprojects into the frame's before rendering. */
  int depth_moved;
  uint64_t frame; /* The snapshot's simulation frame and time. */
  double time;
  unsigned long version; /* The scene's version at the snapshot. */
  render_output_t out;   /* Filled by the worker; out.bytes belongs to the 'done' callback. */
  int code;              /* 0 or a PROTO_E_* code. */
  char err[512];
  uint64_t t_queued_ns, t_started_ns, t_done_ns;
  /*
   * When set, the job is not a render: the worker calls run(renderer, job) instead (with
   * 'scene' as the job left it), then 'done' as for a render.
   */
  void (*run)(renderer_t *r, job_t *j);
  /* A 'run' job that must happen even at shutdown (freeing what the worker owns): it is
   * queued past 'max_queue', and worker_stop runs it rather than cancelling it. */
  int must_run;
  /* A slice of work already admitted (the next part of a long simulation step): queued even
   * when 'max_queue' jobs wait, since refusing it would strand the work half done. Cancelled
   * at shutdown like any other. */
  int continues;
  /* Set by worker_submit: non-zero once the worker is stopping. A 'run' that can take long may
   * look at it and end early with PROTO_E_BUSY (nothing it would have made is wanted then). */
  const atomic_int *halt;
  void (*done)(job_t *j); /* Runs on the loop thread; frees the job. */
  void *ctx;
};

/* Starts the worker thread, which takes ownership of 'r'. Returns NULL on failure. */
worker_t *worker_start(uv_loop_t *loop, renderer_t *r, int max_queue);
/* Queues 'j'. Returns 0, or -1 when 'max_queue' jobs are already waiting (and 'j' is neither
 * must_run nor continues) or the worker has stopped. */
int worker_submit(worker_t *w, job_t *j);
/* Jobs waiting, not counting the one running. */
int worker_queue_depth(worker_t *w);
/*
 * Finishes the running job, fails the waiting ones with PROTO_E_BUSY ("shutting down"), runs
 * every 'done' callback, joins the thread, destroys the renderer and closes the async handle.
 * Must be called on the loop thread; the loop must run afterwards for the handle to close.
 */
void worker_stop(worker_t *w);

#endif
