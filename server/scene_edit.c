/*
 * Edits of a scene's document by a client: an RFC 7386 merge patch (scene.set's patch) that
 * merges the items of keyed arrays by their id, a value set at a dotted path, a list of such
 * changes, and an RFC 6902 JSON Patch (json_patch.c). Each builds the whole new document on a
 * copy and hands it to scene_commit once, which validates, compiles and applies it, or changes
 * nothing: a list of changes is one version or none.
 */
#include <stdio.h>
#include <string.h>

#include "json_patch.h"
#include "proto.h"
#include "scene_internal.h"

/* Whether 'f' describes a keyed array: one whose items are objects with an "id" member. */
static int keyed_array(const sch_field_t *f) {
  return f && f->type == SCH_ARRAY && f->items && sch_field_member(f->items, "id");
}

/* Whether every item of patch array 'p' (one at least) is an object with a non-empty string
 * "id" that no other item has: an item patch of a keyed array rather than a new value for it.
 * Repeated ids make a new value, which validation then refuses. */
static int item_patch(const cJSON *p) {
  if (!p->child)
    return 0;
  for (const cJSON *it = p->child; it; it = it->next) {
    const char *id = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(it, "id"));
    if (!cJSON_IsObject(it) || !id || !id[0])
      return 0;
    for (const cJSON *q = p->child; q != it; q = q->next)
      if (strcmp(cJSON_GetObjectItemCaseSensitive(q, "id")->valuestring, id) == 0)
        return 0;
  }
  return 1;
}

static int merge_patch(cJSON *target, const cJSON *patch, const sch_field_t *f);

/* Applies item patch 'patch' to keyed array 'target' (items described by 'items'): each item
 * merges into the item with its id, or is appended when none has it. */
static int merge_items(cJSON *target, const cJSON *patch, const sch_field_t *items) {
  for (const cJSON *p = patch->child; p; p = p->next) {
    cJSON *t = sch_item_by_id(target, cJSON_GetObjectItemCaseSensitive(p, "id")->valuestring);
    if (!t) {
      t = cJSON_CreateObject();
      if (!t || !cJSON_AddItemToArray(target, t)) {
        cJSON_Delete(t);
        return -1;
      }
    }
    if (merge_patch(t, p, items) != 0)
      return -1;
  }
  return 0;
}

/* Puts 'v' (taken) as member 'name' of object 'target', in place of the member there. */
static int put_member(cJSON *target, const char *name, cJSON *v) {
  /* The *InObject* forms give the new item its key; ViaPointer would leave it nameless. */
  cJSON_bool linked = cJSON_GetObjectItemCaseSensitive(target, name)
                          ? cJSON_ReplaceItemInObjectCaseSensitive(target, name, v)
                          : cJSON_AddItemToObject(target, name, v);
  if (!linked)
    cJSON_Delete(v);
  return linked ? 0 : -1;
}

/*
 * RFC 7386 on 'target' (an object, modified in place, described by 'f' or NULL) from 'patch'
 * (an object): a null member removes the target's member, an object member merges recursively
 * into an object (replacing a non-object), an item patch (item_patch) of a keyed array merges
 * item by item, and anything else, other arrays included, replaces the member whole. Returns -1
 * on OOM, leaving 'target' partly patched (the caller discards it).
 */
static int merge_patch(cJSON *target, const cJSON *patch, const sch_field_t *f) {
  for (const cJSON *p = patch->child; p; p = p->next) {
    cJSON *t = cJSON_GetObjectItemCaseSensitive(target, p->string);
    const sch_field_t *mf = sch_field_member(f, p->string);
    if (cJSON_IsNull(p)) {
      if (t)
        cJSON_DeleteItemFromObjectCaseSensitive(target, p->string);
      continue;
    }
    if (cJSON_IsObject(p)) {
      if (!cJSON_IsObject(t)) {
        t = cJSON_CreateObject();
        if (!t || put_member(target, p->string, t) != 0)
          return -1;
      }
      if (merge_patch(t, p, mf) != 0)
        return -1;
      continue;
    }
    if (cJSON_IsArray(p) && cJSON_IsArray(t) && keyed_array(mf) && item_patch(p)) {
      if (merge_items(t, p, mf->items) != 0)
        return -1;
      continue;
    }
    cJSON *v = cJSON_Duplicate(p, 1);
    if (!v || put_member(target, p->string, v) != 0)
      return -1;
  }
  return 0;
}

