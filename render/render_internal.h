/*
 * What the renderer's passes share: the pass table's entry type, the frame the passes hand each
 * other, the renderer's state (device, padding, each pass's own state) and small helpers.
 * Included only by the files of render/; the rest of the server sees render.h.
 */
#ifndef VOLFX_RENDER_INTERNAL_H
#define VOLFX_RENDER_INTERNAL_H

#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "render.h"
#include "cl_device.h"
#include "../kernels/common.h"
#include "proto_error.h"

/*
 * Fixed local sizes: PoCL compiles a kernel once per local size, at its first launch. An
 * objects work-item covers a packet of PACKET pixels in a row, so its work-group covers
 * 32x8 pixels; a waves or tonemap work-item covers WAVES_PACKET or TONEMAP_PACKET pixels
 * (common.h), and their work-groups cover the same 32x8. The per-pixel buffers are padded to
 * whole work-groups of every pass.
 */
#define PACKET 16
#define OBJECTS_LX 2
#define OBJECTS_LY 8
#define TONEMAP_LX (PACKET * OBJECTS_LX / TONEMAP_PACKET)
#define TONEMAP_LY 8

#define MAX_SIDE 16384 /* Largest width or height the renderer accepts, whatever the limits. */
/* Most samples an anti-aliased frame is drawn with (render.antialias n is lowered until n^2
 * width height fits): the pixels of the largest frame the default limits allow. */
#define AA_MAX_SAMPLES ((size_t)4096 * 4096)

/* A mesh object as the cached BVH saw it. */
typedef struct mesh_key {
  const mesh_t *mesh; /* Holds a reference, so the address cannot be reused while cached. */
  float position[3], scale[3], rotation[3];
} mesh_key_t;

/*
 * What the passes of a frame hand each other. The frame plan (render.c) sizes the frame and its
 * per-pixel buffers and says which passes run; the objects pass sets up the camera and the
 * scene's geometry on the device, which later passes draw over and test against.
 */
typedef struct render_frame {
  vfx_frame_t consts; /* The frame's constants, as the objects pass set them up. */
  size_t pitch, rows; /* The drawn frame's size, padded to whole work-groups of every pass. */
  cl_mem linear, depth, rgba8; /* Per-pixel buffers, for cap_pixels pixels. */
  size_t cap_pixels;
  int antialias; /* Samples per pixel along each axis: the drawn frame is n times the asked. */

  /* Set by the plan before the passes run. */
  int fuse_tonemap;  /* The last drawing pass (PASS_TONEMAPS) tone-maps into rgba8 itself. */
  int base_optional; /* The first pass need not draw an empty scene: only the fusing pass
                        follows, and it starts from the background (set 'base_skipped'). */
  int base_skipped;  /* It did not draw: linear and depth hold nothing of this frame. */

  /* Where the picture or the aov asked for ends up, and its rows' pitch in pixels; the plan
   * starts it at linear (or depth for the depth aov), and a pass that moves it says so. */
  cl_mem out;
  size_t out_pitch;

  /* The scene's geometry on the device, written by the objects pass, read by the shadow map
   * of the volumes pass: object records (cap_objs floats), the mesh BVH (cap_nodes and
   * cap_tris records), and their host copies. */
  cl_mem objs, nodes, tris;
  size_t cap_objs, cap_nodes, cap_tris;
  float *host_objs;
  size_t host_objs_cap;
  mesh_key_t *bvh_keys; /* The mesh objects the BVH holds, in scene order. */
  int bvh_nkeys;
  int bvh_ntri;
} render_frame_t;

/* A pass may tone-map its own output when it is the last to draw (render_frame_t.fuse_tonemap). */
#define PASS_TONEMAPS 1
/* A pass reads what the first pass drew (linear and depth): when it runs, the first pass draws
 * even an empty scene (no base_optional). */
#define PASS_NEEDS_BASE 2

/*
 * One pass of the frame plan, listed in RENDER_PASSES (render.h). Each pass keeps its kernels,
 * buffers and caches in a state of its own, which 'init' creates and 'free' releases (also
 * after a failed init). 'wants' says whether a frame needs the pass; 'run' draws it, and sets
 * '*ran' to the name to record in the frame's timings, or NULL when it had nothing to do.
 * 'reset', when not NULL, drops what the pass keeps of the scenes it drew.
 */
typedef struct render_pass {
  const char *name;
  unsigned layers; /* The LAYER_* bits it draws; 0 for a pass that finishes the picture. */
  unsigned aovs;   /* Bit 1 << aov of each aov other than beauty the pass writes. */
  int flags;       /* PASS_* */
  int (*init)(renderer_t *r, void **state, char *err, size_t errlen);
  void (*free)(renderer_t *r, void *state);
  int (*wants)(const renderer_t *r, const render_scene_t *scene, const render_params_t *p);
  int (*run)(renderer_t *r, void *state, const render_scene_t *scene, const render_params_t *p,
             const char **ran, char *err, size_t errlen);
  void (*reset)(renderer_t *r, void *state);
} render_pass_t;

