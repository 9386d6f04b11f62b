/*
 * Scenes: the JSON document a client edits and the immutable snapshot the renderer reads.
 * Every change (merge patch, set at a path, whole replacement) is made on a copy of the
 * document, which is validated against scene_schema, checked across fields and compiled into
 * a new render_scene_t; only when all of that succeeds do the copy and the snapshot replace
 * the scene's, so a failed change leaves the document, the version and the snapshot exactly as
 * they were. The mesh and volume files a document names come from scene_files.c, which caches
 * them, so patches that keep a file do not read it again.
 * Waves carry animations (anim.c): the clock moves them, writing the current values into the
 * document and compiling a new snapshot once per advance, however many steps it takes.
 */
#include "scene.h"

#include <limits.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "anim.h"
#include "datapath.h"
#include "scene_files.h"
#include "seeding.h"
#include "proto.h"

/* Shortest distance between eye and target, relative to their magnitude: below this the
 * single-precision view direction the kernels compute is noise. */
#define EYE_TARGET_EPS 1e-6
/* Smallest sine of the angle between camera.up and the view direction (about 0.06 degrees). */
#define UP_PARALLEL_EPS 1e-3
/* Most cell-steps cloud.init.steps may take (grid cells x steps): 256^3 x 256, a few seconds
 * of a thread-pool thread (seeding.h). */
#define CLOUD_INIT_STEP_CELLS (1ull << 32)

/* Member 'name' of 'obj', case-sensitively; the validated document always has it. */
static cJSON *get(const cJSON *obj, const char *name) {
  return cJSON_GetObjectItemCaseSensitive(obj, name);
}

static void vec3d(const cJSON *a, double out[3]) {
  int i = 0;
  out[0] = out[1] = out[2] = 0;
  for (const cJSON *it = a ? a->child : NULL; it && i < 3; it = it->next)
    out[i++] = it->valuedouble;
}

static void vec3f(const cJSON *a, float out[3]) {
  double d[3];
  vec3d(a, d);
  for (int i = 0; i < 3; i++)
    out[i] = (float)d[i];
}

/* ---- Volume files ---- */

/* 'v' as the shortest decimal that reads back as it (sch_format_number), for a message. */
typedef struct {
  char s[32];
} num_text_t;

static num_text_t num_text(double v) {
  num_text_t t;
  sch_format_number(t.s, sizeof t.s, v);
  return t;
}

static uint32_t g_volume_side = 256; /* Largest side of a volume file's grid (cloud_side). */

void scene_set_volume_limit(uint32_t side) {
  g_volume_side = side;
}

/* The checks of volumes[] that the schema cannot make: boxes, file fields, unique ids. */
static int check_volumes(const cJSON *doc, scene_error_t *err) {
  int i = 0;
  const cJSON *vols = get(doc, "volumes");
  for (const cJSON *v = vols->child; v; v = v->next, i++) {
    char p[64];
    double lo[3], hi[3];
    const cJSON *b = get(v, "bounds");
    vec3d(get(b, "min"), lo);
    vec3d(get(b, "max"), hi);
    for (int k = 0; k < 3; k++)
      if (!(hi[k] > lo[k])) {
        snprintf(p, sizeof p, "volumes.%d.bounds.max", i);
        return proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                               "%s: must be above bounds.min on every axis (%c: %g <= %g)", p,
                               "xyz"[k], hi[k], lo[k]);
      }
    /* The file's name and dims are checked wherever they are given, so that even a noise
     * volume's document holds no name outside the data directory; a file volume needs both. */
    const cJSON *file = get(v, "file"), *dims = get(v, "dims");
    int from_file = strcmp(get(v, "source")->valuestring, "file") == 0;
    snprintf(p, sizeof p, "volumes.%d.file", i);
    if (from_file && (!file || !file->valuestring[0]))
      return proto_error_set(
          err, PROTO_E_INVALID_PARAMS, p,
          "%s: a file volume needs a file (raw densities under the data directory)", p);
    if (file && file->valuestring[0] && !datapath_name_ok(file->valuestring))
      return proto_error_set(
          err, PROTO_E_INVALID_PARAMS, p,
          "%s: \"%.64s\" must be a relative path inside the data directory: letters, "
          "digits, '_', '-', '.', '/', no component starting with '.'",
          p, file->valuestring);
    snprintf(p, sizeof p, "volumes.%d.dims", i);
    if (from_file && !dims)
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p, "%s: a file volume needs dims", p);
    if (dims) {
      double d[3];
      vec3d(dims, d);
      for (int k = 0; k < 3; k++) {
        snprintf(p, sizeof p, "volumes.%d.dims.%d", i, k);
        if (d[k] != floor(d[k]))
          return proto_error_set(err, PROTO_E_INVALID_PARAMS, p, "%s: %s is not an integer", p,
                                 num_text(d[k]).s);
        if (d[k] > g_volume_side)
          return proto_error_set(
              err, PROTO_E_LIMIT, p,
              "%s: %g voxels is over the limit of %u per side (limits.cloud_side)", p, d[k],
              g_volume_side);
      }
    }
    const char *id = get(v, "id")->valuestring;
    int j = 0;
    for (const cJSON *q = vols->child; id[0] && q != v; q = q->next, j++)
      if (strcmp(get(q, "id")->valuestring, id) == 0) {
        snprintf(p, sizeof p, "volumes.%d.id", i);
        return proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                               "%s: \"%s\" is already the id of volumes.%d", p, id, j);
      }
  }
  return 0;
}

/* The grid of file volume 'v' (volumes['i']): a counted reference, or NULL with 'err' set. */
static density_grid_t *volume_grid(const cJSON *v, int i, scene_error_t *err) {
  double d[3];
  vec3d(get(v, "dims"), d);
  uint32_t dims[3] = {(uint32_t)d[0], (uint32_t)d[1], (uint32_t)d[2]};
  return scene_grid_get(get(v, "file")->valuestring, i, dims,
                        strcmp(get(v, "format")->valuestring, "u8") == 0, err);
}

/* The mesh of mesh object 'o' (objects['i']): a counted reference, or NULL with 'err' set. */
static mesh_t *object_mesh(const cJSON *o, int i, scene_error_t *err) {
  char p[64];
  snprintf(p, sizeof p, "objects.%d.file", i);
  return scene_mesh_get(get(o, "file")->valuestring, p, err);
}

/* Compiles volumes[] into 'rs', loading grid files. Returns 0, or -1 with 'err' set (the
 * grids taken so far belong to rs and go with it). */
