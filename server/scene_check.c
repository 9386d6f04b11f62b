/*
 * A scene document's checks (scene_internal.h): the schema first, then what involves more than
 * one field or a server limit: the camera, unique ids, mesh and volume file names, the waves'
 * strengths and animations, the fluid's tank and blocks, the cloud's grid. Each names the
 * offending path, as the schema does.
 */
#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "anim.h"
#include "datapath.h"
#include "proto.h"
#include "scene_internal.h"

/* Shortest distance between eye and target, relative to their magnitude: below this the
 * single-precision view direction the kernels compute is noise. */
#define EYE_TARGET_EPS 1e-6
/* Smallest sine of the angle between camera.up and the view direction (about 0.06 degrees). */
#define UP_PARALLEL_EPS 1e-3
/* Most cell-steps cloud.init.steps may take (grid cells x steps): 256^3 x 256, a few seconds
 * of a thread-pool thread (seeding.h). */
#define CLOUD_INIT_STEP_CELLS (1ull << 32)

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

static uint32_t g_cloud_side = 256;

void scene_set_cloud_side(uint32_t side) {
  g_cloud_side = side < 1 ? 1 : side > CLOUD_MAX_SIDE ? CLOUD_MAX_SIDE : side;
}

/* The checks of volumes[] that the schema cannot make: boxes, file fields, unique ids. */
static int check_volumes(const cJSON *doc, scene_error_t *err) {
  int i = 0;
  const sch_field_t *item = scene_schema_at("volumes.0");
  const cJSON *vols = sch_member(doc, "volumes");
  for (const cJSON *v = vols->child; v; v = v->next, i++) {
    char p[64];
    double lo[3], hi[3];
    const cJSON *b = sch_member(v, "bounds");
    sch_vec3d(sch_member(b, "min"), lo);
    sch_vec3d(sch_member(b, "max"), hi);
    for (int k = 0; k < 3; k++)
      if (!(hi[k] > lo[k])) {
        snprintf(p, sizeof p, "volumes.%d.bounds.max", i);
        return proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                               "%s: must be above bounds.min on every axis (%c: %g <= %g)", p,
                               "xyz"[k], hi[k], lo[k]);
      }
    /* The file's name and dims are checked wherever they are given, so that even a noise
     * volume's document holds no name outside the data directory; a file volume needs both. */
    const cJSON *file = sch_member(v, "file"), *dims = sch_member(v, "dims");
    int from_file = sch_member_enum(item, v, "source") == VOLUME_GRID;
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
      sch_vec3d(dims, d);
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
    const char *id = sch_member(v, "id")->valuestring;
    int j = 0;
    for (const cJSON *q = vols->child; id[0] && q != v; q = q->next, j++)
      if (strcmp(sch_member(q, "id")->valuestring, id) == 0) {
        snprintf(p, sizeof p, "volumes.%d.id", i);
        return proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                               "%s: \"%s\" is already the id of volumes.%d", p, id, j);
      }
  }
  return 0;
}

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
  const sch_field_t *item = scene_schema_at("objects.0");
  int n = cJSON_GetArraySize(objs), nids = 0, mesh = -1, i = 0, j = -1;
  id_at_t *ids = malloc(((size_t)n + 1) * sizeof *ids);
  if (!ids)
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  for (const cJSON *o = objs->child; o; o = o->next, i++) {
    const cJSON *file = sch_member(o, "file");
    if (mesh < 0 && sch_member_enum(item, o, "shape") == SHAPE_MESH &&
        (!file || !file->valuestring[0]))
      mesh = i;
    const char *id = sch_member(o, "id")->valuestring;
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
                         sch_member(cJSON_GetArrayItem(objs, dup), "id")->valuestring, j);
  }
  free(ids);
  return rc;
}

