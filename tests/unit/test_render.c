/*
 * Renderer tests against an independent reference: a brute-force ray caster in double
 * precision written here from SPEC §4 and render_scene.h (camera, object transforms, shapes,
 * near/far, Lambert shading, shadows, tone maps, anti-aliasing by sub-pixel coverage), plus
 * formats, PNG round trips, parameter errors, device choice, kernel loading and OBJ parsing. Scenes
 * are built directly as render_scene_t structs. Exits non-zero on any failure.
 */
#include <math.h>
#include <png.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "check.h"
#include "render.h"

#define W 96
#define H 64

/* ---- Reference ray caster ------------------------------------------------------------------ */

typedef struct ray {
  double o[3], d[3];
} ray_t;

/* The ray of pixel (x, y) exactly as SPEC §4 words it, computed in double. */
static ray_t camera_ray(const rcamera_t *c, int w, int h, double x, double y) {
  double f[3], r[3], u[3], len = 0;
  for (int i = 0; i < 3; i++)
    f[i] = (double)c->target[i] - c->eye[i], len += f[i] * f[i];
  for (int i = 0; i < 3; i++)
    f[i] /= sqrt(len);
  r[0] = f[1] * c->up[2] - f[2] * c->up[1];
  r[1] = f[2] * c->up[0] - f[0] * c->up[2];
  r[2] = f[0] * c->up[1] - f[1] * c->up[0];
  len = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
  for (int i = 0; i < 3; i++)
    r[i] /= len;
  u[0] = r[1] * f[2] - r[2] * f[1];
  u[1] = r[2] * f[0] - r[0] * f[2];
  u[2] = r[0] * f[1] - r[1] * f[0];
  /* The image plane at distance 1 spans tan(fov/2) * (w/h, 1) either side of its centre. */
  double th = tan(c->fov_y * M_PI / 360), a = (double)w / h;
  double px = ((x + 0.5) / w * 2 - 1) * th * a, py = (1 - (y + 0.5) / h * 2) * th;
  ray_t ray;
  len = 0;
  for (int i = 0; i < 3; i++) {
    ray.o[i] = c->eye[i];
    ray.d[i] = f[i] + px * r[i] + py * u[i];
    len += ray.d[i] * ray.d[i];
  }
  for (int i = 0; i < 3; i++)
    ray.d[i] /= sqrt(len);
  return ray;
}

/* 4x4-free affine algebra: world = M * object + p, M = Rz * Ry * Rx * S. */
typedef struct xform {
  double m[3][3], inv[3][3], p[3];
} xform_t;

static void mat_mul(double a[3][3], double b[3][3], double out[3][3]) {
  double t[3][3];
  for (int i = 0; i < 3; i++) {
    for (int j = 0; j < 3; j++)
      t[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
  }
  memcpy(out, t, sizeof t);
}

static void mat_inverse(double m[3][3], double inv[3][3]) {
  double det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) -
               m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
               m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
  for (int i = 0; i < 3; i++) {
    for (int j = 0; j < 3; j++) {
      int a = (j + 1) % 3, b = (j + 2) % 3, c = (i + 1) % 3, d = (i + 2) % 3;
      inv[i][j] = (m[a][c] * m[b][d] - m[a][d] * m[b][c]) / det;
    }
  }
}

static void make_xform(const robject_t *o, xform_t *x) {
  double rad = M_PI / 180;
  double ax = o->rotation[0] * rad, ay = o->rotation[1] * rad, az = o->rotation[2] * rad;
  double rx[3][3] = {{1, 0, 0}, {0, cos(ax), -sin(ax)}, {0, sin(ax), cos(ax)}};
  double ry[3][3] = {{cos(ay), 0, sin(ay)}, {0, 1, 0}, {-sin(ay), 0, cos(ay)}};
  double rz[3][3] = {{cos(az), -sin(az), 0}, {sin(az), cos(az), 0}, {0, 0, 1}};
  int plane = o->shape == SHAPE_PLANE; /* A plane ignores its scale. */
  double s[3][3] = {{plane ? 1 : o->scale[0], 0, 0},
                    {0, plane ? 1 : o->scale[1], 0},
                    {0, 0, plane ? 1 : o->scale[2]}};
  mat_mul(rz, ry, x->m);
  mat_mul(x->m, rx, x->m);
  mat_mul(x->m, s, x->m);
  mat_inverse(x->m, x->inv);
  for (int i = 0; i < 3; i++)
    x->p[i] = o->position[i];
}

static void apply(double m[3][3], const double v[3], double out[3]) {
  for (int i = 0; i < 3; i++)
    out[i] = m[i][0] * v[0] + m[i][1] * v[1] + m[i][2] * v[2];
}

/* Möller-Trumbore in double; the hit distance or INFINITY. */
static double ray_triangle(const double o[3], const double d[3], const double *a, const double *b,
                           const double *c) {
  double e1[3], e2[3], p[3], s[3], q[3];
  for (int i = 0; i < 3; i++)
    e1[i] = b[i] - a[i], e2[i] = c[i] - a[i], s[i] = o[i] - a[i];
  p[0] = d[1] * e2[2] - d[2] * e2[1], p[1] = d[2] * e2[0] - d[0] * e2[2];
  p[2] = d[0] * e2[1] - d[1] * e2[0];
  double det = e1[0] * p[0] + e1[1] * p[1] + e1[2] * p[2];
  if (fabs(det) < 1e-15)
    return INFINITY;
  double u = (s[0] * p[0] + s[1] * p[1] + s[2] * p[2]) / det;
  q[0] = s[1] * e1[2] - s[2] * e1[1], q[1] = s[2] * e1[0] - s[0] * e1[2];
  q[2] = s[0] * e1[1] - s[1] * e1[0];
  double v = (d[0] * q[0] + d[1] * q[1] + d[2] * q[2]) / det;
  double t = (e2[0] * q[0] + e2[1] * q[1] + e2[2] * q[2]) / det;
  return u >= 0 && v >= 0 && u + v <= 1 ? t : INFINITY;
}

/* The regular tetrahedron of render_scene.h as render.c documents it: vertex 0 at +y, vertex 1
 * towards +z, vertices 2 and 3 at +-120 degrees about y from it. */
static void tetra_vertices(double v[4][3]) {
  double r = sqrt(8.0) / 6, y = -1.0 / 6;
  double v0[4][3] = {{0, 0.5, 0},
                     {0, y, r},
                     {r * sin(2 * M_PI / 3), y, r * cos(2 * M_PI / 3)},
                     {-r * sin(2 * M_PI / 3), y, r * cos(2 * M_PI / 3)}};
  memcpy(v, v0, sizeof v0);
}

/* Keeps 't' as the nearest surface point in [lo, hi]. */
static void consider(double t, double lo, double hi, double *best) {
  if (t >= lo && t <= hi && t < *best)
    *best = t;
}

/*
 * The nearest surface point of object 'ob' along 'ray' in [lo, hi], or INFINITY. Every
 * surface point counts (entry or exit), in object space where the shapes are simple.
 */
