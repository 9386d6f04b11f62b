/*
 * A named scene: its JSON document (what scene.get returns), validated against the scene
 * schema, and the compiled snapshot the renderer reads. Every change is validated as a whole
 * and applied atomically: on error nothing changes and the error names the offending path.
 * Scenes live on the loop thread only; the renderer sees snapshots.
 */
#ifndef VOLFX_SCENE_H
#define VOLFX_SCENE_H

#include <cjson/cJSON.h>
#include <stdint.h>

#include "render_scene.h"
#include "scene_files.h"
#include "scene_schema.h"
#include "schema.h"
#include "seeding.h"
#include "sim_cloud.h"

/*
 * The outcome of one cloud job (step_cloud.c), shared by the job and the scene: a job queued
 * behind another of the same scene starts from the cells and density its predecessor left
 * here, since the scene has not seen them yet when it is submitted. Filled on the worker
 * before the job is answered, read only after that.
 */
typedef struct cloud_link {
  atomic_int refs;
  int ok;                  /* Set once 'cells' and 'density' hold the result. */
  cloud_cells_t *cells;    /* References. */
  density_grid_t *density; /* The smoothed density shown. */
} cloud_link_t;

cloud_link_t *cloud_link_new(void);
cloud_link_t *cloud_link_ref(cloud_link_t *l);
/* Drops a reference; NULL is fine. */
void cloud_link_unref(cloud_link_t *l);

typedef struct scene {
  char name[64];
  char preset[64]; /* The preset or file it was created from ("" for defaults), for scene.list
                      and resetting it. */
  uint64_t id;     /* Unique among every scene this process made: work started for a scene never
                      mistakes a later scene of the same name for it. */
  cJSON *doc;      /* The validated document, defaults filled in. */
  render_scene_t *snapshot; /* Compiled from 'doc'; replaced on every change. */
  unsigned long version;    /* Incremented on every change. */
  uint64_t changes;       /* Counts replacements of 'snapshot': anything that changes what is drawn
                             (edits, steps, the fluid's and the cloud's results). */
  particles_t *particles; /* The fluid's particles (a reference), NULL for none. */
  uint64_t particles_epoch; /* From 1; counts replacements of the particles from outside the
                               simulation (fluid.initial, fluid.set_particles): a fluid step
                               started in an earlier epoch is dropped. */
  /* The cloud: its cells and shown density (references), NULL when cloud.enabled is false. */
  cloud_cells_t *cloud_cells;
  density_grid_t *cloud_density;
  uint64_t cloud_gen;        /* Unique among all scenes; changes when the cells are replaced
                                (seeded, set by a client, loaded), not when stepped. */
  cloud_link_t *cloud_chain; /* The last cloud job in flight, or NULL. */
  uint64_t stops; /* Counts sim.pause and the like: stepping begun before stops at its next
                     slice (stepper.c). */
  /* What one simulation step costs, as the last job measured it (0: not measured yet), so that
   * long stepping is cut into slices of about the same worker time (stepper.c): */
  double cloud_step_ns; /* worker time of the cloud's steps_per_frame automaton steps and density */
  double fluid_step_ns; /* worker time of one fluid step */
  double advance_ns;    /* loop time of scene_advance per step (the waves' animations) */
  uint64_t sim_bytes;   /* The simulation memory this scene is counted for (scene_sim_bytes). */
  /* The clock's base (scene_advance): sim.time is base_time + (frame - base_frame) * dt for
   * the dt and the time and frame it last wrote ('valid' once it has). */
  struct {
    int valid;
    double dt, time, frame, base_time, base_frame;
  } clock;
} scene_t;

/* A scene's error: the carrier of proto_error.h, its code PROTO_E_INVALID_PARAMS,
 * PROTO_E_NOT_FOUND, PROTO_E_LIMIT or PROTO_E_INTERNAL, or a deferral (SCENE_DEFERRED,
 * SCENE_DEFERRED_SEED). */
typedef proto_error_t scene_error_t;

/*
 * The camera's checks across its fields, on a camera that passed the schema: target away from
 * eye (relative to their size), up neither zero nor parallel to the view, near before far.
 * scene.set and a render's camera overrides both use it. 'at' is the camera's path in the
 * request ("camera", "depth.camera"). Returns 0, or -1 with 'err' naming the field.
 */
int scene_check_camera(const cJSON *camera, const char *at, scene_error_t *err);

/* Sets the largest side of a volume file's grid (the cloud_side limit); 256 until set. */
void scene_set_volume_limit(uint32_t side);

/*
 * Sets the budgets every scene is held to (limits.scene_bytes, limits.keyframes): the
 * simulation memory of all scenes together, estimated by scene_sim_bytes, and the animation
 * keys of one document. A change that would pass either is refused with PROTO_E_LIMIT, naming
 * the field, and nothing changes. Unlimited until set.
 */
void scene_set_budget(uint64_t sim_bytes, uint32_t keyframes);

