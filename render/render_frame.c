/*
 * What the passes of a frame share, so that none of them depends on another: device buffers
 * that grow, the per-pixel buffers and the padding of the frame to whole work-groups, work-group
 * sizes the device accepts, the tone map's arguments, and the release of the scene's geometry.
 */
#include <math.h>

#include "render_internal.h"

int render_ensure_buffer(renderer_t *r, cl_mem *buf, size_t *cap, size_t need, size_t size,
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
    proto_error_format(err, errlen, "[render] cannot allocate %zu bytes on %s: %s", need * size,
                       r->dev.device_name, cl_dev_strerror(rc));
    return -1;
  }
  *cap = want;
  return 0;
}

int render_frame_buffers(renderer_t *r, char *err, size_t errlen) {
  render_frame_t *f = &r->frame;
  size_t npix = f->pitch * f->rows;
  if (npix <= f->cap_pixels)
    return 0;
  /* The per-pixel buffers grow together, to exactly the new size: frames can be large. */
  cl_mem *bufs[3] = {&f->linear, &f->depth, &f->rgba8};
  size_t sizes[3] = {4 * sizeof(float), sizeof(float), 4};
  for (int i = 0; i < 3; i++) {
    size_t cap = 0;
    if (*bufs[i])
      clReleaseMemObject(*bufs[i]), *bufs[i] = NULL;
    if (render_ensure_buffer(r, bufs[i], &cap, npix, sizes[i], CL_MEM_READ_WRITE, 0, err, errlen)) {
      f->cap_pixels = 0;
      return PROTO_E_DEVICE;
    }
  }
  f->cap_pixels = npix;
  return 0;
}

void render_frame_require(renderer_t *r, size_t pixels, size_t rows) {
  if (r->row_pixels < pixels)
    r->row_pixels = pixels;
  if (r->row_unit < rows)
    r->row_unit = rows;
}

void render_fit_local(renderer_t *r, cl_kernel k, size_t *local, int dims) {
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

void render_tone_args(const render_scene_t *scene, float *scale, int *op) {
  switch (scene->tone_map) {
  case TONE_REINHARD:
    *op = TONE_OP_REINHARD;
    break;
  case TONE_ACES:
    *op = TONE_OP_ACES;
    break;
  default:
    *op = TONE_OP_NONE;
    break;
  }
  *scale = exp2f(scene->exposure);
  if (!isfinite(*scale))
    *scale = scene->exposure > 0 ? 3.4e38f : 0.0f;
}

void render_geometry_forget(render_frame_t *f) {
  for (int i = 0; i < f->bvh_nkeys; i++)
    mesh_unref((mesh_t *)f->bvh_keys[i].mesh);
  free(f->bvh_keys);
  f->bvh_keys = NULL;
  f->bvh_nkeys = 0;
  f->bvh_ntri = 0;
}

void *render_state_new(void **state, size_t size, char *err, size_t errlen) {
  *state = calloc(1, size);
  if (*state == NULL)
    proto_error_format(err, errlen, "[render] out of memory");
  return *state;
}

void render_release(cl_kernel *kernels, size_t nk, cl_mem *bufs, size_t nb) {
  for (size_t i = 0; i < nk; i++)
    if (kernels[i])
      clReleaseKernel(kernels[i]);
  for (size_t i = 0; i < nb; i++)
    if (bufs[i])
      clReleaseMemObject(bufs[i]);
}

int render_launch(renderer_t *r, cl_int cr, cl_kernel k, const size_t global[2],
                  const size_t local[2], const char *pass, char *err, size_t errlen) {
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, global, local, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clFinish(r->dev.queue);
  if (cr != CL_SUCCESS) {
    proto_error_format(err, errlen, "[render] %s pass failed on %s: %s", pass, r->dev.device_name,
                       cl_dev_strerror(cr));
    return -1;
  }
  return 0;
}

int render_view_basis(const rcamera_t *c, double fw[3], double rt[3], double up[3]) {
  double len;
  for (int i = 0; i < 3; i++)
    fw[i] = (double)c->target[i] - c->eye[i];
  len = sqrt(fw[0] * fw[0] + fw[1] * fw[1] + fw[2] * fw[2]);
  if (!(len > 0) || !isfinite(len))
    return -1;
  for (int i = 0; i < 3; i++)
    fw[i] /= len;
  rt[0] = fw[1] * c->up[2] - fw[2] * c->up[1];
  rt[1] = fw[2] * c->up[0] - fw[0] * c->up[2];
  rt[2] = fw[0] * c->up[1] - fw[1] * c->up[0];
  len = sqrt(rt[0] * rt[0] + rt[1] * rt[1] + rt[2] * rt[2]);
  double up_len =
      sqrt((double)c->up[0] * c->up[0] + (double)c->up[1] * c->up[1] + (double)c->up[2] * c->up[2]);
  if (!(len > 1e-7 * up_len) || !isfinite(len))
    return -2;
  for (int i = 0; i < 3; i++)
    rt[i] /= len;
  up[0] = rt[1] * fw[2] - rt[2] * fw[1];
  up[1] = rt[2] * fw[0] - rt[0] * fw[2];
  up[2] = rt[0] * fw[1] - rt[1] * fw[0];
  return 0;
}