int scene_check_camera(const cJSON *cam, const char *at, scene_error_t *err) {
  double eye[3], target[3], up[3], fwd[3];
  sch_vec3d(sch_member(cam, "eye"), eye);
  sch_vec3d(sch_member(cam, "target"), target);
  sch_vec3d(sch_member(cam, "up"), up);
  for (int i = 0; i < 3; i++)
    fwd[i] = target[i] - eye[i];
  double flen = norm3(fwd);
  double scale = fmax(1.0, fmax(norm3(eye), norm3(target)));
  char path[64];
  if (!(flen > EYE_TARGET_EPS * scale)) {
    snprintf(path, sizeof path, "%s.target", at);
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, path, "%s: must differ from %s.eye", path,
                           at);
  }
  double ulen = norm3(up);
  snprintf(path, sizeof path, "%s.up", at);
  if (ulen == 0)
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, path, "%s: must not be the zero vector",
                           path);
  double c[3] = {fwd[1] * up[2] - fwd[2] * up[1], fwd[2] * up[0] - fwd[0] * up[2],
                 fwd[0] * up[1] - fwd[1] * up[0]};
  if (!(norm3(c) > UP_PARALLEL_EPS * flen * ulen))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, path,
                           "%s: must not be parallel to the view direction (target - eye)", path);
  double near_ = sch_member(cam, "near")->valuedouble, far_ = sch_member(cam, "far")->valuedouble;
  snprintf(path, sizeof path, "%s.far", at);
  if (!(near_ < far_))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, path,
                           "%s: %g must be greater than %s.near (%g)", path, far_, at, near_);
  return 0;
}

/* The checks that involve more than one field, on a document that passed the schema. */
static int check_cross(const cJSON *doc, scene_error_t *err) {
  if (scene_check_camera(sch_member(doc, "camera"), "camera", err) != 0)
    return -1;
  return check_objects(sch_member(doc, "objects"), err);
}

/* Most animation keys in one document (limits.keyframes); unlimited until set. */
static uint32_t g_keyframes = UINT32_MAX;

void scene_check_set_keyframes(uint32_t keyframes) {
  g_keyframes = keyframes;
}

/*
 * Adds the keys of the animations of wave 'w' (waves['i']) to '*total'. Past g_keyframes the
 * document is refused at the entry that passes it: every key is kept in the document, read by
 * each scene.get and copied by each change, and a few thousand already animate any shot.
 */
