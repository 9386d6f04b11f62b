/*
 * Render jobs made from a request's frame params (render_job.h): the params' enums and the
 * depth buffer's schema, their conversion into a job for the render worker (camera override,
 * depth buffer, format and aov), and what a finished job reports.
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "dispatch.h"
#include "render_job.h"

const char *const render_encodings[] = {"binary", "base64", NULL};
/* The 'background' param's values, in render_background_t's order from RENDER_BG_SCENE. */
const char *const render_backgrounds[] = {"scene", "transparent", NULL};
/* How a depth buffer's values are stored, in the 'type' member's order, and their sizes. */
static const char *const depth_types[] = {"f32", "f16", "u16", NULL};
enum { DEPTH_F32, DEPTH_F16, DEPTH_U16 };
static const size_t depth_type_bytes[] = {4, 2, 2};

const sch_field_t render_depth_fields[] = {
    {.name = "width",
     .type = SCH_INTEGER,
     .desc = "The buffer's width: the frame's width.",
     .unit = "pixels",
     .min = 1,
     .max = INFINITY,
     .flags = SCH_REQUIRED},
    {.name = "height",
     .type = SCH_INTEGER,
     .desc = "The buffer's height: the frame's height.",
     .unit = "pixels",
     .min = 1,
     .max = INFINITY,
     .flags = SCH_REQUIRED},
    {.name = "data",
     .type = SCH_STRING,
     .desc = "Base64 of width x height little-endian values of 'type', rows top first.",
     .flags = SCH_REQUIRED},
    {.name = "type",
     .type = SCH_ENUM,
     .desc = "f32: float; f16: IEEE half float (half the bytes); u16: unsigned normalized "
             "(value / 65535), a 16-bit depth buffer, with the ndc_01 convention only.",
     .enum_values = depth_types,
     .def_str = "f32"},
    {.name = "convention",
     .type = SCH_ENUM,
     .desc = "linear: distance along the view axis; ray: distance along the pixel's ray (the "
             "depth aov's); ndc_gl: OpenGL NDC z in [-1, 1]; ndc_01: D3D/Vulkan NDC z in [0, 1].",
     .enum_values = render_depth_convention_names,
     .def_str = "linear"},
    {.name = "near",
     .type = SCH_NUMBER,
     .desc = "The game's near plane distance; needed by the ndc conventions.",
     .unit = "world units",
     .min = 0,
     .max = INFINITY,
     .flags = SCH_NO_DEFAULT | SCH_POSITIVE},
    {.name = "far",
     .type = SCH_NUMBER,
     .desc = "The game's far plane distance; needed by the ndc conventions. For linear and ray, "
             "values at or past it mean no geometry.",
     .unit = "world units",
     .min = 0,
     .max = INFINITY,
     .flags = SCH_NO_DEFAULT | SCH_POSITIVE},
    {.name = "reversed",
     .type = SCH_BOOL,
     .desc = "ndc conventions: reversed Z (the near plane at 1, the far plane at 0 or -1).",
     .def = 0},
    {.name = "camera",
     .type = SCH_ANY,
     .desc = "The camera the buffer was drawn with, when not the frame's: members of the scene "
             "camera, as the frame's camera param. The buffer is reprojected into the frame's "
             "view.",
     .flags = SCH_NO_DEFAULT},
    {0}};

void render_job_release(job_t *j) {
  render_scene_unref(j->scene);
  j->scene = NULL;
  render_depth_free(j->depth);
  j->depth = NULL;
  j->params.depth = NULL;
}

/* Fails a depth param at 'member' with a message; returns PROTO_E_INVALID_PARAMS. */
static int depth_error(char *path, size_t pathlen, char *msg, size_t msglen, const char *member,
                       const char *fmt, ...) __attribute__((format(printf, 6, 7)));
static int depth_error(char *path, size_t pathlen, char *msg, size_t msglen, const char *member,
                       const char *fmt, ...) {
  snprintf(path, pathlen, "depth.%s", member);
  int n = snprintf(msg, msglen, "invalid params: depth.%s ", member);
  va_list ap;
  va_start(ap, fmt);
  if (n > 0 && (size_t)n < msglen)
    vsnprintf(msg + n, msglen - (size_t)n, fmt, ap);
  va_end(ap);
  return PROTO_E_INVALID_PARAMS;
}

