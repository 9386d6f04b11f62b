/*
 * The cloud's methods (SPEC §5.4): cloud.get_cells and cloud.set_cells. The jobs that step the
 * cloud and compute its density live in step_cloud.c.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dispatch.h"
#include "frames.h"
#include "step_cloud.h"

static const cJSON *get(const cJSON *o, const char *name) {
  return cJSON_GetObjectItemCaseSensitive(o, name);
}

static const char *const cloud_fields[] = {"hum", "act", "cld", "density", NULL};

static cloud_field_t field_of(const char *f) {
  return strcmp(f, "hum") == 0 ? CLOUD_HUM : strcmp(f, "act") == 0 ? CLOUD_ACT : CLOUD_CLD;
}

/* The scene of 'call' if it has a cloud; otherwise answers the call and returns NULL. */
static scene_entry_t *cloud_scene(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (e && !e->scene->cloud_cells) {
    call_error(call, PROTO_E_INVALID_PARAMS, "scene",
               "invalid params: scene: '%s' has no cloud (cloud.enabled is false)", e->scene->name);
    return NULL;
  }
  return e;
}

/* What cloud.get_cells sends: the cells or density (references, immutable), read on any
 * thread. */
typedef struct cells_out {
  cloud_cells_t *cells;
  density_grid_t *density; /* For the density field, else NULL. */
  cloud_field_t field;
} cells_out_t;

static unsigned char *cells_bytes(void *ctx, size_t *nbytes) {
  const cells_out_t *o = ctx;
  size_t n = cloud_cells_count(o->cells);
  *nbytes = o->density ? 4 * n : n;
  unsigned char *bytes = malloc(*nbytes);
  if (!bytes)
    return NULL;
  if (o->density) {
    const float *src = o->density->data;
    for (size_t i = 0; i < n; i++) {
      uint32_t u;
      memcpy(&u, &src[i], 4);
      for (int b = 0; b < 4; b++)
        bytes[4 * i + b] = (unsigned char)(u >> (8 * b));
    }
  } else {
    cloud_cells_export(o->cells, o->field, bytes);
  }
  return bytes;
}

static void cells_out_drop(void *ctx) {
  cells_out_t *o = ctx;
  cloud_cells_unref(o->cells);
  density_grid_unref(o->density);
  free(o);
}

static void get_cells_m(call_t *call) {
  scene_entry_t *e = cloud_scene(call);
  if (!e)
    return;
  const scene_t *s = e->scene;
  const char *field = get(call->params, "field")->valuestring;
  int base64 = strcmp(get(call->params, "encoding")->valuestring, "base64") == 0;
  size_t n = cloud_cells_count(s->cloud_cells);
  int dens = strcmp(field, "density") == 0;
  size_t nbytes = dens ? 4 * n : n;
  cells_out_t *o = malloc(sizeof *o);
  if (!o) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  *o = (cells_out_t){.cells = cloud_cells_ref(s->cloud_cells),
                     .density = dens ? density_grid_ref(s->cloud_density) : NULL,
                     .field = field_of(field)};
  cJSON *r = cJSON_CreateObject();
  cJSON_AddStringToObject(r, "field", field);
  cJSON *dims = cJSON_AddArrayToObject(r, "dims");
  for (int i = 0; i < 3; i++)
    cJSON_AddItemToArray(dims, cJSON_CreateNumber(s->cloud_cells->n[i]));
  cJSON_AddNumberToObject(r, "cells", (double)n);
  cJSON_AddNumberToObject(r, "step", (double)s->cloud_cells->step);
  call_result_made(call, r, cells_bytes, cells_out_drop, o, nbytes, dens ? "f32" : "u8", base64);
}