int scene_path_missing(cJSON *doc, const char *path, scene_error_t *err) {
  char why[160];
  sch_path_explain(doc, path, why, sizeof why);
  return proto_error_set(err, PROTO_E_NOT_FOUND, path, "no such path in the scene: %.60s: %s", path,
                         why);
}

/*
 * Applies merge patch 'patch' to the scene. A member set to null is deleted and, the document
 * being validated afterwards, comes back with its default: {"camera": {"fov_y": null}} resets
 * the field of view, {"camera": null} the whole camera. Keyed arrays (objects, waves, volumes)
 * take item patches: {"objects": [{"id": "orb", "scale": [2, 2, 2]}]} changes the orb alone.
 */
int scene_patch(scene_t *s, const cJSON *patch, scene_error_t *err) {
  proto_error_clear(err);
  if (!cJSON_IsObject(patch))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "", "a patch must be a JSON object");
  cJSON *doc = cJSON_Duplicate(s->doc, 1);
  if (!doc || merge_patch(doc, patch, &scene_schema) != 0) {
    cJSON_Delete(doc);
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  }
  return scene_commit(s, doc, NULL, err);
}

/*
 * Sets 'value' at 'path' in 'doc' (not yet validated). The parent of the last component must
 * exist; under an object the member is replaced or added (a name the schema does not know is
 * then refused as invalid), or deleted by null; under an array the component is an index below
 * the length, or equal to it to append, or an item's id; null removes the item. Returns 0, or
 * -1 with 'err' set.
 */
static int edit_path(cJSON *doc, const char *path, const cJSON *value, scene_error_t *err) {
  if (!path || !path[0])
    return proto_error_set(
        err, PROTO_E_INVALID_PARAMS, "",
        "a path must name a member of the scene (use a patch for the whole scene)");
  if (!value)
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, path, "%s: a value is required", path);
  char parent_path[256];
  if (strlen(path) >= sizeof parent_path)
    return proto_error_set(err, PROTO_E_NOT_FOUND, path, "no such path in the scene: %.200s", path);
  snprintf(parent_path, sizeof parent_path, "%s", path);
  char *dot = strrchr(parent_path, '.');
  const char *last = dot ? dot + 1 : parent_path;
  if (dot)
    *dot = '\0';
  cJSON *parent = dot ? sch_path_get(doc, parent_path) : doc;
  cJSON *old = last[0] ? sch_path_get(doc, path) : NULL;
  char end[16];
  snprintf(end, sizeof end, "%d", cJSON_GetArraySize(parent));
  int appends = cJSON_IsArray(parent) && strcmp(last, end) == 0;
  if (!last[0] || !(cJSON_IsObject(parent) || old || appends))
    return scene_path_missing(doc, path, err);
  if (cJSON_IsNull(value)) {
    /* Deleting a member that is absent changes nothing; an item must exist to be removed. */
    if (!old && !cJSON_IsObject(parent))
      return scene_path_missing(doc, path, err);
    if (old)
      cJSON_Delete(cJSON_DetachItemViaPointer(parent, old));
    return 0;
  }
  cJSON *v = cJSON_Duplicate(value, 1);
  int ok = 0;
  if (v && cJSON_IsObject(parent))
    ok = put_member(parent, last, v) == 0;
  else if (v && old)
    ok = cJSON_ReplaceItemViaPointer(parent, old, v);
  else if (v)
    ok = cJSON_AddItemToArray(parent, v);
  if (v && !cJSON_IsObject(parent) && ok && v->string && !(v->type & cJSON_StringIsConst)) {
    cJSON_free(v->string); /* The copy kept the name "value"; an array's item has none. */
    v->string = NULL;
  }
  if (!ok) {
    if (v && !cJSON_IsObject(parent))
      cJSON_Delete(v);
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  }
  return 0;
}

