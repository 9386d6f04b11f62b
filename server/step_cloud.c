/*
 * The cloud's stepping on the server (SPEC §5.4): the automaton steps and density passes that
 * sim.step, sim.play, the background jobs, scene.set and cloud.set_cells submit to the render
 * worker, and the steps the cloud owes the clock.
 *
 * A scene's cells and shown density are immutable and shared (scene.h). A job takes
 * references to them, steps the automaton into new cells on the worker (plain C: see
 * docs/architecture.md), computes their density, blends it with the density shown so far
 * (cloud.smoothing) and hands both back; its 'done' callback makes them the scene's unless the
 * scene was deleted or its cells replaced meanwhile (cloud_gen changed). Jobs queued back to
 * back chain through their cloud_link_t: each starts from what the one before it produced, so
 * pipelined sim.step calls all count.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "log.h"
#include "reclaim.h"
#include "step_cloud.h"
#include "worker.h"

typedef struct cloud_job {
  job_t job;
  server_t *srv;
  char scene[64];
  uint64_t gen;          /* The scene's cloud_gen the job belongs to. */
  call_t *call;          /* cloud.set_cells or a density for scene.set: answered when done. */
  sim_wait_t *wait;      /* Steps: told when done (a stepper), or NULL. */
  const char *field;     /* cloud.set_cells: the field set; NULL otherwise. */
  int answers_version;   /* scene.set: answered with 'version'. */
  uint64_t version;      /* The scene's version after that scene.set. */
  cloud_cells_t *in;     /* The scene's cells at submission (a reference). */
  density_grid_t *shown; /* The scene's density at submission (a reference). */
  cloud_link_t *prev;    /* The job queued before this one, or NULL (a reference). */
  cloud_link_t *res;     /* This job's result (a reference; the scene may hold another). */
  scene_cloud_t cfg;
  unsigned steps;  /* Automaton steps: at most STEPPER_MAX_STEPS × 64 steps_per_frame. */
  uint64_t frames; /* Simulation steps (steps / steps_per_frame), for the cost measured. */
  float keep;      /* Fraction of the shown density kept. */
} cloud_job_t;

/*
 * Worker thread: the steps and the density. The density shown is blended once per simulation
 * step (cloud.steps_per_frame automaton steps), S = D + keep (S - D) with D the density of the
 * cells after that step. Every step of a job runs the same operations on the same values as
 * a job of that one step would, so the cells and the density at a frame are the same bits
 * however the steps were grouped into calls, ticks or snapshots. What is saved is work that
 * cannot change a bit: Kuromiya cells with no active cell left stay as they are, so their
 * steps are counted without being run and their D is computed once; without blending only the
 * last D is computed.
 */