/* The float an IEEE 754 binary16 value 'h' stands for (exactly: every half is a float). */
static float half_to_float(uint16_t h) {
  uint32_t sign = (uint32_t)(h >> 15) << 31, exp = (h >> 10) & 0x1f, man = h & 0x3ff;
  float v;
  if (exp == 0x1f) { /* Infinity or NaN: the float's all-ones exponent. */
    uint32_t u = sign | 0x7f800000u | man << 13;
    memcpy(&v, &u, sizeof v);
    return v;
  }
  v = exp == 0 ? ldexpf((float)man, -24) : ldexpf((float)(man | 0x400), (int)exp - 25);
  return sign ? -v : v;
}

/* The type index of depth param 'o'. */
static int depth_type(const cJSON *o) {
  const cJSON *t = cJSON_GetObjectItem(o, "type");
  for (int i = 0; t && depth_types[i]; i++)
    if (strcmp(t->valuestring, depth_types[i]) == 0)
      return i;
  return DEPTH_F32;
}

/* Decodes the data of the validated depth param 'o' into '*out' (malloc'd), as little-endian f32
 * whatever its type. Returns 0, or PROTO_E_INVALID_PARAMS with 'path' and 'msg' naming
 * depth.data. */
static int depth_decode(const cJSON *o, depth_data_t **out, char *path, size_t pathlen, char *msg,
                        size_t msglen) {
  static uint64_t serial;
  *out = NULL;
  double w = cJSON_GetObjectItem(o, "width")->valuedouble;
  double h = cJSON_GetObjectItem(o, "height")->valuedouble;
  int type = depth_type(o);
  size_t bytes = depth_type_bytes[type], n = (size_t)w * (size_t)h;
  const cJSON *data = cJSON_GetObjectItem(o, "data");
  size_t len = strlen(data->valuestring), want = n * bytes;
  if (proto_b64_decoded_max(len) < want || proto_b64_decoded_max(len) > want + 3)
    return depth_error(path, pathlen, msg, msglen, "data",
                       "holds about %zu bytes, not width x height x %zu = %zu (type %s)",
                       len / 4 * 3, bytes, want, depth_types[type]);
  /* A 2-byte type is decoded into the second half of the f32 room and widened in place, front
   * to back: value i is read from byte 2n + 2i before f32 i is written over bytes 4i to 4i + 3. */
  depth_data_t *d = malloc(sizeof *d + n * 4 + 3);
  if (d == NULL)
    return depth_error(path, pathlen, msg, msglen, "data", "is too large for memory");
  unsigned char *raw = d->bytes + (type == DEPTH_F32 ? 0 : n * 2);
  long got = proto_b64_decode(data->valuestring, len, raw);
  if (got != (long)want) {
    free(d);
    return depth_error(path, pathlen, msg, msglen, "data",
                       got < 0 ? "is not valid base64"
                               : "holds %ld bytes, not width x height x %zu (type %s)",
                       got, bytes, depth_types[type]);
  }
  for (size_t i = 0; type != DEPTH_F32 && i < n; i++) {
    uint16_t v = (uint16_t)(raw[2 * i] | raw[2 * i + 1] << 8);
    float f = type == DEPTH_F16 ? half_to_float(v) : (float)v / 65535.0f;
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    for (int k = 0; k < 4; k++)
      d->bytes[4 * i + k] = (unsigned char)(u >> (8 * k));
  }
  d->len = n * 4;
  d->serial = ++serial;
  *out = d;
  return 0;
}

/*
 * Converts the 'depth' param 'o' (validated by render_depth_fields) for a frame of j->params'
 * size seen through 'cam' into j->depth. Its data comes from '*keep' when that is set, else it
 * is decoded here and, when 'keep' is not NULL, handed over in '*keep'. Returns 0 or
 * PROTO_E_INVALID_PARAMS with 'path' and 'msg' naming the member.
 */