static double ref_object(const robject_t *ob, const ray_t *ray, double lo, double hi) {
  xform_t x;
  make_xform(ob, &x);
  double w[3], o[3], d[3], best = INFINITY;
  for (int i = 0; i < 3; i++)
    w[i] = ray->o[i] - x.p[i];
  apply(x.inv, w, o);
  apply(x.inv, ray->d, d);
  switch (ob->shape) {
  case SHAPE_SPHERE: {
    double a = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    double b = o[0] * d[0] + o[1] * d[1] + o[2] * d[2];
    double c = o[0] * o[0] + o[1] * o[1] + o[2] * o[2] - 0.25;
    double disc = b * b - a * c;
    if (disc >= 0) {
      consider((-b - sqrt(disc)) / a, lo, hi, &best);
      consider((-b + sqrt(disc)) / a, lo, hi, &best);
    }
    break;
  }
  case SHAPE_BOX: {
    double tin = -INFINITY, tout = INFINITY;
    for (int i = 0; i < 3; i++) {
      if (d[i] == 0) {
        if (fabs(o[i]) > 0.5)
          return INFINITY;
        continue;
      }
      double t0 = (-0.5 - o[i]) / d[i], t1 = (0.5 - o[i]) / d[i];
      tin = fmax(tin, fmin(t0, t1));
      tout = fmin(tout, fmax(t0, t1));
    }
    if (tin <= tout) {
      consider(tin, lo, hi, &best);
      consider(tout, lo, hi, &best);
    }
    break;
  }
  case SHAPE_TETRAHEDRON: {
    double v[4][3];
    tetra_vertices(v);
    for (int k = 0; k < 4; k++)
      consider(ray_triangle(o, d, v[(k + 1) % 4], v[(k + 2) % 4], v[(k + 3) % 4]), lo, hi, &best);
    break;
  }
  case SHAPE_PLANE:
    if (d[1] != 0)
      consider(-o[1] / d[1], lo, hi, &best);
    break;
  case SHAPE_MESH:
    for (uint32_t i = 0; i < ob->mesh->ntri; i++) {
      double v[3][3];
      for (int k = 0; k < 3; k++) {
        double s[3];
        for (int a = 0; a < 3; a++)
          s[a] = ob->mesh->tri[9 * i + 3 * k + a];
        apply(x.m, s, v[k]);
        for (int a = 0; a < 3; a++)
          v[k][a] += x.p[a];
      }
      consider(ray_triangle(ray->o, ray->d, v[0], v[1], v[2]), lo, hi, &best);
    }
    break;
  }
  return best;
}

/* The nearest hit of the scene's objects: distance (or INFINITY) and object index (or -1). */
static double ref_trace(const render_scene_t *s, const ray_t *ray, double lo, double hi, int *id) {
  double best = INFINITY;
  *id = -1;
  for (int i = 0; i < s->nobjects; i++) {
    double t = ref_object(&s->objects[i], ray, lo, hi);
    if (t < best)
      best = t, *id = i;
  }
  return best;
}

/* ---- Renderer helpers ---------------------------------------------------------------------- */

static renderer_t *R;

static render_scene_t base_scene(void) {
  render_scene_t s;
  memset(&s, 0, sizeof s);
  atomic_init(&s.refs, 1);
  s.camera = (rcamera_t){.eye = {2.2f, 1.9f, 4.2f},
                         .target = {0, 0.3f, 0},
                         .up = {0, 1, 0},
                         .fov_y = 40,
                         .near_ = 0.05f,
                         .far_ = 100};
  s.background[0] = 0.2f, s.background[1] = 0.3f, s.background[2] = 0.5f;
  s.light.direction[0] = 0, s.light.direction[1] = 1, s.light.direction[2] = 0;
  s.light.color[0] = s.light.color[1] = s.light.color[2] = 1;
  s.light.intensity = 1;
  s.light.ambient = 0.2f;
  s.tone_map = TONE_NONE;
  return s;
}

/* The render.antialias factor the last render() drew with. */
static int rendered_antialias;

/* Renders and returns the bytes (caller frees), or NULL after reporting the error. */
static unsigned char *render(const render_scene_t *s, int w, int h, proto_format_t fmt, aov_t aov,
                             unsigned layers, size_t *n) {
  render_params_t p = {.width = (uint32_t)w,
                       .height = (uint32_t)h,
                       .format = fmt,
                       .aov = aov,
                       .layers = layers,
                       .png_level = -1};
  render_output_t out;
  char err[1024];
  int rc = renderer_render(R, s, &p, &out, err, sizeof err);
  CHECK(rc == 0, "render failed: %d %s", rc, err);
  if (rc != 0)
    return NULL;
  if (n)
    *n = out.nbytes;
  rendered_antialias = out.antialias;
  return out.bytes;
}

static float *render_depth(const render_scene_t *s, int w, int h) {
  return (float *)render(s, w, h, PROTO_FMT_F32, AOV_DEPTH, LAYER_ALL, NULL);
}

/*
 * Compares the rendered depth of 's' with the reference, pixel by pixel. Pixels may differ only
 * on silhouettes, where a neighbour's reference ray hits another object (or none). Returns
 * the number of reference hits, so callers can check the scene was in view.
 */
static int compare_depth(const render_scene_t *s, const char *what) {
  float *depth = render_depth(s, W, H);
  if (depth == NULL)
    return 0;
  static double ref[W * H];
  static int id[W * H];
  int hits = 0, bad = 0, edge_diffs = 0;
  for (int y = 0; y < H; y++) {
    for (int x = 0; x < W; x++) {
      ray_t ray = camera_ray(&s->camera, W, H, x, y);
      ref[y * W + x] = ref_trace(s, &ray, s->camera.near_, s->camera.far_, &id[y * W + x]);
      hits += id[y * W + x] >= 0;
    }
  }
  for (int y = 0; y < H; y++) {
    for (int x = 0; x < W; x++) {
      double want = ref[y * W + x], got = depth[y * W + x];
      int same = (isinf(want) && isinf(got) && got > 0) ||
                 (isfinite(want) && fabs(got - want) <= 2e-4 * fmax(1, want));
      if (same)
        continue;
      int edge = 0;
      for (int dy = -1; dy <= 1; dy++) {
        for (int dx = -1; dx <= 1; dx++) {
          int nx = x + dx, ny = y + dy;
          if (nx >= 0 && ny >= 0 && nx < W && ny < H && id[ny * W + nx] != id[y * W + x])
            edge = 1;
        }
      }
      edge_diffs += edge;
      if (!edge && bad++ < 5)
        fprintf(stderr, "  %s: pixel (%d, %d): depth %.6f, reference %.6f\n", what, x, y, got,
                want);
    }
  }
  if (getenv("VERBOSE")) /* How much of each scene was in view, when tuning a scene. */
    printf("%s: %d hits, %d silhouette diffs\n", what, hits, edge_diffs);
  CHECK(bad == 0, "%s: %d pixels off the silhouettes differ from the reference", what, bad);
  CHECK(edge_diffs <= W * H / 50, "%s: %d silhouette pixels differ", what, edge_diffs);
  free(depth);
  return hits;
}

/* ---- Tests --------------------------------------------------------------------------------- */

