/*
 * The waves pass: each energy wave packed for the frame's eye, culled per tile of the image,
 * and integrated in closed form along every ray (kernels/waves.cl), added to the linear image
 * or stored as the wave_h AOV.
 */
#include <math.h>

#include "render_internal.h"

_Static_assert(WAVES_PACKET == 16, "kernels/waves.cl shades packets of 16 pixels in float16 lanes");

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
      rec[WAVE_COLOR + k] = wv->color[k];
    }
    rec[WAVE_S0] = (float)s0;
    rec[WAVE_L] = (float)bl;
    rec[WAVE_R2] = (float)((double)wv->radius * wv->radius);
    rec[WAVE_EPS2] = (float)((double)wv->softening * wv->softening);
    rec[WAVE_A] = wv->a;
    rec[WAVE_B] = wv->b;
    rec[WAVE_GP] = (float)gp;
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
 * The unit normal of the plane through the eye that holds the rays of pixel column 'x' (or, with
 * 'row', of pixel row 'x'), facing the side where the column (row) number grows when 'grow' is
 * set and the other side otherwise. Every ray of a column lies in one such plane: the column's
 * directions are base + x step_x + y step_y for all y.
 */
static void edge_plane(const vfx_frame_t *f, double x, int row, int grow, double out[3]) {
  double d[3], along[3], across[3];
  for (int i = 0; i < 3; i++) {
    along[i] = row ? f->step_x[i] : f->step_y[i];
    across[i] = row ? f->step_y[i] : f->step_x[i];
  }
  ray_dir(f, row ? 0 : x, row ? x : 0, d);
  cross3(d, along, out);
  double len = sqrt(dot3(out, out));
  if ((dot3(out, across) < 0) == (grow != 0))
    len = -len;
  for (int i = 0; i < 3; i++)
    out[i] = len != 0 ? out[i] / len : 0;
}

/*
 * Whether the segment from 'm' to 'e' (offsets from the eye) with radius 'rad' may reach the
 * side of 'plane' that it faces.
 */
static int may_reach(const double plane[3], const double m[3], const double e[3], double rad) {
  return dot3(plane, m) >= -rad || dot3(plane, e) >= -rad;
}

/*
 * Writes to r->host_lists, for each work-group of the waves pass (a tile of the padded image),
 * the number of the 'n' packed waves whose capsule may meet one of the tile's rays, followed by
 * their indices; a tile's list starts at (n + 1) times its index, row by row. The rays of a
 * tile fill the cone between four planes through the eye: those of its first and last pixel
 * columns and rows. A wave is left out when both ends of its axis lie farther than its radius
 * outside one of them. Each such plane belongs to a column or a row of tiles, so each wave is
 * tested against the columns and rows once, giving the tile columns and rows it may reach; a
 * tile lists the waves that may reach both its column and its row. The kernel then tests only
 * the waves of its tile, most of which are near, instead of every wave for every packet.
 * Returns the number of ints written, or 0 when out of memory.
 */
