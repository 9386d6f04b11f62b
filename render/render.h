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

/*
 * Layers a render may pick (SPEC §3 'layers'), by wire name; LAYER_<ID> is bit i of the i-th.
 * Each is drawn by a pass of the frame plan (its entry's 'layers').
 */
/* clang-format off */
#define RENDER_LAYERS(X)                                                                           \
  X(OBJECTS, "objects")                                                                            \
  X(VOLUMES, "volumes")                                                                            \
  X(CLOUD, "cloud")                                                                                \
  X(FLUID, "fluid")                                                                                \
  X(WAVES, "waves")
/* clang-format on */

#define RENDER_LAYER_INDEX(id, name) LAYER_INDEX_##id,
enum { RENDER_LAYERS(RENDER_LAYER_INDEX) RENDER_LAYER_COUNT };
#define RENDER_LAYER_BIT(id, name) LAYER_##id = 1u << LAYER_INDEX_##id,
enum { RENDER_LAYERS(RENDER_LAYER_BIT) LAYER_ALL = (1u << RENDER_LAYER_COUNT) - 1 };

/* The layers' wire names, bit order, ended by NULL. */
extern const char *const render_layer_names[];

/*
 * The frame plan's passes in the order they run: X(name) is render_pass_<name>, a
 * render_pass_t (render_internal.h) in render_<name>.c. The drawing passes come first; the
 * last ones finish the picture (resolve, or the tone map).
 */
#define RENDER_PASSES(X) X(objects) X(game_depth) X(fluid) X(volumes) X(waves) X(resolve) X(tonemap)

/* What a frame shows: the picture, or one of its other outputs. */
typedef enum { AOV_BEAUTY, AOV_DEPTH, AOV_WAVE_H, AOV_COUNT } aov_t;
/* The aovs' wire names, indexed by aov_t and ended by NULL. */
extern const char *const render_aov_names[];
/* The aov named 'name', or -1. */
int render_aov_parse(const char *name);

/*
 * A client's depth buffer (the game's own picture, drawn with the frame's camera), which clips
 * every effect as the objects' depth does: 'z' holds width x height view-space depths (distance
 * along the camera's view axis, world units), rows top first, +INFINITY where nothing is.
 * render_depth_make converts what the client sent to this (render_game_depth.c).
 */
typedef struct render_depth {
  uint32_t width, height;
  float *z;
} render_depth_t;

/* How a client's depth values are given (the wire names in render_depth_convention_names). */
typedef enum {
  DEPTH_LINEAR, /* View-space distance along the view axis; at or past 'far' (if set) nothing. */
  DEPTH_RAY,    /* Distance along each pixel's ray from the eye, as the depth aov gives it. */
  DEPTH_NDC_GL, /* OpenGL window depth mapped to [-1, 1] NDC z: -1 at near, 1 at far. */
  DEPTH_NDC_01, /* D3D / Vulkan / Metal NDC z in [0, 1]: 0 at near, 1 at far. */
  DEPTH_CONVENTION_COUNT
} render_depth_convention_t;
extern const char *const render_depth_convention_names[];

/*
 * View-space depth of one value 'd' given in 'conv' with the projection's 'near' and 'far' (for
 * the ndc conventions; near > far is reversed Z, and the far plane's value means nothing there:
 * +INFINITY). For DEPTH_RAY, 'cos_axis' is the cosine between the pixel's ray and the view axis.
 * Returns the depth, or NAN when 'd' lies outside the convention's range.
 */
double render_depth_view_z(render_depth_convention_t conv, double d, double near_, double far_,
                           double cos_axis);

/*
 * Converts width x height little-endian f32 values of 'conv' seen through camera 'cam' at that
 * size into a new render_depth_t. 'reversed' (ndc only): reversed Z, the near plane at 1 and the
 * far plane at 0 (ndc_01) or -1 (ndc_gl). 'far_' <= 0 leaves a linear or ray depth unbounded.
 * Returns it, or NULL with 'err' naming the first bad value (non-finite, negative or out of
 * the convention's range) or the lack of memory.
 */
render_depth_t *render_depth_make(const void *le_f32, uint32_t width, uint32_t height,
                                  render_depth_convention_t conv, int reversed, double near_,
                                  double far_, const rcamera_t *cam, char *err, size_t errlen);
/*
 * Redraws 'd', made through camera 'from', as camera 'to' sees it at the same size. Every pixel
 * of 'd' with something in it is placed in the world along its ray; each quad of four
 * neighbouring pixels on one surface (depths within 10%) is drawn into 'to' as two triangles,
 * the depth exact for a plane, keeping the nearest. What 'to' sees that 'from' did not
 * (disoccluded sides, the frame's new edges) holds nothing (+INFINITY), and so does the half
 * pixel along a silhouette, where no quad spans the step; a quad magnified beyond 4 pixels is
 * left out. Meant for the small moves of a frame or two. Returns 0, or -1 with 'err' saying why
 * (out of memory, or a camera that defines no view).
 */
