/*
 * The simulation memory of scenes (scene_sim_bytes): an estimate of what each document keeps
 * (the cloud's cells and densities, the fluid on host and device, the volumes' grids), summed
 * over every scene alive and held to limits.scene_bytes. A change that would pass the budget is
 * refused naming the part that grew most.
 */
#include <math.h>
#include <stdio.h>
#include <string.h>

#include "proto.h"
#include "scene_internal.h"

static uint64_t g_sim_budget = UINT64_MAX; /* limits.scene_bytes; unlimited until set. */
static uint64_t g_sim_total;               /* sim_bytes summed over every scene alive. */

void scene_set_budget(uint64_t sim_bytes, uint32_t keyframes) {
  g_sim_budget = sim_bytes;
  scene_check_set_keyframes(keyframes);
}

uint64_t scene_sim_bytes_total(void) {
  return g_sim_total;
}

/*
 * Bytes a cloud keeps per cell besides its bit planes: the density shown (f32), the density a
 * step computes and the buffer it blends into by turns (f32 each), and the renderer's light
 * grid, a (density, transmittance) pair of f32 per voxel.
 */
#define CLOUD_CELL_BYTES (4 + 4 + 4 + 8)
/* Copies of the hum, act and cld planes: the scene's cells and the two a step writes by turns. */
#define CLOUD_PLANE_COPIES 3
/*
 * Bytes per particle of a simulated fluid: on the host the scene's positions and velocities
 * (24), a step's result until it replaces them (24), the simulation's state and scratch (six
 * f32 each, 48) and its sort order, a copy and each particle's cell (12); on the device the
 * state read and written (48) and 1/density and pressure (8). A fluid that is not simulated
 * keeps the scene's 24 alone.
 */
#define FLUID_PARTICLE_BYTES (24 + 24 + 48 + 12 + 48 + 8)
#define PARTICLE_BYTES 24
/* Bytes per voxel of a volume: its density grid (f32), the light swept through it (f32) and
 * the (density, transmittance) pairs the kernel reads. */
#define VOLUME_VOXEL_BYTES (4 + 4 + 8)
/* How a noise volume is baked (render_volume.c): voxels per noise_scale, and most per side. */
#define NOISE_VOXELS_PER_SCALE 16
#define NOISE_MAX_VOXELS 96

/* The cloud's part: nothing when disabled. */
static uint64_t cloud_bytes(const cJSON *doc) {
  const cJSON *cloud = sch_member(doc, "cloud");
  if (!cJSON_IsTrue(sch_member(cloud, "enabled")))
    return 0;
  double n[3];
  sch_vec3d(sch_member(cloud, "grid"), n);
  uint64_t words = ((uint64_t)n[0] + 63) / 64, rows = (uint64_t)n[1] * (uint64_t)n[2];
  uint64_t cells = (uint64_t)n[0] * rows;
  return 3 * CLOUD_PLANE_COPIES * 8 * words * rows + cells * CLOUD_CELL_BYTES;
}

/* Whether the fluid of 'doc' has an emitter that adds particles. */
static int fluid_emits(const cJSON *doc) {
  for (const cJSON *em = sch_member(sch_member(doc, "fluid"), "emitters")->child; em; em = em->next)
    if (sch_member(em, "rate")->valuedouble > 0)
      return 1;
  return 0;
}

/* The particles a simulated fluid may come to hold: max_particles once emitters fill it. */
static uint64_t fluid_particles(const cJSON *doc, uint64_t particles) {
  uint64_t cap = (uint64_t)sch_member(sch_member(doc, "fluid"), "max_particles")->valuedouble;
  return fluid_emits(doc) && cap > particles ? cap : particles;
}

/* The fluid's part. */
static uint64_t fluid_bytes(const cJSON *doc, uint64_t particles) {
  if (!cJSON_IsTrue(sch_member(sch_member(doc, "fluid"), "enabled")))
    return particles * PARTICLE_BYTES;
  return fluid_particles(doc, particles) * FLUID_PARTICLE_BYTES;
}

/* One volume's part: a file's grid of its dims, or the grid noise is baked into. */
static uint64_t volume_bytes(const cJSON *v) {
  double d[3], lo[3], hi[3];
  if (sch_member_enum(scene_schema_at("volumes.0"), v, "source") == VOLUME_GRID) {
    sch_vec3d(sch_member(v, "dims"), d);
  } else {
    sch_vec3d(sch_member(sch_member(v, "bounds"), "min"), lo);
    sch_vec3d(sch_member(sch_member(v, "bounds"), "max"), hi);
    double scale = sch_member(v, "noise_scale")->valuedouble;
    for (int k = 0; k < 3; k++)
      d[k] =
          fmin(fmax(ceil((hi[k] - lo[k]) / scale * NOISE_VOXELS_PER_SCALE), 4), NOISE_MAX_VOXELS);
  }
  return (uint64_t)d[0] * (uint64_t)d[1] * (uint64_t)d[2] * VOLUME_VOXEL_BYTES;
}