static void cloud_run(renderer_t *r, job_t *j) {
  (void)r;
  cloud_job_t *cj = (cloud_job_t *)j;
  cloud_cells_t *src = cj->in;
  density_grid_t *shown = cj->shown;
  if (cj->prev && cj->prev->ok) {
    src = cj->prev->cells;
    shown = cj->prev->density;
  }
  size_t n = cloud_cells_count(src);
  unsigned per = cj->cfg.steps_per_frame ? cj->cfg.steps_per_frame : 1;
  unsigned frames = cj->steps / per + (cj->steps % per != 0);
  int blend =
      cj->keep > 0 && frames > 0 && shown && memcmp(shown->dims, src->n, sizeof src->n) == 0;
  cloud_cells_t *buf[2] = {NULL, NULL}, *cur = src;
  /* Every density of d is written below: no zeroing. */
  density_grid_t *d = density_grid_alloc(src->n);
  float *next = blend ? reclaim_alloc(n * sizeof *next) : NULL;
  float *still_d = NULL; /* The density of cells that no longer change, once computed. */
  if (!d || (blend && !next))
    goto oom;
  if (cj->steps > 0) {
    buf[0] = cloud_cells_new(src->n);
    buf[1] = cj->steps > 1 ? cloud_cells_new(src->n) : NULL;
    if (!buf[0] || (cj->steps > 1 && !buf[1]))
      goto oom;
  }
  /* With blending, each density computed is blended with the one before, 'prev' (first the one
   * shown, read in place), into d->data and 'next' by turns. */
  const float *prev = blend ? shown->data : NULL;
  /* The step the density in 'prev' shows; the wind carries it along with the cells. */
  uint64_t shown_step = src->step;
  unsigned taken = 0, run = 0;
  uint64_t counted = 0; /* Steps of still cells, counted but not run. */
  int still = 0;
  for (unsigned f = 0; f < frames; f++) {
    for (unsigned i = 0; i < per && taken < cj->steps; i++, taken++) {
      if (j->halt && atomic_load_explicit(j->halt, memory_order_relaxed))
        goto halted; /* A frame of a huge grid takes seconds; a stopping server does not wait. */
      if (!still)
        still = cj->cfg.params.rules == CLOUD_KUROMIYA && !cloud_cells_any(cur, CLOUD_ACT);
      if (still) {
        counted++;
        continue;
      }
      cloud_cells_t *out = buf[run++ % 2];
      cloud_step(cur, out, &cj->cfg.params);
      cur = out;
    }
    if (!blend && f + 1 < frames)
      continue; /* Only the last density is kept. */
    float *target = blend && prev == d->data ? next : d->data;
    if (still && still_d) {
      memcpy(target, still_d, n * sizeof *target);
    } else {
      if (cloud_density(cur, cj->cfg.radius, target) != 0)
        goto oom;
      if (still && f + 1 < frames) {
        still_d = reclaim_alloc(n * sizeof *still_d);
        if (!still_d)
          goto oom;
        memcpy(still_d, target, n * sizeof *target);
      }
    }
    if (blend) {
      uint64_t now = cur->step + counted;
      cloud_blend_shifted(target, prev, src->n, cloud_wind_shift(&cj->cfg.params, shown_step, now),
                          cj->keep);
      shown_step = now;
      prev = target;
    }
  }
  if (counted > 0) {
    if (cur == src) { /* Shared and immutable: the count goes on a copy. */
      cloud_cells_unref(buf[0]);
      buf[0] = cur = cloud_cells_copy(src);
      if (!cur)
        goto oom;
    }
    cur->step += counted;
  }
  if (frames == 0 && cloud_density(cur, cj->cfg.radius, d->data) != 0)
    goto oom;
  if (blend && prev == next) { /* The last blend went to 'next': it is the density. */
    float *last = next;
    next = d->data;
    d->data = last;
  }
  cj->res->cells = cloud_cells_ref(cur);
  cj->res->density = d;
  cj->res->ok = 1;
  reclaim_free(next, n * sizeof *next);
  reclaim_free(still_d, n * sizeof *still_d);
  cloud_cells_unref(buf[0]);
  cloud_cells_unref(buf[1]);
  return;
halted:
  j->code = PROTO_E_BUSY;
  snprintf(j->err, sizeof j->err, "the server is shutting down");
  goto fail;
oom:
  j->code = PROTO_E_INTERNAL;
  snprintf(j->err, sizeof j->err, "out of memory for a %ux%ux%u cloud", src->n[0], src->n[1],
           src->n[2]);
fail:
  density_grid_unref(d);
  reclaim_free(next, n * sizeof *next);
  reclaim_free(still_d, n * sizeof *still_d);
  cloud_cells_unref(buf[0]);
  cloud_cells_unref(buf[1]);
}

/* Loop thread: publishes the result and answers the call. */
static void cloud_done(job_t *j) {
  cloud_job_t *cj = (cloud_job_t *)j;
  scene_entry_t *e = server_find_scene(cj->srv, cj->scene);
  scene_t *s = e ? e->scene : NULL;
  if (s && s->cloud_chain == cj->res) {
    cloud_link_unref(s->cloud_chain);
    s->cloud_chain = NULL;
  }
  if (j->code == 0 && s && s->cloud_gen == cj->gen) {
    cloud_cells_t *c = cloud_cells_ref(cj->res->cells);
    density_grid_t *d = density_grid_ref(cj->res->density);
    if (scene_set_cloud(s, c, d, 0) != 0) {
      cloud_cells_unref(c);
      density_grid_unref(d);
      j->code = PROTO_E_INTERNAL;
      snprintf(j->err, sizeof j->err, "out of memory");
    }
  }
  if (j->code == 0 && s && cj->frames > 0) /* What a step costs, for sizing slices. */
    s->cloud_step_ns = (double)(j->t_done_ns - j->t_started_ns) / (double)cj->frames;
  if (j->code != 0 && !cj->call && !cj->wait)
    LOG(LOG_WARN, "cloud", "a cloud step failed: %s", j->err);
  if (cj->wait) {
    char err[600];
    snprintf(err, sizeof err, "%s: cloud: %s", proto_err_message(j->code), j->err);
    cj->wait->done(cj->wait, j->code, err);
  }
  if (cj->call) {
    if (j->code != 0) {
      call_error(cj->call, j->code, NULL, "%s: cloud: %s", proto_err_message(j->code), j->err);
    } else if (cj->answers_version) {
      cJSON *r = cJSON_CreateObject();
      cJSON_AddNumberToObject(r, "version", (double)cj->version);
      call_result(cj->call, r);
    } else {
      cJSON *r = cJSON_CreateObject();
      cJSON_AddStringToObject(r, "field", cj->field);
      cJSON_AddNumberToObject(r, "cells", (double)cloud_cells_count(cj->res->cells));
      call_result(cj->call, r);
    }
  }
  cloud_cells_unref(cj->in);
  density_grid_unref(cj->shown);
  cloud_link_unref(cj->prev);
  cloud_link_unref(cj->res);
  free(cj);
}

/* A job of 'steps' automaton steps of the cloud of 's' (0: the density alone), chained after
 * the job in flight, if any; NULL on OOM. */
