/*
 * The renderer: it compiles a render_scene_t into the flat world-space records of
 * kernels/common.h, keeps a BVH of the scene's mesh triangles, and runs the passes of a frame
 * on the OpenCL device: "objects" (ray casting and shading), "fluid" (the particles as metaballs
 * over a uniform grid built here each frame, depth-tested against the objects), "waves" (the
 * energy waves' closed-form glow, added to the linear image, or their H as the wave_h AOV),
 * "tonemap",
 * "readback" and "encode" (PNG, on the host). Device buffers live across frames and only grow.
 *
 * One thread uses a renderer at a time (the render worker); it starts no threads of its own.
 */
#include "render.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "cl_device.h"
#include "../kernels/common.h"

/*
 * Fixed local sizes: PoCL compiles a kernel once per local size, at its first launch. An
 * objects work-item covers a packet of PACKET pixels in a row, so its work-group covers
 * 32x8 pixels; a waves or tonemap work-item covers WAVES_PACKET or TONEMAP_PACKET pixels
 * (common.h), and their work-groups cover the same 32x8. The per-pixel buffers are padded to
 * whole work-groups of every pass.
 */
#define PACKET 8
#define OBJECTS_LX 4
#define OBJECTS_LY 8
#define TONEMAP_LX (PACKET * OBJECTS_LX / TONEMAP_PACKET)
#define TONEMAP_LY 8

#define MAX_SIDE 16384 /* Largest width or height the renderer accepts, whatever the limits. */
#define BVH_LEAF 4     /* Triangles per leaf the builder aims for. */
#define BVH_BINS 16    /* Bins of the SAH split search. */
#define FLUID_MAX_CELLS (1 << 21) /* The fluid grid's cells grow beyond h to stay under this. */

/* -cl-fast-relaxed-math is out: it lets the compiler assume no infinities, and misses are
 * +INFINITY. */
static const char build_options[] = "-cl-std=CL1.2 -cl-mad-enable -cl-no-signed-zeros";

/* A mesh object as the cached BVH saw it. */
typedef struct mesh_key {
  const mesh_t *mesh; /* Holds a reference, so the address cannot be reused while cached. */
  float position[3], scale[3], rotation[3];
} mesh_key_t;

struct renderer {
  cl_dev_t dev;
  cl_kernel objects, tonemap, waves, waves_march, fluid;
  size_t objects_local[2], tonemap_local[2], waves_local[2], fluid_local[2];
  vfx_frame_t frame; /* The current frame's constants, as the objects pass set them up. */

  cl_mem linear, depth, rgba8; /* Per-pixel buffers, for cap_pixels pixels. */
  size_t cap_pixels;
  size_t pitch, rows; /* The current frame's size, rounded up to whole objects work-groups. */
  cl_mem objs;        /* Object records, cap_objs floats. */
  size_t cap_objs;
  cl_mem nodes, tris; /* The mesh BVH, cap_nodes and cap_tris records. */
  size_t cap_nodes, cap_tris;
  cl_mem wave_recs; /* Wave records, cap_waves floats. */
  size_t cap_waves;
  cl_mem wave_lists; /* Per waves work-group, the waves it may meet: cap_lists ints. */
  size_t cap_lists;
  cl_mem hbuf; /* The wave_h AOV, cap_h pixels (allocated at the first wave_h frame). */
  size_t cap_h;
  cl_mem fluid_cells, fluid_pos; /* The fluid grid: cap_fcells ints and cap_fpos floats. */
  size_t cap_fcells, cap_fpos;

  /* The BVH on the device holds these mesh objects. Comparing them each frame, rather than the
   * scene pointer, keeps the BVH across snapshots that changed other things (the camera, a
   * colour) and cannot be fooled by a freed scene's address coming back. */
  mesh_key_t *bvh_keys;
  int bvh_nkeys;
  int bvh_ntri;

  float *host_objs; /* Staging for the object records. */
  size_t host_objs_cap;
  float *host_waves; /* Staging for the wave records. */
  size_t host_waves_cap;
  int32_t *host_lists; /* Staging for the wave lists. */
  size_t host_lists_cap;
  int32_t *host_fcells; /* Staging for the fluid grid's (start, count) pairs. */
  size_t host_fcells_cap;
  float *host_fpos; /* Staging for the fluid grid's padded lists. */
  size_t host_fpos_cap;
  unsigned char *scratch; /* Tone-mapped bytes waiting for the PNG encoder. */
  size_t scratch_cap;
};

static void set_err(char *err, size_t errlen, const char *fmt, ...) {
  if (err == NULL || errlen == 0)
    return;
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(err, errlen, fmt, ap);
  va_end(ap);
}

static double now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec / 1e6;
}

static void add_pass(render_output_t *out, const char *name, double ms) {
  if (out->npasses < RENDER_MAX_PASSES) {
    out->passes[out->npasses].name = name;
    out->passes[out->npasses].ms = ms;
    out->npasses++;
  }
}

/* ---- Transforms ---------------------------------------------------------------------------- */

/* Stores an int in a float slot of a record, bit for bit, as the kernels' as_int() reads it. */
static void set_int(float *slot, int32_t v) {
  memcpy(slot, &v, sizeof v);
}

/* The rotation Rz * Ry * Rx for angles in degrees, so X is applied first. */
static void rotation(const float deg[3], double r[3][3]) {
  double a = deg[0] * (M_PI / 180), b = deg[1] * (M_PI / 180), c = deg[2] * (M_PI / 180);
  double ca = cos(a), sa = sin(a), cb = cos(b), sb = sin(b), cc = cos(c), sc = sin(c);
  r[0][0] = cc * cb, r[0][1] = cc * sb * sa - sc * ca, r[0][2] = cc * sb * ca + sc * sa;
  r[1][0] = sc * cb, r[1][1] = sc * sb * sa + cc * ca, r[1][2] = sc * sb * ca - cc * sa;
  r[2][0] = -sb, r[2][1] = cb * sa, r[2][2] = cb * ca;
}

static int usable_scale(const float s[3]) {
  for (int i = 0; i < 3; i++) {
    if (!isfinite(s[i]) || fabs(s[i]) < 1e-12)
      return 0;
  }
  return 1;
}

/*
 * Writes the world-space form of the object-space half-space n.x <= d of an object placed by
 * rotation 'r', scale 's' (NULL for none) and position 'p' as a unit (nx, ny, nz, d) at 'out':
 * with x = R S o + p, n.o <= d becomes (R S^-1 n).(x - p) <= d.
 */
static void world_plane(const double r[3][3], const float *s, const float p[3], const double n[3],
                        double d, float *out) {
  double m[3], w[3];
  for (int i = 0; i < 3; i++)
    m[i] = s ? n[i] / s[i] : n[i];
  double len = 0, dp = 0;
  for (int i = 0; i < 3; i++) {
    w[i] = r[i][0] * m[0] + r[i][1] * m[1] + r[i][2] * m[2];
    len += w[i] * w[i];
    dp += w[i] * p[i];
  }
  len = sqrt(len);
  for (int i = 0; i < 3; i++)
    out[i] = (float)(w[i] / len);
  out[3] = (float)((d + dp) / len);
}

/* The regular tetrahedron of render_scene.h: circumradius 0.5, vertex 0 at +y, vertex 1 in the
 * +z half of the y-z plane, vertices 2 and 3 at +-120 degrees about y from it. */
static void tetra_vertex(int k, double v[3]) {
  double r = sqrt(2.0) / 3, y = -1.0 / 6;
  static const double sin120 = 0.86602540378443865, cos120 = -0.5;
  double xs[4] = {0, 0, r * sin120, -r * sin120};
  double zs[4] = {0, r, r * cos120, r * cos120};
  v[0] = xs[k], v[1] = k ? y : 0.5, v[2] = zs[k];
}

/*
 * The radius of a sphere about an object's centre that holds every point within 'r' of the
 * centre before the scale 's': r times the largest scale, with a margin for rounding.
 */
static float bound_radius(const float s[3], double r) {
  double m = fmax(fabs(s[0]), fmax(fabs(s[1]), fabs(s[2])));
  return (float)(r * m * 1.001 + 1e-6);
}

/* Packs an ellipsoid record (SPH_*). The matrix S^-1 R^T takes world offsets to object space. */
static void pack_sphere(const robject_t *o, float *rec) {
  double r[3][3];
  rotation(o->rotation, r);
  memcpy(rec + SPH_CENTER, o->position, 3 * sizeof(float));
  for (int i = 0; i < 3; i++) {
    for (int j = 0; j < 3; j++)
      rec[SPH_MINV + 3 * i + j] = (float)(r[j][i] / o->scale[i]);
  }
  memcpy(rec + SPH_COLOR, o->color, 3 * sizeof(float));
  rec[SPH_RADIUS] = bound_radius(o->scale, 0.5);
}

