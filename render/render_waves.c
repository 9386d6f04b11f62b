/*
 * The waves pass: each energy wave packed for the frame's eye, culled per tile of the image,
 * and integrated in closed form along every ray (kernels/waves.cl), added to the linear image
 * or stored as the wave_h AOV.
 */
#include <math.h>

#include "render_internal.h"

_Static_assert(WAVES_PACKET == 16, "kernels/waves.cl shades packets of 16 pixels in float16 lanes");

/* The waves pass's kernels, device buffers and host staging. */
typedef struct waves_state {
  cl_kernel waves, waves_march; /* The closed form, and the ray march for comparisons. */
  size_t waves_local[2];
  cl_mem wave_recs; /* Wave records, cap_waves floats. */
  size_t cap_waves;
  cl_mem wave_lists; /* Per waves work-group, the waves it may meet: cap_lists ints. */
  size_t cap_lists;
  cl_mem hbuf; /* The wave_h AOV, cap_h pixels (allocated at the first wave_h frame). */
  size_t cap_h;
  float *host_waves; /* Staging for the wave records. */
  size_t host_waves_cap;
  int32_t *host_lists; /* Staging for the wave lists. */
  size_t host_lists_cap;
} waves_state_t;

/*
 * Packs the usable waves of 'scene' into ws->host_waves as records for the eye 'eye' (WAVE_* of
 * common.h), working in double so that the offsets from the eye are exact to float rounding.
 * A wave with a zero or non-finite axis, a radius, softening or clamp that is not positive, or
 * any non-finite number is left out (the scene model refuses them; this keeps the kernel safe
 * whatever it is given). Returns the number packed, or -1 when out of memory.
 */
