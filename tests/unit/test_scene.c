/*
 * Unit tests of the scene model: schema validation and defaults, merge patches, set-at-path,
 * atomicity of refused changes (document, version and snapshot untouched), snapshots, the
 * clock, mesh files under the data directory, and the published JSON Schema. Exits non-zero
 * when any check fails; every failure prints its line and expression.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "proto.h"
#include "reclaim.h"
#include "render_scene.h"
#include "scene.h"

static int failures;

#define CHECK(cond)                                                                                \
  do {                                                                                             \
    if (!(cond)) {                                                                                 \
      fprintf(stderr, "%s:%d: check failed: %s\n", __FILE__, __LINE__, #cond);                     \
      failures++;                                                                                  \
    }                                                                                              \
  } while (0)

#define CHECK_NEAR(a, b) CHECK(fabs((double)(a) - (double)(b)) < 1e-6)

/* Parses 'text' or dies: the test's own JSON must be right. */
static cJSON *J(const char *text) {
  cJSON *v = cJSON_Parse(text);
  if (!v) {
    fprintf(stderr, "bad test JSON: %s\n", text);
    exit(2);
  }
  return v;
}

static double num_at(const scene_t *s, const char *path) {
  cJSON *v = sch_path_get(s->doc, path);
  return cJSON_IsNumber(v) ? v->valuedouble : NAN;
}

static const char *str_at(const scene_t *s, const char *path) {
  cJSON *v = sch_path_get(s->doc, path);
  return cJSON_IsString(v) ? v->valuestring : "";
}

static int patch_text(scene_t *s, const char *text, scene_error_t *err) {
  cJSON *p = J(text);
  int rc = scene_patch(s, p, err);
  cJSON_Delete(p);
  return rc;
}

static scene_t *new_scene(void) {
  scene_error_t err;
  scene_t *s = scene_create("main", NULL, &err);
  if (!s) {
    fprintf(stderr, "scene_create: %s\n", err.message);
    exit(2);
  }
  return s;
}

static void test_defaults(void) {
  scene_t *s = new_scene();
  CHECK(s->version == 1);
  CHECK(strcmp(s->name, "main") == 0);
  CHECK(num_at(s, "camera.fov_y") == 45);
  CHECK(num_at(s, "camera.eye.0") == 0 && num_at(s, "camera.eye.1") == 2 &&
        num_at(s, "camera.eye.2") == 8);
  CHECK(num_at(s, "camera.target.1") == 0.5);
  CHECK(num_at(s, "camera.near") == 0.01 && num_at(s, "camera.far") == 1000);
  CHECK(num_at(s, "light.intensity") == 3);
  CHECK(num_at(s, "light.shadow_map") == 1024);
  CHECK(num_at(s, "light.ambient") == 0.15);
  double x = num_at(s, "light.direction.0"), y = num_at(s, "light.direction.1"),
         z = num_at(s, "light.direction.2");
  CHECK_NEAR(x * x + y * y + z * z, 1);
  CHECK(x > 0 && y > 0 && z > 0);
  CHECK(cJSON_GetArraySize(sch_path_get(s->doc, "objects")) == 0);
  CHECK(num_at(s, "sim.dt") == 1.0 / 60.0);
  CHECK(num_at(s, "sim.time") == 0 && num_at(s, "sim.frame") == 0);
  CHECK(cJSON_IsFalse(sch_path_get(s->doc, "sim.playing")));
  CHECK(num_at(s, "render.exposure") == 0);
  CHECK(strcmp(str_at(s, "render.tone_map"), "aces") == 0);
  CHECK(cJSON_IsFalse(sch_path_get(s->doc, "render.transparent_background")));
  /* Members come out in schema order. */
  CHECK(strcmp(s->doc->child->string, "camera") == 0);
  CHECK(strcmp(sch_path_get(s->doc, "camera")->child->string, "eye") == 0);

  render_scene_t *rs = s->snapshot;
  CHECK(rs && atomic_load(&rs->refs) == 1);
  CHECK(rs->nobjects == 0 && rs->objects == NULL);
  CHECK(rs->camera.fov_y == 45.0f && rs->camera.eye[2] == 8.0f);
  CHECK(rs->tone_map == TONE_ACES && rs->exposure == 0 && !rs->transparent_background);
  CHECK(rs->light.shadow_map == 1024);
  CHECK_NEAR(rs->light.direction[0], x);
  CHECK(rs->frame == 0 && rs->time == 0);
  CHECK(scene_dt(s) == 1.0 / 60.0 && scene_time(s) == 0 && scene_frame(s) == 0);

  /* sch_defaults gives the same document. */
  cJSON *d = sch_defaults(&scene_schema);
  CHECK(d && cJSON_Compare(d, s->doc, 1));
  cJSON_Delete(d);
  scene_destroy(s);

  /* A partial preset keeps what it says and gets the rest. */
  scene_error_t err;
  cJSON *preset = J("{\"camera\": {\"fov_y\": 70}, \"objects\": [{\"shape\": \"sphere\"}]}");
  s = scene_create("p", preset, &err);
  CHECK(s && num_at(s, "camera.fov_y") == 70 && num_at(s, "camera.far") == 1000);
  CHECK(s && num_at(s, "objects.0.scale.1") == 1 && num_at(s, "objects.0.color.0") == 0.8);
  CHECK(s && strcmp(str_at(s, "objects.0.id"), "") == 0);
  CHECK(s && sch_path_get(s->doc, "objects.0.file") == NULL); /* SCH_NO_DEFAULT */
  CHECK(s && s->snapshot->nobjects == 1 && s->snapshot->objects[0].shape == SHAPE_SPHERE);
  scene_destroy(s);
  cJSON_Delete(preset);

  preset = J("{\"camera\": {\"fov_y\": 0}}");
  CHECK(scene_create("bad", preset, &err) == NULL);
  CHECK(err.code == PROTO_E_INVALID_PARAMS && strcmp(err.path, "camera.fov_y") == 0);
  cJSON_Delete(preset);
}

