/*
 * The particle fluid's simulation (SPEC §5.2): weakly compressible SPH after Müller et al.
 * 2003 run by kernels/sph.cl. The host keeps the authoritative particle arrays. Before each
 * substep it sorts them by grid cell (a stable counting sort, so the order and therefore every
 * sum is reproducible), uploads them with the table of cell starts, runs sph_density and
 * sph_forces, and reads the new state back. The read-back costs well under a millisecond at
 * the sizes we run and buys determinism, adaptive substeps and trivial emitters.
 */
#include "sim_fluid.h"
#include "proto_error.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define LOCAL 64             /* SPH_LOCAL of kernels/sph.cl. */
#define MAX_CELLS (1u << 20) /* The grid's cells grow beyond the support radius past this. */
#define MAX_COLLIDERS 256    /* Opaque objects that collide; the rest are ignored. */
#define COL_STRIDE 20        /* SPHC_STRIDE of kernels/sph.cl. */
#define COL_PLANES 1         /* SPHC_PLANES: a tetrahedron's four planes start here. */
#define COL_SPHERE 0
#define COL_BOX 1
#define COL_PLANE 2
#define COL_TETRA 3
#define WALL_N 64 /* SPH_WALL_N of kernels/sph.cl. */

/* The spiky kernel's factor: W(r) = SPIKY(h) (h - r)³ for r < h. */
#define SPIKY(h) (15.0 / (M_PI * pow((h), 6)))

struct fluid_sim {
  cl_dev_t *dev; /* Borrowed. */
  fluid_params_t p;
  cl_kernel k_density, k_forces;

  uint32_t n, cap;         /* Particles and capacity (max_particles). */
  size_t stride;           /* Floats per state component on the device: cap rounded up. */
  float *state, *scratch;  /* Host state, 6 * stride floats each: px py pz vx vy vz. */
  uint32_t *ids, *ids_tmp; /* Original index of each particle, in the sorted order. */
  int32_t *cell_of;        /* Per particle, its cell key; scratch for the sort. */
  int32_t *cell_start;     /* ncells + 1 entries. */
  float wall_key[3];       /* h, mass and rest density of the wall tables on the device. */
  int nx, ny, nz;          /* The grid. */
  float inv_cell;          /* 1 / cell size in y and z. */
  float inv_cell_x;        /* 1 / cell size in x: half the cell, so runs fit h more tightly. */
  uint32_t ncells;

  cl_mem d_state, d_out, d_inv_rho, d_pr2, d_cells, d_colliders, d_wall;
  float wall[3 * (WALL_N + 1)]; /* The wall tables the device has (wall_tables). */
  float *colliders;             /* ncolliders records of COL_STRIDE floats. */
  int ncolliders;

  uint64_t frame; /* The frame the next step starts from: it picks the emitters' draws. */
  int last_substeps;
};

