/*
 * The objects pass: the scene's objects compiled into the flat world-space records of
 * kernels/common.h (spheres, convex solids as planes, meshes through a BVH kept across frames
 * while the meshes stay put), the camera's frame constants, and the ray cast that writes
 * linear colour and depth for the passes after it.
 */
#include <math.h>

#include "render_internal.h"

#define BVH_LEAF 4  /* Triangles per leaf the builder aims for. */
#define BVH_BINS 16 /* Bins of the SAH split search. */

/* ---- Transforms ---------------------------------------------------------------------------- */

/* Stores an int in a float slot of a record, bit for bit, as the kernels' as_int() reads it. */
static void set_int(float *slot, int32_t v) {
  memcpy(slot, &v, sizeof v);
}

void rotation_zyx(const double deg[3], double r[3][3]) {
  double a = deg[0] * (M_PI / 180), b = deg[1] * (M_PI / 180), c = deg[2] * (M_PI / 180);
  double ca = cos(a), sa = sin(a), cb = cos(b), sb = sin(b), cc = cos(c), sc = sin(c);
  r[0][0] = cc * cb, r[0][1] = cc * sb * sa - sc * ca, r[0][2] = cc * sb * ca + sc * sa;
  r[1][0] = sc * cb, r[1][1] = sc * sb * sa + cc * ca, r[1][2] = sc * sb * ca - cc * sa;
  r[2][0] = -sb, r[2][1] = cb * sa, r[2][2] = cb * ca;
}

/* An object's rotation matrix from its float angles (rotation_zyx). */
static void rotation(const float deg[3], double r[3][3]) {
  double d[3] = {deg[0], deg[1], deg[2]};
  rotation_zyx(d, r);
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
    if (k >= r->frame.bvh_nkeys)
      return 0;
    const mesh_key_t *key = &r->frame.bvh_keys[k++];
    if (key->mesh != o->mesh || memcmp(key->position, o->position, sizeof key->position) ||
        memcmp(key->scale, o->scale, sizeof key->scale) ||
        memcmp(key->rotation, o->rotation, sizeof key->rotation))
      return 0;
  }
  return k == r->frame.bvh_nkeys;
}

/*
 * Makes the device BVH hold the mesh objects of 'scene' (world = T R S mesh), rebuilding it
 * only when they changed since it was built. Returns 0 or a PROTO_E_* code.
 */
static int bvh_update(renderer_t *r, const render_scene_t *scene, char *err, size_t errlen) {
  if (bvh_matches(r, scene))
    return 0;
  render_geometry_forget(&r->frame);

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
    proto_error_format(err, errlen, "[render] scene has too many mesh triangles (%zu)", ntri);
    return PROTO_E_LIMIT;
  }
  r->frame.bvh_keys = calloc(nmesh ? (size_t)nmesh : 1, sizeof *r->frame.bvh_keys);
  size_t alloc = ntri ? ntri : 1;
  float *world = malloc(alloc * 9 * sizeof(float));
  float *box = malloc(alloc * 6 * sizeof(float));
  float *cent = malloc(alloc * 3 * sizeof(float));
  int32_t *owner = malloc(alloc * sizeof(int32_t));
  bvh_builder_t b = {.box = box, .cent = cent, .idx = malloc(alloc * sizeof(uint32_t))};
  float *packed = NULL, root[12];
  box_empty(root), box_empty(root + 6);
  int rc = PROTO_E_INTERNAL;
  if (!r->frame.bvh_keys || !world || !box || !cent || !owner || !b.idx) {
    proto_error_format(err, errlen, "[render] out of memory building the mesh BVH (%zu triangles)",
                       ntri);
    goto done;
  }

  /* World-space triangles of every mesh object; the key list is kept in scene order. */
  size_t t = 0;
  int k = 0;
  for (int i = 0; i < scene->nobjects; i++) {
    const robject_t *o = &scene->objects[i];
    if (o->shape != SHAPE_MESH || o->mesh == NULL)
      continue;
    mesh_key_t *key = &r->frame.bvh_keys[k];
    key->mesh = mesh_ref(o->mesh);
    memcpy(key->position, o->position, sizeof key->position);
    memcpy(key->scale, o->scale, sizeof key->scale);
    memcpy(key->rotation, o->rotation, sizeof key->rotation);
    r->frame.bvh_nkeys = ++k;
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
      proto_error_format(err, errlen,
                         "[render] out of memory building the mesh BVH (%zu triangles)", ntri);
      goto done;
    }
    packed = malloc(ntri * TRI_STRIDE * sizeof(float));
    if (packed == NULL) {
      proto_error_format(err, errlen,
                         "[render] out of memory building the mesh BVH (%zu triangles)", ntri);
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
    if (render_ensure_buffer(r, &r->frame.nodes, &r->frame.cap_nodes, b.nnodes,
                             NODE_STRIDE * sizeof(float), CL_MEM_READ_ONLY, 1, err, errlen) ||
        render_ensure_buffer(r, &r->frame.tris, &r->frame.cap_tris, ntri,
                             TRI_STRIDE * sizeof(float), CL_MEM_READ_ONLY, 1, err, errlen))
      goto done;
    cl_int cr =
        clEnqueueWriteBuffer(r->dev.queue, r->frame.nodes, CL_TRUE, 0,
                             b.nnodes * NODE_STRIDE * sizeof(float), b.nodes, 0, NULL, NULL);
    if (cr == CL_SUCCESS)
      cr = clEnqueueWriteBuffer(r->dev.queue, r->frame.tris, CL_TRUE, 0,
                                ntri * TRI_STRIDE * sizeof(float), packed, 0, NULL, NULL);
    if (cr != CL_SUCCESS) {
      proto_error_format(err, errlen, "[render] uploading the mesh BVH failed: %s",
                         cl_dev_strerror(cr));
      goto done;
    }
  }
  r->frame.bvh_ntri = (int)ntri;
  rc = 0;

