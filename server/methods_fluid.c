/*
 * The fluid's methods (SPEC §5.2): fluid.set_particles and fluid.get_particles. The stepping
 * of the particles lives in step_fluid.c.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dispatch.h"
#include "frames.h"
#include "sim_fluid.h"
#include "step_fluid.h"

static const cJSON *get(const cJSON *o, const char *name) {
  return cJSON_GetObjectItemCaseSensitive(o, name);
}

static void set_particles_m(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  const cJSON *jp = get(call->params, "positions");
  const cJSON *jv = get(call->params, "velocities");
  const char *names[2] = {"positions", "velocities"};
  const cJSON *src[2] = {jp, jv};
  float *buf[2] = {NULL, NULL};
  long nbytes[2] = {0, 0};
  uint32_t limit = call->srv->cfg.limits.particles;
  if (limit > FLUID_MAX_PARTICLES)
    limit = FLUID_MAX_PARTICLES;
  for (int k = 0; k < 2; k++) {
    if (!src[k])
      continue;
    size_t len = strlen(src[k]->valuestring);
    size_t max = proto_b64_decoded_max(len);
    if ((uint64_t)max / 12 > (uint64_t)limit + 1) {
      call_error(call, PROTO_E_LIMIT, names[k], "%s: %s: more than the limit of %u particles",
                 proto_err_message(PROTO_E_LIMIT), names[k], limit);
      goto out;
    }
    buf[k] = malloc(max ? max : 1);
    if (!buf[k]) {
      call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
      goto out;
    }
    nbytes[k] = proto_b64_decode(src[k]->valuestring, len, buf[k]);
    if (nbytes[k] < 0) {
      call_error(call, PROTO_E_INVALID_PARAMS, names[k], "invalid params: %s: not valid base64",
                 names[k]);
      goto out;
    }
    if (nbytes[k] % 12 != 0) {
      call_error(call, PROTO_E_INVALID_PARAMS, names[k],
                 "invalid params: %s: %ld bytes is not a multiple of 12 (x, y, z as f32)", names[k],
                 nbytes[k]);
      goto out;
    }
  }
  if (jv && nbytes[1] != nbytes[0]) {
    call_error(call, PROTO_E_INVALID_PARAMS, "velocities",
               "invalid params: velocities: %ld bytes, but positions has %ld", nbytes[1],
               nbytes[0]);
    goto out;
  }
  uint32_t n = (uint32_t)(nbytes[0] / 12);
  if (n > limit) {
    call_error(call, PROTO_E_LIMIT, "positions", "%s: positions: %u particles, the limit is %u",
               proto_err_message(PROTO_E_LIMIT), n, limit);
    goto out;
  }
  scene_error_t serr;
  if (scene_particles_fit_budget(e->scene, n, "positions", &serr) != 0) {
    call_error(call, serr.code, serr.path, "%s: %s", proto_err_message(serr.code), serr.message);
    goto out;
  }
  fluid_params_t fp;
  fluid_params_of(e->scene->doc, &fp);
  for (uint32_t i = 0; i < n; i++)
    for (int c = 0; c < 3; c++) {
      /* Assembled from the bytes: the wire is little-endian whatever the host is. */
      const unsigned char *b = (const unsigned char *)buf[0] + 12 * (size_t)i + 4 * c;
      uint32_t u =
          (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 | (uint32_t)b[3] << 24;
      float x;
      memcpy(&x, &u, 4);
      buf[0][3 * (size_t)i + c] = x;
      if (!isfinite(x)) {
        call_error(call, PROTO_E_INVALID_PARAMS, "positions",
                   "invalid params: positions: particle %u is not finite", i);
        goto out;
      }
      if (x < fp.bounds_min[c] || x > fp.bounds_max[c]) {
        call_error(call, PROTO_E_INVALID_PARAMS, "positions",
                   "invalid params: positions: particle %u lies outside fluid.bounds", i);
        goto out;
      }
      if (jv) {
        b = (const unsigned char *)buf[1] + 12 * (size_t)i + 4 * c;
        u = (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 | (uint32_t)b[3] << 24;
        memcpy(&x, &u, 4);
        buf[1][3 * (size_t)i + c] = x;
        if (!isfinite(x)) {
          call_error(call, PROTO_E_INVALID_PARAMS, "velocities",
                     "invalid params: velocities: particle %u is not finite", i);
          goto out;
        }
      }
    }
  particles_t *p = particles_new(n);
  if (!p) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    goto out;
  }
  memcpy(p->pos, buf[0], (size_t)n * 12);
  if (jv)
    memcpy(p->vel, buf[1], (size_t)n * 12);
  if (scene_set_particles(e->scene, p) != 0) {
    particles_unref(p);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    goto out;
  }
  e->scene->particles_epoch++; /* Step jobs in flight now step stale particles: dropped. */
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "count", n);
  call_result(call, r);