/* splitmix64: the emitters' random numbers, reproducible from the seed. */
static uint64_t rng_next(uint64_t *s) {
  uint64_t z = (*s += 0x9E3779B97F4A7C15ull);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

/* A uniform float in [0, 1). */
static float rng_unit(uint64_t *s) {
  return (float)(rng_next(s) >> 40) * (1.0f / 16777216.0f);
}

float fluid_lattice_mass(float h, float spacing, float rest_density) {
  if (!(h > 0) || !(spacing > 0))
    return 0;
  double sum = 0;
  int k = (int)ceil(h / spacing);
  for (int i = -k; i <= k; i++) {
    for (int j = -k; j <= k; j++) {
      for (int l = -k; l <= k; l++) {
        double q = h - spacing * sqrt((double)(i * i + j * j + l * l));
        if (q > 0)
          sum += q * q * q;
      }
    }
  }
  return (float)(rest_density / (SPIKY(h) * sum));
}

void fluid_params_default(fluid_params_t *p) {
  memset(p, 0, sizeof *p);
  p->h = 0.61f;
  p->rest_density = 1000;
  p->particle_mass = fluid_lattice_mass(p->h, p->h / 2, p->rest_density);
  p->stiffness = 1000;
  p->viscosity = 50;
  p->wall_friction = 1;
  p->gravity[1] = -9.81f;
  for (int i = 0; i < 3; i++)
    p->bounds_min[i] = -5, p->bounds_max[i] = 5;
  p->seed = 1;
  p->max_particles = 65536;
}

static int finite3(const float *v) {
  return isfinite(v[0]) && isfinite(v[1]) && isfinite(v[2]);
}

/* Checks 'p'; returns 0 or -1 with a message naming the field. */
static int params_check(const fluid_params_t *p, char *err, size_t errlen) {
  if (!(p->h > 0) || !isfinite(p->h))
    return proto_error_format(err, errlen, "fluid.h must be a positive number"), -1;
  if (!(p->particle_mass > 0) || !isfinite(p->particle_mass))
    return proto_error_format(err, errlen, "fluid.particle_mass must be a positive number"), -1;
  if (!(p->rest_density > 0) || !isfinite(p->rest_density))
    return proto_error_format(err, errlen, "fluid.rest_density must be a positive number"), -1;
  if (!(p->stiffness > 0) || !isfinite(p->stiffness))
    return proto_error_format(err, errlen, "fluid.stiffness must be a positive number"), -1;
  if (!(p->viscosity >= 0) || !isfinite(p->viscosity))
    return proto_error_format(err, errlen, "fluid.viscosity must be a number >= 0"), -1;
  if (!(p->wall_friction >= 0 && p->wall_friction <= 1))
    return proto_error_format(err, errlen, "fluid.wall_friction must lie in [0, 1]"), -1;
  if (!finite3(p->gravity))
    return proto_error_format(err, errlen, "fluid.gravity must be finite"), -1;
  if (!finite3(p->bounds_min) || !finite3(p->bounds_max))
    return proto_error_format(err, errlen, "fluid.bounds must be finite"), -1;
  for (int i = 0; i < 3; i++) {
    if (!(p->bounds_max[i] > p->bounds_min[i]))
      return proto_error_format(err, errlen, "fluid.bounds: max must exceed min on every axis"), -1;
  }
  if (p->max_particles == 0 || p->max_particles > FLUID_MAX_PARTICLES)
    return proto_error_format(err, errlen, "fluid.max_particles must lie in [1, %u]",
                              FLUID_MAX_PARTICLES),
           -1;
  if (p->nemitters < 0 || p->nemitters > FLUID_MAX_EMITTERS)
    return proto_error_format(err, errlen, "fluid.emitters: at most %d", FLUID_MAX_EMITTERS), -1;
  for (int e = 0; e < p->nemitters; e++) {
    const fluid_emitter_t *m = &p->emitters[e];
    if ((m->shape != FLUID_EMIT_SPHERE && m->shape != FLUID_EMIT_BOX) || !finite3(m->position) ||
        !finite3(m->size) || !finite3(m->velocity) || !(m->rate >= 0) || !isfinite(m->rate) ||
        m->size[0] < 0 || m->size[1] < 0 || m->size[2] < 0)
      return proto_error_format(err, errlen,
                                "fluid.emitters[%d]: bad shape, size, rate or velocity", e),
             -1;
  }
  return 0;
}

/*
 * The wall tables for support 'h' at WALL_N + 1 distances d in [0, h] from a wall: the density
 * that the fluid beyond the wall would add to a particle, minus its derivative along d (the
 * pressure's push is -p / rho² times the gradient of the density), and the sum of the
 * viscosity kernel's Laplacians (the wall drags like fluid at rest). The fluid beyond is a
 * cubic lattice of particles of 'mass' at the spacing s at which that lattice has rest_density, in
 * layers s/2, 3s/2, ... behind the wall and lined up with the particle across it: a particle
 * of a lattice at rest beside the wall then sees exactly the density it would see inside.
 */
static void wall_tables(double h, double mass, double rest_density, float *out) {
  double K = SPIKY(h), L = 45.0 / (M_PI * pow(h, 6));
  /* The spacing whose lattice mass is 'mass', by bisection (the mass falls as it shrinks). */
  double lo = h / 64, hi = 2 * h;
  for (int it = 0; it < 60; it++) {
    double mid = (lo + hi) / 2;
    if (fluid_lattice_mass((float)h, (float)mid, (float)rest_density) > mass)
      hi = mid;
    else
      lo = mid;
  }
  double sp = (lo + hi) / 2, h2 = h * h;
  int k = (int)ceil(h / sp);
  for (int t = 0; t <= WALL_N; t++) {
    double d = h * t / WALL_N, rho = 0, grad = 0, lap = 0;
    for (int j = 0; j <= k; j++) {
      double z = d + sp / 2 + j * sp;
      for (int a = -k; a <= k; a++) {
        for (int b = -k; b <= k; b++) {
          double r2 = z * z + sp * sp * (a * a + b * b);
          if (r2 >= h2)
            continue;
          double r = sqrt(r2), q = h - r;
          rho += K * q * q * q;
          grad += 3 * K * q * q * z / r;
          lap += L * q;
        }
      }
    }
    out[t] = (float)(mass * rho);
    out[WALL_N + 1 + t] = (float)(mass * grad);
    out[2 * (WALL_N + 1) + t] = (float)(mass * lap);
  }
}

/* Sizes the grid over the bounds: cells of the support radius in y and z and half of it in x,
 * or larger if there would be more than MAX_CELLS of them (the neighbour search stays exact,
 * only slower). */
static void grid_init(fluid_sim_t *s) {
  double ext[3], cell = s->p.h;
  for (int i = 0; i < 3; i++)
    ext[i] = (double)s->p.bounds_max[i] - s->p.bounds_min[i];
  for (;;) {
    double n = fmax(1, ceil(2 * ext[0] / cell));
    for (int i = 1; i < 3; i++)
      n *= fmax(1, ceil(ext[i] / cell));
    if (n <= MAX_CELLS)
      break;
    cell *= 1.25;
  }
  s->inv_cell = (float)(1.0 / cell);
  s->inv_cell_x = (float)(2.0 / cell);
  s->nx = (int)fmax(1, ceil(2 * ext[0] / cell));
  s->ny = (int)fmax(1, ceil(ext[1] / cell));
  s->nz = (int)fmax(1, ceil(ext[2] / cell));
  s->ncells = (uint32_t)s->nx * (uint32_t)s->ny * (uint32_t)s->nz;
}

void fluid_sim_destroy(fluid_sim_t *s) {
  if (s == NULL)
    return;
  cl_mem bufs[] = {s->d_state, s->d_out,       s->d_inv_rho, s->d_pr2,
                   s->d_cells, s->d_colliders, s->d_wall};
  for (size_t i = 0; i < sizeof bufs / sizeof bufs[0]; i++) {
    if (bufs[i])
      clReleaseMemObject(bufs[i]);
  }
  if (s->k_density)
    clReleaseKernel(s->k_density);
  if (s->k_forces)
    clReleaseKernel(s->k_forces);
  free(s->state);
  free(s->scratch);
  free(s->ids);
  free(s->ids_tmp);
  free(s->cell_of);
  free(s->cell_start);
  free(s->colliders);
  free(s);
}

/*
 * Floats of the state on host and device: six components of 'stride' each, then 8 zeros. The
 * kernels' masked lanes read up to 7 floats past a run's end; where the particles fill the
 * stride exactly, a velocity run ends at the last component, so the zeros must be uploaded too
 * (never-written device memory could hold a NaN that a zero weight does not cancel).
 */
static size_t state_floats(const fluid_sim_t *s) {
  return 6 * s->stride + 8;
}

fluid_sim_t *fluid_sim_create(cl_dev_t *dev, const fluid_params_t *p, char *err, size_t errlen) {
  if (dev == NULL || dev->program == NULL)
    return proto_error_format(err, errlen, "[fluid] no built OpenCL program"), NULL;
  if (params_check(p, err, errlen) != 0)
    return NULL;
  fluid_sim_t *s = calloc(1, sizeof *s);
  if (s == NULL)
    return proto_error_format(err, errlen, "[fluid] out of memory"), NULL;
  s->dev = dev;
  s->p = *p;
  s->cap = p->max_particles;
  s->stride = ((size_t)s->cap + LOCAL - 1) / LOCAL * LOCAL;
  grid_init(s);
  /* The kernels read eight particles at a time past a run's end: 8 floats of slack. */
  size_t nstate = state_floats(s);
  s->state = calloc(nstate, sizeof(float));
  s->scratch = calloc(nstate, sizeof(float));
  s->ids = calloc(s->cap, sizeof(uint32_t));
  s->ids_tmp = calloc(s->cap, sizeof(uint32_t));
  s->cell_of = calloc(s->cap, sizeof(int32_t));
  s->cell_start = calloc((size_t)s->ncells + 1, sizeof(int32_t));
  s->colliders = calloc(MAX_COLLIDERS * COL_STRIDE, sizeof(float));
  if (!s->state || !s->scratch || !s->ids || !s->ids_tmp || !s->cell_of || !s->cell_start ||
      !s->colliders) {
    proto_error_format(err, errlen, "[fluid] out of memory for %u particles", s->cap);
    fluid_sim_destroy(s);
    return NULL;
  }

  cl_int rc = CL_SUCCESS;
  cl_context ctx = dev->context;
  s->d_state = clCreateBuffer(ctx, CL_MEM_READ_ONLY, nstate * sizeof(float), NULL, &rc);
  if (rc == CL_SUCCESS)
    s->d_out = clCreateBuffer(ctx, CL_MEM_WRITE_ONLY, nstate * sizeof(float), NULL, &rc);
  if (rc == CL_SUCCESS)
    s->d_inv_rho =
        clCreateBuffer(ctx, CL_MEM_READ_WRITE, (s->stride + 8) * sizeof(float), NULL, &rc);
  if (rc == CL_SUCCESS)
    s->d_pr2 = clCreateBuffer(ctx, CL_MEM_READ_WRITE, (s->stride + 8) * sizeof(float), NULL, &rc);
  if (rc == CL_SUCCESS)
    s->d_cells =
        clCreateBuffer(ctx, CL_MEM_READ_ONLY, ((size_t)s->ncells + 1) * sizeof(int32_t), NULL, &rc);
  if (rc == CL_SUCCESS)
    s->d_colliders = clCreateBuffer(ctx, CL_MEM_READ_ONLY,
                                    MAX_COLLIDERS * COL_STRIDE * sizeof(float), NULL, &rc);
  if (rc == CL_SUCCESS)
    s->d_wall = clCreateBuffer(ctx, CL_MEM_READ_ONLY, sizeof s->wall, NULL, &rc);
  /* The kernels' masked lanes read past the live particles; zeros there keep them finite. */
  float zero = 0;
  size_t per = (s->stride + 8) * sizeof(float);
  if (rc == CL_SUCCESS)
    rc = clEnqueueFillBuffer(dev->queue, s->d_inv_rho, &zero, sizeof zero, 0, per, 0, NULL, NULL);
  if (rc == CL_SUCCESS)
    rc = clEnqueueFillBuffer(dev->queue, s->d_pr2, &zero, sizeof zero, 0, per, 0, NULL, NULL);
  if (rc == CL_SUCCESS)
    rc = clFinish(dev->queue);
  if (rc != CL_SUCCESS) {
    proto_error_format(err, errlen, "[fluid] device buffers for %u particles: %s", s->cap,
                       cl_dev_strerror(rc));
    fluid_sim_destroy(s);
    return NULL;
  }
  if ((s->k_density = cl_dev_kernel(dev, "sph_density", err, errlen)) == NULL ||
      (s->k_forces = cl_dev_kernel(dev, "sph_forces", err, errlen)) == NULL) {
    fluid_sim_destroy(s);
    return NULL;
  }
  return s;
}

/* Whether every particle of 'state' (n of them, 'stride' apart) lies inside the bounds. */
static int inside_bounds(const fluid_params_t *p, const float *state, size_t stride, uint32_t n) {
  for (uint32_t k = 0; k < n; k++) {
    for (int i = 0; i < 3; i++) {
      float x = state[i * stride + k];
      if (!(x >= p->bounds_min[i] && x <= p->bounds_max[i]))
        return 0;
    }
  }
  return 1;
}

int fluid_sim_set_params(fluid_sim_t *s, const fluid_params_t *p, char *err, size_t errlen) {
  if (params_check(p, err, errlen) != 0)
    return -1;
  if (p->max_particles != s->cap)
    return proto_error_format(err, errlen,
                              "fluid.max_particles cannot change on a live simulation"),
           -1;
  if (!inside_bounds(p, s->state, s->stride, s->n))
    return proto_error_format(err, errlen,
                              "fluid.bounds: particles would lie outside the new bounds"),
           -1;
  fluid_sim_t grid = *s;
  grid.p = *p;
  grid_init(&grid);
  if (grid.ncells > s->ncells) {
    /* A larger grid needs a larger table of cell starts, here and on the device. */
    cl_int rc;
    cl_mem cells = clCreateBuffer(s->dev->context, CL_MEM_READ_ONLY,
                                  ((size_t)grid.ncells + 1) * sizeof(int32_t), NULL, &rc);
    int32_t *table = calloc((size_t)grid.ncells + 1, sizeof(int32_t));
    if (cells == NULL || table == NULL) {
      if (cells)
        clReleaseMemObject(cells);
      free(table);
      return proto_error_format(err, errlen, "[fluid] out of memory for a grid of %u cells",
                                grid.ncells),
             -1;
    }
    clReleaseMemObject(s->d_cells);
    free(s->cell_start);
    s->d_cells = cells, s->cell_start = table;
  }
  s->p = *p;
  s->nx = grid.nx, s->ny = grid.ny, s->nz = grid.nz, s->ncells = grid.ncells;
  s->inv_cell = grid.inv_cell, s->inv_cell_x = grid.inv_cell_x;
  return 0;
}

int fluid_sim_set_particles(fluid_sim_t *s, const float *pos, const float *vel, uint32_t n,
                            char *err, size_t errlen) {
  if (n > s->cap)
    return proto_error_format(
               err, errlen, "fluid.set_particles: %u particles exceed max_particles %u", n, s->cap),
           -1;
  if (n > 0 && pos == NULL)
    return proto_error_format(err, errlen, "fluid.set_particles: no positions"), -1;
  for (uint32_t k = 0; k < n; k++) {
    for (int i = 0; i < 3; i++) {
      float x = pos[3 * k + i];
      if (!isfinite(x))
        return proto_error_format(err, errlen, "fluid.set_particles: position %u is not finite", k),
               -1;
      if (x < s->p.bounds_min[i] || x > s->p.bounds_max[i])
        return proto_error_format(err, errlen,
                                  "fluid.set_particles: position %u lies outside the bounds", k),
               -1;
      if (vel != NULL && !isfinite(vel[3 * k + i]))
        return proto_error_format(err, errlen, "fluid.set_particles: velocity %u is not finite", k),
               -1;
    }
  }
  for (uint32_t k = 0; k < n; k++) {
    for (int i = 0; i < 3; i++) {
      s->state[i * s->stride + k] = pos[3 * k + i];
      s->state[(3 + i) * s->stride + k] = vel ? vel[3 * k + i] : 0.0f;
    }
    s->ids[k] = k;
  }
  s->n = n;
  return 0;
}

void fluid_sim_get_particles(const fluid_sim_t *s, float *pos, float *vel) {
  for (uint32_t k = 0; k < s->n; k++) {
    uint32_t id = s->ids[k];
    for (int i = 0; i < 3; i++) {
      if (pos)
        pos[3 * id + i] = s->state[i * s->stride + k];
      if (vel)
        vel[3 * id + i] = s->state[(3 + i) * s->stride + k];
    }
  }
}

void fluid_sim_set_frame(fluid_sim_t *s, uint64_t frame) {
  s->frame = frame;
}

uint32_t fluid_sim_count(const fluid_sim_t *s) {
  return s->n;
}

int fluid_sim_last_substeps(const fluid_sim_t *s) {
  return s->last_substeps;
}

/* An object's rotation matrix from its float angles (rotation_zyx). */
static void rotation(const float deg[3], double r[3][3]) {
  double d[3] = {deg[0], deg[1], deg[2]};
  rotation_zyx(d, r);
}

/*
 * The four face planes of the tetrahedron object 'o' (render_scene.h: the regular tetrahedron
 * of circumradius 0.5 with a vertex at +y, scaled, rotated by 'r', moved to its position) into
 * 'out' as (unit outward normal, offset) in the world, the solid being n . x < offset. Before
 * the scale, the face opposite vertex v_k (|v_k| = 0.5) is -2 v_k . u = 1/6; a point q = S u
 * of the scaled object satisfies (S^-1 (-2 v_k)) . q = 1/6.
 */
static void tetra_planes(const robject_t *o, const double r[3][3], float *out) {
  double rr = sqrt(2.0) / 3, vy = -1.0 / 6, s120 = sqrt(3.0) / 2;
  const double v[4][3] = {
      {0, 0.5, 0}, {0, vy, rr}, {rr * s120, vy, -0.5 * rr}, {-rr * s120, vy, -0.5 * rr}};
  for (int k = 0; k < 4; k++) {
    double m[3], len = 0;
    for (int i = 0; i < 3; i++) {
      m[i] = -2 * v[k][i] / o->scale[i];
      len += m[i] * m[i];
    }
    len = sqrt(len);
    double n[3], off = 1.0 / 6 / len;
    for (int i = 0; i < 3; i++)
      n[i] = (r[i][0] * m[0] + r[i][1] * m[1] + r[i][2] * m[2]) / len;
    for (int i = 0; i < 3; i++) {
      out[4 * k + i] = (float)n[i];
      off += n[i] * o->position[i];
    }
    out[4 * k + 3] = (float)off;
  }
}

int fluid_sim_set_colliders(fluid_sim_t *s, const robject_t *objs, int n, char *err,
                            size_t errlen) {
  if (n < 0 || (n > 0 && objs == NULL))
    return proto_error_format(err, errlen, "fluid: no objects array for %d colliders", n), -1;
  float recs[MAX_COLLIDERS * COL_STRIDE];
  int count = 0;
  for (int k = 0; k < n && count < MAX_COLLIDERS; k++) {
    const robject_t *o = &objs[k];
    int kind = o->shape == SHAPE_SPHERE        ? COL_SPHERE
               : o->shape == SHAPE_BOX         ? COL_BOX
               : o->shape == SHAPE_PLANE       ? COL_PLANE
               : o->shape == SHAPE_TETRAHEDRON ? COL_TETRA
                                               : -1;
    if (kind < 0)
      continue;
    if (!finite3(o->position) || !finite3(o->rotation) || !finite3(o->scale))
      return proto_error_format(err, errlen,
                                "objects[%d]: position, rotation and scale must be finite", k),
             -1;
    if (kind != COL_PLANE &&
        (fabsf(o->scale[0]) < 1e-12f || fabsf(o->scale[1]) < 1e-12f || fabsf(o->scale[2]) < 1e-12f))
      return proto_error_format(err, errlen, "objects[%d]: a zero scale cannot collide", k), -1;
    float *c = recs + COL_STRIDE * count++;
    memset(c, 0, COL_STRIDE * sizeof(float));
    double r[3][3];
    rotation(o->rotation, r);
    c[0] = (float)kind;
    if (kind == COL_TETRA) {
      tetra_planes(o, r, c + COL_PLANES);
      continue;
    }
    for (int i = 0; i < 3; i++) {
      c[1 + i] = o->position[i];
      c[13 + i] = 0.5f * fabsf(o->scale[i]);
      for (int j = 0; j < 3; j++)
        c[4 + 3 * i + j] = (float)r[i][j];
    }
  }
  memcpy(s->colliders, recs, (size_t)count * COL_STRIDE * sizeof(float));
  s->ncolliders = count;
  return 0;
}

/*
 * Adds the particles the emitters owe for the step from frame f to f + 1 of 'dt' seconds, up
 * to the capacity: floor(rate dt (f + 1)) - floor(rate dt f) each, placed by random numbers
 * drawn from the seed, the frame and the emitter. What a step emits depends on the frame
 * alone, not on the steps before it, so a simulation continued from a snapshot, or stepped in
 * other groupings, emits exactly the same particles.
 */
static void emit(fluid_sim_t *s, double dt) {
  double f = (double)s->frame;
  for (int e = 0; e < s->p.nemitters; e++) {
    const fluid_emitter_t *m = &s->p.emitters[e];
    double per = (double)m->rate * dt;
    double whole = floor(per * (f + 1)) - floor(per * f);
    uint64_t rng = s->p.seed ^ (0x5851F42D4C957F2Dull * (s->frame + 1));
    rng = rng_next(&rng) ^ (0x2545F4914F6CDD1Dull * (uint64_t)(e + 1));
    for (double k = 0; k < whole && s->n < s->cap; k++) {
      float q[3];
      if (m->shape == FLUID_EMIT_SPHERE) {
        /* Rejection sampling of the unit ball. */
        do {
          for (int i = 0; i < 3; i++)
            q[i] = 2 * rng_unit(&rng) - 1;
        } while (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] > 1);
        for (int i = 0; i < 3; i++)
          q[i] = m->position[i] + q[i] * m->size[0];
      } else {
        for (int i = 0; i < 3; i++)
          q[i] = m->position[i] + (rng_unit(&rng) - 0.5f) * m->size[i];
      }
      uint32_t at = s->n++;
      for (int i = 0; i < 3; i++) {
        float x = fminf(fmaxf(q[i], s->p.bounds_min[i]), s->p.bounds_max[i]);
        s->state[i * s->stride + at] = x;
        s->state[(3 + i) * s->stride + at] = m->velocity[i];
      }
      s->ids[at] = at;
    }
  }
}

