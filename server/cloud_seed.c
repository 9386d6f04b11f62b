/*
 * Fresh cloud cells (cloud_seed.h): the seeding and its steps, and the cache that carries them
 * from the thread pool to the request's retry.
 */
#include "cloud_seed.h"

#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "proto.h"

struct cloud_seed_entry {
  scene_cloud_t key;
  cloud_cells_t *cells;    /* References. */
  density_grid_t *density; /* Unsmoothed. */
  int pins;                /* Guarded by g_lock. */
  struct cloud_seed_entry *next;
};

static pthread_mutex_t g_lock = PTHREAD_MUTEX_INITIALIZER;
static struct cloud_seed_entry *g_entries; /* Guarded by g_lock. */
static scene_cloud_t *g_want;              /* Armed deferral (loop thread only), or NULL. */

void cloud_seed_defer(scene_cloud_t *want) {
  g_want = want;
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

/* The cached entry for 'c', or NULL. Called with g_lock held. */
static struct cloud_seed_entry *find(const scene_cloud_t *c) {
  for (struct cloud_seed_entry *e = g_entries; e; e = e->next)
    if (same_seeding(&e->key, c))
      return e;
  return NULL;
}

static int oom(const scene_cloud_t *c, scene_error_t *err) {
  err->code = PROTO_E_INTERNAL;
  snprintf(err->path, sizeof err->path, "cloud");
  snprintf(err->message, sizeof err->message, "out of memory for a %ux%ux%u cloud", c->n[0],
           c->n[1], c->n[2]);
  return -1;
}

int cloud_seed_get(const scene_cloud_t *c, cloud_cells_t **cells, density_grid_t **density,
                   scene_error_t *err) {
  pthread_mutex_lock(&g_lock);
  struct cloud_seed_entry *e = find(c);
  if (e) {
    *cells = cloud_cells_ref(e->cells);
    *density = density_grid_ref(e->density);
  }
  pthread_mutex_unlock(&g_lock);
  if (e)
    return 0;
  if (g_want) {
    *g_want = *c;
    err->code = SCENE_DEFERRED_SEED;
    snprintf(err->path, sizeof err->path, "cloud");
    snprintf(err->message, sizeof err->message, "cloud: %ux%ux%u cells are being seeded", c->n[0],
             c->n[1], c->n[2]);
    return -1;
  }
  return seed(c, cells, density) == 0 ? 0 : oom(c, err);
}

int cloud_seed_make(const scene_cloud_t *c, cloud_seed_pin_t **pin) {
  *pin = NULL;
  struct cloud_seed_entry *made = calloc(1, sizeof *made);
  if (!made || seed(c, &made->cells, &made->density) != 0) {
    free(made);
    return -1;
  }
  made->key = *c;
  pthread_mutex_lock(&g_lock);
  /* Another request may have made the same cells meanwhile: they are equal, keep those. */
  struct cloud_seed_entry *e = find(c);
  if (!e) {
    e = made;
    e->next = g_entries;
    g_entries = e;
    made = NULL;
  }
  e->pins++;
  pthread_mutex_unlock(&g_lock);
  if (made) {
    cloud_cells_unref(made->cells);
    density_grid_unref(made->density);
    free(made);
  }
  *pin = e;
  return 0;
}

void cloud_seed_unpin(cloud_seed_pin_t *pin) {
  if (!pin)
    return;
  pthread_mutex_lock(&g_lock);
  pin->pins--;
  pthread_mutex_unlock(&g_lock);
}

void cloud_seed_prune(void) {
  pthread_mutex_lock(&g_lock);
  for (struct cloud_seed_entry **pp = &g_entries; *pp;) {
    struct cloud_seed_entry *e = *pp;
    if (e->pins == 0) {
      *pp = e->next;
      cloud_cells_unref(e->cells);
      density_grid_unref(e->density);
      free(e);
    } else {
      pp = &e->next;
    }
  }
  pthread_mutex_unlock(&g_lock);
}