/* Packs a convex record (CONV_*) for a box, tetrahedron or plane. */
static void pack_convex(const robject_t *o, float *rec) {
  double r[3][3];
  rotation(o->rotation, r);
  int used = 0;
  if (o->shape == SHAPE_BOX) {
    for (int axis = 0; axis < 3; axis++) {
      for (int sign = -1; sign <= 1; sign += 2) {
        double n[3] = {0, 0, 0};
        n[axis] = sign;
        world_plane(r, o->scale, o->position, n, 0.5, rec + 4 * used++);
      }
    }
  } else if (o->shape == SHAPE_TETRAHEDRON) {
    /* The face opposite vertex k has the outward normal -v_k / |v_k| at the inradius 1/6. */
    for (int k = 0; k < 4; k++) {
      double v[3];
      tetra_vertex(k, v);
      double n[3] = {-2 * v[0], -2 * v[1], -2 * v[2]};
      world_plane(r, o->scale, o->position, n, 1.0 / 6, rec + 4 * used++);
    }
  } else {
    double n[3] = {0, 1, 0};
    world_plane(r, NULL, o->position, n, 0.0, rec + 4 * used++);
  }
  set_int(rec + CONV_NPLANES, used);
  for (; used < CONV_PLANES; used++) {
    float *pl = rec + 4 * used;
    pl[0] = pl[1] = pl[2] = 0, pl[3] = 1;
  }
  memcpy(rec + CONV_COLOR, o->color, 3 * sizeof(float));
  memcpy(rec + CONV_BOUND, o->position, 3 * sizeof(float));
  /* A box's corners lie at half its scaled diagonal; a tetrahedron's vertices lie within 0.5
   * of its centre before scaling. */
  double sx = o->scale[0], sy = o->scale[1], sz = o->scale[2];
  float half_diagonal = (float)(0.5 * sqrt(sx * sx + sy * sy + sz * sz) * 1.001 + 1e-6);
  rec[CONV_BOUND + 3] = o->shape == SHAPE_PLANE ? INFINITY
                        : o->shape == SHAPE_BOX ? half_diagonal
                                                : bound_radius(o->scale, 0.5);
}

/* ---- Mesh BVH ------------------------------------------------------------------------------ */

typedef struct bvh_builder {
  const float *box;  /* Per triangle: its bounds, min xyz then max xyz. */
  const float *cent; /* Per triangle: its centroid. */
  uint32_t *idx;     /* Triangle order; leaves own contiguous ranges. */
  float *nodes;      /* NODE_STRIDE floats per node. */
  size_t nnodes, cap;
} bvh_builder_t;

/* Boxes are 6 floats, min xyz then max xyz; an empty box has min > max. The comparisons are
 * written out because fminf and fmaxf, with their NaN rules, compile to library calls. */
static void box_empty(float *b) {
  b[0] = b[1] = b[2] = INFINITY;
  b[3] = b[4] = b[5] = -INFINITY;
}

static inline void box_union(float *b, const float *o) {
  for (int i = 0; i < 3; i++) {
    b[i] = o[i] < b[i] ? o[i] : b[i];
    b[i + 3] = o[i + 3] > b[i + 3] ? o[i + 3] : b[i + 3];
  }
}

static inline void box_point(float *b, const float *p) {
  for (int i = 0; i < 3; i++) {
    b[i] = p[i] < b[i] ? p[i] : b[i];
    b[i + 3] = p[i] > b[i + 3] ? p[i] : b[i + 3];
  }
}

static double box_area(const float *b) {
  double x = b[3] - b[0], y = b[4] - b[1], z = b[5] - b[2];
  return x < 0 ? 0 : 2 * (x * y + y * z + z * x);
}

/* The bin of centroid coordinate 'c' for bins of width 1/'scale' from 'lo'. The float is
 * clamped before the conversion, which would be undefined for huge or NaN values. */
static int bin_of(float c, float lo, float scale) {
  float k = (c - lo) * scale;
  return !(k > 0) ? 0 : k >= BVH_BINS ? BVH_BINS - 1 : (int)k;
}

/*
 * Builds the subtree over idx[lo, hi) at the next free node and its successors, splitting by a
 * binned surface-area heuristic. 'bounds' holds the triangles' box and their centroids' box;
 * one pass over the triangles bins them and yields both boxes of each child. Returns 0, or
 * -1 when out of memory.
 */
static int bvh_split(bvh_builder_t *b, size_t lo, size_t hi, int depth, const float bounds[12]) {
  if (b->nnodes == b->cap) {
    size_t cap = b->cap ? 2 * b->cap : 1024;
    float *nodes = realloc(b->nodes, cap * NODE_STRIDE * sizeof(float));
    if (nodes == NULL)
      return -1;
    b->nodes = nodes, b->cap = cap;
  }
  size_t at = b->nnodes++;
  memcpy(b->nodes + at * NODE_STRIDE, bounds, 6 * sizeof(float));

  size_t n = hi - lo;
  const float *cb = bounds + 6;
  int axis = 0;
  for (int i = 1; i < 3; i++) {
    if (cb[i + 3] - cb[i] > cb[axis + 3] - cb[axis])
      axis = i;
  }
  float extent = cb[axis + 3] - cb[axis];
  if (n > BVH_LEAF && depth < BVH_MAX_DEPTH - 1 && extent > 0) {
    size_t count[BVH_BINS] = {0};
    float bin[BVH_BINS][12];
    for (int k = 0; k < BVH_BINS; k++)
      box_empty(bin[k]), box_empty(bin[k] + 6);
    float scale = BVH_BINS / extent;
    for (size_t i = lo; i < hi; i++) {
      uint32_t t = b->idx[i];
      int k = bin_of(b->cent[3 * (size_t)t + axis], cb[axis], scale);
      count[k]++;
      box_union(bin[k], b->box + 6 * (size_t)t);
      box_point(bin[k] + 6, b->cent + 3 * (size_t)t);
    }
    /* Sweep from the right, then from the left, for the boundary of least cost. */
    double right_area[BVH_BINS];
    size_t right_count[BVH_BINS], rc = 0, lc = 0;
    float acc[6];
    box_empty(acc);
    for (int k = BVH_BINS - 1; k > 0; k--) {
      box_union(acc, bin[k]);
      rc += count[k];
      right_area[k] = box_area(acc);
      right_count[k] = rc;
    }
    box_empty(acc);
    int split = -1;
    double best = INFINITY;
    for (int k = 0; k < BVH_BINS - 1; k++) {
      box_union(acc, bin[k]);
      lc += count[k];
      if (lc == 0 || right_count[k + 1] == 0)
        continue;
      double cost = box_area(acc) * lc + right_area[k + 1] * right_count[k + 1];
      if (cost < best)
        best = cost, split = k;
    }
    /* A small node whose split costs more than testing its triangles stays a leaf. */
    double area = box_area(bounds);
    if (split >= 0 && n <= 4 * BVH_LEAF && best + area >= area * n)
      split = -1;
    if (split >= 0) {
      size_t i = lo, j = hi;
      while (i < j) {
        uint32_t t = b->idx[i];
        if (bin_of(b->cent[3 * (size_t)t + axis], cb[axis], scale) <= split) {
          i++;
        } else {
          b->idx[i] = b->idx[--j];
          b->idx[j] = t;
        }
      }
      float left[12], right[12];
      box_empty(left), box_empty(left + 6), box_empty(right), box_empty(right + 6);
      for (int k = 0; k < BVH_BINS; k++) {
        float *side = k <= split ? left : right;
        box_union(side, bin[k]);
        box_union(side + 6, bin[k] + 6);
      }
      if (bvh_split(b, lo, i, depth + 1, left) != 0)
        return -1;
      float *node = b->nodes + at * NODE_STRIDE;
      set_int(node + NODE_FIRST, (int32_t)b->nnodes);
      set_int(node + NODE_COUNT, 0);
      return bvh_split(b, i, hi, depth + 1, right);
    }
  }
  float *node = b->nodes + at * NODE_STRIDE;
  set_int(node + NODE_FIRST, (int32_t)lo);
  set_int(node + NODE_COUNT, (int32_t)n);
  return 0;
}

/* Whether the mesh objects of 'scene' are those the cached BVH was built from. */
static int bvh_matches(const renderer_t *r, const render_scene_t *scene) {
  int k = 0;
  for (int i = 0; i < scene->nobjects; i++) {
    const robject_t *o = &scene->objects[i];
    if (o->shape != SHAPE_MESH || o->mesh == NULL)
      continue;
    if (k >= r->bvh_nkeys)
      return 0;
    const mesh_key_t *key = &r->bvh_keys[k++];
    if (key->mesh != o->mesh || memcmp(key->position, o->position, sizeof key->position) ||
        memcmp(key->scale, o->scale, sizeof key->scale) ||
        memcmp(key->rotation, o->rotation, sizeof key->rotation))
      return 0;
  }
  return k == r->bvh_nkeys;
}