static void test_patch(void) {
  scene_t *s = new_scene();
  scene_error_t err;
  cJSON *before = cJSON_Duplicate(s->doc, 1);
  render_scene_t *old = render_scene_ref(s->snapshot); /* As a render job would. */

  CHECK(patch_text(s, "{\"camera\": {\"fov_y\": 60}}", &err) == 0);
  CHECK(s->version == 2);
  cJSON_SetNumberValue(sch_path_get(before, "camera.fov_y"), 60);
  CHECK(cJSON_Compare(before, s->doc, 1)); /* Only fov_y changed. */
  CHECK(s->snapshot != old && s->snapshot->camera.fov_y == 60.0f);
  CHECK(old->camera.fov_y == 45.0f); /* The job's snapshot is untouched. */
  render_scene_unref(old);

  /* Items that all carry distinct ids merge into the items with those ids, or are appended. */
  CHECK(patch_text(s,
                   "{\"objects\": [{\"id\": \"a\", \"shape\": \"box\"}, {\"id\": \"b\", "
                   "\"shape\": \"sphere\", \"position\": [1, 2, 3]}]}",
                   &err) == 0);
  CHECK(cJSON_GetArraySize(sch_path_get(s->doc, "objects")) == 2);
  CHECK(patch_text(s, "{\"objects\": [{\"id\": \"c\", \"shape\": \"plane\"}]}", &err) == 0);
  CHECK(cJSON_GetArraySize(sch_path_get(s->doc, "objects")) == 3);
  CHECK(strcmp(str_at(s, "objects.2.id"), "c") == 0);
  CHECK(patch_text(s, "{\"objects\": [{\"id\": \"b\", \"scale\": [2, 2, 2]}]}", &err) == 0);
  CHECK(num_at(s, "objects.b.scale.0") == 2 && num_at(s, "objects.1.position.2") == 3);
  CHECK(strcmp(str_at(s, "objects.b.shape"), "sphere") == 0);
  /* Any other array is replaced whole. */
  CHECK(patch_text(s, "{\"objects\": [{\"shape\": \"plane\"}]}", &err) == 0);
  CHECK(cJSON_GetArraySize(sch_path_get(s->doc, "objects")) == 1);
  CHECK(strcmp(str_at(s, "objects.0.id"), "") == 0);
  CHECK(s->snapshot->nobjects == 1 && s->snapshot->objects[0].shape == SHAPE_PLANE);

  /* null deletes, and the default comes back. */
  CHECK(patch_text(s, "{\"camera\": {\"fov_y\": null}}", &err) == 0);
  CHECK(num_at(s, "camera.fov_y") == 45);
  CHECK(patch_text(s, "{\"camera\": {\"eye\": [5, 5, 5], \"near\": 0.5}}", &err) == 0);
  CHECK(patch_text(s, "{\"camera\": null, \"objects\": null}", &err) == 0);
  CHECK(num_at(s, "camera.eye.0") == 0 && num_at(s, "camera.near") == 0.01);
  CHECK(cJSON_GetArraySize(sch_path_get(s->doc, "objects")) == 0);
  /* Deleting a member that is not there is fine, as RFC 7386 says. */
  CHECK(patch_text(s, "{\"camera\": {\"fov_y\": null, \"far\": 10}}", &err) == 0);
  CHECK(num_at(s, "camera.far") == 10);
  /* An empty patch still validates and counts as a change. */
  unsigned long v = s->version;
  CHECK(patch_text(s, "{}", &err) == 0 && s->version == v + 1);

  cJSON_Delete(before);
  scene_destroy(s);
}

/* Applies 'patch' (owned) and checks it is refused with 'path' and changes nothing. */
static void expect_refused(scene_t *s, cJSON *patch, int code, const char *path,
                           const char *message, int line) {
  scene_error_t err;
  cJSON *before = cJSON_Duplicate(s->doc, 1);
  unsigned long version = s->version;
  render_scene_t *snap = s->snapshot;
  int rc = scene_patch(s, patch, &err);
  int ok = rc == -1 && err.code == code && strcmp(err.path, path) == 0 &&
           (!message || strcmp(err.message, message) == 0) && cJSON_Compare(before, s->doc, 1) &&
           s->version == version && s->snapshot == snap && err.message[0];
  if (!ok) {
    fprintf(stderr,
            "%s:%d: patch not refused as expected: rc %d code %d path \"%s\" (want \"%s\"): %s\n",
            __FILE__, line, rc, err.code, err.path, path, err.message);
    failures++;
  }
  cJSON_Delete(before);
  cJSON_Delete(patch);
}

#define REFUSED(s, text, path)                                                                     \
  expect_refused(s, J(text), PROTO_E_INVALID_PARAMS, path, NULL, __LINE__)

