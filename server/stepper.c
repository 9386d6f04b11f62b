/*
 * Long simulation stepping cut into slices that other scenes' renders can run between.
 *
 * A slice moves the scene's clock by some steps (scene_advance), owes them to the cloud and the
 * fluid (cloud_owe_steps, fluid_owe_steps) and submits jobs taking at most a slice's worth of
 * what they owe; its jobs report back through the stepper's sim_wait_t, and when the last one
 * is done the next slice is planned. The slice's size comes from the cost of a step that the
 * scene's last jobs measured (scene_t.cloud_step_ns, fluid_step_ns): about STEPPER_SLICE_NS of
 * worker time, never less than one step (a frame of a huge cloud is its own slice). Jobs chain
 * as pipelined jobs always did (cloud_link_t, the fluid's device state), and the state at a
 * frame does not depend on how its steps were grouped (docs/protocol.md, the frame-indexed
 * clock), so the slices compute exactly what one job of all the steps would.
 *
 * A scene without a cloud or fluid to step still moves its clock in parts: a wave animated
 * toward a target moves step by step, so a long run of steps can cost the loop thread
 * milliseconds; the parts are sized by scene_t.advance_ns, and between them the stepper waits
 * behind an empty job on the worker.
 */
#include "stepper.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "step_cloud.h"
#include "step_fluid.h"
#include "worker.h"

struct stepper {
  sim_wait_t wait; /* First member: the jobs report to it. */
  server_t *srv;
  char scene[64];
  uint64_t scene_id;
  uint64_t stops;      /* The scene's 'stops' at the start. */
  int cloud, fluid;    /* Which simulations it began stepping. */
  uint64_t cloud_gen;  /* Their cells' generation and particles' epoch at the start: */
  uint64_t epoch;      /* replaced ones end the stepping. */
  uint64_t clock_left; /* Clock steps not taken yet. */
  uint64_t cloud_left; /* Steps each simulation owes that this stepper waits for: */
  uint64_t fluid_left; /* those owed at its start and its own, less those submitted. */
  double dt;
  int pending; /* Jobs of the slice in flight. */
  int cancelled;
  stepper_end_t end; /* A failure of the slice in flight, if any. */
  stepper_cb cb;
  void *ctx;
};

/* The scene the stepper steps, or NULL when it was deleted (a later scene of the same name is
 * not it). */
static scene_entry_t *scene_of(const stepper_t *st) {
  scene_entry_t *e = server_find_scene(st->srv, st->scene);
  return e && e->scene->id == st->scene_id ? e : NULL;
}

uint64_t stepper_slice_steps(const scene_entry_t *e) {
  const scene_t *s = e->scene;
  double ns =
      (cloud_wants_step(e) ? s->cloud_step_ns : 0) + (fluid_wants_step(e) ? s->fluid_step_ns : 0);
  if (!(ns > 0))
    return 1; /* Unmeasured: one step, and its jobs measure it. */
  double n = STEPPER_SLICE_NS / ns;
  return n < 1 ? 1 : n > STEPPER_MAX_STEPS ? STEPPER_MAX_STEPS : (uint64_t)n;
}

/* The clock steps one advance may take: about STEPPER_ADVANCE_NS of loop time at the cost
 * measured (a thousand while unknown). */
static uint64_t advance_steps(const scene_t *s) {
  if (!(s->advance_ns > 0))
    return 1000;
  double n = STEPPER_ADVANCE_NS / s->advance_ns;
  return n < 1 ? 1 : n > STEPPER_MAX_STEPS ? STEPPER_MAX_STEPS : (uint64_t)n;
}

static uint64_t min3(uint64_t a, uint64_t b, uint64_t c) {
  uint64_t m = a < b ? a : b;
  return m < c ? m : c;
}

/* Ends the stepping: the callback, then the stepper is freed. */
static void finish(stepper_t *st, scene_entry_t *e) {
  st->end.scene = e;
  if (st->cb)
    st->cb(st->ctx, &st->end);
  free(st);
}

