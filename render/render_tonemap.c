/*
 * The "tonemap" pass (kernels/tonemap.cl): the linear picture exposed, compressed by the
 * scene's operator and sRGB-encoded into 8-bit RGBA, padding included, for a format whose
 * source is the display picture. An anti-aliased frame's resolve pass, or a last drawing pass
 * that tone-maps its own pixels (the waves), takes its place.
 */
#include "render_internal.h"

typedef struct tonemap_state {
  cl_kernel kernel;
  size_t local[2];
} tonemap_state_t;

static void tonemap_free(renderer_t *r, void *state) {
  (void)r;
  tonemap_state_t *ts = state;
  if (ts)
    render_release(&ts->kernel, 1, NULL, 0);
  free(ts);
}

static int tonemap_init(renderer_t *r, void **state, char *err, size_t errlen) {
  tonemap_state_t *ts = render_state_new(state, sizeof *ts, err, errlen);
  if (ts == NULL)
    return -1;
  if ((ts->kernel = cl_dev_kernel(&r->dev, "tonemap", err, errlen)) == NULL)
    return -1;
  ts->local[0] = TONEMAP_LX;
  ts->local[1] = TONEMAP_LY;
  render_fit_local(r, ts->kernel, ts->local, 2);
  /* The rows are a multiple of the objects work-group's; the tone map's must not be taller. */
  while (ts->local[1] > r->group[1] && ts->local[1] > 1)
    ts->local[1] /= 2;
  render_frame_require(r, TONEMAP_PACKET * ts->local[0], ts->local[1]);
  return 0;
}

static int tonemap_wants(const renderer_t *r, const render_scene_t *scene,
                         const render_params_t *p) {
  (void)scene;
  const render_format_t *fmt = render_format_get(p->format);
  return p->aov == AOV_BEAUTY && fmt && fmt->source == RENDER_SOURCE_DISPLAY &&
         r->frame.antialias == 1 && !r->frame.fuse_tonemap;
}

static int tonemap_run(renderer_t *r, void *state, const render_scene_t *scene,
                       const render_params_t *p, const char **ran, char *err, size_t errlen) {
  (void)p, (void)ran;
  tonemap_state_t *ts = state;
  cl_int op;
  cl_float scale;
  render_tone_args(scene, &scale, &op);
  cl_kernel k = ts->kernel;
  cl_int cr =
      KERNEL_ARGS(CL_SUCCESS, k, 0, {sizeof(cl_mem), &r->frame.linear},
                  {sizeof(cl_mem), &r->frame.rgba8}, {sizeof scale, &scale}, {sizeof op, &op});
  size_t global[2] = {r->frame.pitch / TONEMAP_PACKET, r->frame.rows};
  if (render_launch(r, cr, k, global, ts->local, "tonemap", err, errlen) != 0)
    return PROTO_E_DEVICE;
  r->frame.out = r->frame.rgba8;
  r->frame.out_pitch = r->frame.pitch;
  return 0;
}

const render_pass_t render_pass_tonemap = {.name = "tonemap",
                                           .init = tonemap_init,
                                           .free = tonemap_free,
                                           .wants = tonemap_wants,
                                           .run = tonemap_run};