done:
  if (rc != 0)
    render_geometry_forget(&r->frame);
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
  double fw[3], rt[3], up[3];
  int basis = render_view_basis(c, fw, rt, up);
  if (basis != 0) {
    proto_error_format(err, errlen,
                       basis == -1 ? "camera: target must differ from eye"
                                   : "camera: up must not be parallel to the view direction");
    return PROTO_E_INVALID_PARAMS;
  }
  if (!(c->fov_y > 0 && c->fov_y < 180)) {
    proto_error_format(err, errlen, "camera: fov_y must lie in (0, 180) degrees");
    return PROTO_E_INVALID_PARAMS;
  }
  if (!(c->near_ >= 0) || !(c->far_ > c->near_) || isnan(c->far_)) {
    proto_error_format(err, errlen, "camera: need 0 <= near < far");
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
 * Packs the scene's objects into r->frame.host_objs and the counts and offsets of 'f'; with 'draw'
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
  if (need > r->frame.host_objs_cap) {
    float *p = realloc(r->frame.host_objs, need * sizeof(float));
    if (p == NULL) {
      proto_error_format(err, errlen, "[render] out of memory for %d objects", scene->nobjects);
      return PROTO_E_INTERNAL;
    }
    r->frame.host_objs = p, r->frame.host_objs_cap = need;
  }
  f->nsph = nsph;
  f->nconv = nconv;
  f->conv_off = nsph * SPH_STRIDE;
  f->mesh_off = f->conv_off + nconv * CONV_STRIDE;
  int s = 0, c = 0, m = 0;
  for (int i = 0; draw && i < scene->nobjects; i++) {
    const robject_t *o = &scene->objects[i];
    if (o->shape == SHAPE_SPHERE && usable_scale(o->scale)) {
      pack_sphere(o, r->frame.host_objs + (size_t)s++ * SPH_STRIDE);
    } else if (((o->shape == SHAPE_BOX || o->shape == SHAPE_TETRAHEDRON) &&
                usable_scale(o->scale)) ||
               o->shape == SHAPE_PLANE) {
      pack_convex(o, r->frame.host_objs + f->conv_off + (size_t)c++ * CONV_STRIDE);
    } else if (o->shape == SHAPE_MESH && o->mesh != NULL) {
      memcpy(r->frame.host_objs + f->mesh_off + 3 * m++, o->color, 3 * sizeof(float));
    }
  }
  r->frame.host_objs[need - 1] = 0;
  *nfloats = need;
  return 0;
}

/* The objects pass's state: its kernel and work-group; what it draws goes to r->frame. */
typedef struct objects_state {
  cl_kernel kernel;
  size_t local[2];
} objects_state_t;

static void objects_free(renderer_t *r, void *state) {
  objects_state_t *os = state;
  render_geometry_forget(&r->frame);
  if (os)
    render_release(&os->kernel, 1, NULL, 0);
  free(os);
}

static int objects_init(renderer_t *r, void **state, char *err, size_t errlen) {
  objects_state_t *os = render_state_new(state, sizeof *os, err, errlen);
  if (os == NULL)
    return -1;
  if ((os->kernel = cl_dev_kernel(&r->dev, "objects", err, errlen)) == NULL)
    return -1;
  os->local[0] = OBJECTS_LX;
  os->local[1] = OBJECTS_LY;
  render_fit_local(r, os->kernel, os->local, 2);
  r->group[0] = os->local[0];
  r->group[1] = os->local[1];
  render_frame_require(r, PACKET * os->local[0], os->local[1] ? os->local[1] : 1);
  return 0;
}