static void fail(stepper_t *st, int code, const char *fmt, const char *arg) {
  st->end.code = code;
  snprintf(st->end.err, sizeof st->end.err, fmt, arg);
}

/* Why the stepping must end before the next slice, or NULL. Fills st->end for failures. */
static const char *stop_reason(stepper_t *st, scene_entry_t *e) {
  if (st->srv->stopping || !st->srv->worker) {
    fail(st, PROTO_E_BUSY, "%s", "the server is shutting down");
    return "";
  }
  if (!e) {
    fail(st, PROTO_E_NOT_FOUND, "scene '%s' was deleted while it stepped", st->scene);
    return "";
  }
  const scene_t *s = e->scene;
  if (st->cancelled)
    return "cancelled";
  if (s->stops != st->stops)
    return "sim.pause";
  if (st->cloud && s->cloud_gen != st->cloud_gen)
    return "the cloud's cells were replaced";
  if (st->fluid && s->particles_epoch != st->epoch)
    return "the fluid's particles were replaced";
  return NULL;
}

static void yield_run(renderer_t *r, job_t *j) {
  (void)r;
  (void)j;
}

static int slice(stepper_t *st);

static void yield_done(job_t *j) {
  stepper_t *st = j->ctx;
  int code = j->code;
  free(j);
  if (code != 0) {
    fail(st, code, "%s", "the server is shutting down");
    finish(st, scene_of(st));
    return;
  }
  slice(st);
}

/* Queues an empty job to take the next slice behind whatever waits on the worker. Returns 0,
 * or -1 with st->end set. */
static int yield(stepper_t *st) {
  job_t *j = calloc(1, sizeof *j);
  if (!j) {
    fail(st, PROTO_E_INTERNAL, "%s", "out of memory");
    return -1;
  }
  j->run = yield_run;
  j->done = yield_done;
  j->ctx = st;
  j->continues = 1;
  if (worker_submit(st->srv->worker, j) != 0) {
    free(j);
    fail(st, PROTO_E_BUSY, "%s", "the server is shutting down");
    return -1;
  }
  return 0;
}

/* Moves the clock by up to 'n' steps within the loop time allowed, owing them to the
 * simulations stepped. */
static void advance(stepper_t *st, scene_entry_t *e, uint64_t n, int cloud, int fluid) {
  scene_t *s = e->scene;
  uint64_t k = min3(st->clock_left, n, advance_steps(s));
  if (k == 0)
    return;
  uint64_t t0 = uv_hrtime();
  scene_advance(s, k, st->dt);
  s->advance_ns = (double)(uv_hrtime() - t0) / (double)k;
  st->clock_left -= k;
  if (cloud) {
    cloud_owe_steps(e, k);
    st->cloud_left += k;
  }
  if (fluid) {
    fluid_owe_steps(e, k);
    st->fluid_left += k;
  }
}

/* Submits the slice's job of one simulation: up to 'n' of the steps '*left' counts. Returns 0,
 * or -1 with st->end set (the worker refused it). */
static int submit(stepper_t *st, scene_entry_t *e, int is_cloud, uint64_t n, uint64_t *left) {
  if (*left == 0)
    return 0;
  uint64_t want = n < *left ? n : *left;
  int64_t taken = is_cloud ? cloud_submit_step(st->srv, e, want, &st->wait)
                           : fluid_submit_step(st->srv, e, want, st->dt, &st->wait);
  if (taken < 0) {
    fail(st, PROTO_E_BUSY, "%s", "the render queue is full");
    return -1;
  }
  /* None taken: none owed any more (another job took them); nothing left to wait for. */
  *left = taken == 0 ? 0 : *left - (uint64_t)taken;
  st->pending += taken > 0;
  return 0;
}

