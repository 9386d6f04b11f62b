/*
 * The fluid's stepping on the server: the per-scene host of the particle simulation (SPEC
 * §5.2), the step jobs that sim.step, sim.play and the background jobs submit to the render
 * worker, and the steps the fluid owes the clock.
 *
 * The particles live on the host in the scene (an immutable particles_t). Each scene with a
 * fluid has a fluid_host_t, whose fluid_sim_t lives on the OpenCL device of the renderer and so
 * is created, used and destroyed on the worker thread only. A step job uploads the scene's
 * current particles, steps them and reads them back into a new particles_t, which its 'done'
 * callback swaps into the scene unless the scene went away or its particles were replaced
 * meanwhile (fluid.set_particles or a new fluid.initial wins: the scene's particles_epoch).
 * Emitters (fluid.emitters) add particles inside the simulation, up to fluid.max_particles. Step
 * jobs queued back to back chain: each continues from the state the last one left on the device, so
 * pipelined sim.step calls all count.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "log.h"
#include "sim_fluid.h"
#include "step_fluid.h"
#include "worker.h"

#define MIN_CAPACITY 1024u
/*
 * Slots every simulation keeps free past its capacity. kernels/sph.cl reads neighbours eight
 * at a time, up to seven past the end of a run, and the device copy of the last velocity
 * component has no written slack beyond its stride (the capacity rounded up to the kernels'
 * work-group size, a power of two from 16 to 64): a particle within seven of the stride's end
 * would fold unwritten memory (NaN, as often as not) into its viscosity sum. safe_cap keeps
 * this many slots between the capacity and the stride.
 */
#define OVERREACH 8u
#define STRIDE_ALIGN 64u
/* Room past max_particles for what the emitters add in the step that reaches it (each adds the
 * whole part of its accumulated rate × dt); trimmed after that step. */
#define MAX_OVERSHOOT 4096u

struct fluid_host {
  fluid_sim_t *sim;     /* Worker thread only. */
  uint32_t cap;         /* sim's max_particles. Worker thread only. */
  uint64_t sim_gen;     /* The scene's particles_epoch the sim's particles descend from; 0:
                           none. Worker thread only. */
  scene_entry_t *entry; /* NULL once the scene is removed. Loop thread only. */
  int busy;             /* Step jobs in flight. Loop thread only. */
  uint64_t owed;        /* Steps the clock took that no job has taken yet (sim.play ticks that
                           found a job running, a full queue). Loop thread only. */
  uint64_t owed_gen;    /* The particles_epoch 'owed' belongs to. Loop thread only. */
};

typedef struct fluid_job {
  job_t job;
  fluid_host_t *host;
  sim_wait_t *wait; /* Told when done (a stepper), or NULL (sim.play). */
  particles_t *in;  /* The particles stepped (a reference). */
  particles_t *out; /* The result, NULL on failure. */
  uint64_t gen;     /* The scene's particles_epoch when submitted. */
  uint64_t first;   /* The frame the first step starts from. */
  fluid_params_t params;
  uint32_t emit_max; /* The emitters stop at this many particles. */
  unsigned steps;    /* At most STEPPER_MAX_STEPS. */
  double dt;
} fluid_job_t;

static const cJSON *get(const cJSON *o, const char *name) {
  return cJSON_GetObjectItemCaseSensitive(o, name);
}

static void vec3(const cJSON *a, float out[3]) {
  for (int i = 0; i < 3; i++)
    out[i] = (float)cJSON_GetArrayItem(a, i)->valuedouble;
}

/* The most particles the emitters fill the scene's fluid to: fluid.max_particles within the
 * server's limit. */
static uint32_t emit_cap(const cJSON *doc, uint32_t limit) {
  double m = get(get(doc, "fluid"), "max_particles")->valuedouble;
  if (limit > FLUID_MAX_PARTICLES)
    limit = FLUID_MAX_PARTICLES;
  return m < (double)limit ? (uint32_t)m : limit;
}

/* Whether the fluid of 'doc' has an emitter that adds particles. */
static int emits(const cJSON *doc) {
  for (const cJSON *em = get(get(doc, "fluid"), "emitters")->child; em; em = em->next)
    if (get(em, "rate")->valuedouble > 0)
      return 1;
  return 0;
}