static void test_refused(void) {
  scene_t *s = new_scene();
  scene_error_t err;
  CHECK(patch_text(s, "{\"objects\": [{\"id\": \"x\", \"shape\": \"box\"}]}", &err) == 0);

  expect_refused(s, J("{\"camera\": {\"fov_y\": 500}}"), PROTO_E_INVALID_PARAMS, "camera.fov_y",
                 "camera.fov_y: 500 is out of range [1, 179] (degrees)", __LINE__);
  expect_refused(s,
                 J("{\"objects\": [{\"shape\": \"box\"}, {\"shape\": \"box\"}, "
                   "{\"shape\": \"box\", \"colour\": [1, 0, 0]}]}"),
                 PROTO_E_INVALID_PARAMS, "objects.2.colour",
                 "objects.2: unknown member \"colour\"; did you mean \"color\"?", __LINE__);
  REFUSED(s, "{\"camera\": {\"near\": \"far\"}}", "camera.near");
  REFUSED(s, "{\"camera\": {\"fov_y\": true}}", "camera.fov_y");
  REFUSED(s, "{\"camera\": {\"eye\": [1, 2]}}", "camera.eye");
  REFUSED(s, "{\"camera\": {\"eye\": [1, 2, \"3\"]}}", "camera.eye.2");
  REFUSED(s, "{\"camera\": {\"eye\": {\"x\": 1}}}", "camera.eye");
  REFUSED(s, "{\"camera\": {\"eye\": [1, 1, 1], \"target\": [1, 1, 1]}}", "camera.target");
  REFUSED(s, "{\"camera\": {\"eye\": [0, 0, 5], \"target\": [0, 0, 0], \"up\": [0, 0, -2]}}",
          "camera.up");
  REFUSED(s, "{\"camera\": {\"up\": [0, 0, 0]}}", "camera.up");
  REFUSED(s, "{\"camera\": {\"near\": 5, \"far\": 5}}", "camera.far");
  REFUSED(s, "{\"camera\": {\"near\": 0}}", "camera.near"); /* Exclusive minimum. */
  REFUSED(s, "{\"camera\": 3}", "camera");
  REFUSED(s, "{\"objects\": [{\"position\": [0, 0, 0]}]}", "objects.0.shape");
  REFUSED(s, "{\"objects\": [{\"shape\": \"cube\"}]}", "objects.0.shape");
  REFUSED(s, "{\"objects\": [{\"shape\": \"box\", \"scale\": [1, 0, 1]}]}", "objects.0.scale.1");
  REFUSED(s, "{\"objects\": [{\"shape\": \"box\", \"rotation\": [0, 36001, 0]}]}",
          "objects.0.rotation.1");
  REFUSED(s, "{\"objects\": [{\"shape\": \"box\"}, 7]}", "objects.1");
  REFUSED(s, "{\"objects\": {\"0\": {\"shape\": \"box\"}}}", "objects");
  /* An item with an id no item has is appended after "x". */
  REFUSED(s,
          "{\"objects\": [{\"shape\": \"box\", \"id\": "
          "\"0123456789012345678901234567890123456789012345678901234567890123\"}]}",
          "objects.1.id");
  REFUSED(s,
          "{\"objects\": [{\"shape\": \"box\", \"id\": \"t\"}, {\"shape\": \"box\"}, "
          "{\"shape\": \"box\", \"id\": \"t\"}]}",
          "objects.2.id");
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\"}]}", "objects.0.file");
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"\"}]}", "objects.0.file");
  REFUSED(s, "{\"light\": {\"shadow_map\": 100.5}}", "light.shadow_map");
  REFUSED(s, "{\"light\": {\"shadow_map\": 8193}}", "light.shadow_map");
  REFUSED(s, "{\"light\": {\"direction\": [0, 0, 0]}}", "light.direction");
  REFUSED(s, "{\"background\": [0, -0.1, 0]}", "background.1");
  REFUSED(s, "{\"sim\": {\"dt\": 0}}", "sim.dt");
  REFUSED(s, "{\"sim\": {\"playing\": 1}}", "sim.playing");
  REFUSED(s, "{\"render\": {\"tone_map\": \"filmic\"}}", "render.tone_map");
  REFUSED(s, "{\"waves\": [7]}", "waves.0");
  REFUSED(s, "{\"Camera\": {}}", "Camera"); /* Names are case-sensitive. */
  expect_refused(s, J("[1, 2]"), PROTO_E_INVALID_PARAMS, "", NULL, __LINE__);

  /* Values JSON text cannot carry, built in C. */
  cJSON *p = J("{\"light\": {}}");
  cJSON_AddItemToObject(cJSON_GetObjectItem(p, "light"), "intensity", cJSON_CreateNumber(NAN));
  expect_refused(s, p, PROTO_E_INVALID_PARAMS, "light.intensity",
                 "light.intensity: NaN is not a finite number", __LINE__);
  p = J("{\"background\": [0, 0, 0]}");
  cJSON_SetNumberValue(cJSON_GetArrayItem(cJSON_GetObjectItem(p, "background"), 1), INFINITY);
  expect_refused(s, p, PROTO_E_INVALID_PARAMS, "background.1", NULL, __LINE__);
  p = J("{\"sim\": {}}");
  cJSON_AddItemToObject(cJSON_GetObjectItem(p, "sim"), "time", cJSON_CreateNumber(-INFINITY));
  expect_refused(s, p, PROTO_E_INVALID_PARAMS, "sim.time", NULL, __LINE__);

  /* The object limit. */
  p = J("{\"objects\": []}");
  for (int i = 0; i < 1025; i++)
    cJSON_AddItemToArray(cJSON_GetObjectItem(p, "objects"), J("{\"shape\": \"sphere\"}"));
  expect_refused(s, p, PROTO_E_INVALID_PARAMS, "objects", NULL, __LINE__);

  /* Mesh files are refused without a data directory, and outside it. */
  scene_set_data_dir(NULL);
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"x.obj\"}]}", "objects.0.file");
  scene_set_data_dir("/tmp");
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"../x.obj\"}]}", "objects.0.file");
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"./x.obj\"}]}", "objects.0.file");
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"/etc/x.obj\"}]}", "objects.0.file");
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"a/../../x.obj\"}]}",
          "objects.0.file");
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"/etc/passwd\"}]}", "objects.0.file");
  scene_set_data_dir(NULL);

  /* After all that, the scene still takes a good patch. */
  CHECK(patch_text(s, "{\"camera\": {\"fov_y\": 50}}", &err) == 0);
  CHECK(num_at(s, "camera.fov_y") == 50);

  /* A replacement document with a member given twice is refused too. */
  cJSON *doc = J("{\"camera\": {\"fov_y\": 30, \"fov_y\": 40}}");
  unsigned long v = s->version;
  CHECK(scene_replace(s, doc, &err) == -1 && strcmp(err.path, "camera.fov_y") == 0);
  CHECK(s->version == v && num_at(s, "camera.fov_y") == 50);
  cJSON_Delete(doc);
  scene_destroy(s);
}