/* Plans and submits the next slice, or ends the stepping. Returns 1 when it ended (st freed). */
static int slice(stepper_t *st) {
  scene_entry_t *e = scene_of(st);
  const char *why = stop_reason(st, e);
  if (why) {
    st->end.cut = st->end.code ? NULL : why;
    finish(st, e);
    return 1;
  }
  int cloud = cloud_wants_step(e), fluid = fluid_wants_step(e);
  if (!cloud && !fluid) {
    /* Only the clock: parts of it within the loop time, the rest after a yield. */
    uint64_t t0 = uv_hrtime();
    while (st->clock_left > 0 && (double)(uv_hrtime() - t0) < STEPPER_ADVANCE_NS)
      advance(st, e, STEPPER_MAX_STEPS, 0, 0);
    if (st->clock_left == 0) {
      finish(st, e);
      return 1;
    }
    if (yield(st) != 0) {
      finish(st, e);
      return 1;
    }
    return 0;
  }
  uint64_t n = stepper_slice_steps(e);
  /* The clock takes what the slice has room for beside the steps this stepper still waits
   * for (sim.play's owed steps among them). */
  uint64_t owed = cloud ? st->cloud_left : 0, fowed = fluid ? st->fluid_left : 0;
  if (fowed > owed)
    owed = fowed;
  advance(st, e, n > owed ? n - owed : 0, cloud, fluid);
  if ((cloud && submit(st, e, 1, n, &st->cloud_left) != 0) ||
      (fluid && submit(st, e, 0, n, &st->fluid_left) != 0)) {
    if (st->pending == 0) {
      finish(st, e);
      return 1;
    }
    return 0; /* Ends when the jobs submitted are done. */
  }
  if (st->pending > 0)
    return 0;
  if (st->clock_left == 0) {
    finish(st, e); /* Nothing owed, nothing left. */
    return 1;
  }
  if (yield(st) != 0) {
    finish(st, e);
    return 1;
  }
  return 0;
}

/* A job of the slice is done; the last one plans the next slice. */
static void on_job_done(sim_wait_t *w, int code, const char *err) {
  stepper_t *st = (stepper_t *)w;
  if (code != 0 && st->end.code == 0) {
    st->end.code = code;
    snprintf(st->end.err, sizeof st->end.err, "%s", err);
  }
  if (--st->pending > 0)
    return;
  if (st->end.code != 0)
    finish(st, scene_of(st));
  else
    slice(st);
}

int stepper_start(server_t *srv, scene_entry_t *e, uint64_t steps, double dt, stepper_cb cb,
                  void *ctx, stepper_t **out) {
  const scene_t *s = e->scene;
  int cloud = cloud_wants_step(e), fluid = fluid_wants_step(e);
  /* Room for the first slice's jobs; the later slices are queued past the limit (continues). */
  if ((cloud || fluid) &&
      (!srv->worker || worker_queue_depth(srv->worker) + cloud + fluid > srv->cfg.render_queue))
    return -1;
  stepper_t *st = calloc(1, sizeof *st);
  if (!st)
    return -1;
  st->wait.done = on_job_done;
  st->srv = srv;
  snprintf(st->scene, sizeof st->scene, "%s", s->name);
  st->scene_id = s->id;
  st->stops = s->stops;
  st->cloud = cloud;
  st->fluid = fluid;
  st->cloud_gen = s->cloud_gen;
  st->epoch = s->particles_epoch;
  st->clock_left = steps;
  st->cloud_left = cloud ? cloud_owed(e) : 0;
  st->fluid_left = fluid ? fluid_owed(e) : 0;
  st->dt = dt;
  st->cb = cb;
  st->ctx = ctx;
  if (slice(st))
    return 1;
  if (out)
    *out = st;
  return 0;
}

void stepper_cancel(stepper_t *st) {
  st->cancelled = 1;
}

void stepper_stop_scene(scene_entry_t *e) {
  e->scene->stops++;
}
