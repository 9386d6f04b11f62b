/*
 * libFuzzer target for the scene model: the input is split at its first NUL into a dotted
 * path and a JSON text. The text is applied to a scene as a merge patch (an object), as a change
 * list and as a JSON Patch (an array) and, when a path is given, set at that path; each must
 * either succeed with a document that validates again, or fail leaving the document exactly as
 * it was. Build with -DVOLFX_FUZZ=ON and clang.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "fuzz.h"
#include "scene.h"

/* Applies 'op' (0: patch, 1: path, 2: changes, 3: JSON Patch) and checks atomicity. */
static void apply(scene_t *s, int op, const char *path, const cJSON *value) {
  char *before = cJSON_PrintUnformatted(s->doc);
  unsigned long version = s->version;
  render_scene_t *snap = s->snapshot;
  scene_error_t err;
  int rc = op == 0   ? scene_patch(s, value, &err)
           : op == 1 ? scene_set_path(s, path, value, &err)
           : op == 2 ? scene_set_changes(s, value, &err)
                     : scene_apply_ops(s, value, &err);
  char *after = cJSON_PrintUnformatted(s->doc);
  if (rc != 0) {
    REQUIRE(strcmp(before, after) == 0);
    REQUIRE(s->version == version && s->snapshot == snap);
    REQUIRE(err.message[0] != '\0');
  } else {
    /* What was accepted validates again, unchanged, but for fluid.count: the scene kept its
     * particles through the change, while a fresh one lays out fluid.initial among the
     * objects as they are now. */
    scene_error_t err2;
    scene_t *copy = scene_create("copy", s->doc, &err2);
    REQUIRE(copy != NULL);
    cJSON_SetNumberValue(cJSON_GetObjectItem(cJSON_GetObjectItem(copy->doc, "fluid"), "count"),
                         (s->particles ? s->particles->count : 0));
    char *again = cJSON_PrintUnformatted(copy->doc);
    REQUIRE(strcmp(again, after) == 0);
    free(again);
    scene_destroy(copy);
  }
  free(before);
  free(after);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  static scene_t *scene;
  if (!scene) {
    scene_error_t err;
    scene = scene_create("fuzz", NULL, &err);
    REQUIRE(scene != NULL);
  }
  const uint8_t *nul = memchr(data, 0, size);
  char path[256] = "";
  const uint8_t *json = data;
  size_t jlen = size;
  if (nul && (size_t)(nul - data) < sizeof path) {
    memcpy(path, data, (size_t)(nul - data));
    path[nul - data] = '\0';
    json = nul + 1;
    jlen = size - (size_t)(nul - data) - 1;
  }
  cJSON *v = cJSON_ParseWithLength((const char *)json, jlen);
  if (!v)
    return 0;
  if (cJSON_IsObject(v))
    apply(scene, 0, NULL, v);
  if (cJSON_IsArray(v)) {
    apply(scene, 2, NULL, v);
    apply(scene, 3, NULL, v);
  }
  if (path[0])
    apply(scene, 1, path, v);
  cJSON_Delete(v);
  return 0;
}