static int set_text(scene_t *s, const char *path, const char *value, scene_error_t *err) {
  cJSON *v = J(value);
  int rc = scene_set_path(s, path, v, err);
  cJSON_Delete(v);
  return rc;
}

static void test_set_path(void) {
  scene_t *s = new_scene();
  scene_error_t err;
  CHECK(set_text(s, "camera.fov_y", "30", &err) == 0 && num_at(s, "camera.fov_y") == 30);
  CHECK(s->snapshot->camera.fov_y == 30.0f && s->version == 2);
  CHECK(set_text(s, "camera.eye.1", "3", &err) == 0 && num_at(s, "camera.eye.1") == 3);
  CHECK(num_at(s, "camera.eye.2") == 8);
  CHECK(set_text(s, "render", "{\"exposure\": 1.5}", &err) == 0);
  CHECK(num_at(s, "render.exposure") == 1.5 && strcmp(str_at(s, "render.tone_map"), "aces") == 0);

  /* Appending to an array: index == length. */
  CHECK(set_text(s, "objects.0", "{\"shape\": \"sphere\", \"id\": \"ball\"}", &err) == 0);
  CHECK(set_text(s, "objects.1", "{\"shape\": \"box\"}", &err) == 0);
  CHECK(cJSON_GetArraySize(sch_path_get(s->doc, "objects")) == 2);
  CHECK(num_at(s, "objects.1.scale.0") == 1); /* Defaults filled in the new item. */
  CHECK(set_text(s, "objects.1.color", "[1, 0, 0]", &err) == 0);
  CHECK(s->snapshot->nobjects == 2 && s->snapshot->objects[1].color[0] == 1.0f &&
        s->snapshot->objects[1].color[1] == 0.0f);
  CHECK(set_text(s, "objects.0.position.2", "-4", &err) == 0);
  CHECK(s->snapshot->objects[0].position[2] == -4.0f);

  /* Paths that do not exist. */
  unsigned long v = s->version;
  render_scene_t *snap = s->snapshot;
  const char *missing[] = {"objects.3",      "objects.5.color", "camera.nope.x",
                           "camera.fov_y.x", "objects.01",      "objects.-1",
                           "camera.",        "nope.x",          "camera.eye.4"};
  for (size_t i = 0; i < sizeof missing / sizeof *missing; i++) {
    int rc = set_text(s, missing[i], "1", &err);
    CHECK(rc == -1 && err.code == PROTO_E_NOT_FOUND && strcmp(err.path, missing[i]) == 0);
  }
  CHECK(s->version == v && s->snapshot == snap);

  /* Existing parent, bad value or unknown member: invalid, with the value's path. */
  CHECK(set_text(s, "camera.bogus", "1", &err) == -1 && err.code == PROTO_E_INVALID_PARAMS &&
        strcmp(err.path, "camera.bogus") == 0);
  CHECK(set_text(s, "camera.fov_y", "0", &err) == -1 && err.code == PROTO_E_INVALID_PARAMS &&
        strcmp(err.path, "camera.fov_y") == 0);
  CHECK(set_text(s, "camera.eye.3", "1", &err) == -1 && err.code == PROTO_E_INVALID_PARAMS &&
        strcmp(err.path, "camera.eye") == 0); /* Appending makes four components. */
  CHECK(set_text(s, "objects.1.id", "\"ball\"", &err) == -1 &&
        strcmp(err.path, "objects.1.id") == 0);
  CHECK(set_text(s, "objects.2", "null", &err) == -1 && strcmp(err.path, "objects.2") == 0);
  CHECK(scene_set_path(s, "", cJSON_GetObjectItem(s->doc, "camera"), &err) == -1);
  CHECK(s->version == v && s->snapshot == snap && num_at(s, "camera.fov_y") == 30);

  /* null at an object member restores the default. */
  CHECK(set_text(s, "camera.fov_y", "null", &err) == 0 && num_at(s, "camera.fov_y") == 45);
  CHECK(set_text(s, "objects.1.file", "null", &err) == 0); /* Absent already: no change. */

  /* Unit vectors are normalised, in the document and the snapshot. */
  CHECK(set_text(s, "light.direction", "[3, 0, 4]", &err) == 0);
  CHECK_NEAR(num_at(s, "light.direction.0"), 0.6);
  CHECK_NEAR(num_at(s, "light.direction.1"), 0);
  CHECK_NEAR(num_at(s, "light.direction.2"), 0.8);
  CHECK_NEAR(s->snapshot->light.direction[2], 0.8);
  CHECK(set_text(s, "light.direction", "[0, 1e-300, 0]", &err) == 0);
  CHECK(num_at(s, "light.direction.1") == 1);
  scene_destroy(s);
}

