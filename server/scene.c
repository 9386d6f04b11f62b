/*
 * Scenes: the JSON document a client edits and the immutable snapshot the renderer reads.
 * Every change (merge patch, set at a path, whole replacement; scene_edit.c) is made on a copy
 * of the document, which scene_commit checks (scene_check.c), holds to the memory budget
 * (scene_budget.c), seeds (seeding.h) and compiles into a new render_scene_t
 * (scene_compile.c); only when all of that succeeds do the copy and the snapshot replace the
 * scene's, so a failed change leaves the document, the version and the snapshot exactly as
 * they were. The mesh and volume files a document names come from scene_files.c, which caches
 * them, so patches that keep a file do not read it again.
 * Waves carry animations (anim.c): the clock moves them, writing the current values into the
 * document and compiling a new snapshot once per advance, however many steps it takes.
 */
#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "anim.h"
#include "proto.h"
#include "scene_files.h"
#include "scene_internal.h"

/* Generations of cloud cells, unique across scenes so that a job of a deleted scene can never
 * match a new scene of the same name. Loop thread only. */
static uint64_t g_cloud_gen;
static uint64_t g_scene_ids; /* The last scene_t.id given. */

cloud_link_t *cloud_link_new(void) {
  cloud_link_t *l = calloc(1, sizeof *l);
  if (l)
    atomic_init(&l->refs, 1);
  return l;
}

cloud_link_t *cloud_link_ref(cloud_link_t *l) {
  if (l)
    atomic_fetch_add(&l->refs, 1);
  return l;
}

void cloud_link_unref(cloud_link_t *l) {
  if (l && atomic_fetch_sub(&l->refs, 1) == 1) {
    cloud_cells_unref(l->cells);
    density_grid_unref(l->density);
    free(l);
  }
}

int scene_cloud_config(const scene_t *s, scene_cloud_t *out) {
  return scene_cloud_of(s->doc, out);
}

/* Whether member 'name' of the clouds of 'a' and 'b' are equal. */
static int cloud_same(const cJSON *a, const cJSON *b, const char *name) {
  return cJSON_Compare(sch_member(sch_member(a, "cloud"), name),
                       sch_member(sch_member(b, "cloud"), name), 1);
}

/*
 * The cells and density 'doc' gives the scene: none when the cloud is disabled; 'saved' and
 * 'saved_density' (a snapshot's) when given and of the grid; the scene's own when it was
 * enabled already with the same grid, seed and init; and otherwise freshly seeded cells, grown
 * by init.steps automaton steps (seeding.h). Sets '*seeded' for cells other than the
 * scene's. Returns 0, or -1 with 'err' set (out of memory, or a seeding deferred).
 */
static int cloud_prepare(const scene_t *s, const cJSON *doc, cloud_cells_t *saved,
                         density_grid_t *saved_density, cloud_cells_t **cells,
                         density_grid_t **density, int *seeded, scene_error_t *err) {
  scene_cloud_t c;
  *cells = NULL;
  *density = NULL;
  *seeded = 0;
  if (scene_cloud_of(doc, &c) != 0)
    return 0;
  *seeded = 1;
  if (saved && memcmp(saved->n, c.n, sizeof c.n) == 0) {
    *cells = cloud_cells_ref(saved);
    *density = density_grid_ref(saved_density);
    return 0;
  }
  if (s->doc && s->cloud_cells && cloud_same(s->doc, doc, "grid") &&
      cloud_same(s->doc, doc, "seed") && cloud_same(s->doc, doc, "init")) {
    *cells = cloud_cells_ref(s->cloud_cells);
    *density = density_grid_ref(s->cloud_density);
    *seeded = 0;
    return 0;
  }
  return cloud_seed_get(&c, cells, density, err);
}

/* Whether every particle of 'p' (NULL: none) lies inside the bounds of checked 'fluid'. Returns
 * 0, or -1 with 'err' at 'path' naming the first that does not, as 'what' holds it. */