static const char *tmp_dir;

static void test_shapes(void) {
  render_scene_t s = base_scene();
  robject_t ob[2];
  memset(ob, 0, sizeof ob);
  s.objects = ob;
  s.nobjects = 1;

  ob[0] = (robject_t){.shape = SHAPE_SPHERE,
                      .position = {0.2f, 0.4f, -0.1f},
                      .scale = {1.6f, 1.0f, 2.2f},
                      .rotation = {20, 35, -15},
                      .color = {1, 0, 0}};
  CHECK(compare_depth(&s, "ellipsoid") > 300, "ellipsoid not in view");

  ob[0] = (robject_t){.shape = SHAPE_BOX,
                      .position = {-0.3f, 0.5f, 0.2f},
                      .scale = {1.5f, 0.8f, 1.1f},
                      .rotation = {25, -40, 10},
                      .color = {0, 1, 0}};
  CHECK(compare_depth(&s, "box") > 300, "box not in view");

  ob[0] = (robject_t){.shape = SHAPE_TETRAHEDRON,
                      .position = {0.1f, 0.3f, 0},
                      .scale = {2.2f, 1.7f, 2.0f},
                      .rotation = {-15, 70, 20},
                      .color = {0, 0, 1}};
  CHECK(compare_depth(&s, "tetrahedron") > 300, "tetrahedron not in view");

  /* The plane ignores its scale; seen from above and, tilted, from below. */
  ob[0] = (robject_t){.shape = SHAPE_PLANE,
                      .position = {0, -0.5f, 0},
                      .scale = {3, 3, 3},
                      .rotation = {8, 0, -5},
                      .color = {1, 1, 1}};
  CHECK(compare_depth(&s, "plane") > 1000, "plane not in view");
  ob[0].position[1] = 3.5f;
  s.camera.target[1] = 3;
  CHECK(compare_depth(&s, "plane from below") > 1000, "plane not in view from below");
  s.camera.target[1] = 0.3f;

  /* Everything together, so occlusion between shapes is checked too. */
  robject_t all[5] = {
      {.shape = SHAPE_PLANE, .scale = {1, 1, 1}, .color = {1, 1, 1}},
      {.shape = SHAPE_SPHERE, .position = {-0.8f, 0.6f, 0.5f}, .scale = {1.2f, 1.2f, 1.2f}},
      {.shape = SHAPE_BOX,
       .position = {0.6f, 0.5f, -0.3f},
       .scale = {1, 1, 1},
       .rotation = {0, 30, 0}},
      {.shape = SHAPE_TETRAHEDRON, .position = {0.3f, 0.35f, 1.2f}, .scale = {1, 1, 1}},
      {.shape = SHAPE_SPHERE,
       .position = {0, 0, 0},
       .scale = {0.1f, 4, 0.1f},
       .rotation = {0, 0, 60}},
  };
  s.objects = all;
  s.nobjects = 5;
  CHECK(compare_depth(&s, "all shapes") > 3000, "scene not in view");
}

/* Writes an OBJ file into the temp directory and returns its path (static storage). */
static const char *write_file(const char *name, const char *text) {
  static char path[4][512];
  static int k;
  char *p = path[k++ % 4];
  snprintf(p, 512, "%s/%s", tmp_dir, name);
  FILE *f = fopen(p, "w");
  CHECK(f != NULL, "cannot write %s", p);
  if (f) {
    fputs(text, f);
    fclose(f);
  }
  return p;
}

/* A square pyramid written with every face form: a quad, v//vn, v/vt, negative indices. */
static const char pyramid_obj[] = "# pyramid\n"
                                  "o pyramid\n"
                                  "v -0.5 0 -0.5\n"
                                  "v 0.5 0 -0.5\n"
                                  "v 0.5 0.0 0.5\n"
                                  "v -0.5 0 0.5 1.0\n"
                                  "v 0 0.8 0\n"
                                  "vt 0 0\n"
                                  "vn 0 1 0\n"
                                  "s off\n"
                                  "f 1/1/1 2/1/1 3/1/1 4/1/1\n"
                                  "f 1//1 5//1 2//1\n"
                                  "\tf 2/1 5/1 3/1   \r\n"
                                  "f -3 -1 -2\n"
                                  "f 4 5 1 # last side\n";

static void test_mesh(void) {
  char err[512];
  mesh_t *m = mesh_load_obj(write_file("pyramid.obj", pyramid_obj), err, sizeof err);
  CHECK(m != NULL, "pyramid.obj: %s", err);
  if (m == NULL)
    return;
  CHECK(m->ntri == 6, "pyramid has %u triangles, want 6 (a fanned quad and four sides)", m->ntri);
  /* "f -3 -1 -2" after five vertices is v3, v5, v4. */
  const float *t = m->tri + 9 * 4;
  CHECK(t[0] == 0.5f && t[2] == 0.5f && t[4] == 0.8f && t[6] == -0.5f && t[8] == 0.5f,
        "negative indices resolved wrongly");

  render_scene_t s = base_scene();
  robject_t ob[1] = {{.shape = SHAPE_MESH,
                      .position = {0.2f, -0.3f, 0.1f},
                      .scale = {2.5f, 2.0f, 1.8f},
                      .rotation = {10, 25, -5},
                      .color = {1, 1, 0},
                      .mesh = m}};
  s.objects = ob;
  s.nobjects = 1;
  CHECK(compare_depth(&s, "mesh") > 500, "mesh not in view");
  /* The same scene address with the mesh moved: the cached BVH must not be reused. */
  ob[0].position[0] = -0.6f;
  ob[0].rotation[1] = 60;
  CHECK(compare_depth(&s, "mesh moved") > 500, "moved mesh not in view");

  /* A mesh beside analytic shapes, twice, and a larger mesh (a 24x24 grid folded into a
   * wave) so the BVH has depth. */
  robject_t mix[3] = {
      ob[0],
      {.shape = SHAPE_SPHERE, .position = {1, 0.5f, 0}, .scale = {1, 1, 1}},
      {.shape = SHAPE_MESH, .position = {0, 0, -1.5f}, .scale = {3, 1, 3}, .mesh = NULL}};
  size_t cap = 65536, len = 0;
  char *text = malloc(cap);
  for (int j = 0; j <= 24; j++) {
    for (int i = 0; i <= 24; i++)
      len += (size_t)snprintf(text + len, cap - len, "v %g %g %g\n", i / 24.0 - 0.5,
                              0.3 * sin(i * 0.7) * cos(j * 0.5), j / 24.0 - 0.5);
  }
  for (int j = 0; j < 24; j++) {
    for (int i = 0; i < 24; i++) {
      int a = j * 25 + i + 1;
      len += (size_t)snprintf(text + len, cap - len, "f %d %d %d %d\n", a, a + 1, a + 26, a + 25);
    }
  }
  mesh_t *grid = mesh_load_obj(write_file("grid.obj", text), err, sizeof err);
  free(text);
  CHECK(grid != NULL && grid->ntri == 24 * 24 * 2, "grid.obj: %s", grid ? "" : err);
  mix[2].mesh = grid;
  s.objects = mix;
  s.nobjects = grid ? 3 : 2;
  CHECK(compare_depth(&s, "meshes and a sphere") > 1500, "mixed scene not in view");
  mesh_unref(grid);

  /* The renderer holds its own references: the scene's may go first. */
  mesh_t *held = mesh_ref(m);
  CHECK(atomic_load(&m->refs) >= 2, "mesh_ref did not count");
  mesh_unref(held);
  mesh_unref(m);
}