static void bvh_forget(renderer_t *r) {
  for (int i = 0; i < r->bvh_nkeys; i++)
    mesh_unref((mesh_t *)r->bvh_keys[i].mesh);
  free(r->bvh_keys);
  r->bvh_keys = NULL;
  r->bvh_nkeys = 0;
  r->bvh_ntri = 0;
}

/*
 * (Re)creates 'buf' with room for at least 'need' elements of 'size' bytes; with 'headroom' it
 * asks for half as much again, so that a slowly growing scene does not reallocate every frame.
 */
static int ensure_buffer(renderer_t *r, cl_mem *buf, size_t *cap, size_t need, size_t size,
                         cl_mem_flags flags, int headroom, char *err, size_t errlen) {
  if (*buf != NULL && *cap >= need)
    return 0;
  size_t want = headroom ? need + need / 2 : need;
  if (*buf)
    clReleaseMemObject(*buf);
  cl_int rc;
  *buf = clCreateBuffer(r->dev.context, flags, want * size, NULL, &rc);
  if (*buf == NULL) {
    *buf = clCreateBuffer(r->dev.context, flags, need * size, NULL, &rc);
    want = need;
  }
  if (*buf == NULL) {
    *cap = 0;
    set_err(err, errlen, "[render] cannot allocate %zu bytes on %s: %s", need * size,
            r->dev.device_name, cl_dev_strerror(rc));
    return -1;
  }
  *cap = want;
  return 0;
}

/*
 * Makes the device BVH hold the mesh objects of 'scene' (world = T R S mesh), rebuilding it
 * only when they changed since it was built. Returns 0 or a PROTO_E_* code.
 */
static int bvh_update(renderer_t *r, const render_scene_t *scene, char *err, size_t errlen) {
  if (bvh_matches(r, scene))
    return 0;
  bvh_forget(r);

  size_t ntri = 0;
  int nmesh = 0;
  for (int i = 0; i < scene->nobjects; i++) {
    const robject_t *o = &scene->objects[i];
    if (o->shape == SHAPE_MESH && o->mesh != NULL) {
      nmesh++;
      if (usable_scale(o->scale))
        ntri += o->mesh->ntri;
    }
  }
  if (ntri > INT32_MAX / TRI_STRIDE) {
    set_err(err, errlen, "[render] scene has too many mesh triangles (%zu)", ntri);
    return PROTO_E_LIMIT;
  }
  r->bvh_keys = calloc(nmesh ? (size_t)nmesh : 1, sizeof *r->bvh_keys);
  size_t alloc = ntri ? ntri : 1;
  float *world = malloc(alloc * 9 * sizeof(float));
  float *box = malloc(alloc * 6 * sizeof(float));
  float *cent = malloc(alloc * 3 * sizeof(float));
  int32_t *owner = malloc(alloc * sizeof(int32_t));
  bvh_builder_t b = {.box = box, .cent = cent, .idx = malloc(alloc * sizeof(uint32_t))};
  float *packed = NULL, root[12];
  box_empty(root), box_empty(root + 6);
  int rc = PROTO_E_INTERNAL;
  if (!r->bvh_keys || !world || !box || !cent || !owner || !b.idx) {
    set_err(err, errlen, "[render] out of memory building the mesh BVH (%zu triangles)", ntri);
    goto done;
  }

  /* World-space triangles of every mesh object; the key list is kept in scene order. */
  size_t t = 0;
  int k = 0;
  for (int i = 0; i < scene->nobjects; i++) {
    const robject_t *o = &scene->objects[i];
    if (o->shape != SHAPE_MESH || o->mesh == NULL)
      continue;
    mesh_key_t *key = &r->bvh_keys[k];
    key->mesh = mesh_ref(o->mesh);
    memcpy(key->position, o->position, sizeof key->position);
    memcpy(key->scale, o->scale, sizeof key->scale);
    memcpy(key->rotation, o->rotation, sizeof key->rotation);
    r->bvh_nkeys = ++k;
    if (!usable_scale(o->scale))
      continue;
    double m[3][3];
    rotation(o->rotation, m);
    for (uint32_t j = 0; j < o->mesh->ntri; j++, t++) {
      const float *src = o->mesh->tri + 9 * (size_t)j;
      float *dst = world + 9 * t;
      for (int v = 0; v < 3; v++) {
        double s[3] = {src[3 * v] * (double)o->scale[0], src[3 * v + 1] * (double)o->scale[1],
                       src[3 * v + 2] * (double)o->scale[2]};
        for (int a = 0; a < 3; a++)
          dst[3 * v + a] =
              (float)(m[a][0] * s[0] + m[a][1] * s[1] + m[a][2] * s[2] + o->position[a]);
      }
      float *tb = box + 6 * t, *c = cent + 3 * t;
      box_empty(tb);
      for (int v = 0; v < 3; v++)
        box_point(tb, dst + 3 * v);
      for (int a = 0; a < 3; a++)
        c[a] = (dst[a] + dst[3 + a] + dst[6 + a]) * (1.0f / 3);
      box_union(root, tb);
      box_point(root + 6, c);
      owner[t] = k - 1;
      b.idx[t] = (uint32_t)t;
    }
  }

  if (ntri > 0) {
    if (bvh_split(&b, 0, ntri, 0, root) != 0) {
      set_err(err, errlen, "[render] out of memory building the mesh BVH (%zu triangles)", ntri);
      goto done;
    }
    packed = malloc(ntri * TRI_STRIDE * sizeof(float));
    if (packed == NULL) {
      set_err(err, errlen, "[render] out of memory building the mesh BVH (%zu triangles)", ntri);
      goto done;
    }
    for (size_t i = 0; i < ntri; i++) {
      const float *v = world + 9 * (size_t)b.idx[i];
      float *dst = packed + TRI_STRIDE * i;
      for (int a = 0; a < 3; a++) {
        dst[a] = v[a];
        dst[3 + a] = v[3 + a] - v[a];
        dst[6 + a] = v[6 + a] - v[a];
      }
      set_int(dst + TRI_COLOR, owner[b.idx[i]]);
    }
    rc = PROTO_E_DEVICE;
    if (ensure_buffer(r, &r->nodes, &r->cap_nodes, b.nnodes, NODE_STRIDE * sizeof(float),
                      CL_MEM_READ_ONLY, 1, err, errlen) ||
        ensure_buffer(r, &r->tris, &r->cap_tris, ntri, TRI_STRIDE * sizeof(float), CL_MEM_READ_ONLY,
                      1, err, errlen))
      goto done;
    cl_int cr =
        clEnqueueWriteBuffer(r->dev.queue, r->nodes, CL_TRUE, 0,
                             b.nnodes * NODE_STRIDE * sizeof(float), b.nodes, 0, NULL, NULL);
    if (cr == CL_SUCCESS)
      cr = clEnqueueWriteBuffer(r->dev.queue, r->tris, CL_TRUE, 0,
                                ntri * TRI_STRIDE * sizeof(float), packed, 0, NULL, NULL);
    if (cr != CL_SUCCESS) {
      set_err(err, errlen, "[render] uploading the mesh BVH failed: %s", cl_dev_strerror(cr));
      goto done;
    }
  }
  r->bvh_ntri = (int)ntri;
  rc = 0;

done:
  if (rc != 0)
    bvh_forget(r);
  free(world);
  free(box);
  free(cent);
  free(owner);
  free(b.idx);
  free(b.nodes);
  free(packed);
  return rc;
}

/* ---- Frame set-up -------------------------------------------------------------------------- */

/*
 * Fills the camera part of 'f' from SPEC §4's pinhole. Returns 0, or PROTO_E_INVALID_PARAMS for
 * a camera that defines no image.
 */