static int depth_from_param(const cJSON *o, depth_data_t **keep, job_t *j, const rcamera_t *cam,
                            const rcamera_t *drawn, char *path, size_t pathlen, char *msg,
                            size_t msglen) {
  double w = cJSON_GetObjectItem(o, "width")->valuedouble;
  double h = cJSON_GetObjectItem(o, "height")->valuedouble;
  if (w != j->params.width)
    return depth_error(path, pathlen, msg, msglen, "width", "%.15g is not the frame's width %u", w,
                       j->params.width);
  if (h != j->params.height)
    return depth_error(path, pathlen, msg, msglen, "height", "%.15g is not the frame's height %u",
                       h, j->params.height);
  const cJSON *conv_item = cJSON_GetObjectItem(o, "convention");
  int conv = DEPTH_LINEAR;
  for (int i = 0; conv_item && render_depth_convention_names[i]; i++)
    if (strcmp(conv_item->valuestring, render_depth_convention_names[i]) == 0)
      conv = i;
  const cJSON *nr = cJSON_GetObjectItem(o, "near"), *fr = cJSON_GetObjectItem(o, "far");
  double near_ = nr ? nr->valuedouble : 0, far_ = fr ? fr->valuedouble : 0;
  int ndc = conv == DEPTH_NDC_GL || conv == DEPTH_NDC_01;
  if (ndc && !nr)
    return depth_error(path, pathlen, msg, msglen, "near", "is needed by the %s convention",
                       render_depth_convention_names[conv]);
  if (ndc && !fr)
    return depth_error(path, pathlen, msg, msglen, "far", "is needed by the %s convention",
                       render_depth_convention_names[conv]);
  if (ndc && !(far_ > near_))
    return depth_error(path, pathlen, msg, msglen, "far", "%.15g must be greater than near %.15g",
                       far_, near_);
  if (depth_type(o) == DEPTH_U16 && conv != DEPTH_NDC_01)
    return depth_error(path, pathlen, msg, msglen, "type",
                       "u16 is a window depth in [0, 1]: it needs the ndc_01 convention, not %s",
                       render_depth_convention_names[conv]);
  const depth_data_t *pre = keep ? *keep : NULL;
  depth_data_t *own = NULL;
  if (pre == NULL) {
    int rc = depth_decode(o, &own, path, pathlen, msg, msglen);
    if (rc)
      return rc;
    pre = own;
  }
  if (pre->len != (size_t)w * (size_t)h * 4) {
    free(own);
    return depth_error(path, pathlen, msg, msglen, "data",
                       "holds %zu bytes, not width x height x 4", pre->len);
  }
  int reversed = ndc && cJSON_IsTrue(cJSON_GetObjectItem(o, "reversed"));
  char why[256];
  /* A buffer drawn with another camera is read in that camera, then reprojected. */
  int moved =
      drawn && (memcmp(drawn->eye, cam->eye, sizeof cam->eye) != 0 ||
                memcmp(drawn->target, cam->target, sizeof cam->target) != 0 ||
                memcmp(drawn->up, cam->up, sizeof cam->up) != 0 || drawn->fov_y != cam->fov_y);
  j->depth =
      render_depth_make(pre->bytes, (uint32_t)w, (uint32_t)h, (render_depth_convention_t)conv,
                        reversed, near_, far_, moved ? drawn : cam, why, sizeof why);
  if (j->depth == NULL) {
    free(own);
    return depth_error(path, pathlen, msg, msglen, "data", "%s%s", why,
                       reversed ? " (reversed)" : "");
  }
  if (moved) { /* The worker reprojects it into the frame's view (worker.c). */
    j->depth_camera = *drawn;
    j->depth_moved = 1;
  }
  if (own && keep)
    *keep = own;
  else
    free(own);
  j->params.depth = j->depth;
  return 0;
}
const sch_field_t render_layer_item = {.type = SCH_ENUM,
                                       .desc = "objects, volumes, cloud, fluid or waves.",
                                       .enum_values = render_layer_names};

static void vec3_of(const cJSON *o, const char *name, float out[3]) {
  const cJSON *v = cJSON_GetObjectItem(o, name);
  for (int i = 0; i < 3; i++)
    out[i] = (float)cJSON_GetArrayItem(v, i)->valuedouble;
}