static void test_obj_errors(void) {
  char err[512];
  mesh_t *m = mesh_load_obj(write_file("bad1.obj", "v 0 0 0\nv 1 0 0\nf 1 2 9\n"), err, sizeof err);
  CHECK(m == NULL && strstr(err, "bad1.obj:3:") && strstr(err, "9"), "got \"%s\"", err);
  m = mesh_load_obj(write_file("bad2.obj", "# x\nv 0 0\n"), err, sizeof err);
  CHECK(m == NULL && strstr(err, "bad2.obj:2:"), "got \"%s\"", err);
  m = mesh_load_obj(write_file("bad3.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n"), err, sizeof err);
  CHECK(m == NULL && strstr(err, "bad3.obj:4:"), "got \"%s\"", err);
  m = mesh_load_obj(write_file("bad4.obj", "v 0 0 0\nf 0 1 1\n"), err, sizeof err);
  CHECK(m == NULL && strstr(err, "bad4.obj:2:"), "got \"%s\"", err);
  m = mesh_load_obj(write_file("bad5.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x\n"), err,
                    sizeof err);
  CHECK(m == NULL && strstr(err, "bad5.obj:4:"), "got \"%s\"", err);
  m = mesh_load_obj(write_file("empty.obj", "v 0 0 0\n"), err, sizeof err);
  CHECK(m == NULL && strstr(err, "empty.obj"), "got \"%s\"", err);
  m = mesh_load_obj("/nonexistent/volfx.obj", err, sizeof err);
  CHECK(m == NULL && strstr(err, "/nonexistent/volfx.obj"), "got \"%s\"", err);

  /* A sparse file over 64 MiB is refused before it is read. */
  const char *big = write_file("big.obj", "");
  CHECK(truncate(big, (65 << 20)) == 0, "truncate failed");
  m = mesh_load_obj(big, err, sizeof err);
  CHECK(m == NULL && strstr(err, "big.obj") && strstr(err, "limit"), "got \"%s\"", err);
  unlink(big);
}

/* A sphere placed where SPEC's ray of pixel (px, py) points shows up at that pixel only. */
static void camera_case(const rcamera_t *cam, int px, int py) {
  render_scene_t s = base_scene();
  s.camera = *cam;
  ray_t ray = camera_ray(cam, W, H, px, py);
  robject_t ob = {.shape = SHAPE_SPHERE, .scale = {0.04f, 0.04f, 0.04f}};
  for (int i = 0; i < 3; i++)
    ob.position[i] = (float)(ray.o[i] + 6 * ray.d[i]);
  s.objects = &ob;
  s.nobjects = 1;
  float *depth = render_depth(&s, W, H);
  if (depth == NULL)
    return;
  int nhit = 0;
  for (int i = 0; i < W * H; i++)
    nhit += isfinite(depth[i]);
  CHECK(fabs(depth[py * W + px] - 5.98) < 2e-3, "pixel (%d, %d) depth %f, want 5.98", px, py,
        depth[py * W + px]);
  CHECK(nhit == 1, "%d pixels see the marker sphere, want 1", nhit);
  free(depth);
}

static void test_camera(void) {
  rcamera_t a = {.eye = {1, 2, 3},
                 .target = {-1, 0.5f, -2},
                 .up = {0, 1, 0},
                 .fov_y = 50,
                 .near_ = 0.1f,
                 .far_ = 50};
  camera_case(&a, 70, 13);
  camera_case(&a, 5, 60);
  /* Looking down with +z as up: right = forward x up decides the mirror sense. */
  rcamera_t b = {.eye = {0, 5, 0},
                 .target = {0, 0, 0.001f},
                 .up = {0, 0, 1},
                 .fov_y = 30,
                 .near_ = 0.1f,
                 .far_ = 50};
  camera_case(&b, 10, 50);
  camera_case(&b, 90, 2);

  /* render_params_t.camera overrides the scene's camera. */
  render_scene_t s = base_scene();
  robject_t ob = {.shape = SHAPE_SPHERE, .scale = {2, 2, 2}};
  s.objects = &ob;
  s.nobjects = 1;
  rcamera_t away = s.camera;
  away.target[0] = 20, away.target[1] = 2.5f, away.target[2] = 6;
  render_params_t p = {.width = W,
                       .height = H,
                       .format = PROTO_FMT_F32,
                       .aov = AOV_DEPTH,
                       .layers = LAYER_ALL,
                       .camera = &away};
  render_output_t out;
  char err[256];
  CHECK(renderer_render(R, &s, &p, &out, err, sizeof err) == 0, "%s", err);
  int nhit = 0;
  for (int i = 0; i < W * H; i++)
    nhit += isfinite(((float *)out.bytes)[i]);
  CHECK(nhit == 0, "the override camera looks away, yet %d pixels hit", nhit);
  free(out.bytes);
}

/* Checks pixel (x, y) of an RGBA float frame against 'want'. */
static void check_rgb(const float *px, const double want[3], const char *what, int x, int y) {
  for (int c = 0; c < 3; c++)
    CHECK(fabs(px[c] - want[c]) <= 1e-4 + 1e-3 * want[c], "%s at (%d, %d) channel %d: %f, want %f",
          what, x, y, c, px[c], want[c]);
  CHECK(px[3] == 1.0f, "%s: alpha %f on an object", what, px[3]);
}

static void test_lambert(void) {
  render_scene_t s = base_scene();
  s.camera = (rcamera_t){.eye = {0, 0, 5},
                         .target = {0, 0, 0},
                         .up = {0, 1, 0},
                         .fov_y = 40,
                         .near_ = 0.1f,
                         .far_ = 100};
  double l[3] = {0.6, 0.5, 0.62};
  double ll = sqrt(l[0] * l[0] + l[1] * l[1] + l[2] * l[2]);
  for (int i = 0; i < 3; i++)
    s.light.direction[i] = (float)(l[i] / ll), l[i] = s.light.direction[i];
  s.light.color[0] = 1, s.light.color[1] = 0.9f, s.light.color[2] = 0.7f;
  s.light.intensity = 1.7f;
  s.light.ambient = 0.15f;
  robject_t ob = {.shape = SHAPE_SPHERE, .scale = {2.5f, 2.5f, 2.5f}, .color = {0.8f, 0.5f, 0.3f}};
  s.objects = &ob;
  s.nobjects = 1;
  float *img = (float *)render(&s, W, H, PROTO_FMT_RGBAF32, AOV_BEAUTY, LAYER_ALL, NULL);
  if (img == NULL)
    return;
  /* A lit pixel, one near the terminator and one facing away. */
  int pts[3][2] = {{60, 20}, {48, 32}, {33, 45}};
  int lit = 0, dark = 0;
  for (int k = 0; k < 3; k++) {
    int x = pts[k][0], y = pts[k][1];
    ray_t ray = camera_ray(&s.camera, W, H, x, y);
    int id;
    double t = ref_trace(&s, &ray, 0.1, 100, &id), n[3], len = 0;
    CHECK(id == 0, "pixel (%d, %d) misses the sphere", x, y);
    for (int i = 0; i < 3; i++)
      n[i] = ray.o[i] + t * ray.d[i], len += n[i] * n[i];
    double ndl = fmax(0, (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]) / sqrt(len));
    lit += ndl > 0.3, dark += ndl == 0;
    double want[3];
    for (int c = 0; c < 3; c++)
      want[c] =
          ob.color[c] * s.light.color[c] * s.light.intensity * ndl + ob.color[c] * s.light.ambient;
    check_rgb(img + 4 * (y * W + x), want, "lambert", x, y);
  }
  CHECK(lit >= 1 && dark >= 1, "test points should include lit and unlit ones (%d, %d)", lit, dark);
  free(img);
}