out:
  free(buf[0]);
  free(buf[1]);
}

/* What fluid.get_particles sends: the particles (a reference, immutable; NULL for none), read
 * on any thread. */
typedef struct particles_out {
  particles_t *particles;
  int velocities;
} particles_out_t;

static unsigned char *particles_bytes(void *ctx, size_t *nbytes) {
  const particles_out_t *o = ctx;
  size_t n = o->particles ? (size_t)o->particles->count * 3 : 0;
  const float *src = !o->particles ? NULL : o->velocities ? o->particles->vel : o->particles->pos;
  *nbytes = 4 * n;
  unsigned char *bytes = malloc(*nbytes ? *nbytes : 1);
  if (!bytes)
    return NULL;
  for (size_t i = 0; i < n; i++) {
    uint32_t u;
    memcpy(&u, &src[i], 4);
    for (int b = 0; b < 4; b++)
      bytes[4 * i + b] = (unsigned char)(u >> (8 * b));
  }
  return bytes;
}

static void particles_out_drop(void *ctx) {
  particles_out_t *o = ctx;
  particles_unref(o->particles);
  free(o);
}

static void get_particles_m(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  const char *field = get(call->params, "field")->valuestring;
  int base64 = strcmp(get(call->params, "encoding")->valuestring, "base64") == 0;
  particles_t *p = e->scene->particles;
  uint32_t n = p ? p->count : 0;
  particles_out_t *o = malloc(sizeof *o);
  if (!o) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  *o = (particles_out_t){.particles = p ? particles_ref(p) : NULL,
                         .velocities = strcmp(field, "velocities") == 0};
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "count", n);
  cJSON_AddStringToObject(r, "field", field);
  call_result_made(call, r, particles_bytes, particles_out_drop, o, (size_t)n * 12, "f32", base64);
}

static const char *const fields[] = {"positions", "velocities", NULL};

static const sch_field_t set_params[] = {
    PARAM_SCENE,
    {.name = "positions",
     .type = SCH_STRING,
     .desc = "Base64 of n × (x, y, z) little-endian f32, each inside fluid.bounds; n at most "
             "limits.particles. Replaces every particle.",
     .unit = "world units",
     .flags = SCH_REQUIRED},
    {.name = "velocities",
     .type = SCH_STRING,
     .desc = "Base64 of n × (x, y, z) little-endian f32, as many as positions; absent: at rest.",
     .unit = "world units/second",
     .flags = SCH_NO_DEFAULT},
    {0}};
static const sch_field_t get_params[] = {
    PARAM_SCENE,
    {.name = "field",
     .type = SCH_ENUM,
     .desc = "Which array: positions (world units) or velocities (world units/second).",
     .enum_values = fields,
     .def_str = "positions"},
    {.name = "encoding",
     .type = SCH_ENUM,
     .desc = "binary: an attachment after the line; base64: inline in 'data'.",
     .enum_values = render_encodings,
     .def_str = "binary"},
    {0}};

static const int set_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, PROTO_E_LIMIT, 0};
static const int get_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, 0};

const method_t method_fluid_set_particles = {
    .name = "fluid.set_particles",
    .summary = "Replaces the fluid's particles; validated as a whole, nothing changes on error.",
    .params = METHOD_PARAMS(set_params),
    .result = "{count}",
    .errors = set_errors,
    .handler = set_particles_m};
const method_t method_fluid_get_particles = {
    .name = "fluid.get_particles",
    .summary = "The fluid's particle positions or velocities as little-endian f32 x, y, z.",
    .params = METHOD_PARAMS(get_params),
    .result = "{count, field} and an f32 attachment of 12 × count bytes.",
    .errors = get_errors,
    .handler = get_particles_m};
