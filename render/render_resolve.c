/*
 * The "resolve" pass of an anti-aliased frame (render.antialias n > 1): the passes before it
 * drew the frame at n times its width and height; resolve_tonemap or resolve_linear
 * (kernels/tonemap.cl) average each pixel's n x n samples into r->resolved, rows of
 * render_resolved_pitch pixels, which the read-back then takes. It replaces the tone-map pass.
 */
#include "render_internal.h"

/* Output pixels of a row per resolve work-item (kernels/tonemap.cl), and its fixed work-group,
 * so that PoCL compiles the kernel once (at the warm-up) rather than for each frame size. */
#define RESOLVE_PACKET 16
#define RESOLVE_LX 1
#define RESOLVE_LY 8

size_t render_resolved_pitch(uint32_t width) {
  return round_up(width, RESOLVE_PACKET);
}

int render_resolve_init(renderer_t *r, char *err, size_t errlen) {
  if ((r->resolve8 = cl_dev_kernel(&r->dev, "resolve_tonemap", err, errlen)) == NULL ||
      (r->resolvef = cl_dev_kernel(&r->dev, "resolve_linear", err, errlen)) == NULL)
    return -1;
  return 0;
}

void render_resolve_free(renderer_t *r) {
  if (r->resolve8)
    clReleaseKernel(r->resolve8);
  if (r->resolvef)
    clReleaseKernel(r->resolvef);
  if (r->resolved)
    clReleaseMemObject(r->resolved);
  r->resolve8 = r->resolvef = NULL;
  r->resolved = NULL;
  r->cap_resolved = 0;
}

int render_pass_resolve(renderer_t *r, const render_scene_t *scene, const render_params_t *p, int n,
                        char *err, size_t errlen) {
  int f32 = p->format == PROTO_FMT_RGBAF32;
  size_t pitch = render_resolved_pitch(p->width);
  size_t bytes = pitch * p->height * (f32 ? 4 * sizeof(float) : 4);
  if (render_ensure_buffer(r, &r->resolved, &r->cap_resolved, bytes, 1, CL_MEM_WRITE_ONLY, 0, err,
                           errlen) != 0)
    return PROTO_E_DEVICE;
  cl_kernel k = f32 ? r->resolvef : r->resolve8;
  cl_int in_pitch = (cl_int)r->pitch, hi_w = (cl_int)(n * p->width), cn = n;
  cl_int out_pitch = (cl_int)pitch, out_h = (cl_int)p->height, op;
  cl_float scale;
  render_tone_args(scene, &scale, &op);
  cl_int cr =
      KERNEL_ARGS(CL_SUCCESS, k, 0, {sizeof(cl_mem), &r->linear}, {sizeof in_pitch, &in_pitch},
                  {sizeof hi_w, &hi_w}, {sizeof cn, &cn}, {sizeof(cl_mem), &r->resolved},
                  {sizeof out_pitch, &out_pitch}, {sizeof out_h, &out_h});
  if (cr == CL_SUCCESS && !f32)
    cr = clSetKernelArg(k, 7, sizeof scale, &scale);
  if (cr == CL_SUCCESS && !f32)
    cr = clSetKernelArg(k, 8, sizeof op, &op);
  size_t local[2] = {RESOLVE_LX, RESOLVE_LY};
  size_t global[2] = {round_up(pitch / RESOLVE_PACKET, local[0]), round_up(p->height, local[1])};
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, global, local, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clFinish(r->dev.queue);
  if (cr != CL_SUCCESS) {
    set_err(err, errlen, "[render] resolve pass failed on %s: %s", r->dev.device_name,
            cl_dev_strerror(cr));
    return PROTO_E_DEVICE;
  }
  return 0;
}