/* The emitters of the fluid of 'doc' into 'p'. */
static void emitters_of(const cJSON *doc, fluid_params_t *p) {
  p->nemitters = 0;
  for (const cJSON *em = get(get(doc, "fluid"), "emitters")->child;
       em && p->nemitters < FLUID_MAX_EMITTERS; em = em->next) {
    fluid_emitter_t *m = &p->emitters[p->nemitters++];
    int box = strcmp(get(em, "shape")->valuestring, "box") == 0;
    m->shape = box ? FLUID_EMIT_BOX : FLUID_EMIT_SPHERE;
    vec3(get(em, "position"), m->position);
    if (box) {
      vec3(get(em, "size"), m->size);
    } else {
      m->size[0] = (float)get(em, "radius")->valuedouble;
      m->size[1] = m->size[2] = 0;
    }
    m->rate = (float)get(em, "rate")->valuedouble;
    vec3(get(em, "velocity"), m->velocity);
  }
}

void fluid_params_of(const cJSON *doc, fluid_params_t *p) {
  const cJSON *f = get(doc, "fluid");
  fluid_params_default(p);
  p->h = (float)get(f, "h")->valuedouble;
  p->rest_density = (float)get(f, "rest_density")->valuedouble;
  double mass = get(f, "particle_mass")->valuedouble;
  p->particle_mass = mass > 0 ? (float)mass : fluid_lattice_mass(p->h, p->h / 2, p->rest_density);
  p->stiffness = (float)get(f, "stiffness")->valuedouble;
  p->viscosity = (float)get(f, "viscosity")->valuedouble;
  vec3(get(f, "gravity"), p->gravity);
  vec3(get(get(f, "bounds"), "min"), p->bounds_min);
  vec3(get(get(f, "bounds"), "max"), p->bounds_max);
  p->seed = (uint64_t)get(get(doc, "sim"), "seed")->valuedouble;
  emitters_of(doc, p);
}

/* The capacity for 'n' particles: a power of two, so that a growing fluid rarely reallocates. */
static uint32_t capacity_for(uint32_t n) {
  uint32_t c = MIN_CAPACITY;
  while (c < n && c < FLUID_MAX_PARTICLES)
    c <<= 1;
  return c;
}

/* A capacity of at least 'want' with OVERREACH slots before the next multiple of STRIDE_ALIGN
 * (and so before the stride of any work-group size dividing it). */
static uint32_t safe_cap(uint32_t want) {
  return (want + OVERREACH + STRIDE_ALIGN - 1) / STRIDE_ALIGN * STRIDE_ALIGN - OVERREACH;
}

/* Keeps the first 'n' particles of 'sim' (the oldest: get_particles returns them in the order
 * they were set or emitted). */
static int trim(fluid_sim_t *sim, uint32_t n, char *err, size_t errlen) {
  uint32_t have = fluid_sim_count(sim);
  if (have <= n)
    return 0;
  float *pos = malloc((size_t)have * 12), *vel = malloc((size_t)have * 12);
  int rc = -1;
  if (pos && vel) {
    fluid_sim_get_particles(sim, pos, vel);
    rc = fluid_sim_set_particles(sim, pos, vel, n, err, errlen);
  } else {
    snprintf(err, errlen, "out of memory");
  }
  free(pos);
  free(vel);
  return rc;
}

