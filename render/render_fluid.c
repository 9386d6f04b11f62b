/*
 * The fluid pass: the particles sorted into a uniform grid each frame (per-cell lists on the
 * device) and ray cast as metaballs by kernels/fluid.cl, depth-tested against the
 * objects.
 */
#include <math.h>
#include <pthread.h>

#include "render_internal.h"

#define FLUID_MAX_CELLS (1 << 21) /* The fluid grid's cells grow beyond h to stay under this. */

/* ---- Fluid --------------------------------------------------------------------------------- */

#define FLUID_THREAD_MIN 8192 /* Particles in a half below which the build stays on one thread. */
#define FLUID_AXIS_MAX 4      /* Most cells a particle reaches along one axis (cells >= h). */

/*
 * Along axis 'a', the first cell '*lo' of the run of at most FLUID_AXIS_MAX cells that the
 * ball of radius 'h' about coordinate 'p' reaches, and per cell of it the squared distance from
 * p to the cell's slab (0 inside). Returns the number of cells. In float, with truncation for
 * floor (the clamp to the grid takes care of the negative side).
 */
static inline int fluid_axis(const vfx_fluid_t *fl, float p, float h, int a, int *lo, float *d2) {
  float cell = fl->cell, o = fl->origin[a], u0 = (p - h - o) * fl->inv_cell;
  float u1 = (p + h - o) * fl->inv_cell;
  int n = fl->dims[a];
  int first = u0 < 0 ? 0 : u0 >= n ? n - 1 : (int)u0;
  int last = u1 < 0 ? 0 : u1 >= n ? n - 1 : (int)u1;
  if (last - first >= FLUID_AXIS_MAX)
    last = first + FLUID_AXIS_MAX - 1;
  for (int c = first; c <= last; c++) {
    float s0 = o + c * cell, s1 = s0 + cell;
    float e = p < s0 ? s0 - p : p > s1 ? p - s1 : 0;
    d2[c - first] = e * e;
  }
  *lo = first;
  return last - first + 1;
}

/*
 * One pass of the grid build over particles [i0, i1) of 'fd': for every cell c whose box lies
 * closer than h to a particle (see fluid_build), either counts it in cur[c] ('out' NULL) or
 * writes the particle's x, y, z at entry cur[c]++ of the lists in 'out'. Particles with a
 * non-finite coordinate are left out.
 */
typedef struct {
  const vfx_fluid_t *fl;
  const rfluid_t *fd;
  uint32_t i0, i1;
  int32_t *cur;
  float *out;
} fluid_scan_t;

/* fluid_scan's pass, with 'write' a constant so that each pass gets a loop of its own. */
static inline void fluid_scan_pass(const fluid_scan_t *w, int write) {
  /* Everything the loops read in locals, so that the stores into the lists (which the compiler
   * must assume may alias them) do not force reloads. */
  const vfx_fluid_t *fl = w->fl;
  const float *pos = w->fd->positions;
  float h = w->fd->h, *out = w->out;
  float h2 = h * h;
  int32_t *cur = w->cur;
  size_t d0 = (size_t)fl->dims[0], d1 = (size_t)fl->dims[1];
  for (uint32_t i = w->i0; i < w->i1; i++) {
    float px = pos[3 * (size_t)i], py = pos[3 * (size_t)i + 1], pz = pos[3 * (size_t)i + 2];
    if (!isfinite(px) || !isfinite(py) || !isfinite(pz))
      continue;
    int x0, y0, z0;
    float dx2[FLUID_AXIS_MAX], dy2[FLUID_AXIS_MAX], dz2[FLUID_AXIS_MAX];
    int nx = fluid_axis(fl, px, h, 0, &x0, dx2);
    int ny = fluid_axis(fl, py, h, 1, &y0, dy2);
    int nz = fluid_axis(fl, pz, h, 2, &z0, dz2);
    for (int k = 0; k < nz; k++) {
      if (dz2[k] >= h2)
        continue;
      for (int j = 0; j < ny; j++) {
        float dyz = dz2[k] + dy2[j];
        if (dyz >= h2)
          continue;
        int32_t *row = cur + ((size_t)(z0 + k) * d1 + (size_t)(y0 + j)) * d0 + x0;
        for (int q = 0; q < nx; q++) {
          if (dyz + dx2[q] >= h2)
            continue;
          if (write) {
            float *e = out + 3 * (size_t)row[q];
            e[0] = px, e[1] = py, e[2] = pz;
          }
          row[q]++;
        }
      }
    }
  }
}