#define RENDER_PASSES_MAX 16

struct renderer {
  cl_dev_t dev;
  render_frame_t frame;
  size_t row_pixels, row_unit;    /* What the padded pitch and rows are multiples of. */
  size_t group[2];                /* The objects pass's work-group, which others may share. */
  void *state[RENDER_PASSES_MAX]; /* Each pass's own state, in the table's order. */
  int kernels_ready; /* Every pass's kernels were created: the program binary is worth saving. */
};

static inline double now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return ts.tv_sec * 1e3 + ts.tv_nsec / 1e6;
}

static inline size_t round_up(size_t n, size_t m) {
  return (n + m - 1) / m * m;
}

/* One kernel argument: its size and where its value lies, as clSetKernelArg takes them. */
typedef struct kernel_arg {
  size_t size;
  const void *value;
} kernel_arg_t;

/* Sets the arguments first, first + 1, ... of 'k' to the n of 'args' while 'cr' is CL_SUCCESS.
 * Returns the first failure, 'cr' if it was one, or CL_SUCCESS. */
static inline cl_int set_kernel_args(cl_int cr, cl_kernel k, cl_uint first,
                                     const kernel_arg_t *args, size_t n) {
  for (size_t i = 0; i < n && cr == CL_SUCCESS; i++)
    cr = clSetKernelArg(k, first + (cl_uint)i, args[i].size, args[i].value);
  return cr;
}

/* set_kernel_args with the arguments listed as {size, pointer} pairs. */
#define KERNEL_ARGS(cr, k, first, ...)                                                             \
  set_kernel_args((cr), (k), (first), (const kernel_arg_t[]){__VA_ARGS__},                         \
                  sizeof((const kernel_arg_t[]){__VA_ARGS__}) / sizeof(kernel_arg_t))

/* Grows the int32 or float staging array '*p' to 'need' elements. Returns 0, or -1. */
static inline int grow_staging(void **p, size_t *cap, size_t need, size_t size) {
  if (need <= *cap)
    return 0;
  void *q = realloc(*p, need * size);
  if (q == NULL)
    return -1;
  *p = q;
  *cap = need;
  return 0;
}

/* ---- render_frame.c: what every pass may use ---------------------------------------------- */

/*
 * (Re)creates 'buf' with room for at least 'need' elements of 'size' bytes; with 'headroom' it
 * asks for half as much again, so that a slowly growing scene does not reallocate every frame.
 */
int render_ensure_buffer(renderer_t *r, cl_mem *buf, size_t *cap, size_t need, size_t size,
                         cl_mem_flags flags, int headroom, char *err, size_t errlen);

/* Makes the per-pixel buffers hold the frame's padded pitch x rows pixels. Returns 0 or a
 * PROTO_E_* code. */
int render_frame_buffers(renderer_t *r, char *err, size_t errlen);

/* Widens what the frame's pitch and rows are multiples of (powers of two), for a pass whose
 * work-groups cover 'pixels' x 'rows'. Called by the passes' init. */
void render_frame_require(renderer_t *r, size_t pixels, size_t rows);

/* Picks a local size the device accepts for 'k', shrinking 'local' by halves if needed. */
void render_fit_local(renderer_t *r, cl_kernel k, size_t *local, int dims);

/* The tone map's arguments for 'scene': 2^exposure and the TONE_OP_*. */
void render_tone_args(const render_scene_t *scene, float *scale, int *op);

/* A pass's zeroed state of 'size' bytes, stored in '*state' for its 'free' even when the init
 * fails later. Returns it, or NULL with 'err' set. */
void *render_state_new(void **state, size_t size, char *err, size_t errlen);

/* Releases those of the 'nk' kernels and 'nb' buffers that are not NULL. */
void render_release(cl_kernel *kernels, size_t nk, cl_mem *bufs, size_t nb);

/* Runs the 2-D kernel 'k' over 'global' in work-groups of 'local' and waits for it, unless 'cr'
 * (its arguments' setting) already failed. Returns 0, or -1 with 'err' naming the pass. */
int render_launch(renderer_t *r, cl_int cr, cl_kernel k, const size_t global[2],
                  const size_t local[2], const char *pass, char *err, size_t errlen);

/* The orthonormal view basis of camera 'c' (forward, right, up) that every camera ray of a frame
 * is built from. Returns 0, -1 when target and eye coincide, or -2 when up is parallel to the
 * view. */
int render_view_basis(const rcamera_t *c, double fw[3], double rt[3], double up[3]);

/* Drops the geometry's BVH and the mesh references it keeps. */
void render_geometry_forget(render_frame_t *f);

#endif