static int setup_camera(vfx_frame_t *f, const rcamera_t *c, uint32_t w, uint32_t h, char *err,
                        size_t errlen) {
  double fw[3], rt[3], up[3], len;
  for (int i = 0; i < 3; i++)
    fw[i] = (double)c->target[i] - c->eye[i];
  len = sqrt(fw[0] * fw[0] + fw[1] * fw[1] + fw[2] * fw[2]);
  if (!(len > 0) || !isfinite(len)) {
    set_err(err, errlen, "camera: target must differ from eye");
    return PROTO_E_INVALID_PARAMS;
  }
  for (int i = 0; i < 3; i++)
    fw[i] /= len;
  rt[0] = fw[1] * c->up[2] - fw[2] * c->up[1];
  rt[1] = fw[2] * c->up[0] - fw[0] * c->up[2];
  rt[2] = fw[0] * c->up[1] - fw[1] * c->up[0];
  len = sqrt(rt[0] * rt[0] + rt[1] * rt[1] + rt[2] * rt[2]);
  double up_len =
      sqrt((double)c->up[0] * c->up[0] + (double)c->up[1] * c->up[1] + (double)c->up[2] * c->up[2]);
  if (!(len > 1e-7 * up_len) || !isfinite(len)) {
    set_err(err, errlen, "camera: up must not be parallel to the view direction");
    return PROTO_E_INVALID_PARAMS;
  }
  for (int i = 0; i < 3; i++)
    rt[i] /= len;
  up[0] = rt[1] * fw[2] - rt[2] * fw[1];
  up[1] = rt[2] * fw[0] - rt[0] * fw[2];
  up[2] = rt[0] * fw[1] - rt[1] * fw[0];
  if (!(c->fov_y > 0 && c->fov_y < 180)) {
    set_err(err, errlen, "camera: fov_y must lie in (0, 180) degrees");
    return PROTO_E_INVALID_PARAMS;
  }
  if (!(c->near_ >= 0) || !(c->far_ > c->near_) || isnan(c->far_)) {
    set_err(err, errlen, "camera: need 0 <= near < far");
    return PROTO_E_INVALID_PARAMS;
  }
  double th = tan(c->fov_y * (M_PI / 360)), aspect = (double)w / h;
  for (int i = 0; i < 3; i++) {
    f->eye[i] = c->eye[i];
    f->base[i] = (float)(fw[i] - th * aspect * rt[i] + th * up[i]);
    f->step_x[i] = (float)(2 * th * aspect / w * rt[i]);
    f->step_y[i] = (float)(-2 * th / h * up[i]);
  }
  f->near_ = c->near_;
  f->far_ = c->far_;
  return 0;
}

/*
 * Packs the scene's objects into r->host_objs and the counts and offsets of 'f'; with 'draw'
 * false the frame has no objects. Objects with a zero or non-finite scale are left out. The
 * number of floats packed goes to '*nfloats'.
 */
static int pack_objects(renderer_t *r, const render_scene_t *scene, int draw, vfx_frame_t *f,
                        size_t *nfloats, char *err, size_t errlen) {
  int nsph = 0, nconv = 0, nmesh = 0;
  for (int i = 0; draw && i < scene->nobjects; i++) {
    const robject_t *o = &scene->objects[i];
    if (o->shape == SHAPE_SPHERE)
      nsph += usable_scale(o->scale);
    else if (o->shape == SHAPE_BOX || o->shape == SHAPE_TETRAHEDRON)
      nconv += usable_scale(o->scale);
    else if (o->shape == SHAPE_PLANE)
      nconv++;
    else if (o->shape == SHAPE_MESH && o->mesh != NULL)
      nmesh++;
  }
  size_t need = (size_t)nsph * SPH_STRIDE + (size_t)nconv * CONV_STRIDE + (size_t)nmesh * 3 + 1;
  if (need > r->host_objs_cap) {
    float *p = realloc(r->host_objs, need * sizeof(float));
    if (p == NULL) {
      set_err(err, errlen, "[render] out of memory for %d objects", scene->nobjects);
      return PROTO_E_INTERNAL;
    }
    r->host_objs = p, r->host_objs_cap = need;
  }
  f->nsph = nsph;
  f->nconv = nconv;
  f->conv_off = nsph * SPH_STRIDE;
  f->mesh_off = f->conv_off + nconv * CONV_STRIDE;
  int s = 0, c = 0, m = 0;
  for (int i = 0; draw && i < scene->nobjects; i++) {
    const robject_t *o = &scene->objects[i];
    if (o->shape == SHAPE_SPHERE && usable_scale(o->scale)) {
      pack_sphere(o, r->host_objs + (size_t)s++ * SPH_STRIDE);
    } else if (((o->shape == SHAPE_BOX || o->shape == SHAPE_TETRAHEDRON) &&
                usable_scale(o->scale)) ||
               o->shape == SHAPE_PLANE) {
      pack_convex(o, r->host_objs + f->conv_off + (size_t)c++ * CONV_STRIDE);
    } else if (o->shape == SHAPE_MESH && o->mesh != NULL) {
      memcpy(r->host_objs + f->mesh_off + 3 * m++, o->color, 3 * sizeof(float));
    }
  }
  r->host_objs[need - 1] = 0;
  *nfloats = need;
  return 0;
}

/* ---- Passes -------------------------------------------------------------------------------- */

static size_t round_up(size_t n, size_t m) {
  return (n + m - 1) / m * m;
}

/* The pixels of a row that the padded buffers' pitch is a multiple of: the widest work-group of
 * the passes. The widths are powers of two, so each of them divides it. */
static size_t row_pixels(const renderer_t *r) {
  size_t n = PACKET * r->objects_local[0];
  if (n < WAVES_PACKET * r->waves_local[0])
    n = WAVES_PACKET * r->waves_local[0];
  if (n < TONEMAP_PACKET * r->tonemap_local[0])
    n = TONEMAP_PACKET * r->tonemap_local[0];
  return n;
}

/* Runs the objects pass into r->linear and r->depth and keeps the frame's constants in
 * r->frame for the passes after it. Returns 0 or a PROTO_E_* code. */
static int pass_objects(renderer_t *r, const render_scene_t *scene, const render_params_t *p,
                        char *err, size_t errlen) {
  vfx_frame_t f;
  memset(&f, 0, sizeof f);
  r->pitch = round_up(p->width, row_pixels(r));
  r->rows = round_up(p->height, r->objects_local[1]);
  f.width = (int)p->width;
  f.height = (int)p->height;
  f.pitch = (int)r->pitch;
  int rc =
      setup_camera(&f, p->camera ? p->camera : &scene->camera, p->width, p->height, err, errlen);
  if (rc != 0)
    return rc;
  int draw = (p->layers & LAYER_OBJECTS) != 0;
  size_t nobj;
  if ((rc = pack_objects(r, scene, draw, &f, &nobj, err, errlen)) != 0)
    return rc;
  if (draw && (rc = bvh_update(r, scene, err, errlen)) != 0)
    return rc;
  f.ntri = draw ? r->bvh_ntri : 0;

  double l[3] = {scene->light.direction[0], scene->light.direction[1], scene->light.direction[2]};
  double len = sqrt(l[0] * l[0] + l[1] * l[1] + l[2] * l[2]);
  for (int i = 0; i < 3; i++) {
    f.light_dir[i] = len > 0 ? (float)(l[i] / len) : 0.0f;
    f.light_rgb[i] = scene->light.color[i] * scene->light.intensity;
    f.bg[i] = scene->background[i];
  }
  f.ambient = scene->light.ambient;
  f.bg[3] = scene->transparent_background ? 0.0f : 1.0f;

  size_t npix = r->pitch * r->rows;
  if (ensure_buffer(r, &r->objs, &r->cap_objs, nobj, sizeof(float), CL_MEM_READ_ONLY, 1, err,
                    errlen) ||
      ensure_buffer(r, &r->nodes, &r->cap_nodes, 1, NODE_STRIDE * sizeof(float), CL_MEM_READ_ONLY,
                    1, err, errlen) ||
      ensure_buffer(r, &r->tris, &r->cap_tris, 1, TRI_STRIDE * sizeof(float), CL_MEM_READ_ONLY, 1,
                    err, errlen))
    return PROTO_E_DEVICE;
  if (npix > r->cap_pixels) {
    /* The per-pixel buffers grow together, to exactly the new size: frames can be large. */
    cl_mem *bufs[3] = {&r->linear, &r->depth, &r->rgba8};
    size_t sizes[3] = {4 * sizeof(float), sizeof(float), 4};
    for (int i = 0; i < 3; i++) {
      size_t cap = 0;
      if (*bufs[i])
        clReleaseMemObject(*bufs[i]), *bufs[i] = NULL;
      if (ensure_buffer(r, bufs[i], &cap, npix, sizes[i], CL_MEM_READ_WRITE, 0, err, errlen)) {
        r->cap_pixels = 0;
        return PROTO_E_DEVICE;
      }
    }
    r->cap_pixels = npix;
  }

  r->frame = f;
  cl_int cr = clEnqueueWriteBuffer(r->dev.queue, r->objs, CL_FALSE, 0, nobj * sizeof(float),
                                   r->host_objs, 0, NULL, NULL);
  cl_kernel k = r->objects;
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 0, sizeof f, &f);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 1, sizeof(cl_mem), &r->objs);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 2, sizeof(cl_mem), &r->nodes);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 3, sizeof(cl_mem), &r->tris);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 4, sizeof(cl_mem), &r->linear);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 5, sizeof(cl_mem), &r->depth);
  size_t global[2] = {r->pitch / PACKET, r->rows};
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, global, r->objects_local, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clFinish(r->dev.queue);
  if (cr != CL_SUCCESS) {
    set_err(err, errlen, "[render] objects pass failed on %s: %s", r->dev.device_name,
            cl_dev_strerror(cr));
    return PROTO_E_DEVICE;
  }
  return 0;
}