static void test_shadow(void) {
  render_scene_t s = base_scene();
  s.camera = (rcamera_t){.eye = {0, 6, 5},
                         .target = {0, 0, 0},
                         .up = {0, 1, 0},
                         .fov_y = 45,
                         .near_ = 0.1f,
                         .far_ = 100};
  double l[3] = {0.3, 1, 0.2}, ll = sqrt(0.09 + 1 + 0.04);
  for (int i = 0; i < 3; i++)
    s.light.direction[i] = (float)(l[i] / ll), l[i] = s.light.direction[i];
  s.light.intensity = 1.3f;
  s.light.ambient = 0.25f;
  robject_t ob[2] = {
      {.shape = SHAPE_PLANE, .scale = {1, 1, 1}, .color = {0.6f, 0.5f, 0.4f}},
      {.shape = SHAPE_BOX,
       .position = {0, 1.2f, 0},
       .scale = {2.5f, 0.3f, 2.0f},
       .rotation = {0, 20, 0},
       .color = {1, 1, 1}},
  };
  s.objects = ob;
  s.nobjects = 2;
  float *img = (float *)render(&s, W, H, PROTO_FMT_RGBAF32, AOV_BEAUTY, LAYER_ALL, NULL);
  if (img == NULL)
    return;
  /* Classify floor pixels by a reference shadow ray; check those whose neighbours agree. */
  static int cls[W * H]; /* -1 not floor, 0 lit floor, 1 shadowed floor */
  for (int y = 0; y < H; y++) {
    for (int x = 0; x < W; x++) {
      ray_t ray = camera_ray(&s.camera, W, H, x, y);
      int id;
      double t = ref_trace(&s, &ray, 0.1, 100, &id);
      cls[y * W + x] = -1;
      if (id != 0)
        continue;
      ray_t sh;
      for (int i = 0; i < 3; i++)
        sh.o[i] = ray.o[i] + t * ray.d[i] + 1e-9 * (i == 1), sh.d[i] = l[i];
      cls[y * W + x] = isfinite(ref_object(&ob[1], &sh, 0, INFINITY));
    }
  }
  int nlit = 0, nshadow = 0;
  double lit_sum = 0, shadow_sum = 0;
  for (int y = 1; y < H - 1; y++) {
    for (int x = 1; x < W - 1; x++) {
      int c = cls[y * W + x], same = 1;
      for (int d = 0; d < 9; d++)
        same &= cls[(y + d / 3 - 1) * W + x + d % 3 - 1] == c;
      if (c < 0 || !same)
        continue;
      double want[3];
      for (int k = 0; k < 3; k++)
        want[k] = ob[0].color[k] * (s.light.intensity * (c ? 0 : l[1]) + s.light.ambient);
      const float *px = img + 4 * (y * W + x);
      check_rgb(px, want, c ? "shadowed floor" : "lit floor", x, y);
      if (c)
        nshadow++, shadow_sum += px[0];
      else
        nlit++, lit_sum += px[0];
    }
  }
  CHECK(nlit > 100 && nshadow > 50, "too few floor pixels: %d lit, %d shadowed", nlit, nshadow);
  if (nlit && nshadow) {
    /* Red: lit - shadowed = colour * intensity * (n.l) with n = +y. */
    double diff = lit_sum / nlit - shadow_sum / nshadow;
    double want = ob[0].color[0] * s.light.intensity * l[1];
    CHECK(fabs(diff - want) < 1e-3, "shadow darkens by %f, want %f", diff, want);
  }
  free(img);
}

static void test_clipping(void) {
  render_scene_t s = base_scene();
  s.camera = (rcamera_t){.eye = {0, 0, 5},
                         .target = {0, 0, 0},
                         .up = {0, 1, 0},
                         .fov_y = 40,
                         .near_ = 0.1f,
                         .far_ = 100};
  robject_t ob[2] = {
      {.shape = SHAPE_SPHERE, .scale = {2, 2, 2}},
      {.shape = SHAPE_BOX, .position = {0, 0, -30}, .scale = {30, 30, 1}},
  };
  s.objects = ob;
  s.nobjects = 2;
  struct {
    float near_, far_;
    double centre; /* Depth of the centre pixel. */
  } cases[] = {
      {0.1f, 100, 4.0},       /* The sphere's front. */
      {4.5f, 100, 6.0},       /* Near cuts the sphere: its far side shows. */
      {6.5f, 100, 34.5},      /* Past the sphere: the wall. */
      {0.1f, 3.5f, INFINITY}, /* Far ends before everything. */
      {6.5f, 30, INFINITY},   /* Between the sphere and the wall. */
  };
  for (size_t k = 0; k < sizeof cases / sizeof cases[0]; k++) {
    s.camera.near_ = cases[k].near_, s.camera.far_ = cases[k].far_;
    char what[64];
    snprintf(what, sizeof what, "near %g far %g", cases[k].near_, cases[k].far_);
    compare_depth(&s, what);
    float *d = render_depth(&s, W, H);
    if (d == NULL)
      continue;
    /* Pixel (48, 32) is half a pixel off the axis: close enough to the centre value. */
    double got = d[32 * W + 48], want = cases[k].centre;
    CHECK(isinf(want) ? isinf(got) : fabs(got - want) < 2e-3, "%s: centre depth %f, want %f", what,
          got, want);
    free(d);
  }
}