static void *fluid_scan(void *arg) {
  const fluid_scan_t *w = arg;
  if (w->out != NULL)
    fluid_scan_pass(w, 1);
  else
    fluid_scan_pass(w, 0);
  return NULL;
}

/* Runs the two halves of a pass: the second on a thread of its own when there are enough
 * particles to pay for it (and when the thread starts), the first here. */
static void fluid_scan_both(fluid_scan_t w[2]) {
  pthread_t t;
  int threaded =
      w[1].i1 - w[1].i0 >= FLUID_THREAD_MIN && pthread_create(&t, NULL, fluid_scan, &w[1]) == 0;
  fluid_scan(&w[0]);
  if (threaded)
    pthread_join(t, NULL);
  else
    fluid_scan(&w[1]);
}

/* The fluid pass's kernel, device grid and host staging. */
typedef struct fluid_state {
  cl_kernel kernel;
  size_t fluid_local[2];
  cl_mem fluid_cells, fluid_pos; /* The fluid grid: cap_fcells ints and cap_fpos floats. */
  size_t cap_fcells, cap_fpos;
  int32_t *host_fcells; /* Staging for the fluid grid's (start, count) pairs. */
  size_t host_fcells_cap;
  float *host_fpos; /* Staging for the fluid grid's lists. */
  size_t host_fpos_cap;
} fluid_state_t;

/*
 * Builds the fluid grid of vfx_fluid_t (common.h) in fs->host_fcells and fs->host_fpos by a
 * counting sort in two passes over the particles, each visiting only the cells its ball
 * reaches, and fills 'fl'. A cell lists the particles closer than h to its box: one exactly h
 * away adds nothing to the field inside the cell but would still count in the kernel's bounds
 * on the field ahead (G and the crude bound, kernels/fluid.cl), shortening the safe steps; on
 * the Table 1 lattice, where many particles lie exactly h from cell faces, listing them took
 * 22% more samples. (The kernel's points stray outside their cell by rounding only, by about
 * 1e-7 of their distance, where such a particle's share of the field is below 1e-12.)
 * Particles with a non-finite coordinate are left out. Returns the number of cells (0 when no
 * particle is left), or -1 when out of memory.
 */