/*
 * The simulation memory the server keeps for a scene with validated document 'doc' and
 * 'particles' particles: the cloud's cells and densities, the fluid on host and device, the
 * volumes' grids (docs/architecture.md, "Scene memory"). An estimate, the same for a document
 * wherever it is asked.
 */
uint64_t scene_sim_bytes(const cJSON *doc, uint64_t particles);

/* The estimate summed over every scene alive (what scene_set_budget bounds). */
uint64_t scene_sim_bytes_total(void);

/* Whether the scene may hold 'n' particles within the memory budget. Returns 0, or -1 with
 * 'err' (PROTO_E_LIMIT at 'path') when the total would pass it. */
int scene_particles_fit_budget(const scene_t *s, uint64_t n, const char *path, scene_error_t *err);

/*
 * Creates a scene from 'preset' (a document, possibly partial; NULL for all defaults).
 * Returns NULL with 'err' set when the preset does not validate.
 */
scene_t *scene_create(const char *name, const cJSON *preset, scene_error_t *err);
void scene_destroy(scene_t *s);

/* A copy of the document, or of the sub-tree at dotted 'path' (NULL or "" for all; array items
 * by index or id). NULL with err->code PROTO_E_NOT_FOUND, saying what is missing, when the path
 * does not exist. */
cJSON *scene_get(const scene_t *s, const char *path, scene_error_t *err);

/* Applies an RFC 7386 merge patch, in which an array whose items all carry an "id" updates the
 * items of a keyed array (objects, waves, volumes) with those ids, appending new ones, and any
 * other array replaces the array whole. Returns 0 or -1 with 'err'. */
int scene_patch(scene_t *s, const cJSON *patch, scene_error_t *err);
/* Sets one value at a dotted path ("objects.0.color", "objects.orb.color", "camera.fov_y").
 * The parent must exist; an array index may be the array's length to append; null deletes a
 * member (its default comes back) or removes an array's item. Returns 0 or -1 with 'err'. */
int scene_set_path(scene_t *s, const char *path, const cJSON *value, scene_error_t *err);
/* Applies the changes of array 'changes' in order, each {path, value} (as scene_set_path) or
 * {path, patch} (a merge patch of the value at path), and commits the result once: one version,
 * or nothing when any change or the result is refused. Returns 0 or -1 with 'err'. */
int scene_set_changes(scene_t *s, const cJSON *changes, scene_error_t *err);
/* Applies RFC 6902 JSON Patch 'ops' (json_patch.h) and commits the result once, all or
 * nothing. Returns 0 or -1 with 'err'. */
int scene_apply_ops(scene_t *s, const cJSON *ops, scene_error_t *err);

/* Replaces the whole document. Returns 0 or -1 with 'err'. */
int scene_replace(scene_t *s, const cJSON *doc, scene_error_t *err);
/* What a snapshot keeps beside its document (scene.load). */
typedef struct scene_saved {
  cloud_cells_t *cells;    /* The cloud's cells and density, in place of freshly seeded ones */
  density_grid_t *density; /* when the document enables a cloud of their grid; or NULL. */
  particles_t *particles;  /* The fluid's particles, in place of fluid.initial's; or NULL (a
                              snapshot without a fluid section). They must lie inside the
                              document's fluid.bounds (else path "file"). */
} scene_saved_t;

/* The same with the state 'saved' holds (references taken on success). */
int scene_replace_saved(scene_t *s, const cJSON *doc, const scene_saved_t *saved,
                        scene_error_t *err);

/* Advances the clock: sim.time += steps * dt, sim.frame += steps, and the wave animations
 * with it (their current values written into the document); compiles one snapshot per call,
 * however many steps it takes. A toward-target animation costs up to one move per step, so
 * callers take long runs of steps in parts (stepper.c). */
void scene_advance(scene_t *s, uint64_t steps, double dt);

/*
 * Makes 'p' (a reference, taken on success; NULL for none) the fluid's particles: fluid.count,
 * the scene's sim_bytes and a fresh snapshot follow at once. The caller has validated them
 * (scene_particles_fit_budget for a count the scene's estimate does not cover). Returns 0, or -1 on
 * OOM with nothing changed.
 */
int scene_set_particles(scene_t *s, particles_t *p);

/* The limit on each side of the cloud grid (limits.cloud_side; 256 until set). */
void scene_set_cloud_side(uint32_t side);

/* The cloud settings of the scene's document. Returns 0, or -1 when the cloud is disabled. */
int scene_cloud_config(const scene_t *s, scene_cloud_t *out);

/*
 * Makes 'cells' and 'density' (references taken; both of the grid's dimensions) the cloud's,
 * with a fresh snapshot showing 'density'. 'replaced' marks the cells as new (a client set
 * them): cloud_gen changes, so results of jobs in flight are dropped. Returns 0, or -1 on OOM
 * with nothing changed.
 */
int scene_set_cloud(scene_t *s, cloud_cells_t *cells, density_grid_t *density, int replaced);

/* Convenience reads of the validated document. */
double scene_dt(const scene_t *s);
double scene_time(const scene_t *s);
double scene_frame(const scene_t *s);

#endif
