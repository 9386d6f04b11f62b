/*
 * The "game_depth" pass (kernels/game_depth.cl): a client's depth buffer of its own picture
 * (render_params_t.depth) joined into the objects' depth, so that the fluid, the volumes, the
 * cloud and the waves stop at the game's geometry. Also the conversion of the client's values
 * (view-space, ray distance, or OpenGL or D3D NDC depth) to view-space depth on the host.
 */
#include <math.h>

#include "render_internal.h"

const char *const render_depth_convention_names[] = {"linear", "ray", "ndc_gl", "ndc_01", NULL};

double render_depth_view_z(render_depth_convention_t conv, double d, double near_, double far_,
                           double cos_axis) {
  if (!isfinite(d))
    return NAN;
  switch (conv) {
  case DEPTH_LINEAR:
  case DEPTH_RAY:
    if (d < 0)
      return NAN;
    if (far_ > 0 && d >= far_)
      return INFINITY;
    return conv == DEPTH_RAY ? d * cos_axis : d;
  case DEPTH_NDC_GL:
    if (d < -1 || d > 1)
      return NAN;
    d = (d + 1) / 2; /* The [0, 1] depth it maps to, which follows. */
    __attribute__((fallthrough));
  case DEPTH_NDC_01:
    if (d < 0 || d > 1)
      return NAN;
    if (d == 1)
      return INFINITY; /* The far plane: what a cleared depth buffer holds. */
    return near_ * far_ / (far_ - d * (far_ - near_));
  default:
    return NAN;
  }
}

