/*
 * Reference counting of compiled scenes. A snapshot is shared between the loop thread (the
 * scene's current one) and any render jobs still reading it, so the count is atomic and the
 * last holder frees the objects and the waves and drops the mesh references the objects hold.
 */
/* render_scene.h uses size_t without including <stddef.h>; until it does, this comes first. */
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "reclaim.h"
#include "render_scene.h"

render_scene_t *render_scene_ref(render_scene_t *s) {
  /* Taking a reference needs no ordering: the caller already holds one, which keeps 's'
   * alive and its contents visible. */
  if (s)
    atomic_fetch_add_explicit(&s->refs, 1, memory_order_relaxed);
  return s;
}

void render_scene_unref(render_scene_t *s) {
  if (!s)
    return;
  /* Release so this thread's reads of 's' happen before the free; acquire so the freeing
   * thread sees every other holder's. */
  if (atomic_fetch_sub_explicit(&s->refs, 1, memory_order_acq_rel) != 1)
    return;
  for (int i = 0; i < s->nobjects; i++)
    if (s->objects[i].mesh)
      mesh_unref(s->objects[i].mesh);
  free(s->objects);
  free(s->waves);
  particles_unref(s->fluid.owner);
  for (int i = 0; i < s->nvolumes; i++)
    density_grid_unref(s->volumes[i].grid);
  free(s->volumes);
  density_grid_unref(s->cloud.grid);
  free(s);
}

particles_t *particles_new(uint32_t n) {
  particles_t *p = calloc(1, sizeof *p);
  if (!p)
    return NULL;
  size_t floats = (size_t)(n ? n : 1) * 3;
  p->pos = calloc(floats, sizeof(float));
  p->vel = calloc(floats, sizeof(float));
  if (!p->pos || !p->vel) {
    free(p->pos);
    free(p->vel);
    free(p);
    return NULL;
  }
  atomic_init(&p->refs, 1);
  p->count = n;
  return p;
}

particles_t *particles_ref(particles_t *p) {
  if (p)
    atomic_fetch_add_explicit(&p->refs, 1, memory_order_relaxed);
  return p;
}

void particles_unref(particles_t *p) {
  if (!p || atomic_fetch_sub_explicit(&p->refs, 1, memory_order_acq_rel) != 1)
    return;
  size_t bytes = (size_t)(p->count ? p->count : 1) * 3 * sizeof(float);
  reclaim_free(p->pos, bytes);
  reclaim_free(p->vel, bytes);
  free(p);
}

density_grid_t *density_grid_alloc(const uint32_t dims[3]) {
  if (!dims[0] || !dims[1] || !dims[2])
    return NULL;
  density_grid_t *g = calloc(1, sizeof *g);
  if (!g)
    return NULL;
  size_t n = (size_t)dims[0] * dims[1] * dims[2];
  g->data = n <= SIZE_MAX / sizeof(float) ? reclaim_alloc(n * sizeof(float)) : NULL;
  if (!g->data) {
    free(g);
    return NULL;
  }
  atomic_init(&g->refs, 1);
  for (int i = 0; i < 3; i++)
    g->dims[i] = dims[i];
  return g;
}

density_grid_t *density_grid_new(const uint32_t dims[3]) {
  density_grid_t *g = density_grid_alloc(dims);
  if (g)
    memset(g->data, 0, (size_t)dims[0] * dims[1] * dims[2] * sizeof(float));
  return g;
}

density_grid_t *density_grid_ref(density_grid_t *g) {
  if (g)
    atomic_fetch_add_explicit(&g->refs, 1, memory_order_relaxed);
  return g;
}

void density_grid_unref(density_grid_t *g) {
  if (!g || atomic_fetch_sub_explicit(&g->refs, 1, memory_order_acq_rel) != 1)
    return;
  reclaim_free(g->data, (size_t)g->dims[0] * g->dims[1] * g->dims[2] * sizeof(float));
  free(g);
}
