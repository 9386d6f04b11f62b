/*
 * The renderer's frame plan: device, program and the table of passes (RENDER_PASSES of
 * render.h, one file each), and the frame that runs them. A frame asks each pass in turn
 * whether it wants to run ('wants') and runs those that do, in the table's order: the drawing
 * passes ("objects": ray casting and shading into linear colour and depth; "fluid": the
 * particles as metaballs; "volumes": mist, smoke and the cloud; "waves": the energy waves'
 * closed-form glow, or their H as the wave_h aov), with "game_depth" after the objects when the
 * client sent its own depth buffer, then the passes that finish the picture
 * ("resolve" for an anti-aliased frame, else "tonemap" for an 8-bit one), "readback", and the
 * format's encoder (render_format.c) unless the caller keeps that for itself. When the last
 * drawing pass can tone-map its pixels (PASS_TONEMAPS) it does so for an 8-bit frame, and there
 * is no "tonemap" pass. Device buffers live across frames and only grow.
 *
 * One thread uses a renderer at a time (the render worker); it starts no threads of its own.
 */
#include "render_internal.h"

/* -cl-fast-relaxed-math is out: it lets the compiler assume no infinities, and misses are
 * +INFINITY. */
static const char build_options[] = "-cl-std=CL1.2 -cl-mad-enable -cl-no-signed-zeros";

#define RENDER_LAYER_NAME(id, name) name,
const char *const render_layer_names[] = {RENDER_LAYERS(RENDER_LAYER_NAME) NULL};

#define RENDER_PASS_DECLARE(name) extern const render_pass_t render_pass_##name;
RENDER_PASSES(RENDER_PASS_DECLARE)
#define RENDER_PASS_ENTRY(name) &render_pass_##name,
static const render_pass_t *const passes[] = {RENDER_PASSES(RENDER_PASS_ENTRY) NULL};
#define NPASSES (sizeof passes / sizeof passes[0] - 1)
_Static_assert(NPASSES <= RENDER_PASSES_MAX, "more passes than renderer_t keeps states for");

static void add_pass(render_output_t *out, const char *name, double ms) {
  if (out->npasses < RENDER_MAX_PASSES) {
    out->passes[out->npasses].name = name;
    out->passes[out->npasses].ms = ms;
    out->npasses++;
  }
}

/* Copies the image part of the padded per-pixel buffer 'buf' ('pixel' bytes a pixel, 'pitch'
 * pixels a row) to 'dst', rows packed. */
static int read_back(renderer_t *r, cl_mem buf, size_t pixel, size_t pitch,
                     const render_params_t *p, void *dst, char *err, size_t errlen) {
  size_t origin[3] = {0, 0, 0}, region[3] = {p->width * pixel, p->height, 1};
  cl_int cr = clEnqueueReadBufferRect(r->dev.queue, buf, CL_TRUE, origin, origin, region,
                                      pitch * pixel, 0, p->width * pixel, 0, dst, 0, NULL, NULL);
  if (cr != CL_SUCCESS) {
    proto_error_format(err, errlen, "[render] readback failed on %s: %s", r->dev.device_name,
                       cl_dev_strerror(cr));
    return PROTO_E_DEVICE;
  }
  return 0;
}

/* Whether a pass that the frame wants writes the aov 'p' asks for (the beauty always is). */
static int aov_drawn(const renderer_t *r, const render_scene_t *scene, const render_params_t *p) {
  if (p->aov == AOV_BEAUTY)
    return 1;
  for (size_t i = 0; i < NPASSES; i++)
    if ((passes[i]->aovs & (1u << p->aov)) && passes[i]->wants(r, scene, p))
      return 1;
  return 0;
}

/*
 * Which passes the frame drawn as 'dp' runs ('run[i]'), and whether its last drawing pass
 * tone-maps the picture itself: for an 8-bit beauty frame that is not anti-aliased, when that
 * pass can. Then, when no pass runs between the first and that one and none needs what the
 * first drew (PASS_NEEDS_BASE), the first need not draw an empty scene either. The finishing passes
 * are asked last, knowing both.
 */