static int particles_fit(const cJSON *fluid, const particles_t *p, const char *path,
                         const char *what, scene_error_t *err) {
  double lo[3], hi[3];
  sch_vec3d(sch_member(sch_member(fluid, "bounds"), "min"), lo);
  sch_vec3d(sch_member(sch_member(fluid, "bounds"), "max"), hi);
  for (uint32_t i = 0; p && i < p->count; i++) {
    const float *q = p->pos + 3 * (size_t)i;
    for (int k = 0; k < 3; k++)
      if (!(q[k] >= lo[k] && q[k] <= hi[k]))
        return proto_error_set(
            err, PROTO_E_INVALID_PARAMS, path,
            "%s: particle %u at (%g, %g, %g) lies outside fluid.bounds (%g..%g on %c); "
            "move the particles first (fluid.set_particles)",
            what, i, q[0], q[1], q[2], lo[k], hi[k], "xyz"[k]);
  }
  return 0;
}

/*
 * Makes 'doc' (owned, taken in every case) the scene's document if it is valid. A new value of
 * fluid.initial (or the first document) replaces the particles by its blocks; a cloud newly
 * enabled, or with a new grid, seed or init, gets freshly seeded cells, or the cells of 'saved'
 * (a snapshot's state; may be NULL), whose particles likewise replace fluid.initial's; new
 * fluid.bounds must hold the particles kept. Fails with SCENE_DEFERRED or SCENE_DEFERRED_SEED,
 * having changed nothing, when a file or a seeding must be made elsewhere first.
 */
int scene_commit(scene_t *s, cJSON *doc, const scene_saved_t *saved, scene_error_t *err) {
  particles_t *particles = s->particles;
  int reseed = 0;
  cloud_cells_t *cells = NULL;
  density_grid_t *density = NULL;
  int seeded = 0;
  render_scene_t *rs = NULL;
  /* The budget first: a refused change reads no file and seeds nothing. */
  if (scene_check_document(doc, err) != 0 || scene_budget_fits(s, doc, saved, err) != 0 ||
      scene_compile_files_ready(doc, err) != 0 ||
      cloud_prepare(s, doc, saved ? saved->cells : NULL, saved ? saved->density : NULL, &cells,
                    &density, &seeded, err) != 0)
    goto fail;
  const cJSON *fluid = sch_member(doc, "fluid"), *old = s->doc ? sch_member(s->doc, "fluid") : NULL;
  if (saved && saved->particles) {
    if (particles_fit(fluid, saved->particles, "file", "the snapshot's fluid section", err) != 0)
      goto fail;
    particles = particles_ref(saved->particles);
    reseed = 1;
  } else if (!old || !cJSON_Compare(sch_member(fluid, "initial"), sch_member(old, "initial"), 1)) {
    if (particles_seed_get(doc, &particles, err) != 0)
      goto fail;
    reseed = 1;
  } else if (!cJSON_Compare(sch_member(fluid, "bounds"), sch_member(old, "bounds"), 1) &&
             particles_fit(fluid, particles, "fluid.bounds", "fluid.bounds", err) != 0) {
    goto fail; /* The tank may not shrink past the particles it holds. */
  }
  cJSON_SetNumberValue(sch_member(sch_member(doc, "fluid"), "count"),
                       (particles ? (double)particles->count : 0));
  rs = scene_compile(doc, particles, cells, density, err);
  if (!rs)
    goto fail;
  cJSON_Delete(s->doc);
  s->doc = doc;
  render_scene_unref(s->snapshot);
  s->snapshot = rs;
  s->changes++;
  s->version++;
  if (reseed) {
    particles_unref(s->particles);
    s->particles = particles;
    s->particles_epoch++;
  }
  cloud_cells_unref(s->cloud_cells);
  density_grid_unref(s->cloud_density);
  s->cloud_cells = cells;
  s->cloud_density = density;
  if (seeded || !cells) {
    /* Jobs in flight stepped other cells: their results are dropped. */
    s->cloud_gen = cells ? ++g_cloud_gen : 0;
    cloud_link_unref(s->cloud_chain);
    s->cloud_chain = NULL;
  }
  scene_budget_account(s, s->particles ? s->particles->count : 0);
  scene_files_prune();
  seeding_prune();
  return 0;
fail:
  if (reseed)
    particles_unref(particles);
  cloud_cells_unref(cells);
  density_grid_unref(density);
  cJSON_Delete(doc);
  scene_files_prune();
  seeding_prune();
  return -1;
}

