/*
 * The "resolve" pass of an anti-aliased frame (render.antialias n > 1): the passes before it
 * drew the frame at n times its width and height; resolve_tonemap or resolve_linear
 * (kernels/tonemap.cl) average each pixel's n x n samples into a buffer of its own, rows of
 * whole packets, which the read-back then takes. It replaces the tone-map pass.
 */
#include "render_internal.h"

/* Output pixels of a row per resolve work-item (kernels/tonemap.cl), and its fixed work-group,
 * so that PoCL compiles the kernel once (at the warm-up) rather than for each frame size. */
#define RESOLVE_PACKET 16
#define RESOLVE_LX 1
#define RESOLVE_LY 8

/* The pass's kernels, 8-bit and linear output, and the anti-aliased frame, cap_resolved bytes. */
typedef struct resolve_state {
  cl_kernel resolve8, resolvef;
  cl_mem resolved;
  size_t cap_resolved;
} resolve_state_t;

static void resolve_free(renderer_t *r, void *state) {
  (void)r;
  resolve_state_t *rs = state;
  if (rs == NULL)
    return;
  render_release((cl_kernel[]){rs->resolve8, rs->resolvef}, 2, &rs->resolved, 1);
  free(rs);
}

static int resolve_init(renderer_t *r, void **state, char *err, size_t errlen) {
  resolve_state_t *rs = render_state_new(state, sizeof *rs, err, errlen);
  if (rs == NULL)
    return -1;
  if ((rs->resolve8 = cl_dev_kernel(&r->dev, "resolve_tonemap", err, errlen)) == NULL ||
      (rs->resolvef = cl_dev_kernel(&r->dev, "resolve_linear", err, errlen)) == NULL)
    return -1;
  return 0;
}

static int resolve_wants(const renderer_t *r, const render_scene_t *scene,
                         const render_params_t *p) {
  (void)scene, (void)p;
  return r->frame.antialias > 1;
}

/* Averages the n x n samples of each pixel of the frame drawn at n times its size ('p') into
 * the pass's buffer: 8-bit RGBA after the tone map, or linear RGBA floats for a format whose
 * source is the linear picture. */
static int resolve_run(renderer_t *r, void *state, const render_scene_t *scene,
                       const render_params_t *p, const char **ran, char *err, size_t errlen) {
  (void)ran;
  resolve_state_t *rs = state;
  int n = r->frame.antialias;
  uint32_t width = p->width / (uint32_t)n, height = p->height / (uint32_t)n;
  const render_format_t *fmt = render_format_get(p->format);
  int f32 = fmt && fmt->source == RENDER_SOURCE_LINEAR;
  size_t pitch = round_up(width, RESOLVE_PACKET);
  size_t bytes = pitch * height * (f32 ? 4 * sizeof(float) : 4);
  if (render_ensure_buffer(r, &rs->resolved, &rs->cap_resolved, bytes, 1, CL_MEM_WRITE_ONLY, 0, err,
                           errlen) != 0)
    return PROTO_E_DEVICE;
  cl_kernel k = f32 ? rs->resolvef : rs->resolve8;
  cl_int in_pitch = (cl_int)r->frame.pitch, hi_w = (cl_int)(n * width), cn = n;
  cl_int out_pitch = (cl_int)pitch, out_h = (cl_int)height, op;
  cl_float scale;
  render_tone_args(scene, &scale, &op);
  cl_int cr = KERNEL_ARGS(CL_SUCCESS, k, 0, {sizeof(cl_mem), &r->frame.linear},
                          {sizeof in_pitch, &in_pitch}, {sizeof hi_w, &hi_w}, {sizeof cn, &cn},
                          {sizeof(cl_mem), &rs->resolved}, {sizeof out_pitch, &out_pitch},
                          {sizeof out_h, &out_h});
  if (cr == CL_SUCCESS && !f32)
    cr = clSetKernelArg(k, 7, sizeof scale, &scale);
  if (cr == CL_SUCCESS && !f32)
    cr = clSetKernelArg(k, 8, sizeof op, &op);
  size_t local[2] = {RESOLVE_LX, RESOLVE_LY};
  size_t global[2] = {round_up(pitch / RESOLVE_PACKET, local[0]), round_up(height, local[1])};
  if (render_launch(r, cr, k, global, local, "resolve", err, errlen) != 0)
    return PROTO_E_DEVICE;
  r->frame.out = rs->resolved;
  r->frame.out_pitch = pitch;
  return 0;
}

const render_pass_t render_pass_resolve = {.name = "resolve",
                                           .init = resolve_init,
                                           .free = resolve_free,
                                           .wants = resolve_wants,
                                           .run = resolve_run};