/* Grid cell of one coordinate, exactly as sph_cell in kernels/sph.cl computes it. */
static int cell_coord(float p, float origin, float inv_cell, int n) {
  int c = (int)floorf((p - origin) * inv_cell);
  return c < 0 ? 0 : c >= n ? n - 1 : c;
}

/*
 * Puts the particles back in the order they were set or emitted. The sort below is stable,
 * so starting from this order makes the sorted order (by cell, then by that order) a function
 * of the particles alone, and with it the order of every sum on the device: a simulation
 * continued from its own last substep and one set up again from the same particles (the next
 * sim.step call, a snapshot, another process) compute the same bits.
 */
static void unsort(fluid_sim_t *s) {
  size_t st = s->stride;
  for (uint32_t k = 0; k < s->n; k++) {
    uint32_t id = s->ids[k];
    for (int i = 0; i < 6; i++)
      s->scratch[i * st + id] = s->state[i * st + k];
  }
  for (uint32_t k = 0; k < s->n; k++)
    s->ids[k] = k;
  float *t = s->state;
  s->state = s->scratch, s->scratch = t;
}

/* Sorts the particles by cell, then by the order they were set or emitted, and fills the
 * table of cell starts. */
static void sort_by_cell(fluid_sim_t *s) {
  unsort(s);
  size_t st = s->stride;
  memset(s->cell_start, 0, ((size_t)s->ncells + 1) * sizeof(int32_t));
  for (uint32_t k = 0; k < s->n; k++) {
    int x = cell_coord(s->state[k], s->p.bounds_min[0], s->inv_cell_x, s->nx);
    int y = cell_coord(s->state[st + k], s->p.bounds_min[1], s->inv_cell, s->ny);
    int z = cell_coord(s->state[2 * st + k], s->p.bounds_min[2], s->inv_cell, s->nz);
    int32_t key = (z * s->ny + y) * s->nx + x;
    s->cell_of[k] = key;
    s->cell_start[key + 1]++;
  }
  for (uint32_t c = 0; c < s->ncells; c++)
    s->cell_start[c + 1] += s->cell_start[c];
  /* Scatter with a running cursor per cell; cell_start is restored afterwards. */
  for (uint32_t k = 0; k < s->n; k++) {
    int32_t at = s->cell_start[s->cell_of[k]]++;
    for (int i = 0; i < 6; i++)
      s->scratch[i * st + (size_t)at] = s->state[i * st + k];
    s->ids_tmp[at] = s->ids[k];
  }
  for (uint32_t c = s->ncells; c > 0; c--)
    s->cell_start[c] = s->cell_start[c - 1];
  s->cell_start[0] = 0;
  float *t = s->state;
  s->state = s->scratch, s->scratch = t;
  uint32_t *u = s->ids;
  s->ids = s->ids_tmp, s->ids_tmp = u;
}

