/*
 * The OpenRPC document of rpc.discover, generated from the method table and the scene schema,
 * so that what the server checks and what it publishes cannot drift apart.
 */
#include <string.h>

#include "dispatch.h"

static cJSON *error_json(int code) {
  cJSON *e = cJSON_CreateObject();
  cJSON_AddNumberToObject(e, "code", code);
  cJSON_AddStringToObject(e, "message", proto_err_message(code));
  return e;
}

/* The frame size params are bounded by a configurable limit, which the static schema cannot
 * know: the published maximum is the server's own. */
static void publish_limits(const server_t *s, const sch_field_t *f, cJSON *schema) {
  if (strcmp(f->name, "width") == 0 || strcmp(f->name, "height") == 0) {
    cJSON_DeleteItemFromObject(schema, "maximum");
    cJSON_AddNumberToObject(schema, "maximum", s->cfg.limits.frame_side);
  }
}

/* Member 'name' of the properties of object schema 'o', or NULL. */
static cJSON *property(cJSON *o, const char *name) {
  return cJSON_GetObjectItemCaseSensitive(cJSON_GetObjectItemCaseSensitive(o, "properties"), name);
}

/* Sets the items of vec3 schema 'v' to integers from 1 to 'max'. */
static void integer_sides(cJSON *v, uint32_t max) {
  cJSON *items = cJSON_GetObjectItemCaseSensitive(v, "items");
  if (!items)
    return;
  cJSON_ReplaceItemInObjectCaseSensitive(items, "type", cJSON_CreateString("integer"));
  cJSON_DeleteItemFromObjectCaseSensitive(items, "maximum");
  cJSON_AddNumberToObject(items, "maximum", max);
}

/* The scene's grid sides (cloud.grid, volumes[].dims) are bounded by limits.cloud_side, which the
 * static schema cannot know either. */
static void publish_sides(const server_t *s, cJSON *scene) {
  integer_sides(property(property(scene, "cloud"), "grid"), s->cfg.limits.cloud_side);
  cJSON *vols = cJSON_GetObjectItemCaseSensitive(property(scene, "volumes"), "items");
  integer_sides(property(vols, "dims"), s->cfg.limits.cloud_side);
}

static cJSON *method_json(const server_t *s, const method_t *m) {
  cJSON *o = cJSON_CreateObject();
  cJSON_AddStringToObject(o, "name", m->name);
  cJSON_AddStringToObject(o, "summary", m->summary);
  cJSON_AddStringToObject(o, "paramStructure", "by-name");
  cJSON *params = cJSON_AddArrayToObject(o, "params");
  for (const sch_field_t *f = m->params->fields; f && f->name; f++) {
    cJSON *p = cJSON_CreateObject();
    cJSON_AddStringToObject(p, "name", f->name);
    if (f->desc)
      cJSON_AddStringToObject(p, "description", f->desc);
    cJSON_AddBoolToObject(p, "required", (f->flags & SCH_REQUIRED) != 0);
    cJSON *schema = sch_to_json_schema(f);
    publish_limits(s, f, schema);
    cJSON_AddItemToObject(p, "schema", schema);
    cJSON_AddItemToArray(params, p);
  }
  cJSON *result = cJSON_AddObjectToObject(o, "result");
  cJSON_AddStringToObject(result, "name", "result");
  cJSON_AddStringToObject(result, "description", m->result);
  cJSON_AddItemToObject(result, "schema", cJSON_CreateObject());
  cJSON *errors = cJSON_AddArrayToObject(o, "errors");
  cJSON_AddItemToArray(errors, error_json(PROTO_E_INVALID_PARAMS));
  for (const int *e = m->errors; e && *e; e++)
    cJSON_AddItemToArray(errors, error_json(*e));
  return o;
}

cJSON *discover_document(const server_t *s) {
  cJSON *doc = cJSON_CreateObject();
  cJSON_AddStringToObject(doc, "openrpc", "1.2.6");
  cJSON *info = cJSON_AddObjectToObject(doc, "info");
  cJSON_AddStringToObject(info, "title", "volfxd");
  cJSON_AddStringToObject(info, "version", VOLFX_VERSION);
  cJSON_AddStringToObject(info, "x-protocol", PROTO_VERSION);
  cJSON *methods = cJSON_AddArrayToObject(doc, "methods");
  for (const method_t *const *m = method_table; *m; m++)
    cJSON_AddItemToArray(methods, method_json(s, *m));
  cJSON *components = cJSON_AddObjectToObject(doc, "components");
  cJSON *schemas = cJSON_AddObjectToObject(components, "schemas");
  cJSON *scene = sch_to_json_schema(&scene_schema);
  publish_sides(s, scene);
  cJSON_AddItemToObject(schemas, "Scene", scene);
  cJSON *errors = cJSON_AddObjectToObject(components, "errors");
#define XX(name, code, msg) cJSON_AddItemToObject(errors, #name, error_json(code));
  PROTO_ERROR_MAP(XX)
#undef XX
  return doc;
}