static void plan_frame(renderer_t *r, const render_scene_t *scene, const render_params_t *p,
                       const render_params_t *dp, const render_format_t *fmt, int run[]) {
  render_frame_t *f = &r->frame;
  int last = -1, ndraw = 0;
  for (size_t i = 0; i < NPASSES; i++) {
    run[i] = passes[i]->layers != 0 && passes[i]->wants(r, scene, dp);
    if (run[i])
      last = (int)i, ndraw++;
  }
  f->fuse_tonemap = last > 0 && (passes[last]->flags & PASS_TONEMAPS) && p->aov == AOV_BEAUTY &&
                    fmt->source == RENDER_SOURCE_DISPLAY && f->antialias == 1;
  f->base_optional = f->fuse_tonemap && ndraw == 2 && run[0];
  for (size_t i = 0; i < NPASSES; i++)
    if (passes[i]->layers == 0)
      run[i] = passes[i]->wants(r, scene, dp);
  for (size_t i = 0; i < NPASSES; i++)
    if (run[i] && (passes[i]->flags & PASS_NEEDS_BASE))
      f->base_optional = 0;
}

int renderer_render(renderer_t *r, const render_scene_t *scene, const render_params_t *p,
                    render_output_t *out, char *err, size_t errlen) {
  double start = now_ms();
  memset(out, 0, sizeof *out);
  if (err && errlen)
    err[0] = '\0';
  if (p->width == 0 || p->height == 0 || p->width > MAX_SIDE || p->height > MAX_SIDE) {
    proto_error_format(err, errlen, "width and height must lie in [1, %d], not %ux%u", MAX_SIDE,
                       p->width, p->height);
    return PROTO_E_INVALID_PARAMS;
  }
  int rc = render_format_check(p->format, (int)p->aov, err, errlen);
  if (rc != 0)
    return rc;
  const render_format_t *fmt = render_format_get(p->format);
  if (fmt->encode && (p->png_level < -1 || p->png_level > 9)) {
    proto_error_format(err, errlen, "png level must lie in [-1, 9], not %d", p->png_level);
    return PROTO_E_INVALID_PARAMS;
  }

  size_t npix = (size_t)p->width * p->height;
  /* render.antialias: a beauty frame is drawn at n times its width and height ('dp') and the
   * resolve pass averages each pixel's n x n samples in place of the tone map. */
  int n = p->aov == AOV_BEAUTY && scene->antialias > 1 ? scene->antialias : 1;
  while (n > 1 && ((size_t)n * p->width > MAX_SIDE || (size_t)n * p->height > MAX_SIDE ||
                   (size_t)n * n * npix > AA_MAX_SAMPLES))
    n--;
  render_params_t drawn = *p;
  drawn.width = (uint32_t)n * p->width, drawn.height = (uint32_t)n * p->height;
  const render_params_t *dp = &drawn;
  out->antialias = n;
  render_frame_t *f = &r->frame;
  f->antialias = n;
  if (!aov_drawn(r, scene, dp)) {
    /* No pass draws the aov: it is zero everywhere (the waves' summed H without waves). */
    out->bytes = calloc(npix, fmt->bytes_per_pixel);
    if (out->bytes == NULL) {
      proto_error_format(err, errlen, "[render] out of memory for a %ux%u frame", p->width,
                         p->height);
      return PROTO_E_INTERNAL;
    }
    out->nbytes = npix * fmt->bytes_per_pixel;
    out->total_ms = now_ms() - start;
    return 0;
  }

  /* The frame's size padded to whole work-groups of every pass, and its per-pixel buffers. */
  f->pitch = round_up(dp->width, r->row_pixels);
  f->rows = round_up(dp->height, r->row_unit);
  if ((rc = render_frame_buffers(r, err, errlen)) != 0)
    return rc;
  /* Where the picture or the aov lies until a pass moves it. */
  f->out = p->aov == AOV_DEPTH ? f->depth : f->linear;
  f->out_pitch = f->pitch;
  f->base_skipped = 0;
  int run[NPASSES + 1];
  plan_frame(r, scene, p, dp, fmt, run);
  for (size_t i = 0; i < NPASSES; i++) {
    if (!run[i])
      continue;
    double t = now_ms();
    const char *ran = passes[i]->name;
    if ((rc = passes[i]->run(r, r->state[i], scene, dp, &ran, err, errlen)) != 0)
      return rc;
    if (ran)
      add_pass(out, ran, now_ms() - t);
  }

  size_t nbytes = fmt->bytes_per_pixel * npix;
  unsigned char *bytes = malloc(nbytes);
  if (bytes == NULL) {
    proto_error_format(err, errlen, "[render] out of memory for a %ux%u frame", p->width,
                       p->height);
    return PROTO_E_INTERNAL;
  }
  double t = now_ms();
  if ((rc = read_back(r, f->out, fmt->bytes_per_pixel, f->out_pitch, p, bytes, err, errlen)) != 0) {
    free(bytes);
    out->npasses = 0;
    return rc;
  }
  add_pass(out, "readback", now_ms() - t);
  out->bytes = bytes;
  out->nbytes = nbytes;
  out->total_ms = now_ms() - start;
  if (!p->raw && (rc = render_output_encode(fmt, p, out, err, errlen)) != 0)
    out->npasses = 0;
  return rc;
}