static int compile_volumes(const cJSON *doc, render_scene_t *rs, scene_error_t *err) {
  const cJSON *vols = get(doc, "volumes");
  int n = cJSON_GetArraySize(vols);
  if (n == 0)
    return 0;
  rs->volumes = calloc((size_t)n, sizeof *rs->volumes);
  if (!rs->volumes)
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  int i = 0;
  for (const cJSON *v = vols->child; v; v = v->next, i++) {
    rvolume_t *rv = &rs->volumes[i];
    const cJSON *b = get(v, "bounds");
    vec3f(get(b, "min"), rv->min);
    vec3f(get(b, "max"), rv->max);
    rv->density = (float)get(v, "density")->valuedouble;
    vec3f(get(v, "albedo"), rv->albedo);
    rv->samples = (int)get(v, "samples")->valuedouble;
    rv->phase_g = (float)get(v, "phase_g")->valuedouble;
    rv->seed = (uint32_t)get(v, "seed")->valuedouble;
    rv->noise_scale = (float)get(v, "noise_scale")->valuedouble;
    rs->nvolumes = i + 1;
    if (strcmp(get(v, "source")->valuestring, "file") == 0) {
      rv->source = VOLUME_GRID;
      rv->grid = volume_grid(v, i, err);
      if (!rv->grid)
        return -1;
    } else {
      rv->source = VOLUME_NOISE;
    }
  }
  return 0;
}

/* ---- Validation and compilation ---- */

static double norm3(const double v[3]) {
  return sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
}

/* An item's id and its index, for finding repeated ids. */
typedef struct id_at {
  const char *id;
  int i;
} id_at_t;

static int id_at_cmp(const void *a, const void *b) {
  const id_at_t *x = a, *y = b;
  int c = strcmp(x->id, y->id);
  return c ? c : (x->i > y->i) - (x->i < y->i);
}

/*
 * The first item (in document order) whose id an earlier item has, among the 'n' in 'v' (ids
 * not empty), with that earlier item's index in '*first'; -1 when the ids are unique. Sorted,
 * not compared pairwise: a thousand objects would make half a million comparisons of every
 * change of the scene.
 */
static int repeated_id(id_at_t *v, int n, int *first) {
  qsort(v, (size_t)n, sizeof *v, id_at_cmp);
  int best = -1;
  for (int k = 1; k < n; k++) {
    /* v[k] is the second of its run of equal ids: the first item to repeat that id. */
    int second =
        strcmp(v[k].id, v[k - 1].id) == 0 && (k < 2 || strcmp(v[k - 1].id, v[k - 2].id) != 0);
    if (second && (best < 0 || v[k].i < best)) {
      best = v[k].i;
      *first = v[k - 1].i;
    }
  }
  return best;
}

/* The objects' checks: a mesh names its file, ids are unique when not empty; the first object
 * at fault is named. */
static int check_objects(const cJSON *objs, scene_error_t *err) {
  int n = cJSON_GetArraySize(objs), nids = 0, mesh = -1, i = 0, j = -1;
  id_at_t *ids = malloc(((size_t)n + 1) * sizeof *ids);
  if (!ids)
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  for (const cJSON *o = objs->child; o; o = o->next, i++) {
    const cJSON *file = get(o, "file");
    if (mesh < 0 && strcmp(get(o, "shape")->valuestring, "mesh") == 0 &&
        (!file || !file->valuestring[0]))
      mesh = i;
    const char *id = get(o, "id")->valuestring;
    if (id[0])
      ids[nids++] = (id_at_t){id, i};
  }
  int dup = repeated_id(ids, nids, &j);
  char p[64];
  int rc = 0;
  if (mesh >= 0 && (dup < 0 || mesh <= dup)) {
    snprintf(p, sizeof p, "objects.%d.file", mesh);
    rc =
        proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                        "%s: a mesh object needs a file (an OBJ path under the data directory)", p);
  } else if (dup >= 0) {
    snprintf(p, sizeof p, "objects.%d.id", dup);
    rc = proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                         "%s: \"%s\" is already the id of objects.%d", p,
                         get(cJSON_GetArrayItem(objs, dup), "id")->valuestring, j);
  }
  free(ids);
  return rc;
}

int scene_check_camera(const cJSON *cam, scene_error_t *err) {
  double eye[3], target[3], up[3], fwd[3];
  vec3d(get(cam, "eye"), eye);
  vec3d(get(cam, "target"), target);
  vec3d(get(cam, "up"), up);
  for (int i = 0; i < 3; i++)
    fwd[i] = target[i] - eye[i];
  double flen = norm3(fwd);
  double scale = fmax(1.0, fmax(norm3(eye), norm3(target)));
  if (!(flen > EYE_TARGET_EPS * scale))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "camera.target",
                           "camera.target: must differ from camera.eye");
  double ulen = norm3(up);
  if (ulen == 0)
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "camera.up",
                           "camera.up: must not be the zero vector");
  double c[3] = {fwd[1] * up[2] - fwd[2] * up[1], fwd[2] * up[0] - fwd[0] * up[2],
                 fwd[0] * up[1] - fwd[1] * up[0]};
  if (!(norm3(c) > UP_PARALLEL_EPS * flen * ulen))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "camera.up",
                           "camera.up: must not be parallel to the view direction (target - eye)");
  double near_ = get(cam, "near")->valuedouble, far_ = get(cam, "far")->valuedouble;
  if (!(near_ < far_))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "camera.far",
                           "camera.far: %g must be greater than camera.near (%g)", far_, near_);
  return 0;
}

/* The checks that involve more than one field, on a document that passed the schema. */
static int check_cross(const cJSON *doc, scene_error_t *err) {
  if (scene_check_camera(get(doc, "camera"), err) != 0)
    return -1;
  return check_objects(get(doc, "objects"), err);
}

/* Most animation keys in one document (limits.keyframes); unlimited until set. */
static uint32_t g_keyframes = UINT32_MAX;

/*
 * Adds the keys of the animations of wave 'w' (waves['i']) to '*total'. Past g_keyframes the
 * document is refused at the entry that passes it: every key is kept in the document, read by
 * each scene.get and copied by each change, and a few thousand already animate any shot.
 */
static int count_keys(const cJSON *w, int i, uint64_t *total, scene_error_t *err) {
  const cJSON *anim = get(w, "animate");
  int m = 0;
  for (const cJSON *e = anim ? anim->child : NULL; e; e = e->next, m++) {
    *total += (uint64_t)cJSON_GetArraySize(get(e, "keys"));
    if (*total > g_keyframes) {
      char p[64];
      snprintf(p, sizeof p, "waves.%d.animate.%d.keys", i, m);
      return proto_error_set(
          err, PROTO_E_LIMIT, p,
          "%s: the scene's animations would hold %llu keys, over the limit of %u "
          "(limits.keyframes)",
          p, (unsigned long long)*total, g_keyframes);
    }
  }
  return 0;
}

/* The members of one wave, as the schema describes them. */
static const sch_field_t *wave_fields(void) {
  return sch_path_field(&scene_schema, "waves.0")->fields;
}

/*
 * The checks of the waves that involve more than one field, on a document that passed the
 * schema: ids unique when not empty, a and b not both 0 (such a wave could never show, unless
 * one of them is animated and may grow), and the animations (anim_check), which validate their
 * targets and keys in place and fill in their defaults.
 */
