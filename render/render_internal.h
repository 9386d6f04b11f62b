/*
 * What the renderer's passes share: the renderer's state (device, kernels, buffers that live
 * across frames, host staging) and small helpers. Included only by server/render*.c; the rest
 * of the server sees render.h.
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
#define BVH_LEAF 4                /* Triangles per leaf the builder aims for. */
#define BVH_BINS 16               /* Bins of the SAH split search. */
#define FLUID_MAX_CELLS (1 << 21) /* The fluid grid's cells grow beyond h to stay under this. */

/* A mesh object as the cached BVH saw it. */
typedef struct mesh_key {
  const mesh_t *mesh; /* Holds a reference, so the address cannot be reused while cached. */
  float position[3], scale[3], rotation[3];
} mesh_key_t;

struct renderer {
  cl_dev_t dev;
  cl_kernel objects, tonemap, waves, waves_march, fluid;
  size_t objects_local[2], tonemap_local[2], waves_local[2], fluid_local[2];
  vfx_frame_t frame;    /* The current frame's constants, as the objects pass set them up. */
  int objects_optional; /* Set by render.c: this frame's objects kernel need not run if empty. */
  int objects_skipped;  /* It did not: r->linear and r->depth hold nothing of this frame. */

  cl_mem linear, depth, rgba8; /* Per-pixel buffers, for cap_pixels pixels. */
  size_t cap_pixels;
  size_t pitch, rows; /* The current frame's size, rounded up to whole objects work-groups. */
  cl_mem objs;        /* Object records, cap_objs floats. */
  size_t cap_objs;
  cl_mem nodes, tris; /* The mesh BVH, cap_nodes and cap_tris records. */
  size_t cap_nodes, cap_tris;
  cl_mem wave_recs; /* Wave records, cap_waves floats. */
  size_t cap_waves;
  cl_mem wave_lists; /* Per waves work-group, the waves it may meet: cap_lists ints. */
  size_t cap_lists;
  cl_mem hbuf; /* The wave_h AOV, cap_h pixels (allocated at the first wave_h frame). */
  size_t cap_h;
  cl_mem fluid_cells, fluid_pos; /* The fluid grid: cap_fcells ints and cap_fpos floats. */
  size_t cap_fcells, cap_fpos;
  struct vol_state *vol; /* The volumes pass's kernels, caches and buffers (render_volume.c). */

  /* The BVH on the device holds these mesh objects. Comparing them each frame, rather than the
   * scene pointer, keeps the BVH across snapshots that changed other things (the camera, a
   * colour) and cannot be fooled by a freed scene's address coming back. */
  mesh_key_t *bvh_keys;
  int bvh_nkeys;
  int bvh_ntri;

  float *host_objs; /* Staging for the object records. */
  size_t host_objs_cap;
  float *host_waves; /* Staging for the wave records. */
  size_t host_waves_cap;
  int32_t *host_lists; /* Staging for the wave lists. */
  size_t host_lists_cap;
  int32_t *host_fcells; /* Staging for the fluid grid's (start, count) pairs. */
  size_t host_fcells_cap;
  float *host_fpos; /* Staging for the fluid grid's lists. */
  size_t host_fpos_cap;
  unsigned char *scratch; /* Tone-mapped bytes waiting for the PNG encoder. */
  size_t scratch_cap;

  int antialias;                /* The frame being drawn: render.antialias n, as lowered. */
  cl_kernel resolve8, resolvef; /* render_resolve.c: 8-bit and linear output. */
  cl_mem resolved;              /* The anti-aliased frame, cap_resolved bytes. */
  size_t cap_resolved;
};

static inline void set_err(char *err, size_t errlen, const char *fmt, ...) {
  if (err == NULL || errlen == 0)
    return;
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(err, errlen, fmt, ap);
  va_end(ap);
}

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

/*
 * (Re)creates 'buf' with room for at least 'need' elements of 'size' bytes; with 'headroom' it
 * asks for half as much again, so that a slowly growing scene does not reallocate every frame.
 */
int render_ensure_buffer(renderer_t *r, cl_mem *buf, size_t *cap, size_t need, size_t size,
                         cl_mem_flags flags, int headroom, char *err, size_t errlen);

/* The pixels of a row that the padded buffers' pitch is a multiple of. */
size_t render_row_pixels(const renderer_t *r);

/* The passes, each in its own file. Each returns 0 or a PROTO_E_* code with 'err' set. */

/* render_objects.c: ray casts the objects into r->linear and r->depth and keeps the frame's
 * constants in r->frame for the passes after it. With r->objects_optional set and no object to
 * draw, it launches nothing and sets r->objects_skipped. */
int render_pass_objects(renderer_t *r, const render_scene_t *scene, const render_params_t *p,
                        char *err, size_t errlen);
/* render_objects.c: drops the device BVH and the mesh references it keeps. */
void render_bvh_forget(renderer_t *r);

/* render.c: the tone-map pass's arguments for 'scene': 2^exposure and the TONE_OP_*. */
void render_tone_args(const render_scene_t *scene, float *scale, int *op);

/* render_waves.c: the energy waves' glow added to r->linear (WAVES_ADD), or added and tone-mapped
 * into r->rgba8 (WAVES_TONEMAP, which replaces the tone-map pass and runs even without a wave to
 * draw), or their H stored in r->hbuf (WAVES_STORE_H); WAVES_EMPTY when the objects pass was
 * skipped. 'samples' > 0 marches instead of the closed form. '*ran' says whether there was a
 * wave to draw. */
int render_pass_waves(renderer_t *r, const render_scene_t *scene, int mode, int samples, int *ran,
                      char *err, size_t errlen);

/* render_fluid.c: the particles as metaballs, depth-tested against r->depth. */
int render_pass_fluid(renderer_t *r, const render_scene_t *scene, int *ran, char *err,
                      size_t errlen);

/* render_resolve.c: the kernels of the resolve pass (render_resolve_free undoes it, also after
 * a failure). Returns 0, or -1 with 'err' set. */
int render_resolve_init(renderer_t *r, char *err, size_t errlen);
void render_resolve_free(renderer_t *r);

/* render_resolve.c: averages the n x n samples of each pixel of the frame 'p' asks for, drawn
 * at n times its size into r->linear, into r->resolved: 8-bit RGBA after the tone map, or
 * linear RGBA floats for rgbaf32. Its rows are render_resolved_pitch(p->width) pixels. */
int render_pass_resolve(renderer_t *r, const render_scene_t *scene, const render_params_t *p, int n,
                        char *err, size_t errlen);
size_t render_resolved_pitch(uint32_t width);

/* render_volume.c: creates the volume kernels and state (render_volume_free undoes it, also
 * after a failure). Returns 0, or -1 with 'err' set. */
int render_volume_init(renderer_t *r, char *err, size_t errlen);
void render_volume_free(renderer_t *r);

/* render_volume.c: the scene's volumes (LAYER_VOLUMES in 'layers') and the cloud (LAYER_CLOUD),
 * lit through the objects' shadow map and composited over r->linear up to r->depth. '*ran'
 * says whether a kernel ran. */
int render_pass_volumes(renderer_t *r, const render_scene_t *scene, unsigned layers, int *ran,
                        char *err, size_t errlen);

#endif
