/*
 * Fresh state a commit seeds (seeding.h): the cloud's seeding and its steps, and the cache that
 * carries seedings from the thread pool to the request's retry. The particles' lattice is laid
 * out by seeding_particles.c.
 */
#include "seeding.h"

#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "proto.h"

struct seed_entry {
  seed_kind_t kind;
  scene_cloud_t cloud;     /* SEED_CLOUD: the key. */
  char *fluid;             /* SEED_PARTICLES: the key, the settings as unformatted JSON. */
  cloud_cells_t *cells;    /* References. */
  density_grid_t *density; /* Unsmoothed. */
  particles_t *particles;  /* NULL for none. */
  int pins;                /* Guarded by g_lock. */
  struct seed_entry *next;
};

static pthread_mutex_t g_lock = PTHREAD_MUTEX_INITIALIZER;
static struct seed_entry *g_entries; /* Guarded by g_lock. */
/* Armed deferral (loop thread only): where a want is recorded, or NULL; kinds done anyway. */
static seed_want_t *g_want;
static int g_skip[SEED_KINDS];

void seeding_defer(seed_want_t *want, const int skip[SEED_KINDS]) {
  g_want = want;
  for (int k = 0; k < SEED_KINDS; k++)
    g_skip[k] = want && skip ? skip[k] : 0;
}

void seed_want_clear(seed_want_t *want) {
  cJSON_Delete(want->fluid);
  want->fluid = NULL;
}

static void entry_free(struct seed_entry *e) {
  if (!e)
    return;
  cloud_cells_unref(e->cells);
  density_grid_unref(e->density);
  particles_unref(e->particles);
  free(e->fluid);
  free(e);
}

/* Whether 'a' and 'b' give the same cells and density: every setting but the smoothing and the
 * steps per frame, which act only later. */
static int same_seeding(const scene_cloud_t *a, const scene_cloud_t *b) {
  const cloud_params_t *p = &a->params, *q = &b->params;
  if (memcmp(a->n, b->n, sizeof a->n) != 0 || a->radius != b->radius ||
      a->init_hum != b->init_hum || a->init_act != b->init_act || a->init_steps != b->init_steps ||
      p->rules != q->rules || p->p_ext != q->p_ext || p->p_hum != q->p_hum ||
      p->p_act != q->p_act || p->wind != q->wind || p->seed != q->seed ||
      p->nellipsoids != q->nellipsoids)
    return 0;
  for (int i = 0; i < p->nellipsoids; i++)
    for (int k = 0; k < 3; k++)
      if (p->ellipsoids[i].center[k] != q->ellipsoids[i].center[k] ||
          p->ellipsoids[i].radii[k] != q->ellipsoids[i].radii[k])
        return 0;
  return 1;
}

/*
 * Seeds the cells of 'c', takes its init.steps automaton steps and fills the density of the
 * result (zero with no steps: no cloud cells yet). Returns 0, or -1 when out of memory.
 */
static int seed(const scene_cloud_t *c, cloud_cells_t **cells, density_grid_t **density) {
  cloud_cells_t *buf[2] = {cloud_cells_new(c->n), NULL};
  density_grid_t *d = buf[0] ? density_grid_new(c->n) : NULL;
  if (!d)
    goto oom;
  cloud_cells_seed(buf[0], &c->params, c->init_hum, c->init_act);
  if (c->init_steps > 0) {
    if (!(buf[1] = cloud_cells_new(c->n)))
      goto oom;
    /* Steps alternate between the two buffers, the seeded cells being the first 'in'. */
    for (unsigned i = 0; i < c->init_steps; i++)
      cloud_step(buf[i % 2], buf[(i + 1) % 2], &c->params);
    if (cloud_density(buf[c->init_steps % 2], c->radius, d->data) != 0)
      goto oom;
  }
  *cells = buf[c->init_steps % 2];
  cloud_cells_unref(buf[(c->init_steps + 1) % 2]);
  *density = d;
  return 0;
oom:
  cloud_cells_unref(buf[0]);
  cloud_cells_unref(buf[1]);
  density_grid_unref(d);
  return -1;
}

/* The cached entry of 'kind' for cloud settings 'c' or fluid settings 'fluid', or NULL. Called
 * with g_lock held. */
static struct seed_entry *find(seed_kind_t kind, const scene_cloud_t *c, const char *fluid) {
  for (struct seed_entry *e = g_entries; e; e = e->next)
    if (e->kind == kind &&
        (kind == SEED_CLOUD ? same_seeding(&e->cloud, c) : strcmp(e->fluid, fluid) == 0))
      return e;
  return NULL;
}