/* Runs one substep of 'dt' on the device. Returns 0 or -1 with a message. */
static int substep(fluid_sim_t *s, float dt, char *err, size_t errlen) {
  sort_by_cell(s);
  cl_command_queue q = s->dev->queue;
  /* The whole buffer, the zero tail included (state_floats). */
  size_t bytes = state_floats(s) * sizeof(float);
  cl_int rc = CL_SUCCESS;
  float key[3] = {s->p.h, s->p.particle_mass, s->p.rest_density};
  if (memcmp(key, s->wall_key, sizeof key) != 0) {
    wall_tables(s->p.h, s->p.particle_mass, s->p.rest_density, s->wall);
    rc = clEnqueueWriteBuffer(q, s->d_wall, CL_TRUE, 0, sizeof s->wall, s->wall, 0, NULL, NULL);
    if (rc == CL_SUCCESS)
      memcpy(s->wall_key, key, sizeof key);
  }
  if (rc == CL_SUCCESS)
    rc = clEnqueueWriteBuffer(q, s->d_state, CL_FALSE, 0, bytes, s->state, 0, NULL, NULL);
  if (rc == CL_SUCCESS)
    rc = clEnqueueWriteBuffer(q, s->d_cells, CL_FALSE, 0, ((size_t)s->ncells + 1) * sizeof(int32_t),
                              s->cell_start, 0, NULL, NULL);
  if (rc == CL_SUCCESS && s->ncolliders > 0)
    rc = clEnqueueWriteBuffer(q, s->d_colliders, CL_FALSE, 0,
                              (size_t)s->ncolliders * COL_STRIDE * sizeof(float), s->colliders, 0,
                              NULL, NULL);
  if (rc != CL_SUCCESS)
    return proto_error_format(err, errlen, "[fluid] upload failed: %s", cl_dev_strerror(rc)), -1;

  const fluid_params_t *p = &s->p;
  double h = p->h;
  float mass_kernel = (float)(p->particle_mass * SPIKY(h));
  float mass_spiky = (float)(p->particle_mass * 45.0 / (M_PI * pow(h, 6)));
  float mass_visc = (float)(p->viscosity * p->particle_mass * 45.0 / (M_PI * pow(h, 6)));
  float vmax = sqrtf(p->stiffness);
  cl_int stride = (cl_int)s->stride, n = (cl_int)s->n;
  cl_float ox = p->bounds_min[0], oy = p->bounds_min[1], oz = p->bounds_min[2];
  cl_float hf = (float)h, inv_h = (float)(1 / h);
  cl_int ncol = s->ncolliders;

  cl_kernel kd = s->k_density;
  int a = 0;
  rc = clSetKernelArg(kd, a++, sizeof(cl_mem), &s->d_state);
  rc |= clSetKernelArg(kd, a++, sizeof stride, &stride);
  rc |= clSetKernelArg(kd, a++, sizeof n, &n);
  rc |= clSetKernelArg(kd, a++, sizeof(cl_mem), &s->d_cells);
  rc |= clSetKernelArg(kd, a++, sizeof(int), &s->nx);
  rc |= clSetKernelArg(kd, a++, sizeof(int), &s->ny);
  rc |= clSetKernelArg(kd, a++, sizeof(int), &s->nz);
  rc |= clSetKernelArg(kd, a++, sizeof ox, &ox);
  rc |= clSetKernelArg(kd, a++, sizeof oy, &oy);
  rc |= clSetKernelArg(kd, a++, sizeof oz, &oz);
  rc |= clSetKernelArg(kd, a++, sizeof(float), &s->inv_cell);
  rc |= clSetKernelArg(kd, a++, sizeof(float), &s->inv_cell_x);
  rc |= clSetKernelArg(kd, a++, sizeof hf, &hf);
  rc |= clSetKernelArg(kd, a++, sizeof mass_kernel, &mass_kernel);
  rc |= clSetKernelArg(kd, a++, sizeof(float), &p->rest_density);
  rc |= clSetKernelArg(kd, a++, sizeof(float), &p->stiffness);
  rc |= clSetKernelArg(kd, a++, sizeof(cl_mem), &s->d_wall);
  rc |= clSetKernelArg(kd, a++, sizeof inv_h, &inv_h);
  for (int i = 0; i < 3; i++)
    rc |= clSetKernelArg(kd, a++, sizeof(float), &p->bounds_min[i]);
  for (int i = 0; i < 3; i++)
    rc |= clSetKernelArg(kd, a++, sizeof(float), &p->bounds_max[i]);
  rc |= clSetKernelArg(kd, a++, sizeof(cl_mem), &s->d_inv_rho);
  rc |= clSetKernelArg(kd, a++, sizeof(cl_mem), &s->d_pr2);

  cl_kernel kf = s->k_forces;
  a = 0;
  rc |= clSetKernelArg(kf, a++, sizeof(cl_mem), &s->d_state);
  rc |= clSetKernelArg(kf, a++, sizeof stride, &stride);
  rc |= clSetKernelArg(kf, a++, sizeof n, &n);
  rc |= clSetKernelArg(kf, a++, sizeof(cl_mem), &s->d_cells);
  rc |= clSetKernelArg(kf, a++, sizeof(int), &s->nx);
  rc |= clSetKernelArg(kf, a++, sizeof(int), &s->ny);
  rc |= clSetKernelArg(kf, a++, sizeof(int), &s->nz);
  rc |= clSetKernelArg(kf, a++, sizeof ox, &ox);
  rc |= clSetKernelArg(kf, a++, sizeof oy, &oy);
  rc |= clSetKernelArg(kf, a++, sizeof oz, &oz);
  rc |= clSetKernelArg(kf, a++, sizeof(float), &s->inv_cell);
  rc |= clSetKernelArg(kf, a++, sizeof(float), &s->inv_cell_x);
  rc |= clSetKernelArg(kf, a++, sizeof hf, &hf);
  rc |= clSetKernelArg(kf, a++, sizeof(cl_mem), &s->d_inv_rho);
  rc |= clSetKernelArg(kf, a++, sizeof(cl_mem), &s->d_pr2);
  rc |= clSetKernelArg(kf, a++, sizeof mass_spiky, &mass_spiky);
  rc |= clSetKernelArg(kf, a++, sizeof mass_visc, &mass_visc);
  for (int i = 0; i < 3; i++)
    rc |= clSetKernelArg(kf, a++, sizeof(float), &p->gravity[i]);
  rc |= clSetKernelArg(kf, a++, sizeof dt, &dt);
  rc |= clSetKernelArg(kf, a++, sizeof vmax, &vmax);
  rc |= clSetKernelArg(kf, a++, sizeof(cl_mem), &s->d_colliders);
  rc |= clSetKernelArg(kf, a++, sizeof ncol, &ncol);
  for (int i = 0; i < 3; i++)
    rc |= clSetKernelArg(kf, a++, sizeof(float), &p->bounds_min[i]);
  for (int i = 0; i < 3; i++)
    rc |= clSetKernelArg(kf, a++, sizeof(float), &p->bounds_max[i]);
  rc |= clSetKernelArg(kf, a++, sizeof(cl_mem), &s->d_wall);
  rc |= clSetKernelArg(kf, a++, sizeof inv_h, &inv_h);
  rc |= clSetKernelArg(kf, a++, sizeof(float), &p->rest_density);
  float wall_mu = p->viscosity * p->wall_friction;
  rc |= clSetKernelArg(kf, a++, sizeof wall_mu, &wall_mu);
  rc |= clSetKernelArg(kf, a++, sizeof(cl_mem), &s->d_out);
  if (rc != CL_SUCCESS)
    return proto_error_format(err, errlen, "[fluid] setting kernel arguments failed"), -1;

  size_t local = LOCAL, global = ((size_t)s->n + LOCAL - 1) / LOCAL * LOCAL;
  rc = clEnqueueNDRangeKernel(q, kd, 1, NULL, &global, &local, 0, NULL, NULL);
  if (rc == CL_SUCCESS)
    rc = clEnqueueNDRangeKernel(q, kf, 1, NULL, &global, &local, 0, NULL, NULL);
  /* Only the live part of each component comes back. */
  for (int i = 0; i < 6 && rc == CL_SUCCESS; i++)
    rc = clEnqueueReadBuffer(q, s->d_out, i == 5, i * s->stride * sizeof(float),
                             s->n * sizeof(float), s->state + i * s->stride, 0, NULL, NULL);
  if (rc != CL_SUCCESS)
    return proto_error_format(err, errlen, "[fluid] SPH step failed: %s", cl_dev_strerror(rc)), -1;
  return 0;
}