scene_t *scene_create(const char *name, const cJSON *preset, scene_error_t *err) {
  proto_error_clear(err);
  if (!name || strlen(name) >= sizeof((scene_t *)0)->name) {
    proto_error_set(err, PROTO_E_INVALID_PARAMS, "name", "name: must be 1 to 63 bytes");
    return NULL;
  }
  if (preset && !cJSON_IsObject(preset)) {
    proto_error_set(err, PROTO_E_INVALID_PARAMS, "", "a scene document must be a JSON object");
    return NULL;
  }
  scene_t *s = calloc(1, sizeof *s);
  cJSON *doc = preset ? cJSON_Duplicate(preset, 1) : cJSON_CreateObject();
  if (!s || !doc) {
    free(s);
    cJSON_Delete(doc);
    proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
    return NULL;
  }
  snprintf(s->name, sizeof s->name, "%s", name);
  s->id = ++g_scene_ids;
  /* The first commit takes the version from 0 to 1, what scene.list shows for a new scene. */
  if (scene_commit(s, doc, NULL, err) != 0) {
    free(s);
    return NULL;
  }
  return s;
}

void scene_destroy(scene_t *s) {
  if (!s)
    return;
  scene_budget_release(s);
  render_scene_unref(s->snapshot);
  particles_unref(s->particles);
  cloud_cells_unref(s->cloud_cells);
  density_grid_unref(s->cloud_density);
  cloud_link_unref(s->cloud_chain);
  cJSON_Delete(s->doc);
  free(s);
  scene_files_prune();
  seeding_prune();
}

cJSON *scene_get(const scene_t *s, const char *path, scene_error_t *err) {
  proto_error_clear(err);
  cJSON *v = sch_path_get(s->doc, path);
  if (!v) {
    scene_path_missing(s->doc, path, err);
    return NULL;
  }
  cJSON *copy = cJSON_Duplicate(v, 1);
  if (!copy)
    proto_error_set(err, PROTO_E_INTERNAL, path ? path : "", "out of memory");
  return copy;
}

int scene_replace(scene_t *s, const cJSON *doc, scene_error_t *err) {
  return scene_replace_saved(s, doc, NULL, err);
}

int scene_replace_saved(scene_t *s, const cJSON *doc, const scene_saved_t *saved,
                        scene_error_t *err) {
  proto_error_clear(err);
  if (!cJSON_IsObject(doc))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "",
                           "a scene document must be a JSON object");
  cJSON *copy = cJSON_Duplicate(doc, 1);
  if (!copy)
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  return scene_commit(s, copy, saved, err);
}

/*
 * Advances the clock by 'steps' steps of 'dt' seconds, and the wave animations with it, in
 * the document and in one fresh snapshot. Toward-target animations move step by step, as
 * single steps would (a batch that surely reaches the target lands on it at once), and
 * keyframes depend on the time alone, so a batch of steps ends exactly where single steps
 * would. The
 * clock and the animations are not edits, so 'version' is left alone: it counts changes made
 * by clients. Time and frame stop at the schema's maxima so the document stays valid. Should
 * memory run out, the old snapshot (with the old clock and waves) stays in place until the
 * next change; the document has moved on regardless.
 */
