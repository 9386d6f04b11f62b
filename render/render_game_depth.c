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