/* Worker thread: steps the job's particles into a new buffer. */
static void step_run(renderer_t *r, job_t *j) {
  fluid_job_t *fj = (fluid_job_t *)j;
  fluid_host_t *h = fj->host;
  particles_t *src = fj->in, *chained = NULL;
  if (h->sim && h->sim_gen == fj->gen) {
    /* Continue from the last step job's state, which may not have reached the scene yet. */
    chained = particles_new(fluid_sim_count(h->sim));
    if (!chained) {
      j->code = PROTO_E_INTERNAL;
      snprintf(j->err, sizeof j->err, "out of memory");
      return;
    }
    fluid_sim_get_particles(h->sim, chained->pos, chained->vel);
    src = chained;
  }
  h->sim_gen = 0;
  uint32_t n = src ? src->count : 0; /* NULL: none yet, for the emitters to fill. */
  /* With emitters the capacity is their limit plus MAX_OVERSHOOT, so that the simulation (and
   * the emitters' random sequence) lives on as they fill it; without, room for the particles
   * there are. Either way OVERREACH slots stay free past the capacity. */
  uint32_t emit_max = fj->emit_max;
  int emitting = fj->params.nemitters > 0 && n < emit_max;
  if (fj->params.nemitters > 0 && n <= emit_max)
    fj->params.max_particles = safe_cap(emit_max + MAX_OVERSHOOT);
  else
    fj->params.max_particles = capacity_for(n + OVERREACH);
  if (!emitting)
    fj->params.nemitters = 0;
  if (h->sim && h->cap != fj->params.max_particles) {
    fluid_sim_destroy(h->sim);
    h->sim = NULL;
  }
  if (!h->sim) {
    h->sim = fluid_sim_create(renderer_device(r), &fj->params, j->err, sizeof j->err);
    if (!h->sim) {
      j->code = PROTO_E_DEVICE;
      goto out;
    }
    h->cap = fj->params.max_particles;
  } else {
    /* Emptied first, so that new bounds never conflict with the particles of the last step. */
    if (fluid_sim_set_particles(h->sim, NULL, NULL, 0, j->err, sizeof j->err) != 0 ||
        fluid_sim_set_params(h->sim, &fj->params, j->err, sizeof j->err) != 0) {
      j->code = PROTO_E_INVALID_PARAMS;
      goto out;
    }
  }
  if (fluid_sim_set_particles(h->sim, src ? src->pos : NULL, src ? src->vel : NULL, n, j->err,
                              sizeof j->err) != 0) {
    j->code = PROTO_E_INVALID_PARAMS;
    goto out;
  }
  if (j->scene && fluid_sim_set_colliders(h->sim, j->scene->objects, j->scene->nobjects, j->err,
                                          sizeof j->err) != 0) {
    j->code = PROTO_E_INVALID_PARAMS;
    goto out;
  }
  fluid_sim_set_frame(h->sim, fj->first);
  for (unsigned i = 0; i < fj->steps; i++) {
    if (fluid_sim_step(h->sim, fj->dt, j->err, sizeof j->err) != 0) {
      j->code = PROTO_E_DEVICE;
      goto out;
    }
    if (emitting && fluid_sim_count(h->sim) >= emit_max) {
      /* Full: the emitters stop, and what the last step added beyond max_particles goes,
       * newest first. */
      emitting = 0;
      fj->params.nemitters = 0;
      if (trim(h->sim, emit_max, j->err, sizeof j->err) != 0 ||
          fluid_sim_set_params(h->sim, &fj->params, j->err, sizeof j->err) != 0) {
        j->code = PROTO_E_INTERNAL;
        goto out;
      }
    }
  }
  fj->out = particles_new(fluid_sim_count(h->sim));
  if (!fj->out) {
    j->code = PROTO_E_INTERNAL;
    snprintf(j->err, sizeof j->err, "out of memory");
    goto out;
  }
  fluid_sim_get_particles(h->sim, fj->out->pos, fj->out->vel);
  /* A diverged simulation is not published: the scene keeps the particles it had. */
  for (size_t i = 0; i < 3 * (size_t)fj->out->count; i++)
    if (!isfinite(fj->out->pos[i]) || !isfinite(fj->out->vel[i])) {
      j->code = PROTO_E_DEVICE;
      snprintf(j->err, sizeof j->err,
               "the simulation diverged (particle %zu is not finite); the particles are left as "
               "they were",
               i / 3);
      h->sim_gen = 0; /* Set up again from the scene's particles next time. */
      goto out;
    }
  h->sim_gen = fj->gen;
out:
  particles_unref(chained);
}

/* Loop thread: publishes the stepped particles and answers sim.step. */
static void step_done(job_t *j) {
  fluid_job_t *fj = (fluid_job_t *)j;
  fluid_host_t *h = fj->host;
  h->busy--;
  scene_entry_t *e = h->entry;
  int published = 0;
  if (j->code == 0 && e && fj->gen == e->scene->particles_epoch &&
      scene_set_particles(e->scene, fj->out) == 0)
    published = 1;
  if (!published)
    particles_unref(fj->out);
  if (j->code == 0 && e && fj->steps > 0) /* What a step costs, for sizing slices. */
    e->scene->fluid_step_ns = (double)(j->t_done_ns - j->t_started_ns) / fj->steps;
  if (j->code != 0 && !fj->wait)
    LOG(LOG_WARN, "fluid", "a fluid step failed: %s", j->err);
  if (fj->wait) {
    char err[600];
    snprintf(err, sizeof err, "%s: fluid: %s", proto_err_message(j->code), j->err);
    fj->wait->done(fj->wait, j->code, err);
  }
  particles_unref(fj->in);
  free(fj);
}