static void set_cells_m(call_t *call) {
  scene_entry_t *e = cloud_scene(call);
  if (!e)
    return;
  scene_t *s = e->scene;
  const char *field = get(call->params, "field")->valuestring;
  const char *data = get(call->params, "data")->valuestring;
  int dens = strcmp(field, "density") == 0;
  size_t n = cloud_cells_count(s->cloud_cells), want = dens ? 4 * n : n;
  size_t len = strlen(data);
  if (proto_b64_decoded_max(len) > want + 3) {
    call_error(call, PROTO_E_INVALID_PARAMS, "data",
               "invalid params: data: more than the %zu bytes of %s for %zu cells", want, field, n);
    return;
  }
  unsigned char *buf = malloc(want + 3);
  cloud_cells_t *cells = NULL;
  density_grid_t *grid = NULL;
  if (!buf) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  long got = proto_b64_decode(data, len, buf);
  if (got < 0) {
    call_error(call, PROTO_E_INVALID_PARAMS, "data", "invalid params: data: not valid base64");
    goto out;
  }
  if ((size_t)got != want) {
    call_error(call, PROTO_E_INVALID_PARAMS, "data",
               "invalid params: data: %ld bytes, want %zu (%s: %s for each of %u x %u x %u cells)",
               got, want, field, dens ? "one little-endian f32" : "one byte 0 or 1",
               s->cloud_cells->n[0], s->cloud_cells->n[1], s->cloud_cells->n[2]);
    goto out;
  }
  if (dens) {
    grid = density_grid_new(s->cloud_cells->n);
    if (!grid) {
      call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
      goto out;
    }
    for (size_t i = 0; i < n; i++) {
      const unsigned char *b = buf + 4 * i;
      uint32_t u =
          (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 | (uint32_t)b[3] << 24;
      float x;
      memcpy(&x, &u, 4);
      if (!isfinite(x) || x < 0) {
        call_error(call, PROTO_E_INVALID_PARAMS, "data",
                   "invalid params: data: the density of cell %zu is %g; densities must be "
                   "finite and not negative",
                   i, x);
        goto out;
      }
      grid->data[i] = x;
    }
    if (scene_set_cloud(s, cloud_cells_ref(s->cloud_cells), grid, 1) != 0) {
      cloud_cells_unref(s->cloud_cells);
      call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
      goto out;
    }
    grid = NULL;
  } else {
    for (size_t i = 0; i < n; i++)
      if (buf[i] > 1) {
        call_error(call, PROTO_E_INVALID_PARAMS, "data",
                   "invalid params: data: cell %zu is %u; %s cells must be 0 or 1", i, buf[i],
                   field);
        goto out;
      }
    cells = cloud_cells_copy(s->cloud_cells);
    if (!cells) {
      call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
      goto out;
    }
    cloud_cells_import(cells, field_of(field), buf);
    if (field_of(field) == CLOUD_CLD) {
      /* The density follows the new cloud cells at once (no smoothing); the answer waits. */
      int code = cloud_submit_cells(call->srv, e, cells, field, call);
      cells = NULL;
      if (code == PROTO_E_BUSY)
        call_error(call, PROTO_E_BUSY, NULL, "%s: the render queue is full",
                   proto_err_message(PROTO_E_BUSY));
      else if (code != 0)
        call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
      else
        call_hold(call); /* Answered by the job; the connection's next requests see it. */
      goto out;
    }
    if (scene_set_cloud(s, cells, density_grid_ref(s->cloud_density), 1) != 0) {
      density_grid_unref(s->cloud_density);
      call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
      goto out;
    }
    cells = NULL;
  }
  cJSON *r = cJSON_CreateObject();
  cJSON_AddStringToObject(r, "field", field);
  cJSON_AddNumberToObject(r, "cells", (double)n);
  call_result(call, r);
out:
  free(buf);
  cloud_cells_unref(cells);
  density_grid_unref(grid);
}

static const sch_field_t get_params[] = {
    PARAM_SCENE,
    {.name = "field",
     .type = SCH_ENUM,
     .desc = "hum, act or cld: one byte 0 or 1 per cell (u8); density: the density drawn, one "
             "little-endian f32 per cell. x fastest, then y, then z.",
     .enum_values = cloud_fields,
     .def_str = "cld"},
    {.name = "encoding",
     .type = SCH_ENUM,
     .desc = "binary: an attachment after the line; base64: inline in 'data'.",
     .enum_values = render_encodings,
     .def_str = "binary"},
    {0}};
static const sch_field_t set_params[] = {
    PARAM_SCENE,
    {.name = "field",
     .type = SCH_ENUM,
     .desc = "hum, act or cld (one byte 0 or 1 per cell) or density (one little-endian f32 per "
             "cell, finite and not negative). x fastest, then y, then z.",
     .enum_values = cloud_fields,
     .flags = SCH_REQUIRED},
    {.name = "data",
     .type = SCH_STRING,
     .desc = "Base64 of exactly one value per cell of cloud.grid. Setting cld recomputes the "
             "density before the answer; setting density shows it until the next step.",
     .flags = SCH_REQUIRED},
    {0}};

static const int get_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, PROTO_E_LIMIT, 0};
static const int set_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, PROTO_E_BUSY, 0};

const method_t method_cloud_get_cells = {
    .name = "cloud.get_cells",
    .summary = "One field of the cloud's cells (hum, act, cld as u8 0/1) or its density (f32).",
    .params = METHOD_PARAMS(get_params),
    .result = "{field, dims, cells, step} and an attachment of one u8 or f32 per cell.",
    .errors = get_errors,
    .handler = get_cells_m};
const method_t method_cloud_set_cells = {
    .name = "cloud.set_cells",
    .summary = "Replaces one field of the cloud's cells or its density; validated as a whole, "
               "nothing changes on error.",
    .params = METHOD_PARAMS(set_params),
    .result = "{field, cells}",
    .errors = set_errors,
    .handler = set_cells_m};