/*
 * Packs the usable waves of 'scene' into r->host_waves as records for the eye 'eye' (WAVE_* of
 * common.h), working in double so that the offsets from the eye are exact to float rounding.
 * A wave with a zero or non-finite axis, a radius, softening or clamp that is not positive, or
 * any non-finite number is left out (the scene model refuses them; this keeps the kernel safe
 * whatever it is given). Returns the number packed, or -1 when out of memory.
 */
static int pack_waves(renderer_t *r, const render_scene_t *scene, const float eye[3]) {
  size_t need = (size_t)(scene->nwaves > 0 ? scene->nwaves : 1) * WAVE_STRIDE;
  if (need > r->host_waves_cap) {
    float *p = realloc(r->host_waves, need * sizeof(float));
    if (p == NULL)
      return -1;
    r->host_waves = p, r->host_waves_cap = need;
  }
  int n = 0;
  for (int i = 0; i < scene->nwaves; i++) {
    const rwave_t *wv = &scene->waves[i];
    double d[3], len = 0,
                 finite = wv->a + wv->b + wv->length + wv->radius + wv->softening + wv->clamp +
                          wv->color[0] + wv->color[1] + wv->color[2];
    for (int k = 0; k < 3; k++) {
      d[k] = wv->direction[k];
      len += d[k] * d[k];
      finite += wv->center[k];
    }
    len = sqrt(len);
    if (!isfinite(finite) || !(len > 0) || !isfinite(len) || !(wv->radius > 0) ||
        !(wv->softening > 0) || !(wv->clamp > 0))
      continue;
    double w[3], s0 = 0, gp = 0, bl = wv->length > 0 ? wv->length : 0;
    float *rec = r->host_waves + (size_t)n++ * WAVE_STRIDE;
    memset(rec, 0, WAVE_STRIDE * sizeof(float));
    for (int k = 0; k < 3; k++) {
      d[k] /= len;
      w[k] = (double)eye[k] - wv->center[k];
      s0 += w[k] * d[k];
    }
    for (int k = 0; k < 3; k++) {
      double wp = w[k] - s0 * d[k];
      gp += wp * wp;
      rec[WAVE_W + k] = (float)w[k];
      rec[WAVE_D + k] = (float)d[k];
      rec[WAVE_WP + k] = (float)wp;
      rec[WAVE_BOUND + k] = (float)(w[k] - 0.5 * bl * d[k]);
      rec[WAVE_COLOR + k] = wv->color[k];
    }
    rec[WAVE_S0] = (float)s0;
    rec[WAVE_L] = (float)bl;
    rec[WAVE_R2] = (float)((double)wv->radius * wv->radius);
    rec[WAVE_EPS2] = (float)((double)wv->softening * wv->softening);
    rec[WAVE_A] = wv->a;
    rec[WAVE_B] = wv->b;
    rec[WAVE_GP] = (float)gp;
    /* Rounded up, so that a test in float never culls a ray that enters the wave. */
    rec[WAVE_BOUND + 3] = (float)((wv->radius + 0.5 * bl) * 1.001 + 1e-6);
    rec[WAVE_RADIUS] = wv->radius;
    rec[WAVE_CLAMP] = wv->clamp;
    rec[WAVE_INV_CLAMP] = (float)(1.0 / wv->clamp);
  }
  return n;
}

static void cross3(const double a[3], const double b[3], double out[3]) {
  out[0] = a[1] * b[2] - a[2] * b[1];
  out[1] = a[2] * b[0] - a[0] * b[2];
  out[2] = a[0] * b[1] - a[1] * b[0];
}

static double dot3(const double a[3], const double b[3]) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

/* The direction (not unit) of the camera ray through pixel position ('px', 'py') of 'f'. */
static void ray_dir(const vfx_frame_t *f, double px, double py, double out[3]) {
  for (int i = 0; i < 3; i++)
    out[i] = f->base[i] + px * f->step_x[i] + py * f->step_y[i];
}

/*
 * Writes to r->host_lists, for each work-group of the waves pass (a tile of the padded image),
 * the number of the 'n' packed waves whose capsule may meet one of the tile's rays, followed by
 * their indices; a tile's list starts at (n + 1) times its index, row by row. The rays of a
 * tile fill the cone between the four planes through the eye and its corner pixels' rays, so
 * a wave is left out when both ends of its axis lie farther than its radius outside one of
 * them. The kernel then tests only the waves of its tile, most of which are near, instead of
 * every wave for every packet. Returns the number of ints written, or 0 when out of memory.
 */
static size_t cull_waves(renderer_t *r, int n) {
  size_t tw = WAVES_PACKET * r->waves_local[0], th = r->waves_local[1];
  size_t nx = r->pitch / tw, ny = r->rows / th, stride = (size_t)n + 1;
  size_t need = nx * ny * stride;
  if (need > r->host_lists_cap) {
    int32_t *p = realloc(r->host_lists, need * sizeof(int32_t));
    if (p == NULL)
      return 0;
    r->host_lists = p, r->host_lists_cap = need;
  }
  const vfx_frame_t *f = &r->frame;
  for (size_t ty = 0; ty < ny; ty++) {
    for (size_t tx = 0; tx < nx; tx++) {
      double x0 = tx * tw + 0.5, x1 = (tx + 1) * tw - 0.5;
      double y0 = ty * th + 0.5, y1 = (ty + 1) * th - 0.5;
      double c00[3], c10[3], c01[3], c11[3], mid[3], pl[4][3];
      ray_dir(f, x0, y0, c00), ray_dir(f, x1, y0, c10);
      ray_dir(f, x0, y1, c01), ray_dir(f, x1, y1, c11);
      ray_dir(f, 0.5 * (x0 + x1), 0.5 * (y0 + y1), mid);
      cross3(c00, c01, pl[0]), cross3(c10, c11, pl[1]);
      cross3(c00, c10, pl[2]), cross3(c01, c11, pl[3]);
      /* Unit normals facing into the cone. */
      for (int k = 0; k < 4; k++) {
        double len = sqrt(dot3(pl[k], pl[k]));
        len = dot3(pl[k], mid) < 0 ? -len : len;
        for (int i = 0; i < 3; i++)
          pl[k][i] = len != 0 ? pl[k][i] / len : 0;
      }
      int32_t *list = r->host_lists + (ty * nx + tx) * stride;
      int32_t count = 0;
      for (int i = 0; i < n; i++) {
        const float *rec = r->host_waves + (size_t)i * WAVE_STRIDE;
        double m[3], e[3];
        for (int k = 0; k < 3; k++) {
          m[k] = -(double)rec[WAVE_W + k];
          e[k] = m[k] + (double)rec[WAVE_L] * rec[WAVE_D + k];
        }
        /* A margin for the kernel's rays and records being float. */
        double rad = rec[WAVE_RADIUS] * 1.001 + 1e-5 * (sqrt(dot3(m, m)) + sqrt(dot3(e, e)));
        int out = 0;
        for (int k = 0; k < 4 && !out; k++)
          out = dot3(pl[k], m) < -rad && dot3(pl[k], e) < -rad;
        if (!out)
          list[1 + count++] = i;
      }
      list[0] = count;
    }
  }
  return need;
}

/*
 * Runs the waves pass over the frame the objects pass set up: each ray is integrated from the
 * near distance to r->depth. 'mode' is WAVES_ADD (glow into r->linear) or WAVES_STORE_H (H into
 * r->hbuf); 'samples' > 0 swaps the closed form for a ray march of that many samples per wave.
 * Sets '*ran' to whether there was a wave to draw. Returns 0 or a PROTO_E_* code.
 */