/* Merges 'patch' into the value at 'path' in 'doc' ("" for the document), as scene_patch does
 * at the top. Returns 0, or -1 with 'err' set. */
static int edit_merge(cJSON *doc, const char *path, const cJSON *patch, scene_error_t *err) {
  if (!cJSON_IsObject(patch))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, path, "a patch must be a JSON object");
  cJSON *at = sch_path_get(doc, path);
  if (!at)
    return scene_path_missing(doc, path, err);
  if (cJSON_IsObject(at))
    return merge_patch(at, patch, sch_path_field(&scene_schema, path)) == 0
               ? 0
               : proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  /* A patch replaces a value that is not an object with the patch applied to {}. */
  cJSON *fresh = cJSON_CreateObject();
  int rc = fresh && merge_patch(fresh, patch, sch_path_field(&scene_schema, path)) == 0
               ? edit_path(doc, path, fresh, err)
               : proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  cJSON_Delete(fresh);
  return rc;
}

int scene_set_path(scene_t *s, const char *path, const cJSON *value, scene_error_t *err) {
  proto_error_clear(err);
  cJSON *doc = cJSON_Duplicate(s->doc, 1);
  if (!doc)
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  if (edit_path(doc, path, value, err) != 0) {
    cJSON_Delete(doc);
    return -1;
  }
  return scene_commit(s, doc, NULL, err);
}

/* Prefixes the message of 'err' with 'where' ("changes.2: ..."), keeping its code and path. */
static int error_within(scene_error_t *err, const char *where) {
  char msg[sizeof err->message];
  snprintf(msg, sizeof msg, "%s", err->message);
  snprintf(err->message, sizeof err->message, "%.24s: %.200s", where, msg);
  return -1;
}

/* Applies one item of a change list to 'doc'. Returns 0, or -1 with 'err' set. */
static int edit_change(cJSON *doc, const cJSON *change, scene_error_t *err) {
  const cJSON *path = cJSON_GetObjectItemCaseSensitive(change, "path");
  const cJSON *value = cJSON_GetObjectItemCaseSensitive(change, "value");
  const cJSON *patch = cJSON_GetObjectItemCaseSensitive(change, "patch");
  if (!cJSON_IsObject(change) || !cJSON_IsString(path) || !value == !patch)
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "",
                           "a change is an object {path, value} or {path, patch}");
  for (const cJSON *m = change->child; m; m = m->next)
    if (strcmp(m->string, "path") != 0 && strcmp(m->string, "value") != 0 &&
        strcmp(m->string, "patch") != 0)
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, "",
                             "unknown member \"%.40s\" (a change has path and value or patch)",
                             m->string);
  if (patch)
    return edit_merge(doc, path->valuestring, patch, err);
  return edit_path(doc, path->valuestring, value, err);
}

int scene_set_changes(scene_t *s, const cJSON *changes, scene_error_t *err) {
  proto_error_clear(err);
  if (!cJSON_IsArray(changes))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "", "changes must be an array");
  cJSON *doc = cJSON_Duplicate(s->doc, 1);
  if (!doc)
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  int i = 0;
  for (const cJSON *c = changes->child; c; c = c->next, i++) {
    if (edit_change(doc, c, err) != 0) {
      char where[32];
      snprintf(where, sizeof where, "changes.%d", i);
      cJSON_Delete(doc);
      return error_within(err, where);
    }
  }
  return scene_commit(s, doc, NULL, err);
}

int scene_apply_ops(scene_t *s, const cJSON *ops, scene_error_t *err) {
  proto_error_clear(err);
  cJSON *doc = cJSON_Duplicate(s->doc, 1);
  if (!doc)
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  if (json_patch_apply(doc, ops, err) != 0) {
    cJSON_Delete(doc);
    return -1;
  }
  return scene_commit(s, doc, NULL, err);
}