static int pack_waves(waves_state_t *ws, const render_scene_t *scene, const float eye[3]) {
  size_t need = (size_t)(scene->nwaves > 0 ? scene->nwaves : 1) * WAVE_STRIDE;
  if (need > ws->host_waves_cap) {
    float *p = realloc(ws->host_waves, need * sizeof(float));
    if (p == NULL)
      return -1;
    ws->host_waves = p, ws->host_waves_cap = need;
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
    float *rec = ws->host_waves + (size_t)n++ * WAVE_STRIDE;
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
 * Writes to ws->host_lists, for each work-group of the waves pass (a tile of the padded image),
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
static size_t cull_waves(const renderer_t *r, waves_state_t *ws, int n) {
  size_t tw = WAVES_PACKET * ws->waves_local[0], th = ws->waves_local[1];
  size_t nx = r->frame.pitch / tw, ny = r->frame.rows / th, stride = (size_t)n + 1;
  size_t need = nx * ny * stride;
  /* After the lists: each wave's first and last tile column and row. */
  size_t total = need + 4 * (size_t)n;
  if (total > ws->host_lists_cap) {
    int32_t *p = realloc(ws->host_lists, total * sizeof(int32_t));
    if (p == NULL)
      return 0;
    ws->host_lists = p, ws->host_lists_cap = total;
  }
  /* The planes of the tiles' first and last columns, then of their first and last rows. */
  double(*planes)[2][3] = malloc((nx + ny) * sizeof *planes);
  if (planes == NULL)
    return 0;
  const vfx_frame_t *f = &r->frame.consts;
  for (size_t t = 0; t < nx + ny; t++) {
    int row = t >= nx;
    size_t k = row ? t - nx : t, size = row ? th : tw;
    edge_plane(f, k * size + 0.5, row, 1, planes[t][0]);
    edge_plane(f, (k + 1) * size - 0.5, row, 0, planes[t][1]);
  }
  int32_t *range = ws->host_lists + need;
  for (int i = 0; i < n; i++) {
    const float *rec = ws->host_waves + (size_t)i * WAVE_STRIDE;
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
      int32_t *list = ws->host_lists + (ty * nx + tx) * stride;
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
 * near distance to r->frame.depth. 'mode' is WAVES_ADD (glow into r->frame.linear) or WAVES_STORE_H
 * (H into ws->hbuf); 'samples' > 0 swaps the closed form for a ray march of that many samples per
 * wave. Sets '*ran' to whether there was a wave to draw. Returns 0 or a PROTO_E_* code.
 */
static int waves_draw(renderer_t *r, waves_state_t *ws, const render_scene_t *scene, int mode,
                      int samples, int *ran, char *err, size_t errlen) {
  *ran = 0;
  int n = pack_waves(ws, scene, r->frame.consts.eye);
  if (n < 0) {
    proto_error_format(err, errlen, "[render] out of memory for %d waves", scene->nwaves);
    return PROTO_E_INTERNAL;
  }
  size_t npix = r->frame.pitch * r->frame.rows;
  if (n == 0 && !(mode & (WAVES_STORE_H | WAVES_TONEMAP)))
    return 0;
  if (render_ensure_buffer(r, &ws->wave_recs, &ws->cap_waves, (size_t)(n ? n : 1) * WAVE_STRIDE,
                           sizeof(float), CL_MEM_READ_ONLY, 1, err, errlen))
    return PROTO_E_DEVICE;
  if ((mode & WAVES_STORE_H) && render_ensure_buffer(r, &ws->hbuf, &ws->cap_h, npix, sizeof(float),
                                                     CL_MEM_READ_WRITE, 0, err, errlen))
    return PROTO_E_DEVICE;
  size_t nlists = cull_waves(r, ws, n);
  if (nlists == 0) {
    proto_error_format(err, errlen, "[render] out of memory for the wave lists");
    return PROTO_E_INTERNAL;
  }
  if (render_ensure_buffer(r, &ws->wave_lists, &ws->cap_lists, nlists, sizeof(int32_t),
                           CL_MEM_READ_ONLY, 1, err, errlen))
    return PROTO_E_DEVICE;
  /* Kernels take a buffer argument even when only one mode uses it. */
  cl_mem hout = ws->hbuf ? ws->hbuf : r->frame.depth;
  cl_kernel k = samples > 0 ? ws->waves_march : ws->waves;
  cl_int nw = n, md = mode, ns = samples, op;
  cl_float scale;
  render_tone_args(scene, &scale, &op);
  cl_int cr = CL_SUCCESS;
  if (n > 0)
    cr = clEnqueueWriteBuffer(r->dev.queue, ws->wave_recs, CL_FALSE, 0,
                              (size_t)n * WAVE_STRIDE * sizeof(float), ws->host_waves, 0, NULL,
                              NULL);
  if (cr == CL_SUCCESS)
    cr = clEnqueueWriteBuffer(r->dev.queue, ws->wave_lists, CL_FALSE, 0, nlists * sizeof(int32_t),
                              ws->host_lists, 0, NULL, NULL);
  cr = KERNEL_ARGS(cr, k, 0, {sizeof r->frame.consts, &r->frame.consts},
                   {sizeof(cl_mem), &ws->wave_recs}, {sizeof nw, &nw},
                   {sizeof(cl_mem), &ws->wave_lists}, {sizeof(cl_mem), &r->frame.depth},
                   {sizeof(cl_mem), &r->frame.linear}, {sizeof(cl_mem), &hout}, {sizeof md, &md},
                   {sizeof(cl_mem), &r->frame.rgba8}, {sizeof scale, &scale}, {sizeof op, &op});
  if (cr == CL_SUCCESS && samples > 0)
    cr = clSetKernelArg(k, 11, sizeof ns, &ns);
  size_t global[2] = {r->frame.pitch / WAVES_PACKET, r->frame.rows};
  if (render_launch(r, cr, k, global, ws->waves_local, "waves", err, errlen) != 0)
    return PROTO_E_DEVICE;
  *ran = n > 0;
  return 0;
}

static void waves_free(renderer_t *r, void *state) {
  (void)r;
  waves_state_t *ws = state;
  if (ws == NULL)
    return;
  render_release((cl_kernel[]){ws->waves, ws->waves_march}, 2,
                 (cl_mem[]){ws->wave_recs, ws->wave_lists, ws->hbuf}, 3);
  free(ws->host_waves);
  free(ws->host_lists);
  free(ws);
}

static int waves_init(renderer_t *r, void **state, char *err, size_t errlen) {
  waves_state_t *ws = render_state_new(state, sizeof *ws, err, errlen);
  if (ws == NULL)
    return -1;
  if ((ws->waves = cl_dev_kernel(&r->dev, "waves", err, errlen)) == NULL ||
      (ws->waves_march = cl_dev_kernel(&r->dev, "waves_march", err, errlen)) == NULL)
    return -1;
  /* The waves kernels cover the objects pass's pixels with wider work-items, so they keep its
   * work-group's pixels if the device takes them, or halve them. The march kernel only serves
   * comparisons and is not warmed up. r->group is set: the objects pass is initialised first. */
  ws->waves_local[0] = r->group[0] * PACKET / WAVES_PACKET;
  if (ws->waves_local[0] == 0)
    ws->waves_local[0] = 1;
  ws->waves_local[1] = r->group[1];
  render_fit_local(r, ws->waves, ws->waves_local, 2);
  render_fit_local(r, ws->waves_march, ws->waves_local, 2);
  render_frame_require(r, WAVES_PACKET * ws->waves_local[0], ws->waves_local[1]);
  return 0;
}

/* The waves draw over every aov but depth. */
static int waves_wants(const renderer_t *r, const render_scene_t *scene, const render_params_t *p) {
  (void)r;
  return (p->layers & LAYER_WAVES) && scene->nwaves > 0 && p->aov != AOV_DEPTH;
}

/* The energy waves' glow added to r->frame.linear, or added and tone-mapped into
 * r->frame.rgba8 when the plan fuses the tone map here (which then runs even without a wave to
 * draw), or their H stored for the wave_h aov. */
static int waves_run(renderer_t *r, void *state, const render_scene_t *scene,
                     const render_params_t *p, const char **ran, char *err, size_t errlen) {
  waves_state_t *ws = state;
  int fused = r->frame.fuse_tonemap;
  int mode = p->aov == AOV_WAVE_H ? WAVES_STORE_H : fused ? WAVES_TONEMAP : WAVES_ADD;
  if (r->frame.base_skipped)
    mode |= WAVES_EMPTY;
  int drew;
  int rc = waves_draw(r, ws, scene, mode, p->march_samples, &drew, err, errlen);
  if (rc != 0)
    return rc;
  if (mode & WAVES_STORE_H)
    r->frame.out = ws->hbuf, r->frame.out_pitch = r->frame.pitch;
  if (fused)
    r->frame.out = r->frame.rgba8, r->frame.out_pitch = r->frame.pitch;
  /* Without a wave to draw, the fused kernel was only the tone map. */
  *ran = drew ? "waves" : fused ? "tonemap" : NULL;
  return 0;
}

const render_pass_t render_pass_waves = {.name = "waves",
                                         .layers = LAYER_WAVES,
                                         .aovs = 1u << AOV_WAVE_H,
                                         .flags = PASS_TONEMAPS,
                                         .init = waves_init,
                                         .free = waves_free,
                                         .wants = waves_wants,
                                         .run = waves_run};