static int check_waves(cJSON *doc, scene_error_t *err) {
  const sch_field_t *wf = wave_fields();
  cJSON *waves = get(doc, "waves");
  uint64_t keys = 0;
  int i = 0;
  for (cJSON *w = waves->child; w; w = w->next, i++) {
    char p[64];
    const char *id = get(w, "id")->valuestring;
    int j = 0;
    for (const cJSON *q = waves->child; id[0] && q != w; q = q->next, j++) {
      if (strcmp(get(q, "id")->valuestring, id) == 0) {
        snprintf(p, sizeof p, "waves.%d.id", i);
        return proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                               "%s: \"%s\" is already the id of waves.%d", p, id, j);
      }
    }
    if (get(w, "a")->valuedouble == 0 && get(w, "b")->valuedouble == 0 && !anim_animates(w, "a") &&
        !anim_animates(w, "b")) {
      snprintf(p, sizeof p, "waves.%d.a", i);
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                             "%s: a and b are both 0, so the wave would never show", p);
    }
    if (count_keys(w, i, &keys, err) != 0)
      return -1;
    snprintf(p, sizeof p, "waves.%d", i);
    if (anim_check(w, wf, p, err) != 0)
      return -1;
  }
  return 0;
}

/* Compiles the waves of 'doc' into 'rs' (rs->waves NULL when there are none). Returns 0 or -1
 * on OOM, leaving rs->waves NULL. */
static int compile_waves(const cJSON *doc, render_scene_t *rs) {
  const cJSON *waves = get(doc, "waves");
  int n = cJSON_GetArraySize(waves);
  rs->waves = NULL;
  rs->nwaves = 0;
  if (n == 0)
    return 0;
  rs->waves = calloc((size_t)n, sizeof *rs->waves);
  if (!rs->waves)
    return -1;
  int i = 0;
  for (const cJSON *w = waves->child; w; w = w->next, i++) {
    rwave_t *rw = &rs->waves[i];
    vec3f(get(w, "center"), rw->center);
    vec3f(get(w, "direction"), rw->direction);
    rw->a = (float)get(w, "a")->valuedouble;
    rw->b = (float)get(w, "b")->valuedouble;
    rw->length = (float)get(w, "length")->valuedouble;
    rw->radius = (float)get(w, "radius")->valuedouble;
    rw->softening = (float)get(w, "softening")->valuedouble;
    rw->clamp = (float)get(w, "clamp")->valuedouble;
    vec3f(get(w, "color"), rw->color);
  }
  rs->nwaves = n;
  return 0;
}

static shape_t shape_of(const char *s) {
  static const char *const names[] = {"box", "sphere", "tetrahedron", "plane", "mesh"};
  for (int i = 0; i < 5; i++)
    if (strcmp(s, names[i]) == 0)
      return (shape_t)i;
  return SHAPE_BOX;
}

static tone_map_t tone_map_of(const char *s) {
  if (strcmp(s, "none") == 0)
    return TONE_NONE;
  if (strcmp(s, "reinhard") == 0)
    return TONE_REINHARD;
  return TONE_ACES;
}

/* The lattice spacing of a block of 'initial': its own, or h/2. */
static double block_spacing(const cJSON *fluid, const cJSON *blk) {
  double sp = get(blk, "spacing")->valuedouble;
  return sp > 0 ? sp : 0.5 * get(fluid, "h")->valuedouble;
}

/* The lattice indices (x, y, z) of the particle 'i' of a block of layers nx × nz. */
static void block_index(uint64_t i, uint64_t nx, uint64_t nz, uint64_t idx[3]) {
  idx[0] = i % nx;
  idx[2] = i / nx % nz;
  idx[1] = i / (nx * nz);
}

static int inside(const double v[3], const double lo[3], const double hi[3]) {
  for (int i = 0; i < 3; i++)
    if (!(v[i] >= lo[i] && v[i] <= hi[i]))
      return 0;
  return 1;
}

/* The smallest particle_mass the solver takes (it runs in float32), beside 0 for the lattice
 * mass. */
#define FLUID_MIN_MASS 1e-12

/*
 * The fluid's checks across fields: the tank is not empty, every emitter's centre and every
 * particle of the starting blocks lies inside it, and the blocks hold at most max_particles.
 */
static int check_fluid(const cJSON *doc, scene_error_t *err) {
  const cJSON *fluid = get(doc, "fluid");
  const cJSON *b = get(fluid, "bounds");
  double lo[3], hi[3];
  vec3d(get(b, "min"), lo);
  vec3d(get(b, "max"), hi);
  for (int i = 0; i < 3; i++)
    if (!(lo[i] < hi[i]))
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, "fluid.bounds.max",
                             "fluid.bounds.max: must be above fluid.bounds.min on every axis");
  /* The solver works in float32: a mass it would round to a denormal or to 0 makes NaNs. */
  double mass = get(fluid, "particle_mass")->valuedouble;
  if (mass > 0 && mass < FLUID_MIN_MASS)
    return proto_error_set(
        err, PROTO_E_INVALID_PARAMS, "fluid.particle_mass",
        "fluid.particle_mass: %g is too small for the float32 solver: 0 (the lattice "
        "mass) or from %g",
        mass, FLUID_MIN_MASS);
  char p[64];
  int k = 0;
  for (const cJSON *em = get(fluid, "emitters")->child; em; em = em->next, k++) {
    double c[3];
    vec3d(get(em, "position"), c);
    if (!inside(c, lo, hi)) {
      snprintf(p, sizeof p, "fluid.emitters.%d.position", k);
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p, "%s: must lie inside fluid.bounds", p);
    }
  }
  double total = 0, cap = get(fluid, "max_particles")->valuedouble;
  k = 0;
  for (const cJSON *blk = get(fluid, "initial")->child; blk; blk = blk->next, k++) {
    double o[3], top[3], sp = block_spacing(fluid, blk);
    vec3d(get(blk, "origin"), o);
    if (!inside(o, lo, hi)) {
      snprintf(p, sizeof p, "fluid.initial.%d.origin", k);
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p, "%s: must lie inside fluid.bounds", p);
    }
    uint64_t n = (uint64_t)get(blk, "count")->valuedouble;
    uint64_t nx = (uint64_t)get(blk, "nx")->valuedouble, nz = (uint64_t)get(blk, "nz")->valuedouble;
    /* The far corner: the full rows and layers below the last particle reach their ends. */
    uint64_t far[3] = {n < nx ? n - 1 : nx - 1, (n - 1) / (nx * nz),
                       (n + nx - 1) / nx < nz ? (n + nx - 1) / nx - 1 : nz - 1};
    for (int i = 0; i < 3; i++)
      top[i] = o[i] + sp * (double)far[i];
    if (!inside(top, lo, hi)) {
      snprintf(p, sizeof p, "fluid.initial.%d.count", k);
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                             "%s: the block reaches (%g, %g, %g), outside fluid.bounds", p, top[0],
                             top[1], top[2]);
    }
    total += (double)n;
    if (total > cap) {
      snprintf(p, sizeof p, "fluid.initial.%d.count", k);
      return proto_error_set(
          err, PROTO_E_INVALID_PARAMS, p,
          "%s: the blocks hold %.0f particles, more than fluid.max_particles (%.0f)", p, total,
          cap);
    }
  }
  return 0;
}

/* An opaque object as the fluid collides with it (sim_fluid.h): a sphere (an ellipsoid when
 * scaled), a box or a plane; 'kind' -1 for the shapes that do not collide. */