static long fluid_build(fluid_state_t *fs, const rfluid_t *fd, vfx_fluid_t *fl) {
  float h = fd->h, lo[3] = {INFINITY, INFINITY, INFINITY},
        hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  uint32_t used = 0;
  for (uint32_t i = 0; i < fd->count; i++) {
    const float *p = fd->positions + 3 * (size_t)i;
    if (!isfinite(p[0]) || !isfinite(p[1]) || !isfinite(p[2]))
      continue;
    used++;
    for (int a = 0; a < 3; a++) {
      lo[a] = p[a] < lo[a] ? p[a] : lo[a];
      hi[a] = p[a] > hi[a] ? p[a] : hi[a];
    }
  }
  if (used == 0)
    return 0;
  /* Cells of side h, or larger when the particles spread too far for that many cells: a cell
   * lists every particle within h of it whatever its size, so any side is correct. */
  double ext[3], cell = h;
  for (int a = 0; a < 3; a++)
    ext[a] = (double)hi[a] - lo[a] + 2.0 * h;
  while ((ceil(ext[0] / cell) + 1) * (ceil(ext[1] / cell) + 1) * (ceil(ext[2] / cell) + 1) >
         FLUID_MAX_CELLS)
    cell *= 1.25;
  size_t ncell = 1;
  for (int a = 0; a < 3; a++) {
    fl->origin[a] = (float)((double)lo[a] - h);
    fl->dims[a] = (int)ceil(ext[a] / cell) + 1;
    fl->box_min[a] = fl->origin[a];
    fl->box_max[a] = (float)(fl->origin[a] + fl->dims[a] * cell);
    ncell *= (size_t)fl->dims[a];
  }
  fl->cell = (float)cell;
  fl->inv_cell = (float)(1.0 / cell);

  /* Cell pairs (start, count) for the device, and two arrays of counts, then cursors, one
   * per half of the particles: the second half's entries of a list follow the first's, so
   * the lists come out in particle order however the halves are run. */
  if (grow_staging((void **)&fs->host_fcells, &fs->host_fcells_cap, 4 * ncell, sizeof(int32_t)))
    return -1;
  int32_t *cells = fs->host_fcells, *cur0 = cells + 2 * ncell, *cur1 = cur0 + ncell;
  memset(cur0, 0, 2 * ncell * sizeof(int32_t));
  uint32_t half = fd->count / 2;
  fluid_scan_t w[2] = {{fl, fd, 0, half, cur0, NULL}, {fl, fd, half, fd->count, cur1, NULL}};
  fluid_scan_both(w);
  /* Starts of the lists. */
  size_t at = 0;
  for (size_t c = 0; c < ncell; c++) {
    int32_t m0 = cur0[c], m = m0 + cur1[c];
    cells[2 * c] = (int32_t)at;
    cells[2 * c + 1] = m;
    cur0[c] = (int32_t)at;
    cur1[c] = (int32_t)at + m0;
    at += (size_t)m;
  }
  /* > 0: every particle lists in its own cell. */
  if (at > INT32_MAX / 3 ||
      grow_staging((void **)&fs->host_fpos, &fs->host_fpos_cap, 3 * at, sizeof(float)))
    return -1;
  fl->entries = (int)at;
  for (int k = 0; k < 2; k++)
    w[k].out = fs->host_fpos;
  fluid_scan_both(w);
  return (long)ncell;
}

/*
 * Runs the fluid pass over the frame the objects pass set up: builds the grid of the scene's
 * particles, uploads it and draws the metaballs into r->frame.linear and r->frame.depth where they
 * are nearer than the objects. Sets '*ran' to whether there was a particle to draw. Returns 0 or a
 * PROTO_E_* code.
 */