/* The little-endian f32 at 'p'. */
static float le_f32(const unsigned char *p) {
  uint32_t u = (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
  float v;
  memcpy(&v, &u, sizeof v);
  return v;
}

render_depth_t *render_depth_make(const void *le_f32s, uint32_t width, uint32_t height,
                                  render_depth_convention_t conv, int reversed, double near_,
                                  double far_, const rcamera_t *cam, char *err, size_t errlen) {
  render_depth_t *d = malloc(sizeof *d);
  float *z = malloc((size_t)width * height * sizeof(float));
  if (d == NULL || z == NULL) {
    free(d), free(z);
    proto_error_format(err, errlen, "out of memory for a %ux%u depth buffer", width, height);
    return NULL;
  }
  const unsigned char *in = le_f32s;
  double th = tan(cam->fov_y * (M_PI / 360)), aspect = (double)width / height;
  const char *range = conv == DEPTH_NDC_GL   ? "[-1, 1]"
                      : conv == DEPTH_NDC_01 ? "[0, 1]"
                                             : "finite and not negative";
  for (uint32_t y = 0; y < height; y++) {
    double v = (1 - 2 * (y + 0.5) / height) * th;
    for (uint32_t x = 0; x < width; x++) {
      double u = (2 * (x + 0.5) / width - 1) * th * aspect;
      size_t i = (size_t)y * width + x;
      float raw = le_f32(in + 4 * i);
      double dv = raw; /* Reversed Z is the usual mapping mirrored. */
      if (reversed && conv == DEPTH_NDC_GL)
        dv = -dv;
      else if (reversed && conv == DEPTH_NDC_01)
        dv = 1 - dv;
      double vz = render_depth_view_z(conv, dv, near_, far_, 1 / sqrt(1 + u * u + v * v));
      if (isnan(vz)) {
        proto_error_format(err, errlen, "value %g at pixel (%u, %u) is not %s%s", raw, x, y,
                           conv == DEPTH_LINEAR || conv == DEPTH_RAY ? "" : "in ", range);
        free(d), free(z);
        return NULL;
      }
      z[i] = (float)vz;
    }
  }
  d->width = width, d->height = height, d->z = z;
  return d;
}

/* Neighbouring pixels of a reprojected buffer are one surface when their depths differ by less
 * than this fraction; a quad across a larger step (a silhouette) is not drawn. */
#define REPROJECT_SAME_SURFACE 0.1
/* A quad wider or taller than this many pixels in the new view is not drawn: the moves this is
 * for magnify far less, and the bound keeps a hostile buffer from costing more than a few
 * pixel tests a quad. */
#define REPROJECT_MAX_SPAN 4.0

/* A source pixel placed in the new view: where it lands (pixels, centres at k + 0.5) and 1 / its
 * view-axis depth there (0 when it has nothing, or lies behind the new eye). */
typedef struct landed {
  float x, y, w;
} landed_t;

/* floor(v) for |v| well inside a long's range, without a call into libm. */
static inline long floor_l(float v) {
  long i = (long)v;
  return i - (v < (float)i);
}

/* The depth at pixel centre (px, py) of the triangle 'a', 'b', 'c' (1 / depth interpolated, exact
 * for a plane under perspective), or +INFINITY when the centre lies outside it. A hair of slack
 * draws the seam between two triangles. */
static float triangle_depth(landed_t a, landed_t b, landed_t c, float px, float py) {
  float area = (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x);
  if (!(fabsf(area) > 1e-12f))
    return INFINITY;
  float wa = ((b.x - px) * (c.y - py) - (b.y - py) * (c.x - px)) / area;
  float wb = ((c.x - px) * (a.y - py) - (c.y - py) * (a.x - px)) / area;
  float wc = 1 - wa - wb;
  if (wa < -1e-6f || wb < -1e-6f || wc < -1e-6f)
    return INFINITY;
  float inv = wa * a.w + wb * b.w + wc * c.w;
  return inv > 0 ? 1 / inv : INFINITY;
}

int render_depth_reproject(render_depth_t *d, const rcamera_t *from, const rcamera_t *to, char *err,
                           size_t errlen) {
  uint32_t w = d->width, h = d->height;
  double fs[3], rs[3], us[3], fd[3], rd[3], ud[3];
  if (render_view_basis(from, fs, rs, us) != 0 || render_view_basis(to, fd, rd, ud) != 0 ||
      !(from->fov_y > 0 && from->fov_y < 180) || !(to->fov_y > 0 && to->fov_y < 180)) {
    proto_error_format(err, errlen, "a camera that defines no view");
    return -1;
  }
  size_t n = (size_t)w * h;
  float *z = malloc(n * sizeof *z);
  landed_t *at = malloc(n * sizeof *at);
  if (z == NULL || at == NULL) {
    free(z), free(at);
    proto_error_format(err, errlen, "out of memory for a %ux%u depth buffer", w, h);
    return -1;
  }
  double aspect = (double)w / h, ts = tan(from->fov_y * (M_PI / 360)),
         td = tan(to->fov_y * (M_PI / 360)), off[3];
  for (int k = 0; k < 3; k++)
    off[k] = (double)from->eye[k] - to->eye[k];
  /* Each pixel of the buffer, as the point it saw, in the new view. The point is off + zs dir,
   * dir = fs + u rs + v us, so its coordinates along the new view's axes are each an affine
   * function of u and v times zs plus a constant: a[axis] = {const, 1, u, v} coefficients, the
   * pixel coordinates' scales folded into the x and y axes. */
  double a[3][4];
  const double *axis[3] = {fd, rd, ud};
  double scale[3] = {1, 0.5 * w / (td * aspect), -0.5 * h / td};
  for (int k = 0; k < 3; k++) {
    const double *e = axis[k];
    a[k][0] = scale[k] * (off[0] * e[0] + off[1] * e[1] + off[2] * e[2]);
    a[k][1] = scale[k] * (fs[0] * e[0] + fs[1] * e[1] + fs[2] * e[2]);
    a[k][2] = scale[k] * (rs[0] * e[0] + rs[1] * e[1] + rs[2] * e[2]) * ts * aspect;
    a[k][3] = scale[k] * (us[0] * e[0] + us[1] * e[1] + us[2] * e[2]) * ts;
  }
  for (uint32_t y = 0; y < h; y++) {
    float v = (float)(1 - 2 * (y + 0.5) / h);
    /* Each axis's coefficient of zs along this row, as c0 + c1 u' with u' in [-1, 1]. */
    float c0[3], c1[3];
    for (int k = 0; k < 3; k++)
      c0[k] = (float)(a[k][1] + a[k][3] * v), c1[k] = (float)a[k][2];
    for (uint32_t x = 0; x < w; x++) {
      size_t i = (size_t)y * w + x;
      float zs = d->z[i], u = (float)(2 * (x + 0.5) / w - 1);
      at[i] = (landed_t){0, 0, 0};
      if (!isfinite(zs))
        continue;
      float zd = (float)a[0][0] + zs * (c0[0] + c1[0] * u);
      if (!(zd > 1e-6f * zs))
        continue;
      float inv = 1 / zd;
      at[i] = (landed_t){0.5f * w + ((float)a[1][0] + zs * (c0[1] + c1[1] * u)) * inv,
                         0.5f * h + ((float)a[2][0] + zs * (c0[2] + c1[2] * u)) * inv, inv};
    }
  }
  /* Each quad of four neighbours on one surface, drawn as two triangles. */
  for (size_t i = 0; i < n; i++)
    z[i] = INFINITY;
  for (uint32_t y = 0; y + 1 < h; y++)
    for (uint32_t x = 0; x + 1 < w; x++) {
      size_t i = (size_t)y * w + x;
      landed_t q[4] = {at[i], at[i + 1], at[i + w], at[i + w + 1]};
      float lo = q[0].w, hi = q[0].w, lx = q[0].x, hx = q[0].x, ly = q[0].y, hy = q[0].y;
      for (int k = 1; k < 4; k++) {
        /* Comparisons rather than fminf and fmaxf, which are calls into libm. */
        lo = q[k].w < lo ? q[k].w : lo, hi = q[k].w > hi ? q[k].w : hi;
        lx = q[k].x < lx ? q[k].x : lx, hx = q[k].x > hx ? q[k].x : hx;
        ly = q[k].y < ly ? q[k].y : ly, hy = q[k].y > hy ? q[k].y : hy;
      }
      if (!(lo > 0) || hi > lo * (1 + REPROJECT_SAME_SURFACE) || hx - lx > REPROJECT_MAX_SPAN ||
          hy - ly > REPROJECT_MAX_SPAN || hx < 0 || lx > w || hy < 0 || ly > h)
        continue;
      /* The pixel centres k + 0.5 in [lx, hx] x [ly, hy], each drawn from the triangle of the
       * quad it lies in. A quad is about a pixel: most hold one centre or none. */
      long x0 = floor_l(lx + 0.5f), x1 = floor_l(hx - 0.5f);
      long y0 = floor_l(ly + 0.5f), y1 = floor_l(hy - 0.5f);
      x0 = x0 < 0 ? 0 : x0, y0 = y0 < 0 ? 0 : y0;
      x1 = x1 >= (long)w ? (long)w - 1 : x1, y1 = y1 >= (long)h ? (long)h - 1 : y1;
      for (long yy = y0; yy <= y1; yy++)
        for (long xx = x0; xx <= x1; xx++) {
          float px = xx + 0.5f, py = yy + 0.5f;
          /* The triangle on the centre's side of the diagonal from q[0] to q[3]. */
          float dx = q[3].x - q[0].x, dy = q[3].y - q[0].y;
          float side = dx * (py - q[0].y) - dy * (px - q[0].x);
          float one = dx * (q[1].y - q[0].y) - dy * (q[1].x - q[0].x);
          float t = one != 0 && side * one >= 0 ? triangle_depth(q[0], q[1], q[3], px, py)
                                                : triangle_depth(q[0], q[3], q[2], px, py);
          float *dst = &z[(size_t)yy * w + (size_t)xx];
          if (t < *dst)
            *dst = t;
        }
    }
  free(at);
  free(d->z);
  d->z = z;
  return 0;
}

void render_depth_free(render_depth_t *d) {
  if (d)
    free(d->z);
  free(d);
}

typedef struct game_depth_state {
  cl_kernel kernel;
  size_t local[2];
  cl_mem z; /* The client's view-space depths, for cap_z pixels. */
  size_t cap_z;
} game_depth_state_t;

static void game_depth_free(renderer_t *r, void *state) {
  (void)r;
  game_depth_state_t *gs = state;
  if (gs)
    render_release(&gs->kernel, 1, &gs->z, 1);
  free(gs);
}

static int game_depth_init(renderer_t *r, void **state, char *err, size_t errlen) {
  game_depth_state_t *gs = render_state_new(state, sizeof *gs, err, errlen);
  if (gs == NULL)
    return -1;
  if ((gs->kernel = cl_dev_kernel(&r->dev, "game_depth", err, errlen)) == NULL)
    return -1;
  gs->local[0] = 16;
  gs->local[1] = 4;
  render_fit_local(r, gs->kernel, gs->local, 2);
  render_frame_require(r, gs->local[0], gs->local[1]);
  return 0;
}

/* Every frame given a depth buffer of its size, the depth aov's included. */
static int game_depth_wants(const renderer_t *r, const render_scene_t *scene,
                            const render_params_t *p) {
  (void)r, (void)scene;
  return p->depth != NULL;
}

static int game_depth_run(renderer_t *r, void *state, const render_scene_t *scene,
                          const render_params_t *p, const char **ran, char *err, size_t errlen) {
  (void)scene, (void)ran;
  game_depth_state_t *gs = state;
  const render_depth_t *dz = p->depth;
  int n = r->frame.antialias;
  if (dz->width * (uint32_t)n != p->width || dz->height * (uint32_t)n != p->height) {
    proto_error_format(err, errlen, "the depth buffer is %ux%u, not the frame's %ux%u", dz->width,
                       dz->height, p->width / n, p->height / n);
    return PROTO_E_INVALID_PARAMS;
  }
  size_t npix = (size_t)dz->width * dz->height;
  if (render_ensure_buffer(r, &gs->z, &gs->cap_z, npix, sizeof(float), CL_MEM_READ_ONLY, 0, err,
                           errlen))
    return PROTO_E_DEVICE;
  cl_int cr = clEnqueueWriteBuffer(r->dev.queue, gs->z, CL_FALSE, 0, npix * sizeof(float), dz->z, 0,
                                   NULL, NULL);
  cl_int zw = (cl_int)dz->width;
  cl_kernel k = gs->kernel;
  cr = KERNEL_ARGS(cr, k, 0, {sizeof r->frame.consts, &r->frame.consts}, {sizeof n, &n},
                   {sizeof(cl_mem), &gs->z}, {sizeof zw, &zw}, {sizeof(cl_mem), &r->frame.depth});
  size_t global[2] = {r->frame.pitch, r->frame.rows};
  if (render_launch(r, cr, k, global, gs->local, "game_depth", err, errlen) != 0)
    return PROTO_E_DEVICE;
  return 0;
}

/* It reads and writes the objects' depth, so the objects pass must draw even an empty scene. */
const render_pass_t render_pass_game_depth = {.name = "game_depth",
                                              .flags = PASS_NEEDS_BASE,
                                              .init = game_depth_init,
                                              .free = game_depth_free,
                                              .wants = game_depth_wants,
                                              .run = game_depth_run};