typedef struct solid {
  int kind; /* 0 sphere, 1 box, 2 plane, -1 none. */
  double c[3], r[3][3], semi[3];
} solid_t;

static solid_t solid_of(const cJSON *o) {
  solid_t b;
  const char *shape = get(o, "shape")->valuestring;
  b.kind = strcmp(shape, "sphere") == 0  ? 0
           : strcmp(shape, "box") == 0   ? 1
           : strcmp(shape, "plane") == 0 ? 2
                                         : -1;
  double rot[3], sc[3];
  vec3d(get(o, "position"), b.c);
  vec3d(get(o, "rotation"), rot);
  vec3d(get(o, "scale"), sc);
  rotation_zyx(rot, b.r); /* As the renderer and the simulation build it. */
  for (int i = 0; i < 3; i++)
    b.semi[i] = 0.5 * fabs(sc[i]);
  return b;
}

/* Whether point 'x' lies inside 'b', as the fluid's collision sees it. */
static int solid_inside(const solid_t *b, const float x[3]) {
  double d[3], q[3];
  for (int i = 0; i < 3; i++)
    d[i] = (double)x[i] - b->c[i];
  for (int j = 0; j < 3; j++) /* q = R^T d: the point in object space. */
    q[j] = b->r[0][j] * d[0] + b->r[1][j] * d[1] + b->r[2][j] * d[2];
  if (b->kind == 0) {
    double u = 0;
    for (int i = 0; i < 3; i++)
      u += (q[i] / b->semi[i]) * (q[i] / b->semi[i]);
    return u < 1;
  }
  if (b->kind == 1)
    return fabs(q[0]) < b->semi[0] && fabs(q[1]) < b->semi[1] && fabs(q[2]) < b->semi[2];
  return b->kind == 2 && q[1] < 0;
}

int scene_particles_of(const cJSON *doc, particles_t **out) {
  const cJSON *fluid = get(doc, "fluid");
  const cJSON *blocks = get(fluid, "initial");
  uint64_t total = 0;
  for (const cJSON *blk = blocks->child; blk; blk = blk->next)
    total += (uint64_t)get(blk, "count")->valuedouble;
  *out = NULL;
  if (total == 0)
    return 0;
  particles_t *p = particles_new((uint32_t)total);
  if (!p)
    return -1;
  float lo[3], hi[3];
  vec3f(get(get(fluid, "bounds"), "min"), lo);
  vec3f(get(get(fluid, "bounds"), "max"), hi);
  int nsolid = 0;
  solid_t *solids = malloc(((size_t)cJSON_GetArraySize(get(doc, "objects")) + 1) * sizeof *solids);
  if (!solids) {
    particles_unref(p);
    return -1;
  }
  for (const cJSON *o = get(doc, "objects")->child; o; o = o->next) {
    solids[nsolid] = solid_of(o);
    if (solids[nsolid].kind >= 0 && nsolid < 256) /* The simulation's first 256 colliders. */
      nsolid++;
  }
  size_t at = 0;
  for (const cJSON *blk = blocks->child; blk; blk = blk->next) {
    double o[3], sp = block_spacing(fluid, blk);
    float v[3];
    vec3d(get(blk, "origin"), o);
    vec3f(get(blk, "velocity"), v);
    uint64_t n = (uint64_t)get(blk, "count")->valuedouble;
    uint64_t nx = (uint64_t)get(blk, "nx")->valuedouble, nz = (uint64_t)get(blk, "nz")->valuedouble;
    for (uint64_t i = 0; i < n; i++) {
      uint64_t idx[3];
      block_index(i, nx, nz, idx);
      float *x = p->pos + 3 * at;
      for (int c = 0; c < 3; c++) {
        /* Checked in double; the clamp only absorbs the rounding to float at the walls. */
        x[c] = fminf(fmaxf((float)(o[c] + sp * (double)idx[c]), lo[c]), hi[c]);
        p->vel[3 * at + c] = v[c];
      }
      int hidden = 0;
      for (int k = 0; k < nsolid && !hidden; k++)
        hidden = solid_inside(&solids[k], x);
      if (!hidden)
        at++;
    }
  }
  free(solids);
  if (at == 0) {
    particles_unref(p);
    return 0;
  }
  p->count = (uint32_t)at;
  *out = p;
  return 0;
}

/* Fills rs->fluid from the document and the particles, taking a reference to them when the
 * fluid is drawn; a fluid that is disabled or empty is not drawn. */
static void compile_fluid(const cJSON *doc, particles_t *p, render_scene_t *rs) {
  memset(&rs->fluid, 0, sizeof rs->fluid);
  const cJSON *fluid = get(doc, "fluid");
  if (!cJSON_IsTrue(get(fluid, "enabled")) || !p || p->count == 0)
    return;
  const cJSON *mat = get(fluid, "material");
  rs->fluid.count = p->count;
  rs->fluid.positions = p->pos;
  rs->fluid.owner = particles_ref(p);
  rs->fluid.h = (float)get(fluid, "h")->valuedouble;
  rs->fluid.threshold = (float)get(fluid, "threshold")->valuedouble;
  vec3f(get(mat, "color"), rs->fluid.color);
  rs->fluid.ior = (float)get(mat, "ior")->valuedouble;
  rs->fluid.roughness = (float)get(mat, "roughness")->valuedouble;
}

/* ---- The cloud ---- */

static uint32_t g_cloud_side = 256;
/* Generations of cloud cells, unique across scenes so that a job of a deleted scene can never
 * match a new scene of the same name. Loop thread only. */
static uint64_t g_cloud_gen;

void scene_set_cloud_side(uint32_t side) {
  g_cloud_side = side < 1 ? 1 : side > CLOUD_MAX_SIDE ? CLOUD_MAX_SIDE : side;
}

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

/* The cloud's checks: integral grid sides, within limits.cloud_side when enabled; ellipsoid
 * radii above 0. */
static int check_cloud(const cJSON *doc, scene_error_t *err) {
  const cJSON *cloud = get(doc, "cloud");
  double n[3];
  vec3d(get(cloud, "grid"), n);
  for (int i = 0; i < 3; i++) {
    char p[32];
    snprintf(p, sizeof p, "cloud.grid.%d", i);
    if (n[i] != floor(n[i]))
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                             "%s: %s is not a whole number of cells", p, num_text(n[i]).s);
    /* A disabled cloud has no cells, so only an enabled one is held to the configured limit
     * (the default 64³ must not break every scene of a server with a smaller one); no side
     * may pass the largest limit a server can be given. */
    int enabled = cJSON_IsTrue(get(cloud, "enabled"));
    uint32_t limit = enabled ? g_cloud_side : CLOUD_MAX_SIDE;
    if (n[i] > limit)
      return proto_error_set(err, PROTO_E_LIMIT, p,
                             "%s: %g cells is over the limit of %u per side (%s)", p, n[i], limit,
                             enabled ? "limits.cloud_side" : "the most any server allows");
  }
  /* The seeding steps are bounded so that one change cannot hold a thread for long. */
  double steps = get(get(cloud, "init"), "steps")->valuedouble;
  if (steps * n[0] * n[1] * n[2] > CLOUD_INIT_STEP_CELLS && cJSON_IsTrue(get(cloud, "enabled")))
    return proto_error_set(
        err, PROTO_E_LIMIT, "cloud.init.steps",
        "cloud.init.steps: %g steps of a %gx%gx%g grid is over the limit of %llu "
        "cell-steps",
        steps, n[0], n[1], n[2], CLOUD_INIT_STEP_CELLS);
  int i = 0;
  for (const cJSON *e = get(cloud, "ellipsoids")->child; e; e = e->next, i++) {
    double r[3];
    vec3d(get(e, "radii"), r);
    if (!(r[0] > 0 && r[1] > 0 && r[2] > 0)) {
      char p[64];
      snprintf(p, sizeof p, "cloud.ellipsoids.%d.radii", i);
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p, "%s: every radius must be above 0", p);
    }
  }
  return 0;
}

