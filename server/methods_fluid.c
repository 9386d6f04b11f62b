/*
 * The particle fluid (SPEC §5.2) as the server runs it: fluid.set_particles and
 * fluid.get_particles, and the fluid step jobs that sim.step and sim.play submit.
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

#include "dispatch.h"
#include "fluid.h"
#include "frames.h"
#include "log.h"
#include "sim_fluid.h"
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

/* The simulation parameters of the scene's validated document, emitters included. */
static void params_of(const cJSON *doc, fluid_params_t *p) {
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
  params_of(e->scene->doc, &fj->params);
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

/* ---- Methods ---- */

static void set_particles_m(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  const cJSON *jp = get(call->params, "positions");
  const cJSON *jv = get(call->params, "velocities");
  const char *names[2] = {"positions", "velocities"};
  const cJSON *src[2] = {jp, jv};
  float *buf[2] = {NULL, NULL};
  long nbytes[2] = {0, 0};
  uint32_t limit = call->srv->cfg.limits.particles;
  if (limit > FLUID_MAX_PARTICLES)
    limit = FLUID_MAX_PARTICLES;
  for (int k = 0; k < 2; k++) {
    if (!src[k])
      continue;
    size_t len = strlen(src[k]->valuestring);
    size_t max = proto_b64_decoded_max(len);
    if ((uint64_t)max / 12 > (uint64_t)limit + 1) {
      call_error(call, PROTO_E_LIMIT, names[k], "%s: %s: more than the limit of %u particles",
                 proto_err_message(PROTO_E_LIMIT), names[k], limit);
      goto out;
    }
    buf[k] = malloc(max ? max : 1);
    if (!buf[k]) {
      call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
      goto out;
    }
    nbytes[k] = proto_b64_decode(src[k]->valuestring, len, buf[k]);
    if (nbytes[k] < 0) {
      call_error(call, PROTO_E_INVALID_PARAMS, names[k], "invalid params: %s: not valid base64",
                 names[k]);
      goto out;
    }
    if (nbytes[k] % 12 != 0) {
      call_error(call, PROTO_E_INVALID_PARAMS, names[k],
                 "invalid params: %s: %ld bytes is not a multiple of 12 (x, y, z as f32)", names[k],
                 nbytes[k]);
      goto out;
    }
  }
  if (jv && nbytes[1] != nbytes[0]) {
    call_error(call, PROTO_E_INVALID_PARAMS, "velocities",
               "invalid params: velocities: %ld bytes, but positions has %ld", nbytes[1],
               nbytes[0]);
    goto out;
  }
  uint32_t n = (uint32_t)(nbytes[0] / 12);
  if (n > limit) {
    call_error(call, PROTO_E_LIMIT, "positions", "%s: positions: %u particles, the limit is %u",
               proto_err_message(PROTO_E_LIMIT), n, limit);
    goto out;
  }
  scene_error_t serr;
  if (scene_particles_fit_budget(e->scene, n, "positions", &serr) != 0) {
    call_error(call, serr.code, serr.path, "%s: %s", proto_err_message(serr.code), serr.message);
    goto out;
  }
  fluid_params_t fp;
  params_of(e->scene->doc, &fp);
  for (uint32_t i = 0; i < n; i++)
    for (int c = 0; c < 3; c++) {
      /* Assembled from the bytes: the wire is little-endian whatever the host is. */
      const unsigned char *b = (const unsigned char *)buf[0] + 12 * (size_t)i + 4 * c;
      uint32_t u =
          (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 | (uint32_t)b[3] << 24;
      float x;
      memcpy(&x, &u, 4);
      buf[0][3 * (size_t)i + c] = x;
      if (!isfinite(x)) {
        call_error(call, PROTO_E_INVALID_PARAMS, "positions",
                   "invalid params: positions: particle %u is not finite", i);
        goto out;
      }
      if (x < fp.bounds_min[c] || x > fp.bounds_max[c]) {
        call_error(call, PROTO_E_INVALID_PARAMS, "positions",
                   "invalid params: positions: particle %u lies outside fluid.bounds", i);
        goto out;
      }
      if (jv) {
        b = (const unsigned char *)buf[1] + 12 * (size_t)i + 4 * c;
        u = (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 | (uint32_t)b[3] << 24;
        memcpy(&x, &u, 4);
        buf[1][3 * (size_t)i + c] = x;
        if (!isfinite(x)) {
          call_error(call, PROTO_E_INVALID_PARAMS, "velocities",
                     "invalid params: velocities: particle %u is not finite", i);
          goto out;
        }
      }
    }
  particles_t *p = particles_new(n);
  if (!p) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    goto out;
  }
  memcpy(p->pos, buf[0], (size_t)n * 12);
  if (jv)
    memcpy(p->vel, buf[1], (size_t)n * 12);
  if (scene_set_particles(e->scene, p) != 0) {
    particles_unref(p);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    goto out;
  }
  e->scene->particles_epoch++; /* Step jobs in flight now step stale particles: dropped. */
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "count", n);
  call_result(call, r);
out:
  free(buf[0]);
  free(buf[1]);
}

/* What fluid.get_particles sends: the particles (a reference, immutable; NULL for none), read
 * on any thread. */
typedef struct particles_out {
  particles_t *particles;
  int velocities;
} particles_out_t;

static unsigned char *particles_bytes(void *ctx, size_t *nbytes) {
  const particles_out_t *o = ctx;
  size_t n = o->particles ? (size_t)o->particles->count * 3 : 0;
  const float *src = !o->particles ? NULL : o->velocities ? o->particles->vel : o->particles->pos;
  *nbytes = 4 * n;
  unsigned char *bytes = malloc(*nbytes ? *nbytes : 1);
  if (!bytes)
    return NULL;
  for (size_t i = 0; i < n; i++) {
    uint32_t u;
    memcpy(&u, &src[i], 4);
    for (int b = 0; b < 4; b++)
      bytes[4 * i + b] = (unsigned char)(u >> (8 * b));
  }
  return bytes;
}

static void particles_out_drop(void *ctx) {
  particles_out_t *o = ctx;
  particles_unref(o->particles);
  free(o);
}

static void get_particles_m(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  const char *field = get(call->params, "field")->valuestring;
  int base64 = strcmp(get(call->params, "encoding")->valuestring, "base64") == 0;
  particles_t *p = e->scene->particles;
  uint32_t n = p ? p->count : 0;
  particles_out_t *o = malloc(sizeof *o);
  if (!o) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  *o = (particles_out_t){.particles = p ? particles_ref(p) : NULL,
                         .velocities = strcmp(field, "velocities") == 0};
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "count", n);
  cJSON_AddStringToObject(r, "field", field);
  call_result_made(call, r, particles_bytes, particles_out_drop, o, (size_t)n * 12, "f32", base64);
}