/* Builds the camera for a frame: the scene's camera with the 'camera' param's members over
 * it, validated by the scene schema's camera description. */
static int camera_override(scene_entry_t *e, const cJSON *over, const char *at, rcamera_t *cam,
                           char *path, size_t pathlen, char *msg, size_t msglen) {
  if (!cJSON_IsObject(over)) {
    snprintf(path, pathlen, "%s", at);
    snprintf(msg, msglen, "invalid params: %s must be an object of camera members", at);
    return PROTO_E_INVALID_PARAMS;
  }
  scene_error_t serr;
  cJSON *doc = scene_get(e->scene, "camera", &serr);
  const cJSON *it;
  cJSON_ArrayForEach(it, over) {
    cJSON_DeleteItemFromObject(doc, it->string);
    cJSON_AddItemToObject(doc, it->string, cJSON_Duplicate(it, 1));
  }
  sch_error_t err;
  const sch_field_t *f = sch_path_field(&scene_schema, "camera");
  if (sch_validate(f, doc, at, &err) != 0) {
    cJSON_Delete(doc);
    snprintf(path, pathlen, "%s", err.path);
    snprintf(msg, msglen, "invalid params: %s", err.message);
    return PROTO_E_INVALID_PARAMS;
  }
  /* The same checks as scene.set's, so that a camera the scene refuses is not rendered. */
  if (scene_check_camera(doc, at, &serr) != 0) {
    cJSON_Delete(doc);
    snprintf(path, pathlen, "%s", serr.path);
    snprintf(msg, msglen, "invalid params: %s", serr.message);
    return PROTO_E_INVALID_PARAMS;
  }
  vec3_of(doc, "eye", cam->eye);
  vec3_of(doc, "target", cam->target);
  vec3_of(doc, "up", cam->up);
  cam->fov_y = (float)cJSON_GetObjectItem(doc, "fov_y")->valuedouble;
  cam->near_ = (float)cJSON_GetObjectItem(doc, "near")->valuedouble;
  cam->far_ = (float)cJSON_GetObjectItem(doc, "far")->valuedouble;
  cJSON_Delete(doc);
  return 0;
}