/* The cloud settings of validated 'doc'. Returns 0, or -1 when the cloud is disabled. */
static int cloud_config_of(const cJSON *doc, scene_cloud_t *c) {
  const cJSON *cloud = get(doc, "cloud");
  memset(c, 0, sizeof *c);
  double n[3], origin[3];
  vec3d(get(cloud, "grid"), n);
  vec3d(get(cloud, "origin"), origin);
  double voxel = get(cloud, "voxel")->valuedouble;
  double longest = 0;
  for (int i = 0; i < 3; i++) {
    c->n[i] = (uint32_t)n[i];
    longest = fmax(longest, n[i]);
  }
  cloud_params_t *p = &c->params;
  p->rules =
      strcmp(get(cloud, "rules")->valuestring, "dobashi") == 0 ? CLOUD_DOBASHI : CLOUD_KUROMIYA;
  p->p_ext = get(cloud, "p_ext")->valuedouble;
  p->p_hum = get(cloud, "p_hum")->valuedouble;
  p->p_act = get(cloud, "p_act")->valuedouble;
  p->wind = get(cloud, "wind")->valuedouble;
  p->seed = (uint64_t)get(cloud, "seed")->valuedouble;
  for (const cJSON *e = get(cloud, "ellipsoids")->child; e && p->nellipsoids < CLOUD_MAX_ELLIPSOIDS;
       e = e->next) {
    double ce[3], r[3];
    vec3d(get(e, "center"), ce);
    vec3d(get(e, "radii"), r);
    cloud_ellipsoid_t *el = &p->ellipsoids[p->nellipsoids++];
    /* Cell (i, j, k) has its centre at origin + (i + 0.5) voxel. */
    for (int i = 0; i < 3; i++) {
      el->center[i] = (float)((ce[i] - origin[i]) / voxel - 0.5);
      el->radii[i] = (float)(r[i] / voxel);
    }
  }
  double radius = get(cloud, "metaball_radius")->valuedouble;
  c->radius = radius > 0 ? radius : 9.0 * longest / 64;
  c->keep = (float)get(cloud, "smoothing")->valuedouble;
  c->steps_per_frame = (unsigned)get(cloud, "steps_per_frame")->valuedouble;
  const cJSON *init = get(cloud, "init");
  c->init_hum = get(init, "hum")->valuedouble;
  c->init_act = get(init, "act")->valuedouble;
  c->init_steps = (unsigned)get(init, "steps")->valuedouble;
  return cJSON_IsTrue(get(cloud, "enabled")) ? 0 : -1;
}

int scene_cloud_config(const scene_t *s, scene_cloud_t *out) {
  return cloud_config_of(s->doc, out);
}