static void test_layers_and_background(void) {
  render_scene_t s = base_scene();
  robject_t ob = {.shape = SHAPE_PLANE, .scale = {1, 1, 1}, .color = {1, 1, 1}};
  s.objects = &ob;
  s.nobjects = 1;
  for (int transparent = 0; transparent <= 1; transparent++) {
    s.transparent_background = transparent;
    float *img =
        (float *)render(&s, W, H, PROTO_FMT_RGBAF32, AOV_BEAUTY, LAYER_ALL & ~LAYER_OBJECTS, NULL);
    float *d = (float *)render(&s, W, H, PROTO_FMT_F32, AOV_DEPTH, LAYER_VOLUMES, NULL);
    if (img == NULL || d == NULL) {
      free(img), free(d);
      return;
    }
    int bad = 0, finite = 0;
    for (int i = 0; i < W * H; i++) {
      const float *p = img + 4 * i;
      /* A transparent background is transparent black (premultiplied). */
      float k = transparent ? 0.0f : 1.0f;
      bad += p[0] != k * s.background[0] || p[1] != k * s.background[1] ||
             p[2] != k * s.background[2] || p[3] != k;
      finite += !(isinf(d[i]) && d[i] > 0);
    }
    CHECK(bad == 0, "%d pixels are not the background without the objects layer", bad);
    CHECK(finite == 0, "%d depth pixels are not +inf without the objects layer", finite);
    free(img), free(d);
  }
  /* With the layer, the floor covers the lower half; sky pixels keep the background. */
  s.transparent_background = 1;
  float *img = (float *)render(&s, W, H, PROTO_FMT_RGBAF32, AOV_BEAUTY, LAYER_ALL, NULL);
  if (img) {
    CHECK(img[4 * (H - 1) * W + 3] == 1.0f && img[3] == 0.0f, "alpha: floor %f, sky %f",
          img[4 * (H - 1) * W + 3], img[3]);
    free(img);
  }
}

/* sRGB encoding and the tone maps as render_scene.h and the kernels describe them, in double. */
static int ref_byte(double x, tone_map_t op) {
  x = fmax(x, 0);
  if (op == TONE_REINHARD)
    x = x / (1 + x);
  else if (op == TONE_ACES)
    x = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14);
  x = fmin(x, 1);
  x = x <= 0.0031308 ? 12.92 * x : 1.055 * pow(x, 1 / 2.4) - 0.055;
  return (int)floor(x * 255 + 0.5);
}

static void test_tonemap_and_formats(void) {
  render_scene_t s = base_scene();
  s.light.intensity = 3;
  s.light.direction[0] = 0.6f, s.light.direction[1] = 0.8f, s.light.direction[2] = 0;
  robject_t ob[3] = {
      {.shape = SHAPE_PLANE, .scale = {1, 1, 1}, .color = {0.9f, 0.6f, 0.2f}},
      {.shape = SHAPE_SPHERE,
       .position = {0, 0.8f, 0},
       .scale = {1.6f, 1.6f, 1.6f},
       .color = {0.3f, 0.9f, 1.0f}},
      {.shape = SHAPE_BOX,
       .position = {-1.5f, 0.4f, 0},
       .scale = {0.8f, 0.8f, 0.8f},
       .color = {0.05f, 0.02f, 0.01f}},
  };
  s.objects = ob;
  s.nobjects = 3;
  tone_map_t ops[3] = {TONE_NONE, TONE_REINHARD, TONE_ACES};
  float exposures[3] = {0.7f, -1.5f, 0};
  for (int k = 0; k < 3; k++) {
    s.tone_map = ops[k];
    s.exposure = exposures[k];
    size_t nf, n8;
    float *lin = (float *)render(&s, W, H, PROTO_FMT_RGBAF32, AOV_BEAUTY, LAYER_ALL, &nf);
    unsigned char *rgba = render(&s, W, H, PROTO_FMT_RGBA8, AOV_BEAUTY, LAYER_ALL, &n8);
    CHECK(nf == 16u * W * H && n8 == 4u * W * H, "sizes %zu and %zu", nf, n8);
    if (lin == NULL || rgba == NULL) {
      free(lin), free(rgba);
      continue;
    }
    int off = 0, worst = 0;
    double scale = pow(2, s.exposure);
    for (int i = 0; i < W * H * 4; i++) {
      int want = i % 4 == 3 ? (int)floor(fmin(fmax(lin[i], 0), 1) * 255 + 0.5)
                            : ref_byte(lin[i] * scale, s.tone_map);
      int d = abs(want - rgba[i]);
      off += d != 0;
      worst = d > worst ? d : worst;
    }
    CHECK(worst <= 1 && off < W * H * 4 / 100, "tone map %d: %d bytes off, worst by %d", k, off,
          worst);

    /* The PNG decodes to exactly the rgba8 bytes, at the fast default and at level 6. */
    for (int level = -1; level <= 6; level += 7) {
      render_params_t p = {.width = W,
                           .height = H,
                           .format = PROTO_FMT_PNG,
                           .layers = LAYER_ALL,
                           .png_level = level};
      render_output_t out;
      char err[256];
      CHECK(renderer_render(R, &s, &p, &out, err, sizeof err) == 0, "png: %s", err);
      png_image img;
      memset(&img, 0, sizeof img);
      img.version = PNG_IMAGE_VERSION;
      unsigned char *dec = malloc(4 * W * H);
      int ok = png_image_begin_read_from_memory(&img, out.bytes, out.nbytes);
      img.format = PNG_FORMAT_RGBA;
      ok = ok && img.width == W && img.height == H &&
           png_image_finish_read(&img, NULL, dec, 0, NULL);
      CHECK(ok, "png does not decode: %s", img.message);
      CHECK(!ok || memcmp(dec, rgba, 4 * W * H) == 0, "png differs from the rgba8 frame");
      const char *names[4] = {"objects", "tonemap", "readback", "encode"};
      CHECK(out.npasses == 4, "png frame has %d passes", out.npasses);
      double sum = 0;
      for (int i = 0; i < out.npasses && i < 4; i++) {
        CHECK(strcmp(out.passes[i].name, names[i]) == 0, "pass %d is %s", i, out.passes[i].name);
        CHECK(out.passes[i].ms >= 0, "pass %s took %f ms", names[i], out.passes[i].ms);
        sum += out.passes[i].ms;
      }
      CHECK(out.total_ms >= sum * 0.999, "total %f < sum of passes %f", out.total_ms, sum);
      png_image_free(&img);
      free(dec);
      free(out.bytes);
    }
    free(lin);
    free(rgba);
  }

  size_t n;
  float *d = (float *)render(&s, W, H, PROTO_FMT_F32, AOV_DEPTH, LAYER_ALL, &n);
  CHECK(n == 4u * W * H, "depth is %zu bytes", n);
  free(d);
  float *wave = (float *)render(&s, 33, 17, PROTO_FMT_F32, AOV_WAVE_H, LAYER_ALL, &n);
  CHECK(n == 4u * 33 * 17, "wave_h is %zu bytes", n);
  int nonzero = 0;
  for (int i = 0; wave && i < 33 * 17; i++)
    nonzero += wave[i] != 0;
  CHECK(nonzero == 0, "wave_h has %d non-zero values without waves", nonzero);
  free(wave);

  /* Odd sizes, growing and shrinking the buffers. */
  int sizes[][2] = {{1, 1}, {257, 3}, {5, 300}, {W, H}};
  for (int k = 0; k < 4; k++) {
    unsigned char *b =
        render(&s, sizes[k][0], sizes[k][1], PROTO_FMT_RGBA8, AOV_BEAUTY, LAYER_ALL, &n);
    CHECK(n == 4u * sizes[k][0] * sizes[k][1], "%dx%d rgba8 is %zu bytes", sizes[k][0], sizes[k][1],
          n);
    free(b);
  }
  compare_depth(&s, "after resizing");
}