static int pass_waves(renderer_t *r, const render_scene_t *scene, int mode, int samples, int *ran,
                      char *err, size_t errlen) {
  *ran = 0;
  int n = pack_waves(r, scene, r->frame.eye);
  if (n < 0) {
    set_err(err, errlen, "[render] out of memory for %d waves", scene->nwaves);
    return PROTO_E_INTERNAL;
  }
  size_t npix = r->pitch * r->rows;
  if (n == 0 && !(mode & WAVES_STORE_H))
    return 0;
  if (ensure_buffer(r, &r->wave_recs, &r->cap_waves, (size_t)(n ? n : 1) * WAVE_STRIDE,
                    sizeof(float), CL_MEM_READ_ONLY, 1, err, errlen))
    return PROTO_E_DEVICE;
  if ((mode & WAVES_STORE_H) &&
      ensure_buffer(r, &r->hbuf, &r->cap_h, npix, sizeof(float), CL_MEM_READ_WRITE, 0, err, errlen))
    return PROTO_E_DEVICE;
  size_t nlists = cull_waves(r, n);
  if (nlists == 0) {
    set_err(err, errlen, "[render] out of memory for the wave lists");
    return PROTO_E_INTERNAL;
  }
  if (ensure_buffer(r, &r->wave_lists, &r->cap_lists, nlists, sizeof(int32_t), CL_MEM_READ_ONLY, 1,
                    err, errlen))
    return PROTO_E_DEVICE;
  /* Kernels take a buffer argument even when only one mode uses it. */
  cl_mem hout = r->hbuf ? r->hbuf : r->depth;
  cl_kernel k = samples > 0 ? r->waves_march : r->waves;
  cl_int nw = n, md = mode, ns = samples;
  cl_int cr = CL_SUCCESS;
  if (n > 0)
    cr =
        clEnqueueWriteBuffer(r->dev.queue, r->wave_recs, CL_FALSE, 0,
                             (size_t)n * WAVE_STRIDE * sizeof(float), r->host_waves, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clEnqueueWriteBuffer(r->dev.queue, r->wave_lists, CL_FALSE, 0, nlists * sizeof(int32_t),
                              r->host_lists, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 0, sizeof r->frame, &r->frame);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 1, sizeof(cl_mem), &r->wave_recs);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 2, sizeof nw, &nw);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 3, sizeof(cl_mem), &r->wave_lists);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 4, sizeof(cl_mem), &r->depth);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 5, sizeof(cl_mem), &r->linear);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 6, sizeof(cl_mem), &hout);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 7, sizeof md, &md);
  if (cr == CL_SUCCESS && samples > 0)
    cr = clSetKernelArg(k, 8, sizeof ns, &ns);
  size_t global[2] = {r->pitch / WAVES_PACKET, r->rows};
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, global, r->waves_local, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clFinish(r->dev.queue);
  if (cr != CL_SUCCESS) {
    set_err(err, errlen, "[render] waves pass failed on %s: %s", r->dev.device_name,
            cl_dev_strerror(cr));
    return PROTO_E_DEVICE;
  }
  *ran = n > 0;
  return 0;
}

/* ---- Fluid --------------------------------------------------------------------------------- */

/* Grows the int32 or float staging array '*p' to 'need' elements. Returns 0, or -1. */
static int grow_staging(void **p, size_t *cap, size_t need, size_t size) {
  if (need <= *cap)
    return 0;
  void *q = realloc(*p, need * size);
  if (q == NULL)
    return -1;
  *p = q, *cap = need;
  return 0;
}

/* The range of cells [lo, hi] on each axis that the ball of radius 'h' about 'p' may reach. */
static void fluid_reach(const vfx_fluid_t *fl, const float *p, float h, int lo[3], int hi[3]) {
  for (int a = 0; a < 3; a++) {
    double l = floor((p[a] - h - fl->origin[a]) / fl->cell);
    double u = floor((p[a] + h - fl->origin[a]) / fl->cell);
    lo[a] = l < 0 ? 0 : l >= fl->dims[a] ? fl->dims[a] - 1 : (int)l;
    hi[a] = u < 0 ? 0 : u >= fl->dims[a] ? fl->dims[a] - 1 : (int)u;
  }
}

/* Whether the ball of radius 'h' about 'p' touches cell (i, j, k), boundary included, with a
 * margin for the kernel's float rounding (listing one particle too many costs nothing). */
static int fluid_touches(const vfx_fluid_t *fl, const float *p, double h2, int i, int j, int k) {
  int c[3] = {i, j, k};
  double d2 = 0;
  for (int a = 0; a < 3; a++) {
    double lo = fl->origin[a] + (double)c[a] * fl->cell, hi = lo + fl->cell;
    double e = p[a] < lo ? lo - p[a] : p[a] > hi ? p[a] - hi : 0;
    d2 += e * e;
  }
  return d2 <= h2;
}

/*
 * Builds the fluid grid of vfx_fluid_t (common.h) in r->host_fcells and r->host_fpos by a
 * counting sort, and fills 'fl'. Particles with a non-finite coordinate are left out. Returns
 * the number of cells (0 when no particle is left), or -1 when out of memory.
 */
static long fluid_build(renderer_t *r, const rfluid_t *fd, vfx_fluid_t *fl) {
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
   * lists every particle within h of it whatever its size, so any side >= h is correct. */
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

  if (grow_staging((void **)&r->host_fcells, &r->host_fcells_cap, 2 * ncell, sizeof(int32_t)))
    return -1;
  int32_t *cells = r->host_fcells;
  memset(cells, 0, 2 * ncell * sizeof(int32_t));
  double h2 = (double)h * h * 1.0002 + 1e-12;
  int a[3], b[3];
  for (int pass = 0; pass < 2; pass++) {
    if (pass == 1) {
      /* Starts of the lists, each padded to a multiple of 8; counts restart for the fill. */
      size_t at = 0;
      for (size_t c = 0; c < ncell; c++) {
        int32_t m = cells[2 * c + 1];
        cells[2 * c] = (int32_t)at;
        cells[2 * c + 1] = 0;
        at += (size_t)(m + 7) & ~(size_t)7;
      }
      size_t stride = at ? at : 8;
      if (stride > INT32_MAX / 3 ||
          grow_staging((void **)&r->host_fpos, &r->host_fpos_cap, 3 * stride, sizeof(float)))
        return -1;
      for (size_t i = 0; i < 3 * stride; i++)
        r->host_fpos[i] = FLUID_PAD;
      fl->stride = (int)stride;
    }
    for (uint32_t i = 0; i < fd->count; i++) {
      const float *p = fd->positions + 3 * (size_t)i;
      if (!isfinite(p[0]) || !isfinite(p[1]) || !isfinite(p[2]))
        continue;
      fluid_reach(fl, p, h, a, b);
      for (int k = a[2]; k <= b[2]; k++) {
        for (int j = a[1]; j <= b[1]; j++) {
          for (int q = a[0]; q <= b[0]; q++) {
            if (!fluid_touches(fl, p, h2, q, j, k))
              continue;
            size_t c = ((size_t)k * fl->dims[1] + j) * fl->dims[0] + q;
            if (pass == 1) {
              size_t at = (size_t)cells[2 * c] + (size_t)cells[2 * c + 1];
              r->host_fpos[at] = p[0];
              r->host_fpos[fl->stride + at] = p[1];
              r->host_fpos[2 * (size_t)fl->stride + at] = p[2];
            }
            cells[2 * c + 1]++;
          }
        }
      }
    }
  }
  return (long)ncell;
}

/*
 * Runs the fluid pass over the frame the objects pass set up: builds the grid of the scene's
 * particles, uploads it and draws the metaballs into r->linear and r->depth where they are
 * nearer than the objects. Sets '*ran' to whether there was a particle to draw. Returns 0 or a
 * PROTO_E_* code.
 */
static int pass_fluid(renderer_t *r, const render_scene_t *scene, int *ran, char *err,
                      size_t errlen) {
  const rfluid_t *fd = &scene->fluid;
  *ran = 0;
  if (fd->count == 0 || fd->positions == NULL || !(fd->h > 0) || !isfinite(fd->h) ||
      !(fd->threshold > 0) || !isfinite(fd->threshold))
    return 0;
  vfx_fluid_t fl;
  memset(&fl, 0, sizeof fl);
  long ncell = fluid_build(r, fd, &fl);
  if (ncell < 0) {
    set_err(err, errlen, "[render] out of memory for the grid of %u particles", fd->count);
    return PROTO_E_INTERNAL;
  }
  if (ncell == 0)
    return 0;
  fl.h = fd->h;
  fl.inv_h = 1.0f / fd->h;
  fl.threshold = fd->threshold;
  fl.min_step = fd->h / 2000;
  fl.tol = fd->h * 1e-4f;
  double ior = isfinite(fd->ior) && fd->ior > 0 ? fd->ior : 1.33;
  double f0 = (ior - 1) / (ior + 1);
  fl.f0 = (float)(f0 * f0);
  double rough = isfinite(fd->roughness) ? fd->roughness : 0.1;
  rough = rough < 0.02 ? 0.02 : rough > 1 ? 1 : rough;
  fl.shininess = (float)(2 / (rough * rough) - 2 + 1);
  memcpy(fl.color, fd->color, sizeof fl.color);

  if (ensure_buffer(r, &r->fluid_cells, &r->cap_fcells, 2 * (size_t)ncell, sizeof(int32_t),
                    CL_MEM_READ_ONLY, 1, err, errlen) ||
      ensure_buffer(r, &r->fluid_pos, &r->cap_fpos, 3 * (size_t)fl.stride, sizeof(float),
                    CL_MEM_READ_ONLY, 1, err, errlen))
    return PROTO_E_DEVICE;
  cl_kernel k = r->fluid;
  cl_int cr =
      clEnqueueWriteBuffer(r->dev.queue, r->fluid_cells, CL_FALSE, 0,
                           2 * (size_t)ncell * sizeof(int32_t), r->host_fcells, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clEnqueueWriteBuffer(r->dev.queue, r->fluid_pos, CL_FALSE, 0,
                              3 * (size_t)fl.stride * sizeof(float), r->host_fpos, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 0, sizeof r->frame, &r->frame);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 1, sizeof fl, &fl);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 2, sizeof(cl_mem), &r->fluid_cells);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 3, sizeof(cl_mem), &r->fluid_pos);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 4, sizeof(cl_mem), &r->linear);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 5, sizeof(cl_mem), &r->depth);
  size_t global[2] = {r->pitch, r->rows};
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, global, r->fluid_local, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clFinish(r->dev.queue);
  if (cr != CL_SUCCESS) {
    set_err(err, errlen, "[render] fluid pass failed on %s: %s", r->dev.device_name,
            cl_dev_strerror(cr));
    return PROTO_E_DEVICE;
  }
  *ran = 1;
  return 0;
}

