/*
 * libvolfx's method table and typed wrappers (volfx.h): the name of every volfxd method, and
 * the calls a game loop makes most, each building its params from C arguments and leaving out
 * the ones the caller did not give, so that the server's method table supplies their defaults.
 */
#include <stdio.h>
#include <stdlib.h>

#include "volfx.h"

static const char *const method_names[VOLFX_M_COUNT] = {
#define XX(id, name) [VOLFX_M_##id] = name,
    VOLFX_METHOD_MAP(XX)
#undef XX
};

const char *volfx_method_name(volfx_method_t m) {
  return (unsigned)m < VOLFX_M_COUNT ? method_names[m] : NULL;
}

static int fail_usage(volfx_error_t *err, int code, const char *message) {
  if (err != NULL) {
    err->code = code;
    snprintf(err->message, sizeof(err->message), "%s", message);
    err->path[0] = '\0';
  }
  return code;
}

int volfx_call_method(volfx_conn_t *conn, volfx_method_t m, cJSON *params, cJSON **result,
                      volfx_attachment_t *att, volfx_error_t *err) {
  const char *name = volfx_method_name(m);
  if (name == NULL) {
    cJSON_Delete(params);
    return fail_usage(err, VOLFX_E_INVAL, "volfx_call_method: no such method");
  }
  return volfx_call(conn, name, params, result, att, err);
}

/*
 * A params object with "scene" when 'scene' is not NULL and the string member 'key' when
 * 'value' is not NULL; NULL when out of memory.
 */
static cJSON *params_new(const char *scene, const char *key, const char *value) {
  cJSON *p = cJSON_CreateObject();
  if (p == NULL || (scene != NULL && cJSON_AddStringToObject(p, "scene", scene) == NULL) ||
      (value != NULL && cJSON_AddStringToObject(p, key, value) == NULL)) {
    cJSON_Delete(p);
    return NULL;
  }
  return p;
}

/* volfx_call() of 'params' built by the caller; NULL 'params' means out of memory. */
static int call_built(volfx_conn_t *conn, const char *method, cJSON *params, cJSON **result,
                      volfx_error_t *err) {
  if (params == NULL) {
    if (result != NULL) {
      *result = NULL;
    }
    return fail_usage(err, VOLFX_E_NOMEM, volfx_strerror(VOLFX_E_NOMEM));
  }
  return volfx_call(conn, method, params, result, NULL, err);
}

/* Moves 'item' (taken) into 'p' as 'key'; returns 'p', or NULL (freeing both) when either is. */
static cJSON *params_take(cJSON *p, const char *key, cJSON *item) {
  if (p == NULL || item == NULL) {
    cJSON_Delete(p);
    cJSON_Delete(item);
    return NULL;
  }
  cJSON_AddItemToObject(p, key, item);
  return p;
}

/* volfx_call() of scene.set with 'p', storing the result's version in '*version'. */
static int call_set(volfx_conn_t *conn, cJSON *p, int64_t *version, volfx_error_t *err) {
  cJSON *r = NULL;
  int rc = call_built(conn, "scene.set", p, &r, err);
  if (rc == 0 && version != NULL) {
    const cJSON *v = cJSON_GetObjectItemCaseSensitive(r, "version");
    *version = cJSON_IsNumber(v) ? (int64_t)v->valuedouble : 0;
  }
  cJSON_Delete(r);
  return rc;
}

int volfx_info(volfx_conn_t *conn, cJSON **result, volfx_error_t *err) {
  return volfx_call(conn, "server.info", NULL, result, NULL, err);
}

int volfx_stats(volfx_conn_t *conn, cJSON **result, volfx_error_t *err) {
  return volfx_call(conn, "stats", NULL, result, NULL, err);
}

int volfx_scene_create(volfx_conn_t *conn, const char *name, const char *preset,
                       volfx_error_t *err) {
  if (name == NULL) {
    return fail_usage(err, VOLFX_E_INVAL, "volfx_scene_create: the name is NULL");
  }
  cJSON *p = params_new(NULL, "preset", preset);
  if (p != NULL && cJSON_AddStringToObject(p, "name", name) == NULL) {
    cJSON_Delete(p);
    p = NULL;
  }
  return call_built(conn, "scene.create", p, NULL, err);
}

int volfx_scene_delete(volfx_conn_t *conn, const char *name, volfx_error_t *err) {
  if (name == NULL) {
    return fail_usage(err, VOLFX_E_INVAL, "volfx_scene_delete: the name is NULL");
  }
  return call_built(conn, "scene.delete", params_new(NULL, "name", name), NULL, err);
}

int volfx_scene_get(volfx_conn_t *conn, const char *scene, const char *path, cJSON **result,
                    volfx_error_t *err) {
  return call_built(conn, "scene.get", params_new(scene, "path", path), result, err);
}

int volfx_scene_set(volfx_conn_t *conn, const char *scene, const char *path, cJSON *value,
                    int64_t *version, volfx_error_t *err) {
  if (path == NULL || value == NULL) {
    cJSON_Delete(value);
    return fail_usage(err, VOLFX_E_INVAL, "volfx_scene_set: the path or the value is NULL");
  }
  return call_set(conn, params_take(params_new(scene, "path", path), "value", value), version, err);
}

int volfx_scene_patch(volfx_conn_t *conn, const char *scene, cJSON *patch, int64_t *version,
                      volfx_error_t *err) {
  if (patch == NULL) {
    return fail_usage(err, VOLFX_E_INVAL, "volfx_scene_patch: the patch is NULL");
  }
  return call_set(conn, params_take(params_new(scene, NULL, NULL), "patch", patch), version, err);
}

int volfx_sim_step(volfx_conn_t *conn, const char *scene, int steps, cJSON **result,
                   volfx_error_t *err) {
  cJSON *p = params_new(scene, NULL, NULL);
  if (p != NULL && steps > 0) {
    p = params_take(p, "steps", cJSON_CreateNumber(steps));
  }
  return call_built(conn, "sim.step", p, result, err);
}

int volfx_sim_play(volfx_conn_t *conn, const char *scene, double rate, volfx_error_t *err) {
  cJSON *p = params_new(scene, NULL, NULL);
  if (p != NULL && rate > 0) {
    p = params_take(p, "rate", cJSON_CreateNumber(rate));
  }
  return call_built(conn, "sim.play", p, NULL, err);
}

int volfx_sim_pause(volfx_conn_t *conn, const char *scene, volfx_error_t *err) {
  return call_built(conn, "sim.pause", params_new(scene, NULL, NULL), NULL, err);
}

int volfx_render(volfx_conn_t *conn, cJSON *params, cJSON **result, volfx_attachment_t *att,
                 volfx_error_t *err) {
  return volfx_call(conn, "render", params, result, att, err);
}

int volfx_frames_update(volfx_conn_t *conn, int64_t id, cJSON *view, volfx_error_t *err) {
  cJSON *p = view != NULL ? view : cJSON_CreateObject();
  if (p != NULL && !cJSON_IsObject(p)) {
    cJSON_Delete(p);
    return fail_usage(err, VOLFX_E_INVAL, "volfx_frames_update: the view is not an object");
  }
  if (p != NULL) {
    cJSON_DeleteItemFromObjectCaseSensitive(p, "id");
    p = params_take(p, "id", cJSON_CreateNumber((double)id));
  }
  return call_built(conn, "frames.update", p, NULL, err);
}