/* The colour operator of ref_byte alone, and the sRGB byte of a value it made. */
static double ref_tone(double x, tone_map_t op) {
  x = fmax(x, 0);
  if (op == TONE_REINHARD)
    x = x / (1 + x);
  else if (op == TONE_ACES)
    x = x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14);
  return fmin(x, 1);
}

static int ref_srgb_byte(double x) {
  x = x <= 0.0031308 ? 12.92 * x : 1.055 * pow(x, 1 / 2.4) - 0.055;
  return (int)floor(x * 255 + 0.5);
}

/* Renders with render.antialias 'n'; returns the bytes and sets '*used' to the factor drawn. */
static void *render_aa(render_scene_t *s, int n, int w, int h, proto_format_t fmt, aov_t aov,
                       int *used) {
  s->antialias = n;
  rendered_antialias = 0;
  void *bytes = render(s, w, h, fmt, aov, LAYER_ALL, NULL);
  s->antialias = 0;
  *used = bytes ? rendered_antialias : 0;
  return bytes;
}

/*
 * render.antialias: black objects before a white background, unlit, show in each pixel the
 * fraction of its n x n sub-pixel rays (the reference caster's, at the centres of an n W x n H
 * frame's pixels) that miss them; a lit, tone-mapped scene gives the mean of the n W x n H
 * frame's linear pixels (rgbaf32), and the sRGB byte of the mean of their tone-mapped values
 * (rgba8); depth takes one sample; a factor that would pass the renderer's side is lowered.
 */
static void test_antialias(void) {
  render_scene_t s = base_scene();
  s.background[0] = s.background[1] = s.background[2] = 1;
  s.light.intensity = 0, s.light.ambient = 0;
  robject_t ob[2] = {
      {.shape = SHAPE_SPHERE, .position = {0.6f, 0.5f, 0}, .scale = {1.2f, 1.2f, 1.2f}},
      {.shape = SHAPE_BOX,
       .position = {-0.9f, 0.3f, 0.2f},
       .scale = {0.9f, 0.7f, 0.8f},
       .rotation = {10, 35, 0}},
  };
  s.objects = ob, s.nobjects = 2;
  for (int n = 2; n <= 3; n++) {
    int used;
    float *img = render_aa(&s, n, W, H, PROTO_FMT_RGBAF32, AOV_BEAUTY, &used);
    CHECK(used == n, "antialias %d drew %d", n, used);
    int partial = 0, one_off = 0, bad = 0;
    for (int y = 0; img && y < H; y++)
      for (int x = 0; x < W; x++) {
        int miss = 0, id;
        for (int sy = 0; sy < n; sy++)
          for (int sx = 0; sx < n; sx++) {
            ray_t ray = camera_ray(&s.camera, n * W, n * H, n * x + sx, n * y + sy);
            ref_trace(&s, &ray, s.camera.near_, s.camera.far_, &id);
            miss += id < 0;
          }
        double want = (double)miss / (n * n), got = img[4 * (y * W + x)];
        partial += miss > 0 && miss < n * n;
        double d = fabs(got - want);
        /* A sub-pixel ray that grazes an edge may go either way in float: one sample's worth. */
        one_off += d > 1e-5 && fabs(d - 1.0 / (n * n)) < 1e-5;
        if (d > 1e-5 && fabs(d - 1.0 / (n * n)) >= 1e-5 && bad++ < 5)
          fprintf(stderr, "  antialias %d: pixel (%d, %d) %.5f, coverage %.5f\n", n, x, y, got,
                  want);
      }
    CHECK(bad == 0, "antialias %d: %d pixels off the sub-pixel coverage", n, bad);
    CHECK(one_off <= W * H / 200, "antialias %d: %d pixels one sample off", n, one_off);
    CHECK(partial > 50, "antialias %d: only %d pixels partly covered", n, partial);
    printf("antialias %d: %d partly covered pixels match their coverage, %d by one sample less\n",
           n, partial - one_off, one_off);
    free(img);
  }

  /* Lit and tone-mapped: against the larger frame's pixels, averaged here. */
  s.light.intensity = 2.5f, s.light.ambient = 0.2f;
  s.light.direction[0] = 0.5f, s.light.direction[1] = 0.7f, s.light.direction[2] = 0.5f;
  ob[0].color[0] = 0.9f, ob[0].color[1] = 0.4f, ob[0].color[2] = 0.2f;
  ob[1].color[0] = 0.2f, ob[1].color[1] = 0.6f, ob[1].color[2] = 0.9f;
  s.tone_map = TONE_ACES, s.exposure = 0.4f;
  const int n = 2;
  int used;
  float *big = render_aa(&s, 1, n * W, n * H, PROTO_FMT_RGBAF32, AOV_BEAUTY, &used);
  float *lin = render_aa(&s, n, W, H, PROTO_FMT_RGBAF32, AOV_BEAUTY, &used);
  unsigned char *rgba = render_aa(&s, n, W, H, PROTO_FMT_RGBA8, AOV_BEAUTY, &used);
  double worst_lin = 0, scale = pow(2, s.exposure);
  int worst_byte = 0, off = 0;
  for (int y = 0; big && lin && rgba && y < H; y++)
    for (int x = 0; x < W; x++)
      for (int c = 0; c < 4; c++) {
        double mean = 0, tone = 0;
        for (int sy = 0; sy < n; sy++)
          for (int sx = 0; sx < n; sx++) {
            double v = big[4 * ((size_t)(n * y + sy) * n * W + n * x + sx) + c];
            mean += v / (n * n), tone += ref_tone(v * scale, s.tone_map) / (n * n);
          }
        int i = 4 * (y * W + x) + c;
        worst_lin = fmax(worst_lin, fabs(lin[i] - mean) / fmax(1, mean));
        int want = c == 3 ? (int)floor(fmin(fmax(mean, 0), 1) * 255 + 0.5) : ref_srgb_byte(tone);
        int d = abs(want - rgba[i]);
        off += d != 0;
        worst_byte = d > worst_byte ? d : worst_byte;
      }
  CHECK(worst_lin < 1e-5, "antialias rgbaf32: %.2g from the mean of the larger frame", worst_lin);
  CHECK(worst_byte <= 1 && off < W * H * 4 / 100, "antialias rgba8: %d bytes off, worst by %d", off,
        worst_byte);
  free(big), free(lin), free(rgba);

  /* Depth takes one sample per pixel whatever the factor. */
  float *d1 = render_aa(&s, 1, W, H, PROTO_FMT_F32, AOV_DEPTH, &used);
  float *d3 = render_aa(&s, 3, W, H, PROTO_FMT_F32, AOV_DEPTH, &used);
  CHECK(used == 1, "depth drawn with antialias %d", used);
  CHECK(d1 && d3 && memcmp(d1, d3, sizeof(float) * W * H) == 0, "depth changes with antialias");
  free(d1), free(d3);

  /* A row of 5462 pixels: 4 or 3 times that would pass the renderer's largest side (16384). */
  unsigned char *row = render_aa(&s, 4, 5462, 1, PROTO_FMT_RGBA8, AOV_BEAUTY, &used);
  CHECK(used == 2, "a 5462-pixel row was drawn with antialias %d, not 2", used);
  free(row);
}

