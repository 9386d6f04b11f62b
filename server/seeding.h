/*
 * Fresh state a commit seeds, made off the loop thread: a cloud's cells (the cloud enabled, or
 * given a new grid, seed or init: cells seeded and grown by init.steps automaton steps, and
 * their density, up to seconds at 256³) and the fluid's initial particles (a new
 * fluid.initial: up to 2^20 lattice points, each tested against every object it could lie
 * in). A commit takes them from here (cloud_seed_get, particles_seed_get). While the caller has
 * armed a deferral (server/defer.c), a seeding that is not cached is only recorded in the
 * seed_want_t, and the commit fails with SCENE_DEFERRED_SEED, changing nothing; defer.c makes
 * it on libuv's thread pool (seeding_make), which caches the result, and runs the request
 * again, which then finds it. Unarmed (the scenes made at start-up), seedings are done on the
 * spot.
 *
 * Both seedings are functions of the settings alone (deterministic), so a cached result is
 * exactly what seeding on the spot would give. An entry lives while a request pins it, and
 * until the next prune after that.
 */
#ifndef VOLFX_SEEDING_H
#define VOLFX_SEEDING_H

#include <cjson/cJSON.h>

#include "proto_error.h"
#include "scene_schema.h"

/* proto_error_t.code of a change that needs a seeding first (not a protocol code). */
#define SCENE_DEFERRED_SEED 2

typedef enum { SEED_CLOUD, SEED_PARTICLES, SEED_KINDS } seed_kind_t;

/* A seeding a change needs. */
typedef struct seed_want {
  seed_kind_t kind;
  scene_cloud_t cloud; /* SEED_CLOUD: the cloud's settings. */
  cJSON *fluid;        /* SEED_PARTICLES: {"fluid", "objects"} of the document (owned). */
} seed_want_t;

typedef struct seed_entry seed_pin_t;

/* Until called again with NULL, a seeding that is not cached is recorded in '*want' (and the
 * lookup fails with SCENE_DEFERRED_SEED) instead of being done; 'skip[kind]' set does that
 * kind on the spot all the same. Loop thread only. */
void seeding_defer(seed_want_t *want, const int skip[SEED_KINDS]);
/* Frees what a recorded want owns. */
void seed_want_clear(seed_want_t *want);

/* Seeded and grown cells for 'c' with their density (unsmoothed), as references. Returns 0;
 * -1 with 'err' set when out of memory, or SCENE_DEFERRED_SEED while a deferral is armed and
 * they are not cached. */
int cloud_seed_get(const scene_cloud_t *c, cloud_cells_t **cells, density_grid_t **density,
                   proto_error_t *err);

/* The particles of fluid.initial in the checked document 'doc' (a reference; NULL for none),
 * as seeding_particles_of gives them. Returns 0, or -1 as cloud_seed_get. */
int particles_seed_get(const cJSON *doc, particles_t **out, proto_error_t *err);

/*
 * The particles of fluid.initial in a checked document (only its "fluid" and "objects" are
 * read), in 'out' (NULL when there are none): each block's lattice, less the points inside an
 * opaque object the fluid collides with (which would burst out of it). Any thread. Returns 0,
 * or -1 on OOM.
 */
int seeding_particles_of(const cJSON *doc, particles_t **out);

/* The lattice spacing of block 'blk' of fluid.initial in checked 'fluid': its own, or h/2. */
double seeding_block_spacing(const cJSON *fluid, const cJSON *blk);

/* Makes and caches the seeding 'want' (taking what it owns), pinned by '*pin' until
 * seeding_unpin. Any thread. Returns 0, or -1 when out of memory. */
int seeding_make(seed_want_t *want, seed_pin_t **pin);
/* NULL is fine. */
void seeding_unpin(seed_pin_t *pin);

/* Drops the cached seedings no request pins. */
void seeding_prune(void);

#endif
