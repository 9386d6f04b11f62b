/*
 * Render jobs made from a request's frame params, shared by render, frames.subscribe,
 * frames.update and render.sequence: the params' schema (RENDER_PARAMS_FRAME), their
 * conversion into a job for the render worker, and what a finished job reports (work_ms,
 * statistics, the sync members, the bound on its answer's bytes).
 */
#ifndef VOLFX_RENDER_JOB_H
#define VOLFX_RENDER_JOB_H

#include <math.h>

#include "server.h"
#include "worker.h"

/* A depth param's data decoded from base64 once, so that a subscription's frames do not decode
 * it again (about 1 ms at 640x360). */
typedef struct depth_data {
  uint64_t serial; /* Unique for the server's life: names the data in a subscription's view key. */
  size_t len;      /* Bytes: the depth's width x height x 4. */
  unsigned char bytes[];
} depth_data_t;

/*
 * Fills 'j' (scene reference, params, camera, depth buffer) from validated render params, shared
 * by render, frames.subscribe and render.sequence. A depth param's data is taken from
 * '*depth_data' when that is set; otherwise it is decoded, and handed over in '*depth_data'
 * unless 'depth_data' is NULL, so that a subscription decodes it once. On error answers nothing
 * and returns the PROTO_E_* code with 'path' and 'msg' filled.
 */
int render_job_from_params(server_t *s, scene_entry_t *e, const cJSON *params,
                           depth_data_t **depth_data, job_t *j, char *path, size_t pathlen,
                           char *msg, size_t msglen);
/* A bound on the bytes the answer to render job 'j' writes (its line and frame; 'base64':
 * inline). */
size_t render_answer_bound(const job_t *j, int base64);
/* Records a finished job's passes and frame in the server's stats. */
void render_job_stats(server_t *s, const job_t *j);
/* The work_ms object of a finished job: each pass, "queue" and "total". */
cJSON *render_job_times(const job_t *j);
/* Adds a finished job's sync members to 'o': "version" (the scene's), "render_start" and
 * "encode_end" (render_clock_ms of when the worker took the job and when its bytes were done). */
void render_job_sync(cJSON *o, const job_t *j);
/* A now_ns() time as milliseconds of CLOCK_REALTIME since the Unix epoch, to 0.1 ms, so that a
 * client on the same host can set it beside its own clock. */
double render_clock_ms(uint64_t mono_ns);

/* The params that describe one frame, shared by render, frames.subscribe and render.sequence. */
#define RENDER_PARAMS_FRAME                                                                        \
  PARAM_SCENE,                                                                                     \
      {.name = "width",                                                                            \
       .type = SCH_INTEGER,                                                                        \
       .desc = "Frame width; at most limits.frame_side (larger is -32003).",                       \
       .unit = "pixels",                                                                           \
       .min = 1,                                                                                   \
       .max = INFINITY,                                                                            \
       .def = PROTO_DEFAULT_FRAME_SIDE},                                                           \
      {.name = "height",                                                                           \
       .type = SCH_INTEGER,                                                                        \
       .desc = "Frame height; at most limits.frame_side (larger is -32003).",                      \
       .unit = "pixels",                                                                           \
       .min = 1,                                                                                   \
       .max = INFINITY,                                                                            \
       .def = PROTO_DEFAULT_FRAME_SIDE},                                                           \
      {.name = "format",                                                                           \
       .type = SCH_ENUM,                                                                           \
       .desc = "png, rgba8, rgbaf32, jpeg or webp for the beauty aov; f32 for depth and "          \
               "wave_h.",                                                                          \
       .enum_values = render_format_names,                                                         \
       .def_str = "png"},                                                                          \
      {.name = "aov",                                                                              \
       .type = SCH_ENUM,                                                                           \
       .desc = "beauty, depth (f32 distance along the ray, +inf for none) or wave_h.",             \
       .enum_values = render_aov_names,                                                            \
       .def_str = "beauty"},                                                                       \
      {.name = "layers",                                                                           \
       .type = SCH_ARRAY,                                                                          \
       .desc = "Effects to draw; default all.",                                                    \
       .max = RENDER_LAYER_COUNT,                                                                  \
       .items = &render_layer_item,                                                                \
       .flags = SCH_NO_DEFAULT},                                                                   \
      {.name = "camera",                                                                           \
       .type = SCH_ANY,                                                                            \
       .desc = "Members of the scene camera overriding it for this frame.",                        \
       .flags = SCH_NO_DEFAULT},                                                                   \
      {.name = "background",                                                                       \
       .type = SCH_ENUM,                                                                           \
       .desc = "scene: the scene's background colour; transparent: transparent black, for "        \
               "compositing (colours premultiplied by alpha). Default: transparent when the "      \
               "scene's render.transparent_background is true, else scene.",                       \
       .enum_values = render_backgrounds,                                                          \
       .flags = SCH_NO_DEFAULT},                                                                   \
      {.name = "depth",                                                                            \
       .type = SCH_OBJECT,                                                                         \
       .desc = "The game's depth buffer {width, height, data, convention, near, far, reversed}, "  \
               "drawn with the frame's camera: effects stop at it as at the objects (see "         \
               "Compositing).",                                                                    \
       .fields = render_depth_fields,                                                              \
       .flags = SCH_NO_DEFAULT},                                                                   \
      {.name = "png_level",                                                                        \
       .type = SCH_INTEGER,                                                                        \
       .desc = "zlib level for png, or -1 for the fast default (level 1, no filter).",             \
       .min = -1,                                                                                  \
       .max = 9,                                                                                   \
       .def = -1},                                                                                 \
  {                                                                                                \
    .name = "quality", .type = SCH_INTEGER,                                                        \
    .desc = "jpeg and webp: 1 (smallest) to 100; webp at 100 is lossless. Other formats ignore "   \
            "it.",                                                                                 \
    .min = 1, .max = 100, .def = 85                                                                \
  }

/* The params shared by render and frames.subscribe, ended by {0}: a frame's, and how its
 * bytes travel. */
#define RENDER_PARAMS_COMMON                                                                       \
  RENDER_PARAMS_FRAME, {                                                                           \
    .name = "encoding", .type = SCH_ENUM,                                                          \
    .desc = "binary: an attachment after the line; base64: inline in 'data'.",                     \
    .enum_values = render_encodings, .def_str = "binary"                                           \
  }

extern const char *const render_encodings[];
extern const char *const render_backgrounds[];
extern const sch_field_t render_depth_fields[];

/* Drops what a render job made by render_job_from_params holds (its scene reference and depth
 * buffer) when it will not be submitted. */
void render_job_release(job_t *j);
extern const sch_field_t render_layer_item;

#endif