static void test_bad_params(void) {
  render_scene_t s = base_scene();
  struct {
    proto_format_t fmt;
    aov_t aov;
    const char *fname, *aname;
  } bad[] = {
      {PROTO_FMT_F32, AOV_BEAUTY, "f32", "beauty"},
      {PROTO_FMT_U8, AOV_BEAUTY, "u8", "beauty"},
      {PROTO_FMT_PNG, AOV_DEPTH, "png", "depth"},
      {PROTO_FMT_RGBA8, AOV_DEPTH, "rgba8", "depth"},
      {PROTO_FMT_RGBAF32, AOV_WAVE_H, "rgbaf32", "wave_h"},
  };
  for (size_t k = 0; k < sizeof bad / sizeof bad[0]; k++) {
    render_params_t p = {
        .width = 8, .height = 8, .format = bad[k].fmt, .aov = bad[k].aov, .layers = LAYER_ALL};
    render_output_t out;
    char err[256] = "";
    int rc = renderer_render(R, &s, &p, &out, err, sizeof err);
    CHECK(rc == PROTO_E_INVALID_PARAMS, "%s/%s gave %d", bad[k].fname, bad[k].aname, rc);
    CHECK(strstr(err, bad[k].fname) && strstr(err, bad[k].aname), "message \"%s\"", err);
    CHECK(out.bytes == NULL, "bytes returned on error");
  }
  render_params_t p = {.width = 0, .height = 8, .format = PROTO_FMT_RGBA8, .layers = LAYER_ALL};
  render_output_t out;
  char err[256];
  CHECK(renderer_render(R, &s, &p, &out, err, sizeof err) == PROTO_E_INVALID_PARAMS,
        "zero width accepted");
  p.width = 8;
  s.camera.up[0] = 0, s.camera.up[1] = 0, s.camera.up[2] = 0;
  CHECK(renderer_render(R, &s, &p, &out, err, sizeof err) == PROTO_E_INVALID_PARAMS,
        "a zero up vector accepted");
}

static void test_devices_and_kernels(void) {
  char err[8192];
  renderer_t *r = NULL;
  renderer_opts_t o = {.device = "bogus"};
  CHECK(renderer_create(&o, &r, err, sizeof err) != 0 && r == NULL && strstr(err, "bogus"),
        "device \"bogus\": %s", err);
  o.device = "99";
  CHECK(renderer_create(&o, &r, err, sizeof err) != 0 && strstr(err, "99"), "device 99: %s", err);
  o.device = "0";
  CHECK(renderer_create(&o, &r, err, sizeof err) == 0, "device 0: %s", err);
  renderer_destroy(r);
  r = NULL;
  o.device = "gpu";
  if (renderer_create(&o, &r, err, sizeof err) == 0)
    renderer_destroy(r), r = NULL;
  else
    CHECK(strstr(err, "gpu") != NULL, "device gpu: %s", err);

  /* Kernels from a directory: the repository's own (ctest runs this from the repository
   * root), then a broken set whose build log must come back. */
  o.device = "cpu";
  o.kernels_dir = "kernels";
  if (access("kernels/objects.cl", R_OK) == 0) {
    CHECK(renderer_create(&o, &r, err, sizeof err) == 0, "kernels from kernels/: %s", err);
    renderer_destroy(r);
    r = NULL;
  } else {
    printf("kernels/ is not in the working directory: loading it is not tested\n");
  }
  char dir[512];
  snprintf(dir, sizeof dir, "%s/kernels", tmp_dir);
  mkdir(dir, 0700);
  write_file("kernels/common.h", "/* empty */\n");
  write_file("kernels/tonemap.cl", "__kernel void tonemap(void) {}\n");
  write_file("kernels/objects.cl", "#include \"common.h\"\n__kernel void objects(void) {\n"
                                   "  undeclared_thing = 1;\n}\n");
  o.kernels_dir = dir;
  CHECK(renderer_create(&o, &r, err, sizeof err) != 0 && r == NULL, "broken kernels built");
  CHECK(strstr(err, "objects.cl") && strstr(err, "undeclared_thing"),
        "the build log is missing from \"%s\"", err);
}

/* The format and layer tables agree with the protocol's names and with themselves. */
static void test_tables(void) {
  int n = 0;
  for (const render_format_t *f = render_format_table; f->name; f++, n++) {
    CHECK(render_format_names[n] && strcmp(render_format_names[n], f->name) == 0,
          "render_format_names[%d] is \"%s\"", n, f->name);
    CHECK(proto_format_name(f->id) && strcmp(proto_format_name(f->id), f->name) == 0,
          "format %s is the protocol's", f->name);
    CHECK(render_format_find(f->name) == f && render_format_get(f->id) == f, "%s found", f->name);
    CHECK(f->aovs != 0 && f->bytes_per_pixel > 0 && f->mime, "%s is complete", f->name);
    CHECK(render_format_bound(f, 64, 32) >= 64 * 32 * f->bytes_per_pixel, "%s bound", f->name);
  }
  CHECK(render_format_names[n] == NULL, "as many names as formats");
  CHECK(render_format_get(PROTO_FMT_U8) == NULL, "u8 is no frame format");
  for (int a = 0; a < AOV_COUNT; a++)
    CHECK(render_aov_parse(render_aov_names[a]) == a, "aov %s", render_aov_names[a]);
  CHECK(render_aov_parse("nope") == -1, "unknown aov");
  int layers = 0;
  while (render_layer_names[layers])
    layers++;
  CHECK(layers == RENDER_LAYER_COUNT && LAYER_ALL == (1u << layers) - 1, "%d layers", layers);
  CHECK(strcmp(render_layer_names[0], "objects") == 0 && LAYER_OBJECTS == 1 &&
            strcmp(render_layer_names[4], "waves") == 0 && LAYER_WAVES == 1 << 4,
        "layer bits follow the names");
}

int main(void) {
  char tmpl[] = "/tmp/volfx-test-render-XXXXXX";
  tmp_dir = mkdtemp(tmpl);
  if (tmp_dir == NULL) {
    perror("mkdtemp");
    return 1;
  }
  char err[8192];
  if (renderer_create(NULL, &R, err, sizeof err) != 0) {
    fprintf(stderr, "renderer_create: %s\n", err);
    return 1;
  }
  printf("device: %s / %s\n", renderer_platform_name(R), renderer_device_name(R));

  test_shapes();
  test_mesh();
  test_obj_errors();
  test_camera();
  test_lambert();
  test_shadow();
  test_clipping();
  test_layers_and_background();
  test_tonemap_and_formats();
  test_antialias();
  test_bad_params();
  test_tables();
  test_devices_and_kernels();

  renderer_destroy(R);
  char cmd[600];
  snprintf(cmd, sizeof cmd, "rm -rf '%s'", tmp_dir);
  if (system(cmd) != 0)
    fprintf(stderr, "could not remove %s\n", tmp_dir);
  printf("%d checks, %d failed\n", checks, failures);
  return failures ? 1 : 0;
}
