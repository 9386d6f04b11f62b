/*
 * The renderer: device, program and kernels, and the order of a frame's passes: "objects"
 * (render_objects.c: ray casting and shading into linear colour and depth), "fluid"
 * (render_fluid.c: the particles as metaballs, depth-tested against the objects), "waves"
 * (render_waves.c: the energy waves' closed-form glow, added to the linear image, or their H
 * as the wave_h AOV), "tonemap", "readback" and "encode" (PNG, on the host). When the waves
 * pass is the last before the tone map of an 8-bit frame it tone-maps its pixels itself and
 * there is no "tonemap" pass. Device buffers live across frames and only grow.
 *
 * One thread uses a renderer at a time (the render worker); it starts no threads of its own.
 */
#include <math.h>

#include "render_internal.h"

/* -cl-fast-relaxed-math is out: it lets the compiler assume no infinities, and misses are
 * +INFINITY. */
static const char build_options[] = "-cl-std=CL1.2 -cl-mad-enable -cl-no-signed-zeros";

static void add_pass(render_output_t *out, const char *name, double ms) {
  if (out->npasses < RENDER_MAX_PASSES) {
    out->passes[out->npasses].name = name;
    out->passes[out->npasses].ms = ms;
    out->npasses++;
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

/* Runs the tone-map pass from r->linear into r->rgba8, padding included. */
static int pass_tonemap(renderer_t *r, const render_scene_t *scene, char *err, size_t errlen) {
  cl_int op;
  cl_float scale;
  render_tone_args(scene, &scale, &op);
  cl_kernel k = r->tonemap;
  cl_int cr = KERNEL_ARGS(CL_SUCCESS, k, 0, {sizeof(cl_mem), &r->linear},
                          {sizeof(cl_mem), &r->rgba8}, {sizeof scale, &scale}, {sizeof op, &op});
  size_t global[2] = {r->pitch / TONEMAP_PACKET, r->rows};
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, global, r->tonemap_local, 0, NULL, NULL);
  if (cr == CL_SUCCESS)
    cr = clFinish(r->dev.queue);
  if (cr != CL_SUCCESS) {
    set_err(err, errlen, "[render] tonemap pass failed on %s: %s", r->dev.device_name,
            cl_dev_strerror(cr));
    return PROTO_E_DEVICE;
  }
  return 0;
}

/* Copies the image part of the padded per-pixel buffer 'buf' ('pixel' bytes a pixel, 'pitch'
 * pixels a row) to 'dst', rows packed. */
static int read_back(renderer_t *r, cl_mem buf, size_t pixel, size_t pitch,
                     const render_params_t *p, void *dst, char *err, size_t errlen) {
  size_t origin[3] = {0, 0, 0}, region[3] = {p->width * pixel, p->height, 1};
  cl_int cr = clEnqueueReadBufferRect(r->dev.queue, buf, CL_TRUE, origin, origin, region,
                                      pitch * pixel, 0, p->width * pixel, 0, dst, 0, NULL, NULL);
  if (cr != CL_SUCCESS) {
    set_err(err, errlen, "[render] readback failed on %s: %s", r->dev.device_name,
            cl_dev_strerror(cr));
    return PROTO_E_DEVICE;
  }
  return 0;
}

int renderer_render(renderer_t *r, const render_scene_t *scene, const render_params_t *p,
                    render_output_t *out, char *err, size_t errlen) {
  double start = now_ms();
  memset(out, 0, sizeof *out);
  if (err && errlen)
    err[0] = '\0';
  if (p->width == 0 || p->height == 0 || p->width > MAX_SIDE || p->height > MAX_SIDE) {
    set_err(err, errlen, "width and height must lie in [1, %d], not %ux%u", MAX_SIDE, p->width,
            p->height);
    return PROTO_E_INVALID_PARAMS;
  }
  int beauty = p->aov == AOV_BEAUTY;
  int ok = beauty ? p->format == PROTO_FMT_PNG || p->format == PROTO_FMT_RGBA8 ||
                        p->format == PROTO_FMT_RGBAF32
                  : (p->aov == AOV_DEPTH || p->aov == AOV_WAVE_H) && p->format == PROTO_FMT_F32;
  if (!ok) {
    const char *fmt = proto_format_name(p->format);
    const char *aov = p->aov == AOV_BEAUTY   ? "beauty"
                      : p->aov == AOV_DEPTH  ? "depth"
                      : p->aov == AOV_WAVE_H ? "wave_h"
                                             : "unknown";
    set_err(err, errlen,
            "format \"%s\" is not available for aov \"%s\" (beauty: png, rgba8 or "
            "rgbaf32; depth and wave_h: f32)",
            fmt ? fmt : "unknown", aov);
    return PROTO_E_INVALID_PARAMS;
  }
  if (p->format == PROTO_FMT_PNG && (p->png_level < -1 || p->png_level > 9)) {
    set_err(err, errlen, "png level must lie in [-1, 9], not %d", p->png_level);
    return PROTO_E_INVALID_PARAMS;
  }

  size_t npix = (size_t)p->width * p->height;
  /* render.antialias: a beauty frame is drawn at n times its width and height ('dp') and the
   * resolve pass averages each pixel's n x n samples in place of the tone map. */
  int n = beauty && scene->antialias > 1 ? scene->antialias : 1;
  while (n > 1 && ((size_t)n * p->width > MAX_SIDE || (size_t)n * p->height > MAX_SIDE ||
                   (size_t)n * n * npix > AA_MAX_SAMPLES))
    n--;
  render_params_t drawn = *p;
  drawn.width = (uint32_t)n * p->width, drawn.height = (uint32_t)n * p->height;
  const render_params_t *dp = &drawn;
  out->antialias = n;
  r->antialias = n;
  int waves = (p->layers & LAYER_WAVES) && scene->nwaves > 0 && p->aov != AOV_DEPTH;
  if (p->aov == AOV_WAVE_H && !waves) {
    /* Without waves to draw, their summed H is zero everywhere. */
    out->bytes = calloc(npix, sizeof(float));
    if (out->bytes == NULL) {
      set_err(err, errlen, "[render] out of memory for a %ux%u frame", p->width, p->height);
      return PROTO_E_INTERNAL;
    }
    out->nbytes = npix * sizeof(float);
    out->total_ms = now_ms() - start;
    return 0;
  }

  /* An 8-bit frame whose last pass is the waves pass is tone-mapped by that pass, which saves
   * a launch and writing and reading the linear image; when no pass runs between the objects and
   * the waves, an objects pass with nothing to draw need not run either. A pass that runs after
   * the waves must clear 'fused'; one between the objects and the waves, 'objects_optional'. */
  int fluid = (p->layers & LAYER_FLUID) && scene->fluid.count > 0;
  int volumes = (p->layers & (LAYER_VOLUMES | LAYER_CLOUD)) && p->aov == AOV_BEAUTY &&
                (scene->nvolumes > 0 || scene->cloud.grid != NULL);
  int fused = waves && beauty && p->format != PROTO_FMT_RGBAF32 && n == 1;
  r->objects_optional = fused && !fluid && !volumes;

  double t = now_ms();
  int rc = render_pass_objects(r, scene, dp, err, errlen);
  if (rc != 0)
    return rc;
  add_pass(out, "objects", now_ms() - t);

  if (fluid) {
    t = now_ms();
    int ran;
    if ((rc = render_pass_fluid(r, scene, &ran, err, errlen)) != 0)
      return rc;
    if (ran)
      add_pass(out, "fluid", now_ms() - t);
  }

  if (volumes) {
    t = now_ms();
    int ran;
    if ((rc = render_pass_volumes(r, scene, p->layers, &ran, err, errlen)) != 0)
      return rc;
    if (ran)
      add_pass(out, "volumes", now_ms() - t);
  }

  if (waves) {
    t = now_ms();
    int ran;
    int mode = p->aov == AOV_WAVE_H ? WAVES_STORE_H : fused ? WAVES_TONEMAP : WAVES_ADD;
    if (r->objects_skipped)
      mode |= WAVES_EMPTY;
    if ((rc = render_pass_waves(r, scene, mode, p->march_samples, &ran, err, errlen)) != 0)
      return rc;
    /* Without a wave to draw, the fused kernel was only the tone map. */
    if (ran || fused)
      add_pass(out, ran ? "waves" : "tonemap", now_ms() - t);
  }

  size_t nbytes = (p->format == PROTO_FMT_RGBAF32 ? 16 : 4) * npix;
  unsigned char *bytes = NULL;
  if (p->format != PROTO_FMT_PNG) {
    bytes = malloc(nbytes);
    if (bytes == NULL) {
      set_err(err, errlen, "[render] out of memory for a %ux%u frame", p->width, p->height);
      return PROTO_E_INTERNAL;
    }
  }
  if (n > 1) {
    t = now_ms();
    if ((rc = render_pass_resolve(r, scene, p, n, err, errlen)) != 0)
      goto fail;
    add_pass(out, "resolve", now_ms() - t);
  } else if (beauty && p->format != PROTO_FMT_RGBAF32 && !fused) {
    t = now_ms();
    if ((rc = pass_tonemap(r, scene, err, errlen)) != 0)
      goto fail;
    add_pass(out, "tonemap", now_ms() - t);
  }

  t = now_ms();
  if (p->format == PROTO_FMT_PNG) {
    if (r->scratch_cap < 4 * npix) {
      unsigned char *s = realloc(r->scratch, 4 * npix);
      if (s == NULL) {
        set_err(err, errlen, "[render] out of memory for a %ux%u frame", p->width, p->height);
        rc = PROTO_E_INTERNAL;
        goto fail;
      }
      r->scratch = s, r->scratch_cap = 4 * npix;
    }
    rc = n > 1 ? read_back(r, r->resolved, 4, render_resolved_pitch(p->width), p, r->scratch, err,
                           errlen)
               : read_back(r, r->rgba8, 4, r->pitch, p, r->scratch, err, errlen);
  } else if (p->aov == AOV_DEPTH) {
    rc = read_back(r, r->depth, sizeof(float), r->pitch, p, bytes, err, errlen);
  } else if (p->aov == AOV_WAVE_H) {
    rc = read_back(r, r->hbuf, sizeof(float), r->pitch, p, bytes, err, errlen);
  } else if (n > 1) {
    rc = read_back(r, r->resolved, p->format == PROTO_FMT_RGBAF32 ? 4 * sizeof(float) : 4,
                   render_resolved_pitch(p->width), p, bytes, err, errlen);
  } else if (p->format == PROTO_FMT_RGBAF32) {
    rc = read_back(r, r->linear, 4 * sizeof(float), r->pitch, p, bytes, err, errlen);
  } else {
    rc = read_back(r, r->rgba8, 4, r->pitch, p, bytes, err, errlen);
  }
  if (rc != 0)
    goto fail;
  add_pass(out, "readback", now_ms() - t);

  if (p->format == PROTO_FMT_PNG) {
    t = now_ms();
    if (encode_png(r->scratch, p->width, p->height, p->png_level, &bytes, &nbytes) != 0) {
      set_err(err, errlen, "[render] PNG encoding of a %ux%u frame failed", p->width, p->height);
      rc = PROTO_E_INTERNAL;
      goto fail;
    }
    add_pass(out, "encode", now_ms() - t);
  }
  out->bytes = bytes;
  out->nbytes = nbytes;
  out->total_ms = now_ms() - start;
  return 0;

fail:
  free(bytes);
  out->npasses = 0;
  return rc;
}

/* ---- Life cycle ---------------------------------------------------------------------------- */

/* Picks a local size the device accepts for 'k', shrinking 'local' by halves if needed. */
static void fit_local(renderer_t *r, cl_kernel k, size_t *local, int dims) {
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

/*
 * Renders a tiny frame that holds every kind of object, so each kernel runs once with the
 * local size of real frames: PoCL compiles its work-group function at that first launch.
 */
static int warm_up(renderer_t *r, char *err, size_t errlen) {
  static float tri[9] = {-0.5f, 0, 0, 0.5f, 0, 0, 0, 0.8f, 0};
  mesh_t mesh = {.ntri = 1, .tri = tri};
  atomic_init(&mesh.refs, 1);
  rwave_t wave = {.center = {0, 0.5f, 0},
                  .direction = {1, 0, 0},
                  .a = 1,
                  .b = 1,
                  .length = 1,
                  .radius = 1,
                  .softening = 0.1f,
                  .clamp = 4,
                  .color = {1, 0.5f, 0.2f}};
  robject_t objs[4] = {
      {.shape = SHAPE_SPHERE, .position = {-1, 0.5f, 0}, .scale = {1, 1, 1}, .color = {1, 0, 0}},
      {.shape = SHAPE_BOX, .position = {1, 0.5f, 0}, .scale = {1, 1, 1}, .color = {0, 1, 0}},
      {.shape = SHAPE_PLANE, .scale = {1, 1, 1}, .color = {1, 1, 1}},
      {.shape = SHAPE_MESH, .scale = {1, 1, 1}, .color = {0, 0, 1}, .mesh = &mesh},
  };
  /* A small grid volume around the objects, so the volume and shadow-map kernels run too. */
  static float cells[8] = {0.5f, 1, 1, 0.5f, 1, 0.5f, 0.5f, 1};
  density_grid_t grid = {.dims = {2, 2, 2}, .data = cells};
  atomic_init(&grid.refs, 1);
  rvolume_t vol = {.source = VOLUME_GRID,
                   .min = {-2, 0, -1},
                   .max = {2, 2, 1},
                   .density = 1,
                   .albedo = {0.8f, 0.8f, 0.8f},
                   .samples = 4,
                   .grid = &grid};
  /* A few particles where the camera sees them, so the fluid kernel runs too. */
  static const float drops[9] = {0, 1, 0, 0.2f, 1.1f, 0, -0.15f, 0.95f, 0.1f};
  render_scene_t scene = {
      .fluid = {.count = 3,
                .positions = drops,
                .h = 0.61f,
                .threshold = 0.765625f,
                .color = {0.8f, 0.9f, 1},
                .ior = 1.33f,
                .roughness = 0.1f},
      .camera = {.eye = {0, 2, 5},
                 .target = {0, 0, 0},
                 .up = {0, 1, 0},
                 .fov_y = 45,
                 .near_ = 0.01f,
                 .far_ = 100},
      .light = {.direction = {0, 1, 0}, .color = {1, 1, 1}, .intensity = 1, .ambient = 0.1f},
      .objects = objs,
      .nobjects = 4,
      .waves = &wave,
      .nwaves = 1,
      .volumes = &vol,
      .nvolumes = 1,
      .tone_map = TONE_ACES,
  };
  atomic_init(&scene.refs, 1);
  render_params_t p = {.width = 8, .height = 8, .format = PROTO_FMT_RGBA8, .layers = LAYER_ALL};
  render_output_t out;
  int rc = renderer_render(r, &scene, &p, &out, err, errlen);
  free(out.bytes);
  if (rc == 0) {
    p.aov = AOV_WAVE_H, p.format = PROTO_FMT_F32;
    rc = renderer_render(r, &scene, &p, &out, err, errlen);
    free(out.bytes);
  }
  if (rc == 0) { /* The low-resolution volumes pass and its two kernels. */
    scene.volume_div = 2;
    p.aov = AOV_BEAUTY, p.format = PROTO_FMT_RGBA8;
    rc = renderer_render(r, &scene, &p, &out, err, errlen);
    free(out.bytes);
  }
  if (rc == 0) { /* The tone-map pass, which the waves pass replaces in the frames above. */
    p.layers = LAYER_ALL & ~LAYER_WAVES;
    rc = renderer_render(r, &scene, &p, &out, err, errlen);
    free(out.bytes);
  }
  scene.antialias = 2; /* The resolve kernels, 8-bit and linear. */
  for (int f = 0; rc == 0 && f < 2; f++) {
    p.format = f ? PROTO_FMT_RGBAF32 : PROTO_FMT_RGBA8;
    rc = renderer_render(r, &scene, &p, &out, err, errlen);
    free(out.bytes);
  }
  /* Drop the BVH of the stack mesh and the volume caches' grid references before they go out
   * of scope. */
  render_bvh_forget(r);
  render_volume_free(r);
  if (rc == 0)
    rc = render_volume_init(r, err, errlen);
  return rc;
}

int renderer_create(const renderer_opts_t *opts, renderer_t **out, char *err, size_t errlen) {
  *out = NULL;
  renderer_t *r = calloc(1, sizeof *r);
  if (r == NULL) {
    set_err(err, errlen, "[renderer_create] out of memory");
    return -1;
  }
  if (cl_dev_open(&r->dev, opts ? opts->device : NULL, err, errlen) != 0) {
    free(r);
    return -1;
  }
  if (cl_dev_build(&r->dev, opts ? opts->kernels_dir : NULL, build_options, err, errlen) != 0)
    goto fail;
  if ((r->objects = cl_dev_kernel(&r->dev, "objects", err, errlen)) == NULL ||
      (r->tonemap = cl_dev_kernel(&r->dev, "tonemap", err, errlen)) == NULL ||
      (r->waves = cl_dev_kernel(&r->dev, "waves", err, errlen)) == NULL ||
      (r->waves_march = cl_dev_kernel(&r->dev, "waves_march", err, errlen)) == NULL ||
      (r->fluid = cl_dev_kernel(&r->dev, "fluid", err, errlen)) == NULL ||
      render_resolve_init(r, err, errlen) != 0 || render_volume_init(r, err, errlen) != 0)
    goto fail;
  r->objects_local[0] = OBJECTS_LX;
  r->objects_local[1] = OBJECTS_LY;
  r->tonemap_local[0] = TONEMAP_LX;
  r->tonemap_local[1] = TONEMAP_LY;
  fit_local(r, r->objects, r->objects_local, 2);
  fit_local(r, r->tonemap, r->tonemap_local, 2);
  /* The waves kernels cover the objects pass's pixels with wider work-items, so they keep its
   * work-group's pixels if the device takes them, or halve them. The march kernel only serves
   * comparisons and is not warmed up. */
  r->waves_local[0] = r->objects_local[0] * PACKET / WAVES_PACKET;
  if (r->waves_local[0] == 0)
    r->waves_local[0] = 1;
  r->waves_local[1] = r->objects_local[1];
  fit_local(r, r->waves, r->waves_local, 2);
  fit_local(r, r->waves_march, r->waves_local, 2);
  /* A packet of FLUID_PW x FLUID_PH pixels per fluid work-item; the launch rounds the packets up
   * to whole work-groups and the kernel skips those past the buffers. */
  r->fluid_local[0] = FLUID_LX;
  r->fluid_local[1] = FLUID_LY;
  fit_local(r, r->fluid, r->fluid_local, 2);
  /* Every local size is a power of two and the padded rows are a multiple of the widest
   * work-group (row_pixels); the rows are a multiple of the objects work-group's, so the tone
   * map's must not be taller. */
  while (r->tonemap_local[1] > r->objects_local[1])
    r->tonemap_local[1] /= 2;
  if (warm_up(r, err, errlen) != 0)
    goto fail;
  *out = r;
  return 0;

fail:
  renderer_destroy(r);
  return -1;
}

void renderer_destroy(renderer_t *r) {
  if (r == NULL)
    return;
  /* Getting the binary out of PoCL compiles every kernel for every case (about a second),
   * so it is saved when the renderer goes away rather than delaying the first frame. The
   * next start loads it in milliseconds. */
  if (r->objects && r->tonemap && r->waves)
    cl_dev_save_binary(&r->dev);
  render_bvh_forget(r);
  render_volume_free(r);
  render_resolve_free(r);
  cl_mem bufs[] = {r->linear,    r->depth,      r->rgba8, r->objs,        r->nodes,    r->tris,
                   r->wave_recs, r->wave_lists, r->hbuf,  r->fluid_cells, r->fluid_pos};
  for (size_t i = 0; i < sizeof bufs / sizeof bufs[0]; i++) {
    if (bufs[i])
      clReleaseMemObject(bufs[i]);
  }
  if (r->objects)
    clReleaseKernel(r->objects);
  if (r->tonemap)
    clReleaseKernel(r->tonemap);
  if (r->waves)
    clReleaseKernel(r->waves);
  if (r->waves_march)
    clReleaseKernel(r->waves_march);
  if (r->fluid)
    clReleaseKernel(r->fluid);
  cl_dev_close(&r->dev);
  free(r->host_objs);
  free(r->host_waves);
  free(r->host_lists);
  free(r->host_fcells);
  free(r->host_fpos);
  free(r->scratch);
  free(r);
}

const char *renderer_platform_name(const renderer_t *r) {
  return r->dev.platform_name;
}

const char *renderer_device_name(const renderer_t *r) {
  return r->dev.device_name;
}

cl_dev_t *renderer_device(renderer_t *r) {
  return &r->dev;
}
