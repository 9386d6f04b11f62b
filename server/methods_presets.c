/*
 * scene.presets: the presets scene.create can start a scene from, the NAME.json files of the
 * presets directory (--presets) whose names scene.create takes, sorted.
 */
#include <ctype.h>
#include <dirent.h>
#include <stdlib.h>
#include <string.h>

#include "dispatch.h"

/* Whether the file 'name' is a preset, NAME.json with a name scene.create accepts. */
static int preset_file(const char *name) {
  size_t n = strlen(name);
  if (n <= 5 || n - 5 > 63 || strcmp(name + n - 5, ".json") != 0 || name[0] == '.')
    return 0;
  for (size_t i = 0; i < n - 5; i++)
    if (!isalnum((unsigned char)name[i]) && name[i] != '_' && name[i] != '-' && name[i] != '.')
      return 0;
  return 1;
}

static int by_name(const void *a, const void *b) {
  return strcmp(*(char *const *)a, *(char *const *)b);
}

static void scene_presets(call_t *call) {
  cJSON *r = cJSON_CreateObject();
  cJSON *arr = cJSON_AddArrayToObject(r, "presets");
  DIR *d = opendir(call->srv->cfg.presets_dir);
  char **names = NULL;
  size_t n = 0, cap = 0;
  for (struct dirent *de; d && (de = readdir(d));) {
    if (!preset_file(de->d_name))
      continue;
    if (n == cap) {
      char **grown = realloc(names, (cap = cap ? 2 * cap : 16) * sizeof *names);
      if (!grown)
        break;
      names = grown;
    }
    names[n] = strndup(de->d_name, strlen(de->d_name) - 5);
    n += names[n] != NULL;
  }
  if (d)
    closedir(d);
  qsort(names, n, sizeof *names, by_name);
  for (size_t i = 0; i < n; i++) {
    cJSON_AddItemToArray(arr, cJSON_CreateString(names[i]));
    free(names[i]);
  }
  free(names);
  call_result(call, r);
}

static const sch_field_t presets_params[] = {{0}};
static const int presets_errors[] = {PROTO_E_UNAUTHORIZED, 0};

const method_t method_scene_presets = {
    .name = "scene.presets",
    .summary = "Lists the presets scene.create can start a scene from.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = presets_params},
    .result = "{presets: [name, ...]}",
    .errors = presets_errors,
    .handler = scene_presets};