/* Whether member 'name' of the clouds of 'a' and 'b' are equal. */
static int cloud_same(const cJSON *a, const cJSON *b, const char *name) {
  return cJSON_Compare(get(get(a, "cloud"), name), get(get(b, "cloud"), name), 1);
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
  if (cloud_config_of(doc, &c) != 0)
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

/* Fills rs->cloud from the document, showing 'density' (a reference is taken); no cloud when
 * 'density' is NULL. */
/* The cloud of 'doc' showing 'density', that of 'cells' (NULL: step 0), drawn where the wind
 * has carried it: its box moved along +x by the fraction of a cell the wind has moved the
 * cells beyond whole cells (cloud_wind_fraction). */
static void compile_cloud(const cJSON *doc, const cloud_cells_t *cells, density_grid_t *density,
                          render_scene_t *rs) {
  memset(&rs->cloud, 0, sizeof rs->cloud);
  if (!density)
    return;
  const cJSON *cloud = get(doc, "cloud");
  double n[3], origin[3];
  vec3d(get(cloud, "grid"), n);
  vec3d(get(cloud, "origin"), origin);
  double voxel = get(cloud, "voxel")->valuedouble;
  scene_cloud_t c;
  cloud_config_of(doc, &c);
  origin[0] += cloud_wind_fraction(&c.params, cells ? cells->step : 0) * voxel;
  rs->cloud.source = VOLUME_GRID;
  for (int i = 0; i < 3; i++) {
    rs->cloud.min[i] = (float)origin[i];
    rs->cloud.max[i] = (float)(origin[i] + n[i] * voxel);
  }
  rs->cloud.density = (float)get(cloud, "density")->valuedouble;
  vec3f(get(cloud, "albedo"), rs->cloud.albedo);
  rs->cloud.samples = (int)get(cloud, "samples")->valuedouble;
  rs->cloud.grid = density_grid_ref(density);
}

/* Builds the snapshot of a validated document showing the cloud density 'cloud' (that of
 * 'cells'), loading meshes and volume files; NULL with 'err' set. */
static render_scene_t *compile(const cJSON *doc, particles_t *particles, const cloud_cells_t *cells,
                               density_grid_t *cloud, scene_error_t *err) {
  render_scene_t *rs = calloc(1, sizeof *rs);
  if (!rs) {
    proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
    return NULL;
  }
  atomic_init(&rs->refs, 1);
  const cJSON *cam = get(doc, "camera");
  vec3f(get(cam, "eye"), rs->camera.eye);
  vec3f(get(cam, "target"), rs->camera.target);
  vec3f(get(cam, "up"), rs->camera.up);
  rs->camera.fov_y = (float)get(cam, "fov_y")->valuedouble;
  rs->camera.near_ = (float)get(cam, "near")->valuedouble;
  rs->camera.far_ = (float)get(cam, "far")->valuedouble;
  vec3f(get(doc, "background"), rs->background);

  const cJSON *light = get(doc, "light");
  double dir[3];
  vec3d(get(light, "direction"), dir);
  double dlen = norm3(dir);
  for (int i = 0; i < 3; i++)
    rs->light.direction[i] = (float)(dir[i] / dlen);
  vec3f(get(light, "color"), rs->light.color);
  rs->light.intensity = (float)get(light, "intensity")->valuedouble;
  rs->light.ambient = (float)get(light, "ambient")->valuedouble;
  rs->light.shadow_map = (int)get(light, "shadow_map")->valuedouble;

  const cJSON *render = get(doc, "render");
  rs->exposure = (float)get(render, "exposure")->valuedouble;
  rs->tone_map = tone_map_of(get(render, "tone_map")->valuestring);
  const char *vres = get(render, "volume_resolution")->valuestring;
  rs->volume_div = strcmp(vres, "half") == 0 ? 2 : strcmp(vres, "quarter") == 0 ? 4 : 1;
  rs->transparent_background = cJSON_IsTrue(get(render, "transparent_background"));
  rs->antialias = (int)get(render, "antialias")->valuedouble;

  const cJSON *sim = get(doc, "sim");
  rs->frame = (uint64_t)get(sim, "frame")->valuedouble;
  rs->time = get(sim, "time")->valuedouble;

  const cJSON *objs = get(doc, "objects");
  int n = cJSON_GetArraySize(objs);
  if (n > 0) {
    rs->objects = calloc((size_t)n, sizeof *rs->objects);
    if (!rs->objects) {
      render_scene_unref(rs);
      proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
      return NULL;
    }
  }
  int i = 0;
  for (const cJSON *o = objs->child; o; o = o->next, i++) {
    robject_t *ro = &rs->objects[i];
    ro->shape = shape_of(get(o, "shape")->valuestring);
    vec3f(get(o, "position"), ro->position);
    vec3f(get(o, "scale"), ro->scale);
    vec3f(get(o, "rotation"), ro->rotation);
    vec3f(get(o, "color"), ro->color);
    /* Counted as it goes, so that unref frees exactly the meshes taken so far on failure. */
    rs->nobjects = i + 1;
    if (ro->shape == SHAPE_MESH) {
      ro->mesh = object_mesh(o, i, err);
      if (!ro->mesh) {
        render_scene_unref(rs);
        return NULL;
      }
    }
  }
  if (compile_waves(doc, rs) != 0) {
    render_scene_unref(rs);
    proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
    return NULL;
  }
  compile_fluid(doc, particles, rs);
  compile_cloud(doc, cells, cloud, rs);
  if (compile_volumes(doc, rs, err) != 0) {
    render_scene_unref(rs);
    return NULL;
  }
  return rs;
}

/*
 * Validates 'doc' in place (defaults, normalisation), checks it across fields and sets each
 * keyframed wave field to its value at the document's sim.time (keyframes own their field: a
 * value written there is replaced). Returns 0, or -1 with 'err' set.
 */
static int prepare(cJSON *doc, scene_error_t *err) {
  if (sch_validate(&scene_schema, doc, "", err) != 0)
    return -1;
  if (check_cross(doc, err) != 0 || check_waves(doc, err) != 0 || check_volumes(doc, err) != 0 ||
      check_fluid(doc, err) != 0 || check_cloud(doc, err) != 0)
    return -1;
  double now = get(get(doc, "sim"), "time")->valuedouble;
  const sch_field_t *wf = wave_fields();
  for (cJSON *w = get(doc, "waves")->child; w; w = w->next)
    anim_apply_keys(w, wf, now);
  return 0;
}

/*
 * Looks up every mesh and volume file of the validated 'doc' once before the seedings of a
 * commit (the cloud's cells, the particles; seeding.h): a file that must first be read off the
 * loop thread (a deferral, scene_files.h) then stops the commit before a seeding is looked up,
 * so that a seeding made for the retry is made with the files in hand. Returns 0, or -1 with
 * 'err' set.
 */
static int files_ready(const cJSON *doc, scene_error_t *err) {
  int i = 0;
  for (const cJSON *o = get(doc, "objects")->child; o; o = o->next, i++) {
    if (shape_of(get(o, "shape")->valuestring) != SHAPE_MESH)
      continue;
    mesh_t *m = object_mesh(o, i, err);
    if (!m)
      return -1;
    mesh_unref(m);
  }
  i = 0;
  for (const cJSON *v = get(doc, "volumes")->child; v; v = v->next, i++) {
    if (strcmp(get(v, "source")->valuestring, "file") != 0)
      continue;
    density_grid_t *g = volume_grid(v, i, err);
    if (!g)
      return -1;
    density_grid_unref(g);
  }
  return 0;
}

/* Whether every particle of 'p' (NULL: none) lies inside the bounds of checked 'fluid'. Returns
 * 0, or -1 with 'err' at 'path' naming the first that does not, as 'what' holds it. */
static int particles_fit(const cJSON *fluid, const particles_t *p, const char *path,
                         const char *what, scene_error_t *err) {
  double lo[3], hi[3];
  vec3d(get(get(fluid, "bounds"), "min"), lo);
  vec3d(get(get(fluid, "bounds"), "max"), hi);
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

/* ---- Simulation memory (scene_sim_bytes) ---- */

static uint64_t g_sim_budget = UINT64_MAX; /* limits.scene_bytes; unlimited until set. */
static uint64_t g_sim_total;               /* sim_bytes summed over every scene alive. */
static uint64_t g_scene_ids;               /* The last scene_t.id given. */

void scene_set_budget(uint64_t sim_bytes, uint32_t keyframes) {
  g_sim_budget = sim_bytes;
  g_keyframes = keyframes;
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
  const cJSON *cloud = get(doc, "cloud");
  if (!cJSON_IsTrue(get(cloud, "enabled")))
    return 0;
  double n[3];
  vec3d(get(cloud, "grid"), n);
  uint64_t words = ((uint64_t)n[0] + 63) / 64, rows = (uint64_t)n[1] * (uint64_t)n[2];
  uint64_t cells = (uint64_t)n[0] * rows;
  return 3 * CLOUD_PLANE_COPIES * 8 * words * rows + cells * CLOUD_CELL_BYTES;
}

/* Whether the fluid of 'doc' has an emitter that adds particles. */
static int fluid_emits(const cJSON *doc) {
  for (const cJSON *em = get(get(doc, "fluid"), "emitters")->child; em; em = em->next)
    if (get(em, "rate")->valuedouble > 0)
      return 1;
  return 0;
}

/* The particles a simulated fluid may come to hold: max_particles once emitters fill it. */
static uint64_t fluid_particles(const cJSON *doc, uint64_t particles) {
  uint64_t cap = (uint64_t)get(get(doc, "fluid"), "max_particles")->valuedouble;
  return fluid_emits(doc) && cap > particles ? cap : particles;
}

/* The fluid's part. */
static uint64_t fluid_bytes(const cJSON *doc, uint64_t particles) {
  if (!cJSON_IsTrue(get(get(doc, "fluid"), "enabled")))
    return particles * PARTICLE_BYTES;
  return fluid_particles(doc, particles) * FLUID_PARTICLE_BYTES;
}

/* One volume's part: a file's grid of its dims, or the grid noise is baked into. */
static uint64_t volume_bytes(const cJSON *v) {
  double d[3], lo[3], hi[3];
  if (strcmp(get(v, "source")->valuestring, "file") == 0) {
    vec3d(get(v, "dims"), d);
  } else {
    vec3d(get(get(v, "bounds"), "min"), lo);
    vec3d(get(get(v, "bounds"), "max"), hi);
    double scale = get(v, "noise_scale")->valuedouble;
    for (int k = 0; k < 3; k++)
      d[k] =
          fmin(fmax(ceil((hi[k] - lo[k]) / scale * NOISE_VOXELS_PER_SCALE), 4), NOISE_MAX_VOXELS);
  }
  return (uint64_t)d[0] * (uint64_t)d[1] * (uint64_t)d[2] * VOLUME_VOXEL_BYTES;
}

uint64_t scene_sim_bytes(const cJSON *doc, uint64_t particles) {
  uint64_t sum = cloud_bytes(doc) + fluid_bytes(doc, particles);
  for (const cJSON *v = get(doc, "volumes")->child; v; v = v->next)
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
  const cJSON *ov = old ? get(old, "volumes")->child : NULL;
  int i = 0;
  for (const cJSON *v = get(doc, "volumes")->child; v;
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
static void sim_account(scene_t *s, uint64_t particles) {
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
  const cJSON *fluid = get(doc, "fluid"), *old = s->doc ? get(s->doc, "fluid") : NULL;
  if (saved && saved->particles) {
    *from = "file";
    return saved->particles->count;
  }
  if (!old || !cJSON_Compare(get(fluid, "initial"), get(old, "initial"), 1)) {
    uint64_t n = 0;
    for (const cJSON *blk = get(fluid, "initial")->child; blk; blk = blk->next)
      n += (uint64_t)get(blk, "count")->valuedouble;
    *from = "fluid.initial";
    return n;
  }
  *from = "fluid.enabled";
  return s->particles ? s->particles->count : 0;
}

/* sim_fits for validated 'doc' with the particles it will bring. */
static int budget_fits(const scene_t *s, const cJSON *doc, const scene_saved_t *saved,
                       scene_error_t *err) {
  const char *from = NULL;
  uint64_t n = particles_bound(s, doc, saved, &from);
  return sim_fits(s, doc, n, from, err);
}

/*
 * Makes 'doc' (owned, taken in every case) the scene's document if it is valid. A new value of
 * fluid.initial (or the first document) replaces the particles by its blocks; a cloud newly
 * enabled, or with a new grid, seed or init, gets freshly seeded cells, or the cells of 'saved'
 * (a snapshot's state; may be NULL), whose particles likewise replace fluid.initial's; new
 * fluid.bounds must hold the particles kept. Fails with SCENE_DEFERRED or SCENE_DEFERRED_SEED,
 * having changed nothing, when a file or a seeding must be made elsewhere first.
 */
static int commit(scene_t *s, cJSON *doc, const scene_saved_t *saved, scene_error_t *err) {
  particles_t *particles = s->particles;
  int reseed = 0;
  cloud_cells_t *cells = NULL;
  density_grid_t *density = NULL;
  int seeded = 0;
  render_scene_t *rs = NULL;
  /* The budget first: a refused change reads no file and seeds nothing. */
  if (prepare(doc, err) != 0 || budget_fits(s, doc, saved, err) != 0 ||
      files_ready(doc, err) != 0 ||
      cloud_prepare(s, doc, saved ? saved->cells : NULL, saved ? saved->density : NULL, &cells,
                    &density, &seeded, err) != 0)
    goto fail;
  const cJSON *fluid = get(doc, "fluid"), *old = s->doc ? get(s->doc, "fluid") : NULL;
  if (saved && saved->particles) {
    if (particles_fit(fluid, saved->particles, "file", "the snapshot's fluid section", err) != 0)
      goto fail;
    particles = particles_ref(saved->particles);
    reseed = 1;
  } else if (!old || !cJSON_Compare(get(fluid, "initial"), get(old, "initial"), 1)) {
    if (particles_seed_get(doc, &particles, err) != 0)
      goto fail;
    reseed = 1;
  } else if (!cJSON_Compare(get(fluid, "bounds"), get(old, "bounds"), 1) &&
             particles_fit(fluid, particles, "fluid.bounds", "fluid.bounds", err) != 0) {
    goto fail; /* The tank may not shrink past the particles it holds. */
  }
  cJSON_SetNumberValue(get(get(doc, "fluid"), "count"), (particles ? (double)particles->count : 0));
  rs = compile(doc, particles, cells, density, err);
  if (!rs)
    goto fail;
  cJSON_Delete(s->doc);
  s->doc = doc;
  render_scene_unref(s->snapshot);
  s->snapshot = rs;
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
  sim_account(s, s->particles ? s->particles->count : 0);
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

/* ---- Public API ---- */

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
  if (commit(s, doc, NULL, err) != 0) {
    free(s);
    return NULL;
  }
  return s;
}

void scene_destroy(scene_t *s) {
  if (!s)
    return;
  g_sim_total -= s->sim_bytes;
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
    proto_error_set(err, PROTO_E_NOT_FOUND, path, "no such path in the scene: %s", path);
    return NULL;
  }
  cJSON *copy = cJSON_Duplicate(v, 1);
  if (!copy)
    proto_error_set(err, PROTO_E_INTERNAL, path ? path : "", "out of memory");
  return copy;
}

/*
 * RFC 7386 on 'target' (an object, modified in place) from 'patch' (an object): a null member
 * removes the target's member, an object member merges recursively into an object (replacing
 * a non-object), and anything else, arrays included, replaces the member whole. Returns -1 on
 * OOM, leaving 'target' partly patched (the caller discards it).
 */
static int merge_patch(cJSON *target, const cJSON *patch) {
  for (const cJSON *p = patch->child; p; p = p->next) {
    cJSON *t = cJSON_GetObjectItemCaseSensitive(target, p->string);
    if (cJSON_IsNull(p)) {
      if (t)
        cJSON_DeleteItemFromObjectCaseSensitive(target, p->string);
      continue;
    }
    if (cJSON_IsObject(p)) {
      if (!cJSON_IsObject(t)) {
        cJSON *o = cJSON_CreateObject();
        if (!o)
          return -1;
        /* The *InObject* forms give the new item its key; ViaPointer would leave it nameless. */
        cJSON_bool linked = t ? cJSON_ReplaceItemInObjectCaseSensitive(target, p->string, o)
                              : cJSON_AddItemToObject(target, p->string, o);
        if (!linked) {
          cJSON_Delete(o);
          return -1;
        }
        t = o;
      }
      if (merge_patch(t, p) != 0)
        return -1;
      continue;
    }
    cJSON *v = cJSON_Duplicate(p, 1);
    if (!v)
      return -1;
    cJSON_bool linked = t ? cJSON_ReplaceItemInObjectCaseSensitive(target, p->string, v)
                          : cJSON_AddItemToObject(target, p->string, v);
    if (!linked) {
      cJSON_Delete(v);
      return -1;
    }
  }
  return 0;
}

/*
 * Applies merge patch 'patch' to the scene. A member set to null is deleted and, the document
 * being validated afterwards, comes back with its default: {"camera": {"fov_y": null}} resets
 * the field of view, {"camera": null} the whole camera. Arrays are replaced whole, so an
 * object inside "objects" is changed by sending the whole array (or with scene_set_path).
 */
int scene_patch(scene_t *s, const cJSON *patch, scene_error_t *err) {
  proto_error_clear(err);
  if (!cJSON_IsObject(patch))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "", "a patch must be a JSON object");
  cJSON *doc = cJSON_Duplicate(s->doc, 1);
  if (!doc || merge_patch(doc, patch) != 0) {
    cJSON_Delete(doc);
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  }
  return commit(s, doc, NULL, err);
}

/*
 * Sets 'value' at 'path'. The parent of the last component must exist; under an object the
 * member is replaced or added (a name the schema does not know is then refused as invalid),
 * under an array the index must be below the length, or equal to it to append. Setting an
 * object member to null deletes it, so it gets its default back, as in a merge patch. The
 * empty path is refused: the whole document changes through scene_patch or scene_replace.
 */
int scene_set_path(scene_t *s, const char *path, const cJSON *value, scene_error_t *err) {
  proto_error_clear(err);
  if (!path || !path[0])
    return proto_error_set(
        err, PROTO_E_INVALID_PARAMS, "",
        "a path must name a member of the scene (use a patch for the whole scene)");
  if (!value)
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, path, "%s: a value is required", path);
  char parent_path[256];
  if (strlen(path) >= sizeof parent_path)
    return proto_error_set(err, PROTO_E_NOT_FOUND, path, "no such path in the scene: %.200s", path);
  snprintf(parent_path, sizeof parent_path, "%s", path);
  char *dot = strrchr(parent_path, '.');
  const char *last = dot ? dot + 1 : parent_path;
  if (dot)
    *dot = '\0';
  if (!last[0])
    return proto_error_set(err, PROTO_E_NOT_FOUND, path, "no such path in the scene: %s", path);

  cJSON *doc = cJSON_Duplicate(s->doc, 1);
  cJSON *v = cJSON_Duplicate(value, 1);
  if (!doc || !v) {
    cJSON_Delete(doc);
    cJSON_Delete(v);
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  }
  cJSON *parent = dot ? sch_path_get(doc, parent_path) : doc;
  int ok = 0;
  if (cJSON_IsObject(parent)) {
    cJSON *old = cJSON_GetObjectItemCaseSensitive(parent, last);
    if (cJSON_IsNull(v)) {
      cJSON_Delete(v);
      if (old)
        cJSON_DeleteItemFromObjectCaseSensitive(parent, last);
      ok = 1;
    } else if (old) {
      ok = cJSON_ReplaceItemInObjectCaseSensitive(parent, last, v);
    } else {
      ok = cJSON_AddItemToObject(parent, last, v);
    }
  } else if (cJSON_IsArray(parent)) {
    /* sch_path_get with the full path accepts exactly the indices that exist. */
    cJSON *old = sch_path_get(doc, path);
    int n = cJSON_GetArraySize(parent);
    char index[16];
    snprintf(index, sizeof index, "%d", n);
    if (old)
      ok = cJSON_ReplaceItemViaPointer(parent, old, v);
    else if (strcmp(last, index) == 0)
      ok = cJSON_AddItemToArray(parent, v);
    else
      ok = -1;
  } else {
    ok = -1;
  }
  if (ok != 1) {
    cJSON_Delete(doc);
    cJSON_Delete(v);
    if (ok == -1)
      return proto_error_set(err, PROTO_E_NOT_FOUND, path, "no such path in the scene: %s", path);
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  }
  return commit(s, doc, NULL, err);
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
  return commit(s, copy, saved, err);
}

/* A new snapshot equal to 'old' but for the clock and the waves, compiled afresh from 'doc'
 * (animation moves them); the renderer may still hold 'old', so it is copied rather than
 * changed. NULL on OOM. */
static render_scene_t *snapshot_advanced(const render_scene_t *old, const cJSON *doc,
                                         particles_t *particles, uint64_t frame, double time) {
  render_scene_t *rs = malloc(sizeof *rs);
  if (!rs)
    return NULL;
  memcpy(rs, old, sizeof *rs);
  atomic_init(&rs->refs, 1);
  rs->objects = NULL;
  rs->volumes = NULL;
  if (compile_waves(doc, rs) != 0) {
    free(rs);
    return NULL;
  }
  if (old->nobjects > 0) {
    rs->objects = malloc((size_t)old->nobjects * sizeof *rs->objects);
    if (!rs->objects) {
      free(rs->waves);
      free(rs);
      return NULL;
    }
    memcpy(rs->objects, old->objects, (size_t)old->nobjects * sizeof *rs->objects);
    for (int i = 0; i < rs->nobjects; i++)
      if (rs->objects[i].mesh)
        mesh_ref(rs->objects[i].mesh);
  }
  if (old->nvolumes > 0) {
    rs->volumes = malloc((size_t)old->nvolumes * sizeof *rs->volumes);
    if (!rs->volumes) {
      for (int i = 0; i < rs->nobjects; i++)
        if (rs->objects[i].mesh)
          mesh_unref(rs->objects[i].mesh);
      free(rs->objects);
      free(rs->waves);
      free(rs);
      return NULL;
    }
    memcpy(rs->volumes, old->volumes, (size_t)old->nvolumes * sizeof *rs->volumes);
    for (int i = 0; i < rs->nvolumes; i++)
      density_grid_ref(rs->volumes[i].grid);
  }
  density_grid_ref(rs->cloud.grid);
  compile_fluid(doc, particles, rs);
  rs->frame = frame;
  rs->time = time;
  return rs;
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
  cJSON *sim = get(s->doc, "sim");
  cJSON *jt = get(sim, "time"), *jf = get(sim, "frame");
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
  const sch_field_t *wf = wave_fields();
  for (cJSON *w = get(s->doc, "waves")->child; w; w = w->next)
    anim_advance(w, wf, steps, dt, t);
  render_scene_t *rs = snapshot_advanced(s->snapshot, s->doc, s->particles, (uint64_t)f, t);
  if (rs) {
    render_scene_unref(s->snapshot);
    s->snapshot = rs;
  }
}

int scene_set_particles(scene_t *s, particles_t *p) {
  const cJSON *sim = get(s->doc, "sim");
  render_scene_t *rs =
      snapshot_advanced(s->snapshot, s->doc, p, (uint64_t)get(sim, "frame")->valuedouble,
                        get(sim, "time")->valuedouble);
  if (!rs)
    return -1;
  particles_unref(s->particles);
  s->particles = p;
  cJSON_SetNumberValue(get(get(s->doc, "fluid"), "count"), (p ? (double)p->count : 0));
  render_scene_unref(s->snapshot);
  s->snapshot = rs;
  sim_account(s, p ? p->count : 0);
  return 0;
}

int scene_set_cloud(scene_t *s, cloud_cells_t *cells, density_grid_t *density, int replaced) {
  const cJSON *sim = get(s->doc, "sim");
  render_scene_t *rs =
      snapshot_advanced(s->snapshot, s->doc, s->particles, (uint64_t)get(sim, "frame")->valuedouble,
                        get(sim, "time")->valuedouble);
  if (!rs)
    return -1;
  density_grid_unref(rs->cloud.grid);
  compile_cloud(s->doc, cells, density, rs);
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
  return 0;
}

double scene_dt(const scene_t *s) {
  return get(get(s->doc, "sim"), "dt")->valuedouble;
}

double scene_time(const scene_t *s) {
  return get(get(s->doc, "sim"), "time")->valuedouble;
}

double scene_frame(const scene_t *s) {
  return get(get(s->doc, "sim"), "frame")->valuedouble;
}