static size_t cull_waves(renderer_t *r, int n) {
  size_t tw = WAVES_PACKET * r->waves_local[0], th = r->waves_local[1];
  size_t nx = r->pitch / tw, ny = r->rows / th, stride = (size_t)n + 1;
  size_t need = nx * ny * stride;
  /* After the lists: each wave's first and last tile column and row. */
  size_t total = need + 4 * (size_t)n;
  if (total > r->host_lists_cap) {
    int32_t *p = realloc(r->host_lists, total * sizeof(int32_t));
    if (p == NULL)
      return 0;
    r->host_lists = p, r->host_lists_cap = total;
  }
  /* The planes of the tiles' first and last columns, then of their first and last rows. */
  double(*planes)[2][3] = malloc((nx + ny) * sizeof *planes);
  if (planes == NULL)
    return 0;
  const vfx_frame_t *f = &r->frame;
  for (size_t t = 0; t < nx + ny; t++) {
    int row = t >= nx;
    size_t k = row ? t - nx : t, size = row ? th : tw;
    edge_plane(f, k * size + 0.5, row, 1, planes[t][0]);
    edge_plane(f, (k + 1) * size - 0.5, row, 0, planes[t][1]);
  }
  int32_t *range = r->host_lists + need;
  for (int i = 0; i < n; i++) {
    const float *rec = r->host_waves + (size_t)i * WAVE_STRIDE;
    double m[3], e[3];
    for (int k = 0; k < 3; k++) {
      m[k] = -(double)rec[WAVE_W + k];
      e[k] = m[k] + (double)rec[WAVE_L] * rec[WAVE_D + k];
    }
    /* A margin for the kernel's rays and records being float. */
    double rad = rec[WAVE_RADIUS] * 1.001 + 1e-5 * (sqrt(dot3(m, m)) + sqrt(dot3(e, e)));
    int32_t *rg = range + 4 * (size_t)i;
    rg[0] = rg[2] = INT32_MAX, rg[1] = rg[3] = -1;
    for (size_t t = 0; t < nx + ny; t++) {
      if (!may_reach(planes[t][0], m, e, rad) || !may_reach(planes[t][1], m, e, rad))
        continue;
      int row = t >= nx;
      int32_t k = (int32_t)(row ? t - nx : t), *lo = rg + 2 * row, *hi = lo + 1;
      *lo = k < *lo ? k : *lo;
      *hi = k;
    }
  }
  free(planes);
  for (size_t ty = 0; ty < ny; ty++) {
    for (size_t tx = 0; tx < nx; tx++) {
      int32_t *list = r->host_lists + (ty * nx + tx) * stride;
      int32_t count = 0, x = (int32_t)tx, y = (int32_t)ty;
      for (int i = 0; i < n; i++) {
        const int32_t *rg = range + 4 * (size_t)i;
        if (x >= rg[0] && x <= rg[1] && y >= rg[2] && y <= rg[3])
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
int render_pass_waves(renderer_t *r, const render_scene_t *scene, int mode, int samples, int *ran,
                      char *err, size_t errlen) {
  *ran = 0;
  int n = pack_waves(r, scene, r->frame.eye);
  if (n < 0) {
    set_err(err, errlen, "[render] out of memory for %d waves", scene->nwaves);
    return PROTO_E_INTERNAL;
  }
  size_t npix = r->pitch * r->rows;
  if (n == 0 && !(mode & (WAVES_STORE_H | WAVES_TONEMAP)))
    return 0;
  if (render_ensure_buffer(r, &r->wave_recs, &r->cap_waves, (size_t)(n ? n : 1) * WAVE_STRIDE,
                           sizeof(float), CL_MEM_READ_ONLY, 1, err, errlen))
    return PROTO_E_DEVICE;
  if ((mode & WAVES_STORE_H) && render_ensure_buffer(r, &r->hbuf, &r->cap_h, npix, sizeof(float),
                                                     CL_MEM_READ_WRITE, 0, err, errlen))
    return PROTO_E_DEVICE;
  size_t nlists = cull_waves(r, n);
  if (nlists == 0) {
    set_err(err, errlen, "[render] out of memory for the wave lists");
    return PROTO_E_INTERNAL;
  }
  if (render_ensure_buffer(r, &r->wave_lists, &r->cap_lists, nlists, sizeof(int32_t),
                           CL_MEM_READ_ONLY, 1, err, errlen))
    return PROTO_E_DEVICE;
  /* Kernels take a buffer argument even when only one mode uses it. */
  cl_mem hout = r->hbuf ? r->hbuf : r->depth;
  cl_kernel k = samples > 0 ? r->waves_march : r->waves;
  cl_int nw = n, md = mode, ns = samples, op;
  cl_float scale;
  render_tone_args(scene, &scale, &op);
  cl_int cr = CL_SUCCESS;
  if (n > 0)
    cr =
        clEnqueueWriteBuffer(r->dev.queue, r->wave_recs, CL_FALSE, 0,
                             (size_t)n * WAVE_STRIDE * sizeof(float), r->host_waves, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clEnqueueWriteBuffer(r->dev.queue, r->wave_lists, CL_FALSE, 0, nlists * sizeof(int32_t),
                              r->host_lists, 0, NULL, NULL);
  cr = KERNEL_ARGS(cr, k, 0, {sizeof r->frame, &r->frame}, {sizeof(cl_mem), &r->wave_recs},
                   {sizeof nw, &nw}, {sizeof(cl_mem), &r->wave_lists}, {sizeof(cl_mem), &r->depth},
                   {sizeof(cl_mem), &r->linear}, {sizeof(cl_mem), &hout}, {sizeof md, &md},
                   {sizeof(cl_mem), &r->rgba8}, {sizeof scale, &scale}, {sizeof op, &op});
  if (cr == CL_SUCCESS && samples > 0)
    cr = clSetKernelArg(k, 11, sizeof ns, &ns);
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