/* Change lists and JSON Patch: one version when every step and the result pass, none else. */
static void test_change_lists(void) {
  scene_t *s = new_scene();
  scene_error_t err;
  CHECK(patch_text(s, "{\"objects\": [{\"id\": \"orb\", \"shape\": \"sphere\"}]}", &err) == 0);
  unsigned long v = s->version;
  cJSON *changes = J("[{\"path\": \"camera.fov_y\", \"value\": 30}, {\"path\": "
                     "\"objects.orb.scale\", \"value\": [2, 2, 2]}, {\"path\": \"camera\", "
                     "\"patch\": {\"near\": 0.5}}]");
  CHECK(scene_set_changes(s, changes, &err) == 0 && s->version == v + 1);
  CHECK(num_at(s, "camera.fov_y") == 30 && num_at(s, "objects.0.scale.1") == 2 &&
        num_at(s, "camera.near") == 0.5);
  cJSON_Delete(changes);
  changes = J("[{\"path\": \"camera.fov_y\", \"value\": 50}, {\"path\": \"camera.fovy\", "
              "\"value\": 1}]");
  CHECK(scene_set_changes(s, changes, &err) == -1 && strcmp(err.path, "camera.fovy") == 0 &&
        strstr(err.message, "did you mean \"fov_y\"") != NULL);
  CHECK(s->version == v + 1 && num_at(s, "camera.fov_y") == 30);
  cJSON_Delete(changes);

  cJSON *ops = J("[{\"op\": \"test\", \"path\": \"/camera/fov_y\", \"value\": 30}, {\"op\": "
                 "\"replace\", \"path\": \"/objects/orb/id\", \"value\": \"ball\"}, {\"op\": "
                 "\"copy\", \"from\": \"/objects/0\", \"path\": \"/objects/-\"}, {\"op\": "
                 "\"replace\", \"path\": \"/objects/1/id\", \"value\": \"b~/\"}, {\"op\": "
                 "\"move\", \"from\": \"/objects/b~0~1\", \"path\": \"/objects/0\"}]");
  CHECK(scene_apply_ops(s, ops, &err) == 0 && s->version == v + 2);
  CHECK(strcmp(str_at(s, "objects.0.id"), "b~/") == 0 &&
        strcmp(str_at(s, "objects.1.id"), "ball") == 0);
  cJSON_Delete(ops);
  ops = J("[{\"op\": \"remove\", \"path\": \"/objects/ball\"}, {\"op\": \"test\", \"path\": "
          "\"/camera/fov_y\", \"value\": 31}]");
  CHECK(scene_apply_ops(s, ops, &err) == -1 && strcmp(err.path, "ops.1") == 0);
  CHECK(s->version == v + 2 && cJSON_GetArraySize(sch_path_get(s->doc, "objects")) == 2);
  cJSON_Delete(ops);
  scene_destroy(s);
}

static void test_get(void) {
  scene_t *s = new_scene();
  scene_error_t err;
  CHECK(patch_text(s, "{\"objects\": [{\"shape\": \"box\", \"color\": [0.1, 0.2, 0.3]}]}", &err) ==
        0);
  cJSON *v = scene_get(s, "camera.fov_y", &err);
  CHECK(cJSON_IsNumber(v) && v->valuedouble == 45);
  cJSON_Delete(v);
  v = scene_get(s, "objects.0.color.1", &err);
  CHECK(cJSON_IsNumber(v) && v->valuedouble == 0.2);
  cJSON_Delete(v);
  v = scene_get(s, "objects.0", &err);
  CHECK(cJSON_IsObject(v) && strcmp(cJSON_GetObjectItem(v, "shape")->valuestring, "box") == 0);
  cJSON_Delete(v);
  v = scene_get(s, NULL, &err);
  CHECK(v && v != s->doc && cJSON_Compare(v, s->doc, 1));
  cJSON_Delete(v);
  v = scene_get(s, "", &err);
  CHECK(v && cJSON_Compare(v, s->doc, 1));
  cJSON_Delete(v);
  const char *missing[] = {"objects.1",         "camera.zoom", "camera.",       ".camera",
                           "objects.0.color.3", "objects.x",   "camera.fov_y.0"};
  for (size_t i = 0; i < sizeof missing / sizeof *missing; i++) {
    CHECK(scene_get(s, missing[i], &err) == NULL);
    CHECK(err.code == PROTO_E_NOT_FOUND && strcmp(err.path, missing[i]) == 0);
  }
  scene_destroy(s);
}

static cJSON *prop(cJSON *schema, const char *path) {
  char buf[256];
  snprintf(buf, sizeof buf, "%s", path);
  cJSON *cur = schema;
  for (char *tok = strtok(buf, "."); tok && cur; tok = strtok(NULL, "."))
    cur =
        cJSON_GetObjectItemCaseSensitive(cJSON_GetObjectItemCaseSensitive(cur, "properties"), tok);
  return cur;
}