void scene_advance(scene_t *s, uint64_t steps, double dt) {
  if (steps == 0 || !(dt > 0) || !isfinite(dt))
    return;
  const sch_field_t *ft = sch_path_field(&scene_schema, "sim.time");
  const sch_field_t *ff = sch_path_field(&scene_schema, "sim.frame");
  cJSON *sim = sch_member(s->doc, "sim");
  cJSON *jt = sch_member(sim, "time"), *jf = sch_member(sim, "frame");
  /* The time is the base's plus the frames since it times dt, not a sum of steps, so that it
   * does not depend on how the steps were grouped into calls or ticks. The base is where this
   * clock last left it, while dt, time and frame are as it wrote them; else 0 when the time is
   * the frame times dt (a fresh scene, or a snapshot of one); else the time and frame now. */
  double t0 = jt->valuedouble, f0 = jf->valuedouble;
  if (!(s->clock.valid && s->clock.dt == dt && s->clock.time == t0 && s->clock.frame == f0)) {
    int from_zero = t0 == f0 * dt;
    s->clock.base_time = from_zero ? 0 : t0;
    s->clock.base_frame = from_zero ? 0 : f0;
  }
  double f = fmin(f0 + (double)steps, ff->max);
  double t = fmin(s->clock.base_time + (f - s->clock.base_frame) * dt, ft->max);
  s->clock.valid = 1, s->clock.dt = dt, s->clock.time = t, s->clock.frame = f;
  cJSON_SetNumberValue(jt, t);
  cJSON_SetNumberValue(jf, f);
  const sch_field_t *wf = scene_schema_at("waves.0")->fields;
  for (cJSON *w = sch_member(s->doc, "waves")->child; w; w = w->next)
    anim_advance(w, wf, steps, dt, t);
  render_scene_t *rs = scene_compile_advanced(s->snapshot, s->doc, s->particles, (uint64_t)f, t);
  if (rs) {
    render_scene_unref(s->snapshot);
    s->snapshot = rs;
    s->changes++;
  }
}

int scene_set_particles(scene_t *s, particles_t *p) {
  const cJSON *sim = sch_member(s->doc, "sim");
  render_scene_t *rs = scene_compile_advanced(s->snapshot, s->doc, p,
                                              (uint64_t)sch_member(sim, "frame")->valuedouble,
                                              sch_member(sim, "time")->valuedouble);
  if (!rs)
    return -1;
  particles_unref(s->particles);
  s->particles = p;
  cJSON_SetNumberValue(sch_member(sch_member(s->doc, "fluid"), "count"),
                       (p ? (double)p->count : 0));
  render_scene_unref(s->snapshot);
  s->snapshot = rs;
  s->changes++;
  scene_budget_account(s, p ? p->count : 0);
  return 0;
}

int scene_set_cloud(scene_t *s, cloud_cells_t *cells, density_grid_t *density, int replaced) {
  const cJSON *sim = sch_member(s->doc, "sim");
  render_scene_t *rs = scene_compile_advanced(s->snapshot, s->doc, s->particles,
                                              (uint64_t)sch_member(sim, "frame")->valuedouble,
                                              sch_member(sim, "time")->valuedouble);
  if (!rs)
    return -1;
  density_grid_unref(rs->cloud.grid);
  scene_compile_cloud(s->doc, cells, density, rs);
  cloud_cells_unref(s->cloud_cells);
  density_grid_unref(s->cloud_density);
  s->cloud_cells = cells;
  s->cloud_density = density;
  if (replaced) {
    s->cloud_gen = ++g_cloud_gen;
    cloud_link_unref(s->cloud_chain);
    s->cloud_chain = NULL;
  }
  render_scene_unref(s->snapshot);
  s->snapshot = rs;
  s->changes++;
  return 0;
}

double scene_dt(const scene_t *s) {
  return sch_member(sch_member(s->doc, "sim"), "dt")->valuedouble;
}

double scene_time(const scene_t *s) {
  return sch_member(sch_member(s->doc, "sim"), "time")->valuedouble;
}

double scene_frame(const scene_t *s) {
  return sch_member(sch_member(s->doc, "sim"), "frame")->valuedouble;
}