/* Runs the tone-map pass from r->linear into r->rgba8, padding included. */
static int pass_tonemap(renderer_t *r, const render_scene_t *scene, char *err, size_t errlen) {
  cl_int op;
  cl_float scale = exp2f(scene->exposure);
  switch (scene->tone_map) {
  case TONE_REINHARD:
    op = TONE_OP_REINHARD;
    break;
  case TONE_ACES:
    op = TONE_OP_ACES;
    break;
  default:
    op = TONE_OP_NONE;
    break;
  }
  if (!isfinite(scale))
    scale = scene->exposure > 0 ? 3.4e38f : 0.0f;
  cl_kernel k = r->tonemap;
  cl_int cr = clSetKernelArg(k, 0, sizeof(cl_mem), &r->linear);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 1, sizeof(cl_mem), &r->rgba8);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 2, sizeof scale, &scale);
  if (cr == CL_SUCCESS)
    cr = clSetKernelArg(k, 3, sizeof op, &op);
  size_t global[2] = {r->pitch / TONEMAP_PACKET, r->rows};
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, global, r->tonemap_local, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clFinish(r->dev.queue);
  if (cr != CL_SUCCESS) {
    set_err(err, errlen, "[render] tonemap pass failed on %s: %s", r->dev.device_name,
            cl_dev_strerror(cr));
    return PROTO_E_DEVICE;
  }
  return 0;
}

/* Copies the image part of the padded per-pixel buffer 'buf' ('pixel' bytes a pixel) to 'dst',
 * rows packed. */
static int read_back(renderer_t *r, cl_mem buf, size_t pixel, const render_params_t *p, void *dst,
                     char *err, size_t errlen) {
  size_t origin[3] = {0, 0, 0}, region[3] = {p->width * pixel, p->height, 1};
  cl_int cr = clEnqueueReadBufferRect(r->dev.queue, buf, CL_TRUE, origin, origin, region,
                                      r->pitch * pixel, 0, p->width * pixel, 0, dst, 0, NULL, NULL);
  if (cr != CL_SUCCESS) {
    set_err(err, errlen, "[render] readback failed on %s: %s", r->dev.device_name,
            cl_dev_strerror(cr));
    return PROTO_E_DEVICE;
  }
  return 0;
}

int renderer_render(renderer_t *r, const render_scene_t *scene, const render_params_t *p,
                    render_output_t *out, char *err, size_t errlen) {
  double start = now_ms();
  memset(out, 0, sizeof *out);
  if (err && errlen)
    err[0] = '\0';
  if (p->width == 0 || p->height == 0 || p->width > MAX_SIDE || p->height > MAX_SIDE) {
    set_err(err, errlen, "width and height must lie in [1, %d], not %ux%u", MAX_SIDE, p->width,
            p->height);
    return PROTO_E_INVALID_PARAMS;
  }
  int beauty = p->aov == AOV_BEAUTY;
  int ok = beauty ? p->format == PROTO_FMT_PNG || p->format == PROTO_FMT_RGBA8 ||
                        p->format == PROTO_FMT_RGBAF32
                  : (p->aov == AOV_DEPTH || p->aov == AOV_WAVE_H) && p->format == PROTO_FMT_F32;
  if (!ok) {
    const char *fmt = proto_format_name(p->format);
    const char *aov = p->aov == AOV_BEAUTY   ? "beauty"
                      : p->aov == AOV_DEPTH  ? "depth"
                      : p->aov == AOV_WAVE_H ? "wave_h"
                                             : "unknown";
    set_err(err, errlen,
            "format \"%s\" is not available for aov \"%s\" (beauty: png, rgba8 or "
            "rgbaf32; depth and wave_h: f32)",
            fmt ? fmt : "unknown", aov);
    return PROTO_E_INVALID_PARAMS;
  }
  if (p->format == PROTO_FMT_PNG && (p->png_level < -1 || p->png_level > 9)) {
    set_err(err, errlen, "png level must lie in [-1, 9], not %d", p->png_level);
    return PROTO_E_INVALID_PARAMS;
  }

  size_t npix = (size_t)p->width * p->height;
  int waves = (p->layers & LAYER_WAVES) && scene->nwaves > 0 && p->aov != AOV_DEPTH;
  if (p->aov == AOV_WAVE_H && !waves) {
    /* Without waves to draw, their summed H is zero everywhere. */
    out->bytes = calloc(npix, sizeof(float));
    if (out->bytes == NULL) {
      set_err(err, errlen, "[render] out of memory for a %ux%u frame", p->width, p->height);
      return PROTO_E_INTERNAL;
    }
    out->nbytes = npix * sizeof(float);
    out->total_ms = now_ms() - start;
    return 0;
  }

  double t = now_ms();
  int rc = pass_objects(r, scene, p, err, errlen);
  if (rc != 0)
    return rc;
  add_pass(out, "objects", now_ms() - t);

  if ((p->layers & LAYER_FLUID) && scene->fluid.count > 0) {
    t = now_ms();
    int ran;
    if ((rc = pass_fluid(r, scene, &ran, err, errlen)) != 0)
      return rc;
    if (ran)
      add_pass(out, "fluid", now_ms() - t);
  }

  if (waves) {
    t = now_ms();
    int ran;
    int mode = p->aov == AOV_WAVE_H ? WAVES_STORE_H : WAVES_ADD;
    if ((rc = pass_waves(r, scene, mode, p->march_samples, &ran, err, errlen)) != 0)
      return rc;
    if (ran)
      add_pass(out, "waves", now_ms() - t);
  }

  size_t nbytes = (p->format == PROTO_FMT_RGBAF32 ? 16 : 4) * npix;
  unsigned char *bytes = NULL;
  if (p->format != PROTO_FMT_PNG) {
    bytes = malloc(nbytes);
    if (bytes == NULL) {
      set_err(err, errlen, "[render] out of memory for a %ux%u frame", p->width, p->height);
      return PROTO_E_INTERNAL;
    }
  }
  if (beauty && p->format != PROTO_FMT_RGBAF32) {
    t = now_ms();
    if ((rc = pass_tonemap(r, scene, err, errlen)) != 0)
      goto fail;
    add_pass(out, "tonemap", now_ms() - t);
  }

  t = now_ms();
  if (p->format == PROTO_FMT_PNG) {
    if (r->scratch_cap < 4 * npix) {
      unsigned char *s = realloc(r->scratch, 4 * npix);
      if (s == NULL) {
        set_err(err, errlen, "[render] out of memory for a %ux%u frame", p->width, p->height);
        rc = PROTO_E_INTERNAL;
        goto fail;
      }
      r->scratch = s, r->scratch_cap = 4 * npix;
    }
    rc = read_back(r, r->rgba8, 4, p, r->scratch, err, errlen);
  } else if (p->aov == AOV_DEPTH) {
    rc = read_back(r, r->depth, sizeof(float), p, bytes, err, errlen);
  } else if (p->aov == AOV_WAVE_H) {
    rc = read_back(r, r->hbuf, sizeof(float), p, bytes, err, errlen);
  } else if (p->format == PROTO_FMT_RGBAF32) {
    rc = read_back(r, r->linear, 4 * sizeof(float), p, bytes, err, errlen);
  } else {
    rc = read_back(r, r->rgba8, 4, p, bytes, err, errlen);
  }
  if (rc != 0)
    goto fail;
  add_pass(out, "readback", now_ms() - t);

  if (p->format == PROTO_FMT_PNG) {
    t = now_ms();
    if (encode_png(r->scratch, p->width, p->height, p->png_level, &bytes, &nbytes) != 0) {
      set_err(err, errlen, "[render] PNG encoding of a %ux%u frame failed", p->width, p->height);
      rc = PROTO_E_INTERNAL;
      goto fail;
    }
    add_pass(out, "encode", now_ms() - t);
  }
  out->bytes = bytes;
  out->nbytes = nbytes;
  out->total_ms = now_ms() - start;
  return 0;

fail:
  free(bytes);
  out->npasses = 0;
  return rc;
}