static void test_json_schema(void) {
  cJSON *js = sch_to_json_schema(&scene_schema);
  CHECK(js);
  CHECK(strcmp(cJSON_GetObjectItem(js, "type")->valuestring, "object") == 0);
  CHECK(cJSON_IsFalse(cJSON_GetObjectItem(js, "additionalProperties")));
  cJSON *fov = prop(js, "camera.fov_y");
  CHECK(fov);
  if (fov) {
    CHECK(strcmp(cJSON_GetObjectItem(fov, "type")->valuestring, "number") == 0);
    CHECK(cJSON_GetObjectItem(fov, "default")->valuedouble == 45);
    CHECK(cJSON_GetObjectItem(fov, "minimum")->valuedouble == 1);
    CHECK(cJSON_GetObjectItem(fov, "maximum")->valuedouble == 179);
    CHECK(strcmp(cJSON_GetObjectItem(fov, "x-unit")->valuestring, "degrees") == 0);
    CHECK(cJSON_IsString(cJSON_GetObjectItem(fov, "description")));
  }
  cJSON *near_ = prop(js, "camera.near");
  CHECK(near_ && cJSON_GetObjectItem(near_, "exclusiveMinimum")->valuedouble == 0 &&
        !cJSON_GetObjectItem(near_, "minimum"));
  cJSON *eye = prop(js, "camera.eye");
  CHECK(eye && cJSON_GetObjectItem(eye, "minItems")->valuedouble == 3 &&
        cJSON_GetObjectItem(eye, "maxItems")->valuedouble == 3 &&
        cJSON_GetArraySize(cJSON_GetObjectItem(eye, "default")) == 3);
  cJSON *dir = cJSON_GetObjectItem(prop(js, "light.direction"), "default");
  double x = cJSON_GetArrayItem(dir, 0)->valuedouble, y = cJSON_GetArrayItem(dir, 1)->valuedouble,
         z = cJSON_GetArrayItem(dir, 2)->valuedouble;
  CHECK_NEAR(x * x + y * y + z * z, 1);
  cJSON *objs = prop(js, "objects");
  CHECK(objs && cJSON_GetObjectItem(objs, "maxItems")->valuedouble == 1024);
  cJSON *item = cJSON_GetObjectItem(objs, "items");
  cJSON *req = cJSON_GetObjectItem(item, "required");
  CHECK(cJSON_GetArraySize(req) == 1 &&
        strcmp(cJSON_GetArrayItem(req, 0)->valuestring, "shape") == 0);
  CHECK(cJSON_IsFalse(cJSON_GetObjectItem(item, "additionalProperties")));
  cJSON *shape = prop(item, "shape");
  CHECK(cJSON_GetArraySize(cJSON_GetObjectItem(shape, "enum")) == 5 &&
        !cJSON_GetObjectItem(shape, "default"));
  CHECK(!cJSON_GetObjectItem(prop(item, "file"), "default"));
  CHECK(cJSON_GetObjectItem(prop(item, "id"), "maxLength")->valuedouble == 63);
  cJSON *tm = prop(js, "render.tone_map");
  CHECK(strcmp(cJSON_GetObjectItem(tm, "default")->valuestring, "aces") == 0);
  CHECK(strcmp(cJSON_GetObjectItem(prop(js, "light.shadow_map"), "type")->valuestring, "integer") ==
        0);
  CHECK(cJSON_IsFalse(cJSON_GetObjectItem(prop(js, "sim.playing"), "default")));

  /* Every leaf has a description. */
  char *text = cJSON_PrintUnformatted(js);
  CHECK(text && strstr(text, "\"description\"") != NULL);
  free(text);
  cJSON_Delete(js);

  /* Field look-up by path. */
  CHECK(sch_path_field(&scene_schema, "") == &scene_schema);
  CHECK(sch_path_field(&scene_schema, NULL) == &scene_schema);
  const sch_field_t *f = sch_path_field(&scene_schema, "objects.12.scale");
  CHECK(f && strcmp(f->name, "scale") == 0 && f->type == SCH_VEC3);
  f = sch_path_field(&scene_schema, "camera.fov_y");
  CHECK(f && f->min == 1 && f->max == 179);
  f = sch_path_field(&scene_schema, "objects.orb.scale"); /* Items with an id, by id. */
  CHECK(f && strcmp(f->name, "scale") == 0);
  CHECK(sch_path_field(&scene_schema, "fluid.emitters.x.position") == NULL);
  CHECK(sch_path_field(&scene_schema, "camera.zoom") == NULL);
  CHECK(sch_path_field(&scene_schema, "camera.eye.0") == NULL);
}

