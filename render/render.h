/*
 * The renderer: one OpenCL context, queue and program, owned by one thread at a time (the
 * render worker). It turns a render_scene_t into a frame in the requested format, recording
 * the time of each pass.
 */
#ifndef VOLFX_RENDER_H
#define VOLFX_RENDER_H

#include <stddef.h>
#include <stdint.h>

#include "proto.h"
#include "render_scene.h"

typedef struct renderer renderer_t;

typedef struct renderer_opts {
  const char *device; /* "cpu", "gpu", a device index ("0", "1", ...) or NULL for the default. */
  const char
      *kernels_dir; /* Load the kernel sources from here instead of the embedded copies; or NULL. */
} renderer_opts_t;

/* Layers a render may pick (SPEC §3 'layers'). */
enum {
  LAYER_OBJECTS = 1 << 0,
  LAYER_VOLUMES = 1 << 1,
  LAYER_CLOUD = 1 << 2,
  LAYER_FLUID = 1 << 3,
  LAYER_WAVES = 1 << 4,
  LAYER_ALL = 0x1f
};

typedef enum { AOV_BEAUTY, AOV_DEPTH, AOV_WAVE_H } aov_t;

typedef struct render_params {
  uint32_t width, height;
  proto_format_t format; /* BEAUTY: PNG, RGBA8, RGBAF32. DEPTH, WAVE_H: F32. */
  aov_t aov;
  unsigned layers;         /* LAYER_* bits. */
  int png_level;           /* zlib level 0-9 for PNG; -1 picks the fast default. */
  const rcamera_t *camera; /* Overrides the scene's camera when not NULL. */
  int march_samples;       /* 0: the waves' exact closed form. N > 0: a ray march of N samples
                              per wave and ray instead, for comparisons (tests/bench). */
} render_params_t;

#define RENDER_MAX_PASSES 12

typedef struct render_output {
  unsigned char *bytes; /* malloc'd; the caller frees. */
  size_t nbytes;
  int npasses;
  struct {
    const char *name; /* Static: "objects", "tonemap", "readback", "encode", ... */
    double ms;
  } passes[RENDER_MAX_PASSES];
  double total_ms;
  int antialias; /* Samples per pixel along each axis the frame was drawn with. */
} render_output_t;

/*
 * Picks the device, builds the program (PoCL's cache lives in $XDG_CACHE_HOME/volfx/pocl or
 * ~/.cache/volfx/pocl unless POCL_CACHE_DIR is set) and runs every kernel once. Returns 0, or
 * -1 with a message in 'err' (the build log when the build failed).
 */
int renderer_create(const renderer_opts_t *opts, renderer_t **out, char *err, size_t errlen);
void renderer_destroy(renderer_t *r);

const char *renderer_platform_name(const renderer_t *r);
const char *renderer_device_name(const renderer_t *r);
/* The renderer's OpenCL device, whose program holds every kernel (kernels/sph.cl too), for
 * simulations run on the renderer's thread. */
struct cl_dev *renderer_device(renderer_t *r);

/*
 * Renders one frame. Returns 0, or a PROTO_E_* code (PROTO_E_DEVICE for an OpenCL failure,
 * PROTO_E_INVALID_PARAMS for an unsupported format/aov pair) with a message in 'err'.
 */
int renderer_render(renderer_t *r, const render_scene_t *scene, const render_params_t *p,
                    render_output_t *out, char *err, size_t errlen);

/* Encodes 8-bit RGBA rows as a PNG; 'level' -1 is the fast default (zlib 1, no filter). */
int encode_png(const uint8_t *rgba, uint32_t width, uint32_t height, int level, unsigned char **out,
               size_t *nout);

#endif