/* ---- Life cycle ---------------------------------------------------------------------------- */

/* Picks a local size the device accepts for 'k', shrinking 'local' by halves if needed. */
static void fit_local(renderer_t *r, cl_kernel k, size_t *local, int dims) {
  size_t max = 0;
  if (clGetKernelWorkGroupInfo(k, r->dev.device, CL_KERNEL_WORK_GROUP_SIZE, sizeof max, &max,
                               NULL) != CL_SUCCESS ||
      max == 0)
    return;
  while (local[0] * (dims > 1 ? local[1] : 1) > max) {
    if (dims > 1 && local[1] > 1)
      local[1] /= 2;
    else
      local[0] /= 2;
  }
}

/*
 * Renders a tiny frame that holds every kind of object, so each kernel runs once with the
 * local size of real frames: PoCL compiles its work-group function at that first launch.
 */
static int warm_up(renderer_t *r, char *err, size_t errlen) {
  static float tri[9] = {-0.5f, 0, 0, 0.5f, 0, 0, 0, 0.8f, 0};
  mesh_t mesh = {.ntri = 1, .tri = tri};
  atomic_init(&mesh.refs, 1);
  rwave_t wave = {.center = {0, 0.5f, 0},
                  .direction = {1, 0, 0},
                  .a = 1,
                  .b = 1,
                  .length = 1,
                  .radius = 1,
                  .softening = 0.1f,
                  .clamp = 4,
                  .color = {1, 0.5f, 0.2f}};
  robject_t objs[4] = {
      {.shape = SHAPE_SPHERE, .position = {-1, 0.5f, 0}, .scale = {1, 1, 1}, .color = {1, 0, 0}},
      {.shape = SHAPE_BOX, .position = {1, 0.5f, 0}, .scale = {1, 1, 1}, .color = {0, 1, 0}},
      {.shape = SHAPE_PLANE, .scale = {1, 1, 1}, .color = {1, 1, 1}},
      {.shape = SHAPE_MESH, .scale = {1, 1, 1}, .color = {0, 0, 1}, .mesh = &mesh},
  };
  /* A few particles where the camera sees them, so the fluid kernel runs too. */
  static const float drops[9] = {0, 1, 0, 0.2f, 1.1f, 0, -0.15f, 0.95f, 0.1f};
  render_scene_t scene = {
      .fluid = {.count = 3,
                .positions = drops,
                .h = 0.61f,
                .threshold = 0.765625f,
                .color = {0.8f, 0.9f, 1},
                .ior = 1.33f,
                .roughness = 0.1f},
      .camera = {.eye = {0, 2, 5},
                 .target = {0, 0, 0},
                 .up = {0, 1, 0},
                 .fov_y = 45,
                 .near_ = 0.01f,
                 .far_ = 100},
      .light = {.direction = {0, 1, 0}, .color = {1, 1, 1}, .intensity = 1, .ambient = 0.1f},
      .objects = objs,
      .nobjects = 4,
      .waves = &wave,
      .nwaves = 1,
      .tone_map = TONE_ACES,
  };
  atomic_init(&scene.refs, 1);
  render_params_t p = {.width = 8, .height = 8, .format = PROTO_FMT_RGBA8, .layers = LAYER_ALL};
  render_output_t out;
  int rc = renderer_render(r, &scene, &p, &out, err, errlen);
  free(out.bytes);
  if (rc == 0) {
    p.aov = AOV_WAVE_H, p.format = PROTO_FMT_F32;
    rc = renderer_render(r, &scene, &p, &out, err, errlen);
    free(out.bytes);
  }
  /* Drop the BVH of the stack mesh before it goes out of scope. */
  bvh_forget(r);
  return rc;
}

int renderer_create(const renderer_opts_t *opts, renderer_t **out, char *err, size_t errlen) {
  *out = NULL;
  renderer_t *r = calloc(1, sizeof *r);
  if (r == NULL) {
    set_err(err, errlen, "[renderer_create] out of memory");
    return -1;
  }
  if (cl_dev_open(&r->dev, opts ? opts->device : NULL, err, errlen) != 0) {
    free(r);
    return -1;
  }
  if (cl_dev_build(&r->dev, opts ? opts->kernels_dir : NULL, build_options, err, errlen) != 0)
    goto fail;
  if ((r->objects = cl_dev_kernel(&r->dev, "objects", err, errlen)) == NULL ||
      (r->tonemap = cl_dev_kernel(&r->dev, "tonemap", err, errlen)) == NULL ||
      (r->waves = cl_dev_kernel(&r->dev, "waves", err, errlen)) == NULL ||
      (r->waves_march = cl_dev_kernel(&r->dev, "waves_march", err, errlen)) == NULL ||
      (r->fluid = cl_dev_kernel(&r->dev, "fluid", err, errlen)) == NULL)
    goto fail;
  r->objects_local[0] = OBJECTS_LX;
  r->objects_local[1] = OBJECTS_LY;
  r->tonemap_local[0] = TONEMAP_LX;
  r->tonemap_local[1] = TONEMAP_LY;
  fit_local(r, r->objects, r->objects_local, 2);
  fit_local(r, r->tonemap, r->tonemap_local, 2);
  /* The waves kernels cover the objects pass's pixels with wider work-items, so they keep its
   * work-group's pixels if the device takes them, or halve them. The march kernel only serves
   * comparisons and is not warmed up. */
  r->waves_local[0] = r->objects_local[0] * PACKET / WAVES_PACKET;
  if (r->waves_local[0] == 0)
    r->waves_local[0] = 1;
  r->waves_local[1] = r->objects_local[1];
  fit_local(r, r->waves, r->waves_local, 2);
  fit_local(r, r->waves_march, r->waves_local, 2);
  /* One pixel per fluid work-item; the padded rows hold whole work-groups of it too. */
  r->fluid_local[0] = FLUID_LX;
  r->fluid_local[1] = FLUID_LY;
  fit_local(r, r->fluid, r->fluid_local, 2);
  while (r->fluid_local[1] > r->objects_local[1])
    r->fluid_local[1] /= 2;
  /* Every local size is a power of two and the padded rows are a multiple of the widest
   * work-group (row_pixels); the rows are a multiple of the objects work-group's, so the tone
   * map's must not be taller. */
  while (r->tonemap_local[1] > r->objects_local[1])
    r->tonemap_local[1] /= 2;
  if (warm_up(r, err, errlen) != 0)
    goto fail;
  *out = r;
  return 0;

fail:
  renderer_destroy(r);
  return -1;
}

void renderer_destroy(renderer_t *r) {
  if (r == NULL)
    return;
  /* Getting the binary out of PoCL compiles every kernel for every case (about a second),
   * so it is saved when the renderer goes away rather than delaying the first frame. The
   * next start loads it in milliseconds. */
  if (r->objects && r->tonemap && r->waves)
    cl_dev_save_binary(&r->dev);
  bvh_forget(r);
  cl_mem bufs[] = {r->linear,    r->depth,      r->rgba8, r->objs,        r->nodes,    r->tris,
                   r->wave_recs, r->wave_lists, r->hbuf,  r->fluid_cells, r->fluid_pos};
  for (size_t i = 0; i < sizeof bufs / sizeof bufs[0]; i++) {
    if (bufs[i])
      clReleaseMemObject(bufs[i]);
  }
  if (r->objects)
    clReleaseKernel(r->objects);
  if (r->tonemap)
    clReleaseKernel(r->tonemap);
  if (r->waves)
    clReleaseKernel(r->waves);
  if (r->waves_march)
    clReleaseKernel(r->waves_march);
  if (r->fluid)
    clReleaseKernel(r->fluid);
  cl_dev_close(&r->dev);
  free(r->host_objs);
  free(r->host_waves);
  free(r->host_lists);
  free(r->host_fcells);
  free(r->host_fpos);
  free(r->scratch);
  free(r);
}

const char *renderer_platform_name(const renderer_t *r) {
  return r->dev.platform_name;
}

const char *renderer_device_name(const renderer_t *r) {
  return r->dev.device_name;
}

cl_dev_t *renderer_device(renderer_t *r) {
  return &r->dev;
}