static const char *const fields[] = {"positions", "velocities", NULL};

static const sch_field_t set_params[] = {
    PARAM_SCENE,
    {.name = "positions",
     .type = SCH_STRING,
     .desc = "Base64 of n × (x, y, z) little-endian f32, each inside fluid.bounds; n at most "
             "limits.particles. Replaces every particle.",
     .unit = "world units",
     .flags = SCH_REQUIRED},
    {.name = "velocities",
     .type = SCH_STRING,
     .desc = "Base64 of n × (x, y, z) little-endian f32, as many as positions; absent: at rest.",
     .unit = "world units/second",
     .flags = SCH_NO_DEFAULT},
    {0}};
static const sch_field_t get_params[] = {
    PARAM_SCENE,
    {.name = "field",
     .type = SCH_ENUM,
     .desc = "Which array: positions (world units) or velocities (world units/second).",
     .enum_values = fields,
     .def_str = "positions"},
    {.name = "encoding",
     .type = SCH_ENUM,
     .desc = "binary: an attachment after the line; base64: inline in 'data'.",
     .enum_values = render_encodings,
     .def_str = "binary"},
    {0}};

static const int set_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, PROTO_E_LIMIT, 0};
static const int get_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, 0};

const method_t method_fluid_set_particles = {
    .name = "fluid.set_particles",
    .summary = "Replaces the fluid's particles; validated as a whole, nothing changes on error.",
    .params = METHOD_PARAMS(set_params),
    .result = "{count}",
    .errors = set_errors,
    .handler = set_particles_m};
const method_t method_fluid_get_particles = {
    .name = "fluid.get_particles",
    .summary = "The fluid's particle positions or velocities as little-endian f32 x, y, z.",
    .params = METHOD_PARAMS(get_params),
    .result = "{count, field} and an f32 attachment of 12 × count bytes.",
    .errors = get_errors,
    .handler = get_particles_m};
