/*
 * Fresh cloud cells, made off the loop thread. A scene change that enables a cloud, or gives
 * it a new grid, seed or init, needs cells seeded from the seed and grown by init.steps
 * automaton steps, and their density: up to seconds of work at 256³. A commit takes them from
 * here (cloud_seed_get). While the caller has armed a deferral (server/defer.c), a seeding
 * that is not cached is only recorded, and the commit fails with SCENE_DEFERRED_SEED, changing
 * nothing; defer.c makes the cells on libuv's thread pool (cloud_seed_make), which caches
 * them, and runs the request again, which then finds them. Unarmed (the scenes made at
 * start-up), the cells are made on the spot.
 *
 * The cells are a function of the settings alone (the seeding is deterministic), so cached
 * cells are exactly what seeding on the spot would give. An entry lives while a request pins
 * it, and until the next prune after that.
 */
#ifndef VOLFX_CLOUD_SEED_H
#define VOLFX_CLOUD_SEED_H

#include "scene.h"

/* scene_error_t.code of a change that needs cells seeded first (not a protocol code). */
#define SCENE_DEFERRED_SEED 2

typedef struct cloud_seed_entry cloud_seed_pin_t;

/* Until called again with NULL, a seeding that is not cached is recorded in '*want' (and the
 * lookup fails with SCENE_DEFERRED_SEED) instead of being done. Loop thread only. */
void cloud_seed_defer(scene_cloud_t *want);

/* Seeded and grown cells for 'c' with their density (unsmoothed), as references. Returns 0;
 * -1 with 'err' set when out of memory, or SCENE_DEFERRED_SEED while a deferral is armed and
 * they are not cached. */
int cloud_seed_get(const scene_cloud_t *c, cloud_cells_t **cells, density_grid_t **density,
                   scene_error_t *err);

/* Makes and caches the cells of 'c', pinned by '*pin' until cloud_seed_unpin. Any thread.
 * Returns 0, or -1 when out of memory. */
int cloud_seed_make(const scene_cloud_t *c, cloud_seed_pin_t **pin);
/* NULL is fine. */
void cloud_seed_unpin(cloud_seed_pin_t *pin);

/* Drops the cached cells no request pins. */
void cloud_seed_prune(void);

#endif