int cloud_seed_get(const scene_cloud_t *c, cloud_cells_t **cells, density_grid_t **density,
                   proto_error_t *err) {
  pthread_mutex_lock(&g_lock);
  struct seed_entry *e = find(SEED_CLOUD, c, NULL);
  if (e) {
    *cells = cloud_cells_ref(e->cells);
    *density = density_grid_ref(e->density);
  }
  pthread_mutex_unlock(&g_lock);
  if (e)
    return 0;
  char msg[128];
  if (g_want && !g_skip[SEED_CLOUD]) {
    g_want->kind = SEED_CLOUD;
    g_want->cloud = *c;
    snprintf(msg, sizeof msg, "cloud: %ux%ux%u cells are being seeded", c->n[0], c->n[1], c->n[2]);
    return proto_error_set(err, SCENE_DEFERRED_SEED, "cloud", "%s", msg);
  }
  if (seed(c, cells, density) == 0)
    return 0;
  snprintf(msg, sizeof msg, "out of memory for a %ux%ux%u cloud", c->n[0], c->n[1], c->n[2]);
  return proto_error_set(err, PROTO_E_INTERNAL, "cloud", "%s", msg);
}

/* The settings the particles of 'doc' are laid out from, as a document seeding_particles_of
 * reads: fluid.initial, fluid.h (the default spacing), fluid.bounds and the objects. NULL when
 * out of memory. */
static cJSON *fluid_settings(const cJSON *doc) {
  static const char *const fluid_keys[] = {"initial", "h", "bounds"};
  const cJSON *fluid = cJSON_GetObjectItem(doc, "fluid");
  cJSON *s = cJSON_CreateObject(), *f = s ? cJSON_AddObjectToObject(s, "fluid") : NULL;
  int ok = f != NULL;
  for (size_t i = 0; ok && i < sizeof fluid_keys / sizeof *fluid_keys; i++) {
    cJSON *v = cJSON_Duplicate(cJSON_GetObjectItem(fluid, fluid_keys[i]), 1);
    ok = v && cJSON_AddItemToObject(f, fluid_keys[i], v);
    if (!ok)
      cJSON_Delete(v);
  }
  cJSON *o = ok ? cJSON_Duplicate(cJSON_GetObjectItem(doc, "objects"), 1) : NULL;
  if (!o || !cJSON_AddItemToObject(s, "objects", o)) {
    cJSON_Delete(s);
    cJSON_Delete(o);
    return NULL;
  }
  return s;
}

int particles_seed_get(const cJSON *doc, particles_t **out, proto_error_t *err) {
  cJSON *settings = fluid_settings(doc);
  char *key = settings ? cJSON_PrintUnformatted(settings) : NULL;
  if (!key) {
    cJSON_Delete(settings);
    return proto_error_set(err, PROTO_E_INTERNAL, "fluid.initial", "out of memory");
  }
  pthread_mutex_lock(&g_lock);
  struct seed_entry *e = find(SEED_PARTICLES, NULL, key);
  particles_t *hit = e && e->particles ? particles_ref(e->particles) : NULL;
  pthread_mutex_unlock(&g_lock);
  free(key);
  if (e) {
    cJSON_Delete(settings);
    *out = hit;
    return 0;
  }
  if (g_want && !g_skip[SEED_PARTICLES]) {
    g_want->kind = SEED_PARTICLES;
    g_want->fluid = settings;
    return proto_error_set(err, SCENE_DEFERRED_SEED, "fluid.initial",
                           "fluid.initial: being laid out");
  }
  cJSON_Delete(settings);
  if (seeding_particles_of(doc, out) == 0)
    return 0;
  return proto_error_set(err, PROTO_E_INTERNAL, "fluid.initial", "out of memory");
}

int seeding_make(seed_want_t *want, seed_pin_t **pin) {
  *pin = NULL;
  struct seed_entry *made = calloc(1, sizeof *made);
  int ok = made != NULL;
  if (ok && want->kind == SEED_CLOUD) {
    made->cloud = want->cloud;
    ok = seed(&want->cloud, &made->cells, &made->density) == 0;
  } else if (ok) {
    made->fluid = cJSON_PrintUnformatted(want->fluid);
    ok = made->fluid && seeding_particles_of(want->fluid, &made->particles) == 0;
  }
  if (!ok) {
    seed_want_clear(want);
    entry_free(made);
    return -1;
  }
  made->kind = want->kind;
  seed_want_clear(want);
  pthread_mutex_lock(&g_lock);
  /* Another request may have made the same seeding meanwhile: they are equal, keep that one. */
  struct seed_entry *e = find(made->kind, &made->cloud, made->fluid);
  if (!e) {
    e = made;
    e->next = g_entries;
    g_entries = e;
    made = NULL;
  }
  e->pins++;
  pthread_mutex_unlock(&g_lock);
  entry_free(made);
  *pin = e;
  return 0;
}

void seeding_unpin(seed_pin_t *pin) {
  if (!pin)
    return;
  pthread_mutex_lock(&g_lock);
  pin->pins--;
  pthread_mutex_unlock(&g_lock);
}

void seeding_prune(void) {
  pthread_mutex_lock(&g_lock);
  for (struct seed_entry **pp = &g_entries; *pp;) {
    struct seed_entry *e = *pp;
    if (e->pins == 0) {
      *pp = e->next;
      entry_free(e);
    } else {
      pp = &e->next;
    }
  }
  pthread_mutex_unlock(&g_lock);
}