static int count_keys(const cJSON *w, int i, uint64_t *total, scene_error_t *err) {
  const cJSON *anim = sch_member(w, "animate");
  int m = 0;
  for (const cJSON *e = anim ? anim->child : NULL; e; e = e->next, m++) {
    *total += (uint64_t)cJSON_GetArraySize(sch_member(e, "keys"));
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

/*
 * The checks of the waves that involve more than one field, on a document that passed the
 * schema: ids unique when not empty, a and b not both 0 (such a wave could never show, unless
 * one of them is animated and may grow), and the animations (anim_check), which validate their
 * targets and keys in place and fill in their defaults.
 */
static int check_waves(cJSON *doc, scene_error_t *err) {
  const sch_field_t *wf = scene_schema_at("waves.0")->fields;
  cJSON *waves = sch_member(doc, "waves");
  uint64_t keys = 0;
  int i = 0;
  for (cJSON *w = waves->child; w; w = w->next, i++) {
    char p[64];
    const char *id = sch_member(w, "id")->valuestring;
    int j = 0;
    for (const cJSON *q = waves->child; id[0] && q != w; q = q->next, j++) {
      if (strcmp(sch_member(q, "id")->valuestring, id) == 0) {
        snprintf(p, sizeof p, "waves.%d.id", i);
        return proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                               "%s: \"%s\" is already the id of waves.%d", p, id, j);
      }
    }
    if (sch_member(w, "a")->valuedouble == 0 && sch_member(w, "b")->valuedouble == 0 &&
        !anim_animates(w, "a") && !anim_animates(w, "b")) {
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
  const cJSON *fluid = sch_member(doc, "fluid");
  const cJSON *b = sch_member(fluid, "bounds");
  double lo[3], hi[3];
  sch_vec3d(sch_member(b, "min"), lo);
  sch_vec3d(sch_member(b, "max"), hi);
  for (int i = 0; i < 3; i++)
    if (!(lo[i] < hi[i]))
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, "fluid.bounds.max",
                             "fluid.bounds.max: must be above fluid.bounds.min on every axis");
  /* The solver works in float32: a mass it would round to a denormal or to 0 makes NaNs. */
  double mass = sch_member(fluid, "particle_mass")->valuedouble;
  if (mass > 0 && mass < FLUID_MIN_MASS)
    return proto_error_set(
        err, PROTO_E_INVALID_PARAMS, "fluid.particle_mass",
        "fluid.particle_mass: %g is too small for the float32 solver: 0 (the lattice "
        "mass) or from %g",
        mass, FLUID_MIN_MASS);
  char p[64];
  int k = 0;
  for (const cJSON *em = sch_member(fluid, "emitters")->child; em; em = em->next, k++) {
    double c[3];
    sch_vec3d(sch_member(em, "position"), c);
    if (!inside(c, lo, hi)) {
      snprintf(p, sizeof p, "fluid.emitters.%d.position", k);
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p, "%s: must lie inside fluid.bounds", p);
    }
  }
  double total = 0, cap = sch_member(fluid, "max_particles")->valuedouble;
  k = 0;
  for (const cJSON *blk = sch_member(fluid, "initial")->child; blk; blk = blk->next, k++) {
    double o[3], top[3], sp = seeding_block_spacing(fluid, blk);
    sch_vec3d(sch_member(blk, "origin"), o);
    if (!inside(o, lo, hi)) {
      snprintf(p, sizeof p, "fluid.initial.%d.origin", k);
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p, "%s: must lie inside fluid.bounds", p);
    }
    uint64_t n = (uint64_t)sch_member(blk, "count")->valuedouble;
    uint64_t nx = (uint64_t)sch_member(blk, "nx")->valuedouble,
             nz = (uint64_t)sch_member(blk, "nz")->valuedouble;
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

/* The cloud's checks: integral grid sides, within limits.cloud_side when enabled; ellipsoid
 * radii above 0. */
static int check_cloud(const cJSON *doc, scene_error_t *err) {
  const cJSON *cloud = sch_member(doc, "cloud");
  double n[3];
  sch_vec3d(sch_member(cloud, "grid"), n);
  for (int i = 0; i < 3; i++) {
    char p[32];
    snprintf(p, sizeof p, "cloud.grid.%d", i);
    if (n[i] != floor(n[i]))
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                             "%s: %s is not a whole number of cells", p, num_text(n[i]).s);
    /* A disabled cloud has no cells, so only an enabled one is held to the configured limit
     * (the default 64³ must not break every scene of a server with a smaller one); no side
     * may pass the largest limit a server can be given. */
    int enabled = cJSON_IsTrue(sch_member(cloud, "enabled"));
    uint32_t limit = enabled ? g_cloud_side : CLOUD_MAX_SIDE;
    if (n[i] > limit)
      return proto_error_set(err, PROTO_E_LIMIT, p,
                             "%s: %g cells is over the limit of %u per side (%s)", p, n[i], limit,
                             enabled ? "limits.cloud_side" : "the most any server allows");
  }
  /* The seeding steps are bounded so that one change cannot hold a thread for long. */
  double steps = sch_member(sch_member(cloud, "init"), "steps")->valuedouble;
  if (steps * n[0] * n[1] * n[2] > CLOUD_INIT_STEP_CELLS &&
      cJSON_IsTrue(sch_member(cloud, "enabled")))
    return proto_error_set(
        err, PROTO_E_LIMIT, "cloud.init.steps",
        "cloud.init.steps: %g steps of a %gx%gx%g grid is over the limit of %llu "
        "cell-steps",
        steps, n[0], n[1], n[2], CLOUD_INIT_STEP_CELLS);
  int i = 0;
  for (const cJSON *e = sch_member(cloud, "ellipsoids")->child; e; e = e->next, i++) {
    double r[3];
    sch_vec3d(sch_member(e, "radii"), r);
    if (!(r[0] > 0 && r[1] > 0 && r[2] > 0)) {
      char p[64];
      snprintf(p, sizeof p, "cloud.ellipsoids.%d.radii", i);
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, p, "%s: every radius must be above 0", p);
    }
  }
  return 0;
}

/*
 * Validates 'doc' in place (defaults, normalisation), checks it across fields and sets each
 * keyframed wave field to its value at the document's sim.time (keyframes own their field: a
 * value written there is replaced). Returns 0, or -1 with 'err' set.
 */
int scene_check_document(cJSON *doc, scene_error_t *err) {
  if (sch_validate(&scene_schema, doc, "", err) != 0)
    return -1;
  if (check_cross(doc, err) != 0 || check_waves(doc, err) != 0 || check_volumes(doc, err) != 0 ||
      check_fluid(doc, err) != 0 || check_cloud(doc, err) != 0)
    return -1;
  double now = sch_member(sch_member(doc, "sim"), "time")->valuedouble;
  const sch_field_t *wf = scene_schema_at("waves.0")->fields;
  for (cJSON *w = sch_member(doc, "waves")->child; w; w = w->next)
    anim_apply_keys(w, wf, now);
  return 0;
}