int fluid_wants_step(const scene_entry_t *e) {
  const scene_t *s = e->scene;
  return cJSON_IsTrue(get(get(s->doc, "fluid"), "enabled")) &&
         ((s->particles && s->particles->count > 0) || emits(s->doc));
}

int fluid_busy(const scene_entry_t *e) {
  return e->fluid && e->fluid->busy > 0;
}

/* The host of the scene's fluid, made on first use; NULL when out of memory. */
static fluid_host_t *host_of(scene_entry_t *e) {
  if (!e->fluid) {
    e->fluid = calloc(1, sizeof *e->fluid);
    if (e->fluid)
      e->fluid->entry = e;
  }
  return e->fluid;
}

void fluid_owe_steps(scene_entry_t *e, uint64_t steps) {
  fluid_host_t *h = host_of(e);
  if (!h)
    return;
  if (h->owed_gen != e->scene->particles_epoch)
    h->owed = 0, h->owed_gen = e->scene->particles_epoch;
  h->owed += steps;
}

uint64_t fluid_owed(const scene_entry_t *e) {
  const fluid_host_t *h = e->fluid;
  return h && h->owed_gen == e->scene->particles_epoch ? h->owed : 0;
}

int64_t fluid_submit_step(server_t *srv, scene_entry_t *e, uint64_t max, double dt, sim_wait_t *w) {
  fluid_host_t *h = e->fluid;
  uint64_t owed = fluid_owed(e);
  if (!h || owed == 0)
    return 0; /* Nothing owed: the particles are at the clock's frame. */
  uint64_t take = owed < max ? owed : max;
  if (take > STEPPER_MAX_STEPS)
    take = STEPPER_MAX_STEPS;
  fluid_job_t *fj = calloc(1, sizeof *fj);
  if (!fj)
    return -1;
  fj->host = h;
  fj->wait = w;
  fj->in = particles_ref(e->scene->particles);
  fluid_params_of(e->scene->doc, &fj->params);
  fj->emit_max = emit_cap(e->scene->doc, srv->cfg.limits.particles);
  fj->steps = (unsigned)take;
  fj->dt = dt;
  fj->gen = e->scene->particles_epoch;
  /* The owed steps end at the clock's frame: the oldest starts 'owed' frames before it. */
  uint64_t frame = (uint64_t)scene_frame(e->scene);
  fj->first = frame > owed ? frame - owed : 0;
  fj->job.scene = render_scene_ref(e->scene->snapshot);
  fj->job.run = step_run;
  fj->job.done = step_done;
  fj->job.continues = w != NULL;
  if (worker_submit(srv->worker, &fj->job) != 0) {
    render_scene_unref(fj->job.scene);
    particles_unref(fj->in);
    free(fj);
    return -1;
  }
  h->owed = owed - take;
  h->busy++;
  return (int64_t)take;
}

/* Worker thread (or the stopping thread): frees the device simulation. */
static void destroy_run(renderer_t *r, job_t *j) {
  (void)r;
  fluid_host_t *h = j->ctx;
  fluid_sim_destroy(h->sim);
  h->sim = NULL;
}

/* Loop thread: every step job of this host has been answered before this one. */
static void destroy_done(job_t *j) {
  free(j->ctx);
  free(j);
}

void fluid_scene_removed(server_t *srv, scene_entry_t *e) {
  fluid_host_t *h = e->fluid;
  if (!h)
    return;
  e->fluid = NULL;
  h->entry = NULL;
  job_t *j = calloc(1, sizeof *j);
  if (j) {
    j->run = destroy_run;
    j->done = destroy_done;
    j->must_run = 1;
    j->ctx = h;
    if (srv->worker && worker_submit(srv->worker, j) == 0)
      return;
    free(j);
  }
  /* Only reachable on OOM or with no worker: the simulation is leaked rather than touched
   * from the wrong thread. */
  LOG(LOG_WARN, "fluid", "cannot free the fluid simulation of scene '%s'", e->scene->name);
}