static void objects_reset(renderer_t *r, void *state) {
  (void)state;
  render_geometry_forget(&r->frame);
}

/* Every frame starts here: it sets up the camera and the buffers even when the objects layer is
 * off. */
static int objects_wants(const renderer_t *r, const render_scene_t *scene,
                         const render_params_t *p) {
  (void)r, (void)scene, (void)p;
  return 1;
}

/* Ray casts the objects into r->frame.linear and r->frame.depth and keeps the frame's constants
 * in r->frame.consts for the passes after it. With r->frame.base_optional set and no object to
 * draw, it launches nothing and sets r->frame.base_skipped. Returns 0 or a PROTO_E_* code. */
static int objects_run(renderer_t *r, void *state, const render_scene_t *scene,
                       const render_params_t *p, const char **ran, char *err, size_t errlen) {
  objects_state_t *os = state;
  vfx_frame_t f;
  memset(&f, 0, sizeof f);
  f.width = (int)p->width;
  f.height = (int)p->height;
  f.pitch = (int)r->frame.pitch;
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
  f.ntri = draw ? r->frame.bvh_ntri : 0;

  double l[3] = {scene->light.direction[0], scene->light.direction[1], scene->light.direction[2]};
  double len = sqrt(l[0] * l[0] + l[1] * l[1] + l[2] * l[2]);
  for (int i = 0; i < 3; i++) {
    f.light_dir[i] = len > 0 ? (float)(l[i] / len) : 0.0f;
    f.light_rgb[i] = scene->light.color[i] * scene->light.intensity;
    f.sky[i] = scene->background[i];
  }
  f.ambient = scene->light.ambient;
  /* A transparent background is transparent black, so that every pixel is premultiplied. */
  int clear = p->background == RENDER_BG_TRANSPARENT ||
              (p->background == RENDER_BG_DEFAULT && scene->transparent_background);
  for (int i = 0; i < 3; i++)
    f.bg[i] = clear ? 0.0f : scene->background[i];
  f.bg[3] = clear ? 0.0f : 1.0f;

  if (render_ensure_buffer(r, &r->frame.objs, &r->frame.cap_objs, nobj, sizeof(float),
                           CL_MEM_READ_ONLY, 1, err, errlen) ||
      render_ensure_buffer(r, &r->frame.nodes, &r->frame.cap_nodes, 1, NODE_STRIDE * sizeof(float),
                           CL_MEM_READ_ONLY, 1, err, errlen) ||
      render_ensure_buffer(r, &r->frame.tris, &r->frame.cap_tris, 1, TRI_STRIDE * sizeof(float),
                           CL_MEM_READ_ONLY, 1, err, errlen))
    return PROTO_E_DEVICE;

  r->frame.consts = f;
  /* With nothing to draw, the image is the background at infinite depth: a pass after this one
   * that knows it (r->frame.base_optional) saves the launch and the writing and reading of it. */
  r->frame.base_skipped = r->frame.base_optional && f.nsph == 0 && f.nconv == 0 && f.ntri == 0;
  if (r->frame.base_skipped)
    return 0;
  cl_int cr = clEnqueueWriteBuffer(r->dev.queue, r->frame.objs, CL_FALSE, 0, nobj * sizeof(float),
                                   r->frame.host_objs, 0, NULL, NULL);
  cl_kernel k = os->kernel;
  cr = KERNEL_ARGS(cr, k, 0, {sizeof f, &f}, {sizeof(cl_mem), &r->frame.objs},
                   {sizeof(cl_mem), &r->frame.nodes}, {sizeof(cl_mem), &r->frame.tris},
                   {sizeof(cl_mem), &r->frame.linear}, {sizeof(cl_mem), &r->frame.depth});
  size_t global[2] = {r->frame.pitch / PACKET, r->frame.rows};
  if (render_launch(r, cr, k, global, os->local, "objects", err, errlen) != 0)
    return PROTO_E_DEVICE;
  (void)ran;
  return 0;
}

const render_pass_t render_pass_objects = {.name = "objects",
                                           .layers = LAYER_OBJECTS,
                                           .aovs = 1u << AOV_DEPTH,
                                           .init = objects_init,
                                           .free = objects_free,
                                           .wants = objects_wants,
                                           .run = objects_run,
                                           .reset = objects_reset};