/* ---- Life cycle ---------------------------------------------------------------------------- */

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
  if (rc == 0) { /* The game-depth pass, with a client's depth buffer. */
    float z[64];
    for (int i = 0; i < 64; i++)
      z[i] = 4.0f;
    render_depth_t depth = {.width = 8, .height = 8, .z = z};
    p.depth = &depth;
    rc = renderer_render(r, &scene, &p, &out, err, errlen);
    free(out.bytes);
    p.depth = NULL;
  }
  scene.antialias = 2; /* The resolve kernels, 8-bit and linear. */
  for (int f = 0; rc == 0 && f < 2; f++) {
    p.format = f ? PROTO_FMT_RGBAF32 : PROTO_FMT_RGBA8;
    rc = renderer_render(r, &scene, &p, &out, err, errlen);
    free(out.bytes);
  }
  /* Drop what the passes keep of this scene (the BVH of the stack mesh, the volume caches' grid
   * references) before it goes out of scope. */
  for (size_t i = 0; i < NPASSES; i++)
    if (passes[i]->reset && r->state[i])
      passes[i]->reset(r, r->state[i]);
  return rc;
}

int renderer_create(const renderer_opts_t *opts, renderer_t **out, char *err, size_t errlen) {
  *out = NULL;
  renderer_t *r = calloc(1, sizeof *r);
  if (r == NULL) {
    proto_error_format(err, errlen, "[renderer_create] out of memory");
    return -1;
  }
  if (cl_dev_open(&r->dev, opts ? opts->device : NULL, err, errlen) != 0) {
    free(r);
    return -1;
  }
  if (cl_dev_build(&r->dev, opts ? opts->kernels_dir : NULL, build_options, err, errlen) != 0)
    goto fail;
  /* Each pass creates its kernels and widens the frame's padding to its work-groups. Every local
   * size is a power of two, so the padding is a multiple of each. */
  r->row_pixels = r->row_unit = 1;
  for (size_t i = 0; i < NPASSES; i++)
    if (passes[i]->init(r, &r->state[i], err, errlen) != 0)
      goto fail;
  r->kernels_ready = 1;
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
  if (r->kernels_ready)
    cl_dev_save_binary(&r->dev);
  for (size_t i = NPASSES; i-- > 0;)
    if (r->state[i])
      passes[i]->free(r, r->state[i]);
  render_frame_t *f = &r->frame;
  render_geometry_forget(f);
  render_release(NULL, 0, (cl_mem[]){f->linear, f->depth, f->rgba8, f->objs, f->nodes, f->tris}, 6);
  cl_dev_close(&r->dev);
  free(f->host_objs);
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
