/*
 * What identifies the scene of a bake. A bake directory holds snapshots of one scene at many
 * frames; its manifest (bake.json) records the scene as proto_bake_key gives it, so that a
 * bake can be resumed and rendered only with the scene it was made from. The key is the
 * document without what the clock moves: sim.frame, sim.time and sim.playing, fluid.count, and
 * every wave field an animation drives (its value depends on the time, its animation does
 * not). Two documents with equal keys describe the same shot.
 */
#include <string.h>

#include "proto.h"

static cJSON *member(const cJSON *o, const char *name) {
  return cJSON_GetObjectItemCaseSensitive(o, name);
}

cJSON *proto_bake_key(const cJSON *doc) {
  if (!cJSON_IsObject(doc))
    return NULL;
  cJSON *key = cJSON_Duplicate(doc, 1);
  if (!key)
    return NULL;
  static const char *const clock[] = {"frame", "time", "playing"};
  cJSON *sim = member(key, "sim");
  for (size_t i = 0; i < sizeof clock / sizeof clock[0]; i++)
    cJSON_DeleteItemFromObjectCaseSensitive(sim, clock[i]);
  cJSON_DeleteItemFromObjectCaseSensitive(member(key, "fluid"), "count");
  cJSON *wave;
  cJSON_ArrayForEach(wave, member(key, "waves")) {
    const cJSON *anim;
    cJSON_ArrayForEach(anim, member(wave, "animate")) {
      const char *field = cJSON_GetStringValue(member(anim, "field"));
      if (field && strcmp(field, "animate") != 0)
        cJSON_DeleteItemFromObjectCaseSensitive(wave, field);
    }
  }
  return key;
}

int proto_bake_same(const cJSON *a, const cJSON *b) {
  cJSON *ka = proto_bake_key(a), *kb = proto_bake_key(b);
  int same = ka && kb && cJSON_Compare(ka, kb, 1);
  cJSON_Delete(ka);
  cJSON_Delete(kb);
  return same;
}