int render_depth_reproject(render_depth_t *d, const rcamera_t *from, const rcamera_t *to, char *err,
                           size_t errlen);
void render_depth_free(render_depth_t *d);

/* What background pixels show: RENDER_BG_DEFAULT follows the scene's transparent_background. */
typedef enum { RENDER_BG_DEFAULT, RENDER_BG_SCENE, RENDER_BG_TRANSPARENT } render_background_t;

typedef struct render_params {
  uint32_t width, height;
  proto_format_t format; /* One of render_format_table; it must serve the aov. */
  aov_t aov;
  unsigned layers;         /* LAYER_* bits. */
  int png_level;           /* zlib level 0-9 for PNG; -1 picks the fast default. */
  int quality;             /* 1-100 for the lossy formats (jpeg, webp; 100 is lossless webp). */
  const rcamera_t *camera; /* Overrides the scene's camera when not NULL. */
  int march_samples;       /* 0: the waves' exact closed form. N > 0: a ray march of N samples
                              per wave and ray instead, for comparisons (tests/bench). */
  int raw;                 /* Leave the format's encoding to the caller (render_output_encode):
                              the bytes are the pixels of its source. */
  render_background_t background; /* The scene's, or transparent black (0, 0, 0, 0); either
                              way colours are premultiplied by alpha, the coverage. */
  const render_depth_t *depth;    /* The client's depth, width x height; or NULL. */
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

/* ---- Output formats (render_format.c) -------------------------------------------------------- */

/* The buffer a format's pixels come from. */
typedef enum {
  RENDER_SOURCE_DISPLAY, /* The tone-mapped 8-bit RGBA picture. */
  RENDER_SOURCE_LINEAR,  /* The linear float RGBA picture before the tone map. */
  RENDER_SOURCE_AOV,     /* The aov's own float buffer (depth, wave_h). */
} render_source_t;

/* Encodes the pixels of a frame into a malloc'd '*out' of '*nout' bytes; 'level' is the
 * request's png_level, or its quality for a format whose entry says so. Returns 0, or -1 with
 * nothing allocated. */
typedef int (*render_encode_fn)(const uint8_t *pixels, uint32_t width, uint32_t height, int level,
                                unsigned char **out, size_t *nout);

typedef struct render_format {
  const char *name;  /* Wire name, as proto_format_name(id) gives it; also a file's extension. */
  proto_format_t id; /* The attachment format. */
  unsigned aovs;     /* Bit 1 << aov for each aov the format serves. */
  size_t bytes_per_pixel; /* Of the pixels before encoding. */
  render_source_t source;
  render_encode_fn encode; /* NULL: the pixels are the bytes. */
  int quality; /* 1: 'encode' takes the request's quality as its level, not png_level. */
  int alpha;   /* 1: the format carries alpha (a transparent background can be asked). */
  size_t (*encoded_bound)(uint32_t width, uint32_t height); /* Most bytes 'encode' writes. */
  const char *mime;
} render_format_t;

/* Every format a frame can be asked for, ended by an entry whose name is NULL. */
extern const render_format_t render_format_table[];
/* The table's names in its order, ended by NULL (the params' schema enum). */
extern const char *const render_format_names[];

/* The entry of 'id' or of 'name', or NULL when it is not a frame format. */
const render_format_t *render_format_get(proto_format_t id);
const render_format_t *render_format_find(const char *name);
/* 0 when format 'id' serves aov 'aov'; else PROTO_E_INVALID_PARAMS with 'err' naming both and
 * the pairs that go together. */
int render_format_check(proto_format_t id, int aov, char *err, size_t errlen);
/* The most bytes a frame of 'f' takes, encoded or not. */
size_t render_format_bound(const render_format_t *f, uint32_t width, uint32_t height);
/* Encodes out->bytes, the raw pixels of a frame of 'p' in format 'f', in place when 'f' has an
 * encoder, and records the "encode" pass. Returns 0, or a PROTO_E_* code with 'err' set and
 * the bytes freed. */
int render_output_encode(const render_format_t *f, const render_params_t *p, render_output_t *out,
                         char *err, size_t errlen);

/* encode_png.c: 8-bit RGBA rows as a PNG; 'level' -1 is the fast default (zlib 1, no filter). */
int encode_png(const uint8_t *rgba, uint32_t width, uint32_t height, int level, unsigned char **out,
               size_t *nout);
size_t encode_png_bound(uint32_t width, uint32_t height);

#endif