/* The engine on a schema of its own, for what the scene schema does not use. */
static void test_engine(void) {
  static const double d3[3] = {1, 2, 3};
  static const sch_field_t inner[] = {
      {.name = "k", .type = SCH_INTEGER, .min = -5, .max = 5, .def = 2},
      {.name = "v", .type = SCH_VEC3, .min = 0, .max = 0, .def_vec = d3},
      {0},
  };
  static const sch_field_t item = {.name = "item", .type = SCH_STRING, .max = 3};
  static const sch_field_t fields[] = {
      {.name = "req", .type = SCH_NUMBER, .flags = SCH_REQUIRED},
      {.name = "opt", .type = SCH_NUMBER, .def = 1, .flags = SCH_NO_DEFAULT},
      {.name = "inner", .type = SCH_OBJECT, .fields = inner},
      {.name = "list", .type = SCH_ARRAY, .max = 2, .items = &item},
      {.name = "any", .type = SCH_ANY},
      {.name = "open", .type = SCH_OBJECT, .fields = inner, .flags = SCH_OPEN},
      {0},
  };
  static const sch_field_t root = {.name = "root", .type = SCH_OBJECT, .fields = fields};
  sch_error_t err;

  cJSON *v = J("{\"req\": 1e300, \"open\": {\"extra\": [1]}, \"any\": {\"x\": null}}");
  CHECK(sch_validate(&root, v, "", &err) == 0);
  CHECK(sch_path_get(v, "opt") == NULL);
  CHECK(sch_path_get(v, "inner.k")->valuedouble == 2);
  CHECK(sch_path_get(v, "inner.v.2")->valuedouble == 3);
  CHECK(cJSON_GetArraySize(sch_path_get(v, "list")) == 0);
  CHECK(cJSON_IsArray(sch_path_get(v, "open.extra")));
  CHECK(sch_path_get(v, "open.k")->valuedouble == 2);
  cJSON_Delete(v);

  struct {
    const char *text, *path;
  } bad[] = {
      {"{}", "params.req"},
      {"{\"req\": 1, \"inner\": {\"k\": 1.5}}", "params.inner.k"},
      {"{\"req\": 1, \"inner\": {\"k\": -6}}", "params.inner.k"},
      {"{\"req\": 1, \"list\": [\"abc\", \"abcd\"]}", "params.list.1"},
      {"{\"req\": 1, \"list\": [\"a\", \"b\", \"c\"]}", "params.list"},
      {"{\"req\": 1, \"inner\": {\"z\": 1}}", "params.inner.z"},
  };
  for (size_t i = 0; i < sizeof bad / sizeof *bad; i++) {
    v = J(bad[i].text);
    CHECK(sch_validate(&root, v, "params", &err) == -1);
    CHECK(strcmp(err.path, bad[i].path) == 0);
    CHECK(strncmp(err.message, "params", 6) == 0);
    cJSON_Delete(v);
  }
  v = J("{\"req\": 1, \"inner\": {\"k\": 1.5}}");
  sch_validate(&root, v, "", &err);
  CHECK(strcmp(err.message, "inner.k: 1.5 is not an integer") == 0);
  cJSON_Delete(v);

  /* A nested object with a required member has no default of its own. */
  CHECK(sch_defaults(&root) == NULL);
  cJSON *d = sch_defaults(&fields[2]);
  CHECK(d && sch_path_get(d, "k")->valuedouble == 2);
  cJSON_Delete(d);

  /* Paths through documents. */
  v = J("{\"a\": [{\"b\": [10, 20]}], \"c.d\": 1}");
  CHECK(sch_path_get(v, "a.0.b.1")->valuedouble == 20);
  CHECK(sch_path_get(v, "a.0.b.2") == NULL);
  CHECK(sch_path_get(v, "a.0.b.+1") == NULL);
  CHECK(sch_path_get(v, "a..b") == NULL);
  CHECK(sch_path_get(v, NULL) == v && sch_path_get(v, "") == v);
  cJSON_Delete(v);
}

static void test_advance(void) {
  scene_t *s = new_scene();
  scene_error_t err;
  CHECK(patch_text(s, "{\"sim\": {\"dt\": 0.5}}", &err) == 0);
  unsigned long v = s->version;
  render_scene_t *held = render_scene_ref(s->snapshot);
  scene_advance(s, 3, scene_dt(s));
  CHECK(scene_time(s) == 1.5 && scene_frame(s) == 3);
  CHECK(num_at(s, "sim.time") == 1.5 && num_at(s, "sim.frame") == 3);
  CHECK(s->snapshot != held && s->snapshot->frame == 3 && s->snapshot->time == 1.5);
  CHECK(held->frame == 0 && held->time == 0); /* Never mutated under a reader. */
  CHECK(s->version == v);
  render_scene_unref(held);
  scene_advance(s, 0, 0.5);
  scene_advance(s, 1, NAN);
  CHECK(scene_frame(s) == 3);
  scene_advance(s, 1, 0.25);
  CHECK(scene_time(s) == 1.75 && scene_frame(s) == 4 && s->snapshot->frame == 4);
  /* The clock survives later patches and is settable. */
  CHECK(patch_text(s, "{\"camera\": {\"fov_y\": 40}}", &err) == 0);
  CHECK(s->snapshot->frame == 4 && s->snapshot->time == 1.75);
  CHECK(patch_text(s, "{\"sim\": {\"time\": 0, \"frame\": 0}}", &err) == 0);
  CHECK(s->snapshot->frame == 0);
  scene_destroy(s);
}

static void write_file(const char *path, const char *text) {
  FILE *f = fopen(path, "w");
  if (!f) {
    perror(path);
    exit(2);
  }
  fputs(text, f);
  fclose(f);
}