uint64_t scene_sim_bytes(const cJSON *doc, uint64_t particles) {
  uint64_t sum = cloud_bytes(doc) + fluid_bytes(doc, particles);
  for (const cJSON *v = sch_member(doc, "volumes")->child; v; v = v->next)
    sum += volume_bytes(v);
  return sum;
}

/*
 * The field to blame for the estimate of 'doc' with 'particles' (whose source 'ppath' names)
 * passing the budget: the first part that grew over the scene's document 'old' with 'was'
 * particles (NULL for a new scene: then the largest part), into 'path'.
 */
static void blame(const cJSON *old, uint64_t was, const cJSON *doc, uint64_t particles,
                  const char *ppath, char *path, size_t len) {
  uint64_t best = 0;
  const char *fluid_path = fluid_emits(doc) && fluid_particles(doc, particles) > particles
                               ? "fluid.max_particles"
                               : ppath;
  struct {
    const char *path;
    uint64_t now, before;
  } parts[] = {{"cloud.grid", cloud_bytes(doc), old ? cloud_bytes(old) : 0},
               {fluid_path, fluid_bytes(doc, particles), old ? fluid_bytes(old, was) : 0}};
  snprintf(path, len, "volumes");
  for (size_t k = 0; k < sizeof parts / sizeof *parts; k++) {
    uint64_t grew = parts[k].now > parts[k].before ? parts[k].now - parts[k].before : 0;
    if (grew > best) {
      best = grew;
      snprintf(path, len, "%s", parts[k].path);
    }
  }
  const cJSON *ov = old ? sch_member(old, "volumes")->child : NULL;
  int i = 0;
  for (const cJSON *v = sch_member(doc, "volumes")->child; v;
       v = v->next, i++, ov = ov ? ov->next : NULL) {
    uint64_t now = volume_bytes(v), before = ov ? volume_bytes(ov) : 0;
    if (now > before && now - before > best) {
      best = now - before;
      snprintf(path, len, "volumes.%d", i);
    }
  }
}

/*
 * Whether scene 's' may take validated 'doc' with 'particles' particles (their source named by
 * 'ppath') within the memory budget: a change that does not grow the scene's estimate always
 * may. Returns 0, or -1 with 'err' (PROTO_E_LIMIT) naming the part that grew most.
 */
static int sim_fits(const scene_t *s, const cJSON *doc, uint64_t particles, const char *ppath,
                    scene_error_t *err) {
  uint64_t est = scene_sim_bytes(doc, particles);
  if (est <= s->sim_bytes || g_sim_total - s->sim_bytes + est <= g_sim_budget)
    return 0;
  char path[64];
  blame(s->doc, s->particles ? s->particles->count : 0, doc, particles, ppath, path, sizeof path);
  return proto_error_set(
      err, PROTO_E_LIMIT, path,
      "%s: the scenes' simulation state would take about %llu MiB (this scene %llu "
      "MiB), over the limit of %llu MiB (limits.scene_bytes)",
      path, (unsigned long long)((g_sim_total - s->sim_bytes + est) >> 20),
      (unsigned long long)(est >> 20), (unsigned long long)(g_sim_budget >> 20));
}

/* Counts the scene for 'particles' particles from now on. */
void scene_budget_account(scene_t *s, uint64_t particles) {
  uint64_t est = scene_sim_bytes(s->doc, particles);
  g_sim_total = g_sim_total - s->sim_bytes + est;
  s->sim_bytes = est;
}

int scene_particles_fit_budget(const scene_t *s, uint64_t n, const char *path, scene_error_t *err) {
  proto_error_clear(err);
  if (sim_fits(s, s->doc, n, path, err) == 0)
    return 0;
  snprintf(err->path, sizeof err->path, "%s", path); /* The particles, whatever the fluid says. */
  return -1;
}

/* The particles 'doc' will give scene 's' (at most; blocks lose the points inside objects) and
 * the field they come from, before any are made. */
static uint64_t particles_bound(const scene_t *s, const cJSON *doc, const scene_saved_t *saved,
                                const char **from) {
  const cJSON *fluid = sch_member(doc, "fluid"), *old = s->doc ? sch_member(s->doc, "fluid") : NULL;
  if (saved && saved->particles) {
    *from = "file";
    return saved->particles->count;
  }
  if (!old || !cJSON_Compare(sch_member(fluid, "initial"), sch_member(old, "initial"), 1)) {
    uint64_t n = 0;
    for (const cJSON *blk = sch_member(fluid, "initial")->child; blk; blk = blk->next)
      n += (uint64_t)sch_member(blk, "count")->valuedouble;
    *from = "fluid.initial";
    return n;
  }
  *from = "fluid.enabled";
  return s->particles ? s->particles->count : 0;
}

void scene_budget_release(scene_t *s) {
  g_sim_total -= s->sim_bytes;
  s->sim_bytes = 0;
}

/* sim_fits for validated 'doc' with the particles it will bring. */
int scene_budget_fits(const scene_t *s, const cJSON *doc, const scene_saved_t *saved,
                      scene_error_t *err) {
  const char *from = NULL;
  uint64_t n = particles_bound(s, doc, saved, &from);
  return sim_fits(s, doc, n, from, err);
}
