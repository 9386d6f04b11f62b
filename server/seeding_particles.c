/*
 * The fluid's starting particles (seeding.h): each block of fluid.initial laid out on its
 * cubic lattice, less the points inside an opaque object the fluid collides with, tested as the
 * simulation's colliders see them (the rotation of rotation_zyx, ellipsoids, boxes, planes).
 * Reads a checked document only; any thread.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "seeding.h"

/* The lattice spacing of a block of 'initial': its own, or h/2. */
double seeding_block_spacing(const cJSON *fluid, const cJSON *blk) {
  double sp = sch_member(blk, "spacing")->valuedouble;
  return sp > 0 ? sp : 0.5 * sch_member(fluid, "h")->valuedouble;
}

/* The lattice indices (x, y, z) of the particle 'i' of a block of layers nx × nz. */
static void block_index(uint64_t i, uint64_t nx, uint64_t nz, uint64_t idx[3]) {
  idx[0] = i % nx;
  idx[2] = i / nx % nz;
  idx[1] = i / (nx * nz);
}

/* An opaque object as the fluid collides with it (sim_fluid.h): a sphere (an ellipsoid when
 * scaled), a box or a plane; 'kind' -1 for the shapes that do not collide. */
typedef struct solid {
  int kind; /* 0 sphere, 1 box, 2 plane, -1 none. */
  double c[3], r[3][3], semi[3];
} solid_t;

static solid_t solid_of(const sch_field_t *item, const cJSON *o) {
  solid_t b;
  int shape = sch_member_enum(item, o, "shape");
  b.kind = shape == SHAPE_SPHERE ? 0 : shape == SHAPE_BOX ? 1 : shape == SHAPE_PLANE ? 2 : -1;
  double rot[3], sc[3];
  sch_vec3d(sch_member(o, "position"), b.c);
  sch_vec3d(sch_member(o, "rotation"), rot);
  sch_vec3d(sch_member(o, "scale"), sc);
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

int seeding_particles_of(const cJSON *doc, particles_t **out) {
  const cJSON *fluid = sch_member(doc, "fluid");
  const cJSON *blocks = sch_member(fluid, "initial");
  uint64_t total = 0;
  for (const cJSON *blk = blocks->child; blk; blk = blk->next)
    total += (uint64_t)sch_member(blk, "count")->valuedouble;
  *out = NULL;
  if (total == 0)
    return 0;
  particles_t *p = particles_new((uint32_t)total);
  if (!p)
    return -1;
  float lo[3], hi[3];
  sch_vec3f(sch_member(sch_member(fluid, "bounds"), "min"), lo);
  sch_vec3f(sch_member(sch_member(fluid, "bounds"), "max"), hi);
  int nsolid = 0;
  const sch_field_t *item = scene_schema_at("objects.0");
  solid_t *solids =
      malloc(((size_t)cJSON_GetArraySize(sch_member(doc, "objects")) + 1) * sizeof *solids);
  if (!solids) {
    particles_unref(p);
    return -1;
  }
  for (const cJSON *o = sch_member(doc, "objects")->child; o; o = o->next) {
    solids[nsolid] = solid_of(item, o);
    if (solids[nsolid].kind >= 0 && nsolid < 256) /* The simulation's first 256 colliders. */
      nsolid++;
  }
  size_t at = 0;
  for (const cJSON *blk = blocks->child; blk; blk = blk->next) {
    double o[3], sp = seeding_block_spacing(fluid, blk);
    float v[3];
    sch_vec3d(sch_member(blk, "origin"), o);
    sch_vec3f(sch_member(blk, "velocity"), v);
    uint64_t n = (uint64_t)sch_member(blk, "count")->valuedouble;
    uint64_t nx = (uint64_t)sch_member(blk, "nx")->valuedouble,
             nz = (uint64_t)sch_member(blk, "nz")->valuedouble;
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