static void test_meshes(void) {
  char dir[] = "/tmp/volfx_test_scene_XXXXXX";
  if (!mkdtemp(dir)) {
    perror("mkdtemp");
    exit(2);
  }
  char path[512], outside[512], link[512], sub[512], bad[512];
  snprintf(path, sizeof path, "%s/quad.obj", dir);
  write_file(path, "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n");
  snprintf(bad, sizeof bad, "%s/bad.obj", dir);
  write_file(bad, "f 1 2 3\n");
  snprintf(sub, sizeof sub, "%s/sub", dir);
  CHECK(mkdir(sub, 0700) == 0);
  snprintf(sub, sizeof sub, "%s/sub/tri.obj", dir);
  write_file(sub, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
  snprintf(outside, sizeof outside, "%s_outside.obj", dir);
  write_file(outside, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
  snprintf(link, sizeof link, "%s/escape.obj", dir);
  CHECK(symlink(outside, link) == 0);

  scene_set_data_dir(dir);
  scene_t *s = new_scene();
  scene_error_t err;
  CHECK(patch_text(s,
                   "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"quad.obj\"}, {\"shape\": "
                   "\"mesh\", \"file\": \"sub/tri.obj\"}, {\"shape\": \"box\"}]}",
                   &err) == 0);
  if (s->snapshot->nobjects == 3) {
    mesh_t *m = s->snapshot->objects[0].mesh;
    CHECK(m && m->ntri >= 1);
    CHECK(s->snapshot->objects[1].mesh && s->snapshot->objects[2].mesh == NULL);
    /* A patch that keeps the mesh reuses it instead of reading the file again. */
    CHECK(patch_text(s, "{\"camera\": {\"fov_y\": 50}}", &err) == 0);
    CHECK(s->snapshot->objects[0].mesh == m);
    /* A file changed on disk is read again; the scene's old snapshot keeps the old mesh. */
    write_file(path, "v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\n");
    CHECK(patch_text(s, "{\"camera\": {\"fov_y\": 55}}", &err) == 0);
    CHECK(s->snapshot->objects[0].mesh != m && s->snapshot->objects[0].mesh);
    m = s->snapshot->objects[0].mesh;
    /* A held snapshot keeps its mesh after the scene drops it. */
    render_scene_t *held = render_scene_ref(s->snapshot);
    CHECK(patch_text(s, "{\"objects\": []}", &err) == 0);
    CHECK(held->objects[0].mesh == m && m->ntri >= 1);
    scene_advance(s, 1, 0.1);
    render_scene_unref(held);
  } else {
    fprintf(stderr, "mesh patch refused: %s\n", err.message);
    failures++;
  }

  REFUSED(s, "{\"objects\": [{\"shape\": \"box\"}, {\"shape\": \"mesh\", \"file\": \"no.obj\"}]}",
          "objects.1.file");
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"bad.obj\"}]}", "objects.0.file");
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"escape.obj\"}]}", "objects.0.file");
  REFUSED(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"sub\"}]}", "objects.0.file");
  /* The message names the client's file, not where the data directory is. */
  CHECK(patch_text(s, "{\"objects\": [{\"shape\": \"mesh\", \"file\": \"bad.obj\"}]}", &err) == -1);
  CHECK(strstr(err.message, dir) == NULL);

  /* A mesh object given in the preset. */
  cJSON *preset =
      J("{\"objects\": [{\"shape\": \"mesh\", \"file\": \"quad.obj\", \"scale\": [2, 2, "
        "2]}]}");
  scene_t *s2 = scene_create("m", preset, &err);
  CHECK(s2 && s2->snapshot->objects[0].mesh && s2->snapshot->objects[0].scale[0] == 2.0f);
  scene_destroy(s2);
  cJSON_Delete(preset);
  scene_destroy(s);
  scene_set_data_dir(NULL);

  unlink(link);
  unlink(outside);
  unlink(bad);
  unlink(sub);
  unlink(path);
  snprintf(sub, sizeof sub, "%s/sub", dir);
  rmdir(sub);
  rmdir(dir);
}

/* Big blocks dropped while the reclaimer runs go to its thread, small ones and those dropped
 * before it starts or after it stops are freed on the spot; under ASan, a block the reclaimer
 * lost would be a leak and one freed twice an error. */
static void test_reclaim(void) {
  const uint32_t big[3] = {128, 64, 32}, small[3] = {8, 8, 8};
  density_grid_unref(density_grid_new(big));
  CHECK(reclaim_handed() == 0);
  CHECK(reclaim_start() == 0);
  density_grid_t *g = density_grid_new(big);
  for (size_t i = 0; g && i < (size_t)big[0] * big[1] * big[2]; i++)
    g->data[i] = 1.0f;
  density_grid_unref(density_grid_new(small));
  CHECK(reclaim_handed() == 0);
  density_grid_unref(density_grid_ref(g));
  CHECK(reclaim_handed() == 0);
  density_grid_unref(g);
  CHECK(reclaim_handed() == 1);
  particles_unref(particles_new(1u << 17));
  CHECK(reclaim_handed() == 3);
  /* A block of the size dropped is handed back, zeroed where the grid asks for it; one of
   * another size is not; after RECLAIM_KEEP_MS none is. */
  CHECK(reclaim_reused() == 0);
  g = density_grid_new(big);
  CHECK(reclaim_reused() == 1);
  int zero = g != NULL;
  for (size_t i = 0; g && i < (size_t)big[0] * big[1] * big[2]; i++)
    zero &= g->data[i] == 0;
  CHECK(zero);
  const uint32_t other[3] = {128, 64, 33};
  density_grid_unref(density_grid_alloc(other));
  CHECK(reclaim_reused() == 1);
  density_grid_unref(g);
  struct timespec pause = {.tv_sec = RECLAIM_KEEP_MS / 1000 + 1};
  nanosleep(&pause, NULL);
  density_grid_unref(density_grid_alloc(big));
  CHECK(reclaim_reused() == 1);
  /* The bounds: of RECLAIM_KEEP_BLOCKS + 2 dropped at once, the oldest are freed. */
  density_grid_t *many[RECLAIM_KEEP_BLOCKS + 2];
  for (int i = 0; i < RECLAIM_KEEP_BLOCKS + 2; i++)
    many[i] = density_grid_alloc(big);
  for (int i = 0; i < RECLAIM_KEEP_BLOCKS + 2; i++)
    density_grid_unref(many[i]);
  size_t before = reclaim_reused();
  for (int i = 0; i < RECLAIM_KEEP_BLOCKS + 2; i++)
    many[i] = density_grid_alloc(big);
  size_t taken = reclaim_reused() - before;
  CHECK(taken >= 1 && taken <= RECLAIM_KEEP_BLOCKS);
  for (int i = 0; i < RECLAIM_KEEP_BLOCKS + 2; i++)
    density_grid_unref(many[i]);
  reclaim_stop(); /* Frees what is kept: under ASan a lost one is a leak. */
  size_t handed = reclaim_handed();
  density_grid_unref(density_grid_new(big));
  CHECK(reclaim_handed() == handed);
}

int main(void) {
  test_defaults();
  test_patch();
  test_refused();
  test_set_path();
  test_change_lists();
  test_get();
  test_json_schema();
  test_engine();
  test_advance();
  test_meshes();
  test_reclaim();
  if (failures) {
    fprintf(stderr, "test_scene: %d check(s) failed\n", failures);
    return 1;
  }
  printf("test_scene: all checks passed\n");
  return 0;
}