int render_job_from_params(server_t *s, scene_entry_t *e, const cJSON *params,
                           depth_data_t **depth_data, job_t *j, char *path, size_t pathlen,
                           char *msg, size_t msglen) {
  uint32_t side = s->cfg.limits.frame_side;
  double w = cJSON_GetObjectItem(params, "width")->valuedouble;
  double h = cJSON_GetObjectItem(params, "height")->valuedouble;
  if (w > side || h > side) {
    snprintf(path, pathlen, w > side ? "width" : "height");
    snprintf(msg, msglen, "limit exceeded: %s %.15g is over limits.frame_side (%u)",
             w > side ? "width" : "height", w > side ? w : h, side);
    return PROTO_E_LIMIT;
  }
  memset(j, 0, sizeof *j);
  j->params.width = (uint32_t)w;
  j->params.height = (uint32_t)h;
  j->params.format = render_format_find(cJSON_GetObjectItem(params, "format")->valuestring)->id;
  j->params.aov = (aov_t)render_aov_parse(cJSON_GetObjectItem(params, "aov")->valuestring);
  char why[256];
  if (render_format_check(j->params.format, (int)j->params.aov, why, sizeof why) != 0) {
    snprintf(path, pathlen, "format");
    snprintf(msg, msglen, "invalid params: %s", why);
    return PROTO_E_INVALID_PARAMS;
  }
  const cJSON *layers = cJSON_GetObjectItem(params, "layers");
  if (layers) {
    const cJSON *it;
    cJSON_ArrayForEach(it, layers) {
      for (int i = 0; render_layer_names[i]; i++)
        if (strcmp(it->valuestring, render_layer_names[i]) == 0)
          j->params.layers |= 1u << i;
    }
  } else {
    j->params.layers = LAYER_ALL;
  }
  j->params.png_level = (int)cJSON_GetObjectItem(params, "png_level")->valuedouble;
  j->params.quality = (int)cJSON_GetObjectItem(params, "quality")->valuedouble;
  const cJSON *cam = cJSON_GetObjectItem(params, "camera");
  if (cam) {
    int rc = camera_override(e, cam, "camera", &j->camera, path, pathlen, msg, msglen);
    if (rc)
      return rc;
    j->has_camera = 1;
  }
  const cJSON *bg = cJSON_GetObjectItem(params, "background");
  if (bg)
    j->params.background =
        strcmp(bg->valuestring, "transparent") == 0 ? RENDER_BG_TRANSPARENT : RENDER_BG_SCENE;
  const render_format_t *f = render_format_get(j->params.format);
  if (j->params.background == RENDER_BG_TRANSPARENT && bg && !f->alpha) {
    snprintf(path, pathlen, "background");
    snprintf(msg, msglen,
             "invalid params: format '%s' has no alpha channel for a transparent background: "
             "ask for png or webp",
             f->name);
    return PROTO_E_INVALID_PARAMS;
  }
  const cJSON *depth = cJSON_GetObjectItem(params, "depth");
  if (depth) {
    const cJSON *dcam = cJSON_GetObjectItem(depth, "camera");
    rcamera_t drawn;
    if (dcam) {
      int rc = camera_override(e, dcam, "depth.camera", &drawn, path, pathlen, msg, msglen);
      if (rc)
        return rc;
    }
    /* The frame's camera: the override's, or the scene's. */
    const rcamera_t *cam = j->has_camera ? &j->camera : &e->scene->snapshot->camera;
    int rc = depth_from_param(depth, depth_data, j, cam, dcam ? &drawn : NULL, path, pathlen, msg,
                              msglen);
    if (rc)
      return rc;
  }
  j->scene = render_scene_ref(e->scene->snapshot);
  j->frame = j->scene->frame;
  j->time = j->scene->time;
  j->version = e->scene->version;
  return 0;
}

void render_job_stats(server_t *s, const job_t *j) {
  if (j->code != 0)
    return;
  for (int i = 0; i < j->out.npasses; i++)
    stats_pass(&s->stats, j->out.passes[i].name, j->out.passes[i].ms);
  stats_pass(&s->stats, "queue", (double)(j->t_started_ns - j->t_queued_ns) / 1e6);
  stats_frame(&s->stats, now_ns());
}

cJSON *render_job_times(const job_t *j) {
  cJSON *t = cJSON_CreateObject();
  for (int i = 0; i < j->out.npasses; i++)
    cJSON_AddNumberToObject(t, j->out.passes[i].name, j->out.passes[i].ms);
  cJSON_AddNumberToObject(t, "queue", (double)(j->t_started_ns - j->t_queued_ns) / 1e6);
  cJSON_AddNumberToObject(t, "total", j->out.total_ms);
  return t;
}

double render_clock_ms(uint64_t mono_ns) {
  struct timespec ts;
  clock_gettime(CLOCK_REALTIME, &ts);
  uint64_t now = now_ns();
  double ago_ms = now >= mono_ns ? (double)(now - mono_ns) / 1e6 : -(double)(mono_ns - now) / 1e6;
  double ms = (double)ts.tv_sec * 1e3 + (double)ts.tv_nsec / 1e6 - ago_ms;
  return round(ms * 10.0) / 10.0;
}

void render_job_sync(cJSON *o, const job_t *j) {
  cJSON_AddNumberToObject(o, "version", (double)j->version);
  cJSON_AddNumberToObject(o, "render_start", render_clock_ms(j->t_started_ns));
  cJSON_AddNumberToObject(o, "encode_end", render_clock_ms(j->t_done_ns));
}

/* Per-request state of a render call while its job runs. */
/* A bound on the bytes the answer to 'j' writes: its line and the frame, as its format bounds
 * it; base64 a third more. */
size_t render_answer_bound(const job_t *j, int base64) {
  size_t n =
      render_format_bound(render_format_get(j->params.format), j->params.width, j->params.height);
  return (base64 ? proto_b64_encoded_len(n) : n) + 4096;
}