static cloud_job_t *job_new(server_t *srv, scene_t *s, unsigned steps, float keep, call_t *call) {
  cloud_job_t *cj = calloc(1, sizeof *cj);
  if (!cj)
    return NULL;
  cj->res = cloud_link_new();
  if (!cj->res) {
    free(cj);
    return NULL;
  }
  cj->srv = srv;
  snprintf(cj->scene, sizeof cj->scene, "%s", s->name);
  cj->gen = s->cloud_gen;
  cj->call = call;
  cj->in = cloud_cells_ref(s->cloud_cells);
  cj->shown = density_grid_ref(s->cloud_density);
  cj->prev = cloud_link_ref(s->cloud_chain);
  scene_cloud_config(s, &cj->cfg);
  cj->steps = steps;
  cj->keep = keep;
  cj->job.run = cloud_run;
  cj->job.done = cloud_done;
  return cj;
}

static void job_free(cloud_job_t *cj) {
  cloud_cells_unref(cj->in);
  density_grid_unref(cj->shown);
  cloud_link_unref(cj->prev);
  cloud_link_unref(cj->res);
  free(cj);
}

/* Queues 'cj' as the scene's newest cloud job. Returns 0, or -1 (not queued, not freed). */
static int job_submit(server_t *srv, scene_t *s, cloud_job_t *cj) {
  if (!srv->worker || worker_submit(srv->worker, &cj->job) != 0)
    return -1;
  cloud_link_unref(s->cloud_chain);
  s->cloud_chain = cloud_link_ref(cj->res);
  return 0;
}

int cloud_wants_step(const scene_entry_t *e) {
  return e->scene->cloud_cells != NULL;
}

int cloud_busy(const scene_entry_t *e) {
  return e->scene->cloud_chain != NULL;
}

void cloud_owe_steps(scene_entry_t *e, uint64_t steps) {
  if (e->cloud_owed_gen != e->scene->cloud_gen)
    e->cloud_owed = 0, e->cloud_owed_gen = e->scene->cloud_gen;
  e->cloud_owed += steps;
}

uint64_t cloud_owed(const scene_entry_t *e) {
  return e->cloud_owed_gen == e->scene->cloud_gen ? e->cloud_owed : 0;
}

int64_t cloud_submit_step(server_t *srv, scene_entry_t *e, uint64_t max, sim_wait_t *w) {
  scene_t *s = e->scene;
  scene_cloud_t cfg;
  uint64_t owed = cloud_owed(e);
  if (scene_cloud_config(s, &cfg) != 0 || !s->cloud_cells || owed == 0)
    return 0;
  /* The oldest owed steps first; the job's automaton steps fit an unsigned with room to
   * spare (STEPPER_MAX_STEPS × 64). */
  uint64_t take = owed < max ? owed : max;
  if (take > STEPPER_MAX_STEPS)
    take = STEPPER_MAX_STEPS;
  cloud_job_t *cj = job_new(srv, s, (unsigned)(take * cfg.steps_per_frame), cfg.keep, NULL);
  if (!cj)
    return -1;
  cj->wait = w;
  cj->frames = take;
  cj->job.continues = w != NULL;
  if (job_submit(srv, s, cj) != 0) {
    job_free(cj);
    return -1;
  }
  e->cloud_owed = owed - take;
  return (int64_t)take;
}

int cloud_submit_density(server_t *srv, scene_entry_t *e, call_t *call) {
  scene_t *s = e->scene;
  if (!s->cloud_cells)
    return -1;
  cloud_job_t *cj = job_new(srv, s, 0, 0, call);
  if (!cj)
    return -1;
  cj->answers_version = 1;
  cj->version = s->version;
  if (job_submit(srv, s, cj) != 0) {
    job_free(cj);
    return -1;
  }
  return 0;
}

int cloud_submit_cells(server_t *srv, scene_entry_t *e, cloud_cells_t *cells, const char *field,
                       call_t *call) {
  scene_t *s = e->scene;
  cloud_job_t *cj = job_new(srv, s, 0, 0, call);
  if (!cj) {
    cloud_cells_unref(cells);
    return PROTO_E_INTERNAL;
  }
  cj->field = field;
  cloud_cells_unref(cj->in);
  cj->in = cloud_cells_ref(cells);
  cloud_link_unref(cj->prev);
  cj->prev = NULL;
  if (!srv->worker || worker_submit(srv->worker, &cj->job) != 0) {
    job_free(cj);
    cloud_cells_unref(cells);
    return PROTO_E_BUSY;
  }
  if (scene_set_cloud(s, cells, density_grid_ref(s->cloud_density), 1) != 0) {
    density_grid_unref(s->cloud_density);
    cloud_cells_unref(cells);
    cj->call = NULL; /* Dropped when done: generation 0 is never a cloud's. */
    cj->gen = 0;
    return PROTO_E_INTERNAL;
  }
  cj->gen = s->cloud_gen;
  s->cloud_chain = cloud_link_ref(cj->res);
  return 0;
}