static int fluid_run(renderer_t *r, void *state, const render_scene_t *scene,
                     const render_params_t *p, const char **ran, char *err, size_t errlen) {
  (void)p;
  fluid_state_t *fs = state;
  const rfluid_t *fd = &scene->fluid;
  *ran = NULL;
  if (fd->count == 0 || fd->positions == NULL || !(fd->h > 0) || !isfinite(fd->h) ||
      !(fd->threshold > 0) || !isfinite(fd->threshold))
    return 0;
  vfx_fluid_t fl;
  memset(&fl, 0, sizeof fl);
  long ncell = fluid_build(fs, fd, &fl);
  if (ncell < 0) {
    proto_error_format(err, errlen, "[render] out of memory for the grid of %u particles",
                       fd->count);
    return PROTO_E_INTERNAL;
  }
  if (ncell == 0)
    return 0;
  fl.h = fd->h;
  fl.inv_h = 1.0f / fd->h;
  fl.threshold = fd->threshold;
  fl.min_step = fd->h / 2000;
  fl.tol = fd->h * 1e-3f;
  fl.rows = (int)r->frame.rows;
  double ior = isfinite(fd->ior) && fd->ior > 0 ? fd->ior : 1.33;
  double f0 = (ior - 1) / (ior + 1);
  fl.f0 = (float)(f0 * f0);
  double rough = isfinite(fd->roughness) ? fd->roughness : 0.1;
  rough = rough < 0.02 ? 0.02 : rough > 1 ? 1 : rough;
  fl.shininess = (float)(2 / (rough * rough) - 2 + 1);
  memcpy(fl.color, fd->color, sizeof fl.color);

  if (render_ensure_buffer(r, &fs->fluid_cells, &fs->cap_fcells, 2 * (size_t)ncell, sizeof(int32_t),
                           CL_MEM_READ_ONLY, 1, err, errlen) ||
      render_ensure_buffer(r, &fs->fluid_pos, &fs->cap_fpos, 3 * (size_t)fl.entries, sizeof(float),
                           CL_MEM_READ_ONLY, 1, err, errlen))
    return PROTO_E_DEVICE;
  cl_kernel k = fs->kernel;
  cl_int cr =
      clEnqueueWriteBuffer(r->dev.queue, fs->fluid_cells, CL_FALSE, 0,
                           2 * (size_t)ncell * sizeof(int32_t), fs->host_fcells, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clEnqueueWriteBuffer(r->dev.queue, fs->fluid_pos, CL_FALSE, 0,
                              3 * (size_t)fl.entries * sizeof(float), fs->host_fpos, 0, NULL, NULL);
  cr = KERNEL_ARGS(cr, k, 0, {sizeof r->frame.consts, &r->frame.consts}, {sizeof fl, &fl},
                   {sizeof(cl_mem), &fs->fluid_cells}, {sizeof(cl_mem), &fs->fluid_pos},
                   {sizeof(cl_mem), &r->frame.linear}, {sizeof(cl_mem), &r->frame.depth});
  /* A work-item per packet of FLUID_PW x FLUID_PH pixels; packets past the buffers' rows and
   * pitch are not traced. */
  size_t global[2] = {round_up(round_up(r->frame.pitch, FLUID_PW) / FLUID_PW, fs->fluid_local[0]),
                      round_up(round_up(r->frame.rows, FLUID_PH) / FLUID_PH, fs->fluid_local[1])};
  if (render_launch(r, cr, k, global, fs->fluid_local, "fluid", err, errlen) != 0)
    return PROTO_E_DEVICE;
  *ran = "fluid";
  return 0;
}

static void fluid_free(renderer_t *r, void *state) {
  (void)r;
  fluid_state_t *fs = state;
  if (fs == NULL)
    return;
  render_release(&fs->kernel, 1, (cl_mem[]){fs->fluid_cells, fs->fluid_pos}, 2);
  free(fs->host_fcells);
  free(fs->host_fpos);
  free(fs);
}

static int fluid_init(renderer_t *r, void **state, char *err, size_t errlen) {
  fluid_state_t *fs = render_state_new(state, sizeof *fs, err, errlen);
  if (fs == NULL)
    return -1;
  if ((fs->kernel = cl_dev_kernel(&r->dev, "fluid", err, errlen)) == NULL)
    return -1;
  /* A packet of FLUID_PW x FLUID_PH pixels per fluid work-item; the launch rounds the packets up
   * to whole work-groups and the kernel skips those past the buffers. */
  fs->fluid_local[0] = FLUID_LX;
  fs->fluid_local[1] = FLUID_LY;
  render_fit_local(r, fs->kernel, fs->fluid_local, 2);
  return 0;
}

static int fluid_wants(const renderer_t *r, const render_scene_t *scene, const render_params_t *p) {
  (void)r;
  return (p->layers & LAYER_FLUID) && scene->fluid.count > 0;
}

const render_pass_t render_pass_fluid = {.name = "fluid",
                                         .layers = LAYER_FLUID,
                                         .init = fluid_init,
                                         .free = fluid_free,
                                         .wants = fluid_wants,
                                         .run = fluid_run};
