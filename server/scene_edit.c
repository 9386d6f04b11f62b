/*
 * Edits of a scene's document by a client: an RFC 7386 merge patch (scene.set's patch) and a
 * value set at a dotted path. Each builds the whole new document on a copy and hands it to
 * scene_commit, which validates, compiles and applies it, or changes nothing.
 */
#include <stdio.h>
#include <string.h>

#include "proto.h"
#include "scene_internal.h"

/*
 * RFC 7386 on 'target' (an object, modified in place) from 'patch' (an object): a null member
 * removes the target's member, an object member merges recursively into an object (replacing
 * a non-object), and anything else, arrays included, replaces the member whole. Returns -1 on
 * OOM, leaving 'target' partly patched (the caller discards it).
 */
static int merge_patch(cJSON *target, const cJSON *patch) {
  for (const cJSON *p = patch->child; p; p = p->next) {
    cJSON *t = cJSON_GetObjectItemCaseSensitive(target, p->string);
    if (cJSON_IsNull(p)) {
      if (t)
        cJSON_DeleteItemFromObjectCaseSensitive(target, p->string);
      continue;
    }
    if (cJSON_IsObject(p)) {
      if (!cJSON_IsObject(t)) {
        cJSON *o = cJSON_CreateObject();
        if (!o)
          return -1;
        /* The *InObject* forms give the new item its key; ViaPointer would leave it nameless. */
        cJSON_bool linked = t ? cJSON_ReplaceItemInObjectCaseSensitive(target, p->string, o)
                              : cJSON_AddItemToObject(target, p->string, o);
        if (!linked) {
          cJSON_Delete(o);
          return -1;
        }
        t = o;
      }
      if (merge_patch(t, p) != 0)
        return -1;
      continue;
    }
    cJSON *v = cJSON_Duplicate(p, 1);
    if (!v)
      return -1;
    cJSON_bool linked = t ? cJSON_ReplaceItemInObjectCaseSensitive(target, p->string, v)
                          : cJSON_AddItemToObject(target, p->string, v);
    if (!linked) {
      cJSON_Delete(v);
      return -1;
    }
  }
  return 0;
}

/*
 * Applies merge patch 'patch' to the scene. A member set to null is deleted and, the document
 * being validated afterwards, comes back with its default: {"camera": {"fov_y": null}} resets
 * the field of view, {"camera": null} the whole camera. Arrays are replaced whole, so an
 * object inside "objects" is changed by sending the whole array (or with scene_set_path).
 */
int scene_patch(scene_t *s, const cJSON *patch, scene_error_t *err) {
  proto_error_clear(err);
  if (!cJSON_IsObject(patch))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "", "a patch must be a JSON object");
  cJSON *doc = cJSON_Duplicate(s->doc, 1);
  if (!doc || merge_patch(doc, patch) != 0) {
    cJSON_Delete(doc);
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  }
  return scene_commit(s, doc, NULL, err);
}

/*
 * Sets 'value' at 'path'. The parent of the last component must exist; under an object the
 * member is replaced or added (a name the schema does not know is then refused as invalid),
 * under an array the index must be below the length, or equal to it to append. Setting an
 * object member to null deletes it, so it gets its default back, as in a merge patch. The
 * empty path is refused: the whole document changes through scene_patch or scene_replace.
 */
int scene_set_path(scene_t *s, const char *path, const cJSON *value, scene_error_t *err) {
  proto_error_clear(err);
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
  if (!last[0])
    return proto_error_set(err, PROTO_E_NOT_FOUND, path, "no such path in the scene: %s", path);

  cJSON *doc = cJSON_Duplicate(s->doc, 1);
  cJSON *v = cJSON_Duplicate(value, 1);
  if (!doc || !v) {
    cJSON_Delete(doc);
    cJSON_Delete(v);
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  }
  cJSON *parent = dot ? sch_path_get(doc, parent_path) : doc;
  int ok = 0;
  if (cJSON_IsObject(parent)) {
    cJSON *old = cJSON_GetObjectItemCaseSensitive(parent, last);
    if (cJSON_IsNull(v)) {
      cJSON_Delete(v);
      if (old)
        cJSON_DeleteItemFromObjectCaseSensitive(parent, last);
      ok = 1;
    } else if (old) {
      ok = cJSON_ReplaceItemInObjectCaseSensitive(parent, last, v);
    } else {
      ok = cJSON_AddItemToObject(parent, last, v);
    }
  } else if (cJSON_IsArray(parent)) {
    /* sch_path_get with the full path accepts exactly the indices that exist. */
    cJSON *old = sch_path_get(doc, path);
    int n = cJSON_GetArraySize(parent);
    char index[16];
    snprintf(index, sizeof index, "%d", n);
    if (old)
      ok = cJSON_ReplaceItemViaPointer(parent, old, v);
    else if (strcmp(last, index) == 0)
      ok = cJSON_AddItemToArray(parent, v);
    else
      ok = -1;
  } else {
    ok = -1;
  }
  if (ok != 1) {
    cJSON_Delete(doc);
    cJSON_Delete(v);
    if (ok == -1)
      return proto_error_set(err, PROTO_E_NOT_FOUND, path, "no such path in the scene: %s", path);
    return proto_error_set(err, PROTO_E_INTERNAL, "", "out of memory");
  }
  return scene_commit(s, doc, NULL, err);
}