/* The fastest particle's speed. */
static double max_speed(const fluid_sim_t *s) {
  const float *vx = s->state + 3 * s->stride, *vy = vx + s->stride, *vz = vy + s->stride;
  double m = 0;
  for (uint32_t k = 0; k < s->n; k++) {
    double v2 = (double)vx[k] * vx[k] + (double)vy[k] * vy[k] + (double)vz[k] * vz[k];
    if (v2 > m)
      m = v2;
  }
  return sqrt(m);
}

int fluid_sim_step(fluid_sim_t *s, double dt, char *err, size_t errlen) {
  if (!(dt > 0 && dt <= 1))
    return proto_error_format(err, errlen, "fluid: dt must lie in (0, 1] seconds"), -1;
  emit(s, dt);
  s->frame++;
  s->last_substeps = 0;
  if (s->n == 0)
    return 0;
  const fluid_params_t *p = &s->p;
  double c = sqrt(p->stiffness), h = p->h;
  double g = sqrt((double)p->gravity[0] * p->gravity[0] + (double)p->gravity[1] * p->gravity[1] +
                  (double)p->gravity[2] * p->gravity[2]);
  double fixed = g > 0 ? 0.25 * sqrt(h / g) : INFINITY;
  if (p->viscosity > 0)
    fixed = fmin(fixed, 0.125 * h * h * p->rest_density / p->viscosity);
  /* The substep length is chosen again before each substep from the fastest particle, and
   * the time left is split evenly, so the last substep is never a sliver. */
  double done = 0;
  while (dt - done > 1e-9 * dt) {
    double left = dt - done;
    double limit = fmin(fixed, 0.4 * h / (c + max_speed(s)));
    int budget = FLUID_MAX_SUBSTEPS - s->last_substeps;
    double parts = fmin(ceil(left / limit * (1 - 1e-9)), budget);
    double sub = parts <= 1 ? left : left / parts;
    if (substep(s, (float)sub, err, errlen) != 0)
      return -1;
    s->last_substeps++;
    done = parts <= 1 ? dt : done + sub;
  }
  return 0;
}
