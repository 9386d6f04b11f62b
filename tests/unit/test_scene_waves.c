/*
 * Unit tests of the scene side of the energy waves (SPEC §4, §5.1): the waves' defaults and
 * validation, refusals that name the offending path and leave the scene untouched, their
 * compilation into the snapshot, the animations (toward a target, keyframes, loops, on
 * numbers, points and directions), the cost of many steps, the published schema and the
 * paper-000 preset. Runs from the repository root; exits non-zero when any check fails.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "proto.h"
#include "scene.h"

static int failures;

#define CHECK(cond)                                                                                \
  do {                                                                                             \
    if (!(cond)) {                                                                                 \
      fprintf(stderr, "%s:%d: check failed: %s\n", __FILE__, __LINE__, #cond);                     \
      failures++;                                                                                  \
    }                                                                                              \
  } while (0)

#define PI 3.14159265358979323846

#define CHECK_NEAR(a, b, tol) CHECK(fabs((double)(a) - (double)(b)) <= (tol))

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

static double now_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + (double)ts.tv_nsec / 1e9;
}

/* A scene made from 'text', or death: the test's own scenes must be valid. */
static scene_t *scene_from(const char *text) {
  cJSON *doc = J(text);
  scene_error_t err;
  scene_t *s = scene_create("main", doc, &err);
  cJSON_Delete(doc);
  if (!s) {
    fprintf(stderr, "scene_create: %s (%s)\n", err.message, err.path);
    exit(2);
  }
  return s;
}

static int patch_text(scene_t *s, const char *text, scene_error_t *err) {
  cJSON *p = J(text);
  int rc = scene_patch(s, p, err);
  cJSON_Delete(p);
  return rc;
}

/*
 * Applies 'patch' (taken) and checks that it is refused with code -32602 at 'path', with
 * 'message' when not NULL, and that the document, the version and the snapshot are exactly as
 * they were.
 */
static void expect_refused(scene_t *s, cJSON *patch, const char *path, const char *message,
                           int line) {
  scene_error_t err;
  cJSON *before = cJSON_Duplicate(s->doc, 1);
  unsigned long version = s->version;
  render_scene_t *snap = s->snapshot;
  int rc = scene_patch(s, patch, &err);
  if (rc != -1 || err.code != PROTO_E_INVALID_PARAMS || strcmp(err.path, path) != 0 ||
      (message && strcmp(err.message, message) != 0)) {
    fprintf(stderr, "%s:%d: not refused as expected: rc %d code %d path \"%s\" (want \"%s\"): %s\n",
            __FILE__, line, rc, err.code, err.path, path, err.message);
    failures++;
  }
  CHECK(cJSON_Compare(before, s->doc, 1));
  CHECK(s->version == version);
  CHECK(s->snapshot == snap);
  cJSON_Delete(before);
  cJSON_Delete(patch);
}

#define REFUSED(s, text, path) expect_refused(s, J(text), path, NULL, __LINE__)

static void test_defaults(void) {
  scene_t *s = scene_from("{\"waves\": [{\"center\": [1, 2, 3]}]}");
  CHECK(strcmp(str_at(s, "waves.0.id"), "") == 0);
  CHECK(num_at(s, "waves.0.center.0") == 1 && num_at(s, "waves.0.center.2") == 3);
  CHECK(num_at(s, "waves.0.direction.0") == 1 && num_at(s, "waves.0.direction.1") == 0);
  CHECK(num_at(s, "waves.0.a") == 1 && num_at(s, "waves.0.b") == 0.5);
  CHECK(num_at(s, "waves.0.length") == 2 && num_at(s, "waves.0.radius") == 3);
  CHECK(num_at(s, "waves.0.softening") == 0.05 && num_at(s, "waves.0.clamp") == 4);
  CHECK(num_at(s, "waves.0.color.0") == 0.35 && num_at(s, "waves.0.color.2") == 1.6);
  CHECK(cJSON_IsArray(sch_path_get(s->doc, "waves.0.animate")));
  CHECK(cJSON_GetArraySize(sch_path_get(s->doc, "waves.0.animate")) == 0);
  /* Members come out in schema order. */
  CHECK(strcmp(sch_path_get(s->doc, "waves.0")->child->string, "id") == 0);
  scene_destroy(s);

  /* An empty wave is a wave at the default camera's target. */
  s = scene_from("{\"waves\": [{}]}");
  CHECK(num_at(s, "waves.0.center.1") == 0.5);
  CHECK(s->snapshot->nwaves == 1 && s->snapshot->waves[0].center[1] == 0.5f);
  scene_destroy(s);

  /* No waves: nothing to draw and nothing allocated. */
  s = scene_from("{}");
  CHECK(cJSON_GetArraySize(sch_path_get(s->doc, "waves")) == 0);
  CHECK(s->snapshot->nwaves == 0 && s->snapshot->waves == NULL);
  scene_destroy(s);
}

static void test_direction(void) {
  scene_t *s = scene_from("{\"waves\": [{\"direction\": [0, 3, 4]}]}");
  CHECK(num_at(s, "waves.0.direction.0") == 0);
  CHECK_NEAR(num_at(s, "waves.0.direction.1"), 0.6, 1e-15);
  CHECK_NEAR(num_at(s, "waves.0.direction.2"), 0.8, 1e-15);
  CHECK_NEAR(s->snapshot->waves[0].direction[2], 0.8, 1e-7);
  /* Tiny and huge vectors normalise without underflow or overflow. */
  scene_error_t err;
  CHECK(patch_text(s, "{\"waves\": [{\"direction\": [1e-300, 0, 1e-300]}]}", &err) == 0);
  CHECK_NEAR(num_at(s, "waves.0.direction.0"), sqrt(0.5), 1e-15);
  /* Validating again leaves a normalised direction bit for bit as it was. */
  CHECK(patch_text(s, "{\"waves\": [{\"direction\": [1, -0.12, -0.25]}]}", &err) == 0);
  double d[3];
  for (int i = 0; i < 3; i++)
    d[i] = cJSON_GetArrayItem(sch_path_get(s->doc, "waves.0.direction"), i)->valuedouble;
  CHECK(patch_text(s, "{}", &err) == 0);
  for (int i = 0; i < 3; i++)
    CHECK(cJSON_GetArrayItem(sch_path_get(s->doc, "waves.0.direction"), i)->valuedouble == d[i]);
  scene_destroy(s);
}

static void test_refused(void) {
  scene_t *s = scene_from("{\"waves\": [{\"id\": \"w\", \"a\": 2}]}");

  expect_refused(s, J("{\"waves\": [{\"softening\": 0}]}"), "waves.0.softening",
                 "waves.0.softening: 0 is out of range (0, 1000000] (world units)", __LINE__);
  expect_refused(s, J("{\"waves\": [{\"radius\": -1}]}"), "waves.0.radius",
                 "waves.0.radius: -1 is out of range (0, 1000000] (world units)", __LINE__);
  expect_refused(s, J("{\"waves\": [{}, {\"a\": 0, \"b\": 0}]}"), "waves.1.a",
                 "waves.1.a: a and b are both 0, so the wave would never show", __LINE__);
  expect_refused(s, J("{\"waves\": [{\"direction\": [0, 0, 0]}]}"), "waves.0.direction",
                 "waves.0.direction: a direction cannot be the zero vector", __LINE__);
  expect_refused(s, J("{\"waves\": [{\"colour\": [1, 0, 0]}]}"), "waves.0.colour",
                 "waves.0: unknown member \"colour\"; did you mean \"color\"?", __LINE__);
  REFUSED(s, "{\"waves\": [{\"clamp\": 0}]}", "waves.0.clamp");
  REFUSED(s, "{\"waves\": [{\"a\": -0.5}]}", "waves.0.a");
  REFUSED(s, "{\"waves\": [{\"b\": 2e6}]}", "waves.0.b");
  REFUSED(s, "{\"waves\": [{\"length\": -1}]}", "waves.0.length");
  REFUSED(s, "{\"waves\": [{\"center\": [0, 2e6, 0]}]}", "waves.0.center.1");
  REFUSED(s, "{\"waves\": [{\"color\": [0, -1, 0]}]}", "waves.0.color.1");
  REFUSED(s, "{\"waves\": [{\"direction\": [1, 0]}]}", "waves.0.direction");
  REFUSED(s, "{\"waves\": [{\"a\": \"1\"}]}", "waves.0.a");
  REFUSED(s, "{\"waves\": [{\"id\": \"x\"}, {\"id\": \"y\"}, {\"id\": \"x\"}]}", "waves.2.id");
  REFUSED(s, "{\"waves\": {\"a\": 1}}", "waves");

  /* NaN and Inf cannot be written in JSON text, but a value built in C can hold them. */
  cJSON *p = J("{\"waves\": [{}]}");
  cJSON_AddItemToObject(cJSON_GetArrayItem(cJSON_GetObjectItem(p, "waves"), 0), "softening",
                        cJSON_CreateNumber(NAN));
  expect_refused(s, p, "waves.0.softening", "waves.0.softening: NaN is not a finite number",
                 __LINE__);
  p = J("{\"waves\": [{\"center\": [0, 0, 0]}]}");
  cJSON_SetNumberValue(cJSON_GetArrayItem(sch_path_get(p, "waves.0.center"), 2), INFINITY);
  expect_refused(s, p, "waves.0.center.2", NULL, __LINE__);
  /* Through the path form too. */
  scene_error_t err;
  cJSON *nan = cJSON_CreateNumber(NAN);
  unsigned long v = s->version;
  CHECK(scene_set_path(s, "waves.0.softening", nan, &err) == -1);
  CHECK(strcmp(err.path, "waves.0.softening") == 0 && s->version == v);
  cJSON_Delete(nan);

  /* The wave limit. */
  p = J("{\"waves\": []}");
  for (int i = 0; i < 65; i++)
    cJSON_AddItemToArray(cJSON_GetObjectItem(p, "waves"), J("{}"));
  expect_refused(s, p, "waves", "waves: 65 items is more than the limit of 64", __LINE__);

  /* Animations. */
  expect_refused(s, J("{\"waves\": [{\"animate\": [{\"field\": \"size\", \"target\": 1}]}]}"),
                 "waves.0.animate.0.field", NULL, __LINE__);
  REFUSED(s, "{\"waves\": [{\"animate\": [{\"field\": \"id\", \"target\": 1, \"rate\": 1}]}]}",
          "waves.0.animate.0.field");
  expect_refused(
      s,
      J("{\"waves\": [{\"animate\": [{\"field\": \"a\", \"target\": [1, 2, 3], \"rate\": 1}]}]}"),
      "waves.0.animate.0.target", "waves.0.animate.0.target: expected a number, got an array",
      __LINE__);
  REFUSED(s, "{\"waves\": [{\"animate\": [{\"field\": \"center\", \"target\": 1, \"rate\": 1}]}]}",
          "waves.0.animate.0.target");
  expect_refused(
      s,
      J("{\"waves\": [{\"animate\": [{\"field\": \"softening\", \"target\": 0, \"rate\": 1}]}]}"),
      "waves.0.animate.0.target",
      "waves.0.animate.0.target: 0 is out of range (0, 1000000] (world units)", __LINE__);
  REFUSED(s,
          "{\"waves\": [{\"animate\": [{\"field\": \"direction\", \"target\": [0, 0, 0], "
          "\"rate\": 1}]}]}",
          "waves.0.animate.0.target");
  expect_refused(s,
                 J("{\"waves\": [{\"animate\": [{\"field\": \"length\", \"keys\": [{\"t\": 0, "
                   "\"value\": 1}, {\"t\": 2, \"value\": 2}, {\"t\": 2, \"value\": 3}]}]}]}"),
                 "waves.0.animate.0.keys.2.t",
                 "waves.0.animate.0.keys.2.t: 2 must be greater than the previous key's t (2)",
                 __LINE__);
  REFUSED(s,
          "{\"waves\": [{\"animate\": [{\"field\": \"length\", \"keys\": [{\"t\": 3, \"value\": "
          "1}, {\"t\": 1, \"value\": 2}]}]}]}",
          "waves.0.animate.0.keys.1.t");
  REFUSED(s,
          "{\"waves\": [{\"animate\": [{\"field\": \"color\", \"keys\": [{\"t\": 0, \"value\": "
          "[1, 1, 1]}, {\"t\": 1, \"value\": 1}]}]}]}",
          "waves.0.animate.0.keys.1.value");
  REFUSED(s,
          "{\"waves\": [{\"animate\": [{\"field\": \"radius\", \"keys\": [{\"t\": 0, \"value\": "
          "-1}]}]}]}",
          "waves.0.animate.0.keys.0.value");
  REFUSED(s, "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"keys\": []}]}]}",
          "waves.0.animate.0.keys");
  REFUSED(s, "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"keys\": [{\"value\": 1}]}]}]}",
          "waves.0.animate.0.keys.0.t");
  REFUSED(s, "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"keys\": [{\"t\": 1}]}]}]}",
          "waves.0.animate.0.keys.0.value");
  REFUSED(s, "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"target\": 1}]}]}",
          "waves.0.animate.0.rate");
  REFUSED(s, "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"target\": 1, \"rate\": 0}]}]}",
          "waves.0.animate.0.rate");
  REFUSED(s,
          "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"target\": 1, \"rate\": 1, \"keys\": "
          "[{\"t\": 0, \"value\": 1}]}]}]}",
          "waves.0.animate.0.keys");
  REFUSED(s,
          "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"rate\": 1, \"keys\": [{\"t\": 0, "
          "\"value\": 1}]}]}]}",
          "waves.0.animate.0.rate");
  REFUSED(s,
          "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"target\": 1, \"rate\": 1, \"loop\": "
          "true}]}]}",
          "waves.0.animate.0.loop");
  REFUSED(s, "{\"waves\": [{\"animate\": [{\"field\": \"a\"}]}]}", "waves.0.animate.0");
  REFUSED(s, "{\"waves\": [{\"animate\": [{\"target\": 1, \"rate\": 1}]}]}",
          "waves.0.animate.0.field");
  REFUSED(s,
          "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"target\": 1, \"rate\": 1}, {\"field\": "
          "\"b\", \"target\": 1, \"rate\": 1}, {\"field\": \"a\", \"target\": 2, \"rate\": 1}]}]}",
          "waves.0.animate.2.field");
  REFUSED(s,
          "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"keys\": [{\"t\": 0, \"value\": 1}], "
          "\"interp\": \"cubic\"}]}]}",
          "waves.0.animate.0.interp");
  REFUSED(s, "{\"waves\": [{\"animate\": [{\"field\": \"a\", \"target\": 1, \"speed\": 1}]}]}",
          "waves.0.animate.0.speed");

  /* a = b = 0 is allowed while one of them is animated: the wave may fade in or out. */
  CHECK(patch_text(s,
                   "{\"waves\": [{\"a\": 0, \"b\": 0, \"animate\": [{\"field\": \"a\", \"target\": "
                   "1, \"rate\": 1}]}]}",
                   &err) == 0);
  scene_destroy(s);
}

static void test_compile(void) {
  scene_t *s = scene_from("{\"waves\": [{\"id\": \"one\", \"center\": [1, 2, 3], \"direction\": "
                          "[0, 0, -2], \"a\": 5, \"b\": 0, \"length\": 0, \"radius\": 7.5, "
                          "\"softening\": 0.25, \"clamp\": 9, \"color\": [0.1, 0.2, 30]}, "
                          "{\"id\": \"two\", \"a\": 0, \"b\": 3}]}");
  render_scene_t *rs = s->snapshot;
  CHECK(rs->nwaves == 2);
  const rwave_t *w = &rs->waves[0];
  CHECK(w->center[0] == 1.0f && w->center[1] == 2.0f && w->center[2] == 3.0f);
  CHECK(w->direction[0] == 0.0f && w->direction[1] == 0.0f && w->direction[2] == -1.0f);
  CHECK(w->a == 5.0f && w->b == 0.0f && w->length == 0.0f && w->radius == 7.5f);
  CHECK(w->softening == 0.25f && w->clamp == 9.0f);
  CHECK(w->color[0] == 0.1f && w->color[1] == 0.2f && w->color[2] == 30.0f);
  CHECK(rs->waves[1].a == 0.0f && rs->waves[1].b == 3.0f && rs->waves[1].radius == 3.0f);

  /* A patch compiles a new snapshot; one still held (by a render job) keeps its waves. */
  render_scene_t *held = render_scene_ref(rs);
  scene_error_t err;
  cJSON *four = cJSON_CreateNumber(4);
  CHECK(scene_set_path(s, "waves.1.b", four, &err) == 0);
  cJSON_Delete(four);
  CHECK(s->snapshot != held && s->snapshot->waves[1].b == 4.0f && held->waves[1].b == 3.0f);
  render_scene_unref(held);
  /* The path form appends a wave at index = length. */
  cJSON *w3 = J("{\"a\": 2}");
  CHECK(scene_set_path(s, "waves.2", w3, &err) == 0);
  cJSON_Delete(w3);
  CHECK(s->snapshot->nwaves == 3 && s->snapshot->waves[2].a == 2.0f);
  CHECK(num_at(s, "waves.2.radius") == 3);
  /* Removing every wave leaves none in the snapshot. */
  CHECK(patch_text(s, "{\"waves\": null}", &err) == 0);
  CHECK(s->snapshot->nwaves == 0 && s->snapshot->waves == NULL);
  scene_destroy(s);
}

static void test_toward(void) {
  scene_t *s = scene_from("{\"waves\": [{\"a\": 1, \"animate\": [{\"field\": \"a\", \"target\": 3, "
                          "\"rate\": 1}]}]}");
  unsigned long v = s->version;
  /* The toward entry gets no keyframe defaults. */
  CHECK(sch_path_get(s->doc, "waves.0.animate.0.interp") == NULL);
  CHECK(sch_path_get(s->doc, "waves.0.animate.0.loop") == NULL);
  scene_advance(s, 10, 0.1);
  CHECK_NEAR(num_at(s, "waves.0.a"), 2.0, 1e-12);
  CHECK(s->snapshot->waves[0].a == 2.0f);
  scene_advance(s, 20, 0.1);
  CHECK(num_at(s, "waves.0.a") == 3.0);
  scene_advance(s, 5, 0.1);
  CHECK(num_at(s, "waves.0.a") == 3.0); /* Stays at the target. */
  CHECK(s->snapshot->waves[0].a == 3.0f);
  CHECK(s->version == v); /* Animation is not a client's edit. */
  /* The animation stays in the document, finished. */
  CHECK(cJSON_GetArraySize(sch_path_get(s->doc, "waves.0.animate")) == 1);

  /* Single steps land on the target exactly too, and scene_get shows the value. */
  scene_error_t err;
  CHECK(patch_text(s,
                   "{\"waves\": [{\"a\": 1, \"animate\": [{\"field\": \"a\", \"target\": 3, "
                   "\"rate\": 1}]}]}",
                   &err) == 0);
  for (int i = 0; i < 10; i++)
    scene_advance(s, 1, 0.1);
  CHECK_NEAR(num_at(s, "waves.0.a"), 2.0, 1e-12);
  cJSON *got = scene_get(s, "waves.0.a", &err);
  CHECK(got && cJSON_IsNumber(got) && fabs(got->valuedouble - 2.0) < 1e-12);
  cJSON_Delete(got);
  for (int i = 0; i < 20; i++)
    scene_advance(s, 1, 0.1);
  CHECK(num_at(s, "waves.0.a") == 3.0);

  /* Downwards, to a target below. */
  CHECK(patch_text(s,
                   "{\"waves\": [{\"length\": 5, \"animate\": [{\"field\": \"length\", "
                   "\"target\": 0, \"rate\": 2}]}]}",
                   &err) == 0);
  scene_advance(s, 1, 1);
  CHECK(num_at(s, "waves.0.length") == 3);
  scene_advance(s, 1, 10);
  CHECK(num_at(s, "waves.0.length") == 0);

  /* A point moves along the straight line by rate * time. */
  CHECK(patch_text(s,
                   "{\"waves\": [{\"center\": [0, 0, 0], \"animate\": [{\"field\": \"center\", "
                   "\"target\": [3, 4, 0], \"rate\": 1}]}]}",
                   &err) == 0);
  scene_advance(s, 25, 0.1);
  CHECK_NEAR(num_at(s, "waves.0.center.0"), 1.5, 1e-12);
  CHECK_NEAR(num_at(s, "waves.0.center.1"), 2.0, 1e-12);
  CHECK(num_at(s, "waves.0.center.2") == 0);
  CHECK_NEAR(s->snapshot->waves[0].center[1], 2.0, 1e-6);
  scene_advance(s, 100, 0.1);
  CHECK(num_at(s, "waves.0.center.0") == 3 && num_at(s, "waves.0.center.1") == 4);

  /* A direction turns along the great circle at rate radians per second, staying a unit. */
  CHECK(patch_text(s,
                   "{\"waves\": [{\"direction\": [1, 0, 0], \"animate\": [{\"field\": "
                   "\"direction\", \"target\": [0, 5, 0], \"rate\": 1}]}]}",
                   &err) == 0);
  CHECK(num_at(s, "waves.0.animate.0.target.1") == 1); /* Normalised on input. */
  scene_advance(s, 1, 0.5);
  CHECK_NEAR(num_at(s, "waves.0.direction.0"), cos(0.5), 1e-12);
  CHECK_NEAR(num_at(s, "waves.0.direction.1"), sin(0.5), 1e-12);
  scene_advance(s, 1, 2);
  CHECK(num_at(s, "waves.0.direction.0") == 0 && num_at(s, "waves.0.direction.1") == 1);
  /* Even toward the opposite direction, where a straight line would pass through zero. */
  CHECK(patch_text(s,
                   "{\"waves\": [{\"direction\": [1, 0, 0], \"animate\": [{\"field\": "
                   "\"direction\", \"target\": [-1, 0, 0], \"rate\": 1}]}]}",
                   &err) == 0);
  scene_advance(s, 1, 1);
  double x = num_at(s, "waves.0.direction.0"), y = num_at(s, "waves.0.direction.1"),
         z = num_at(s, "waves.0.direction.2");
  CHECK_NEAR(x * x + y * y + z * z, 1, 1e-12);
  CHECK_NEAR(x, cos(1.0), 1e-12);
  scene_advance(s, 1, 3);
  CHECK(num_at(s, "waves.0.direction.0") == -1);

  /* A colour fades, and the document stays valid afterwards: another patch goes through. */
  CHECK(patch_text(s,
                   "{\"waves\": [{\"color\": [1, 1, 1], \"animate\": [{\"field\": \"color\", "
                   "\"target\": [0, 0, 0], \"rate\": 0.5}]}]}",
                   &err) == 0);
  scene_advance(s, 60, 1.0 / 60);
  CHECK_NEAR(num_at(s, "waves.0.color.0"), 1 - 0.5 / sqrt(3), 1e-12);
  scene_advance(s, 600, 1.0 / 60);
  CHECK(num_at(s, "waves.0.color.0") == 0 && num_at(s, "waves.0.color.2") == 0);
  CHECK(patch_text(s, "{\"camera\": {\"fov_y\": 50}}", &err) == 0);

  /* The beam grows out of M: length from 0. */
  CHECK(patch_text(s,
                   "{\"waves\": [{\"length\": 0, \"animate\": [{\"field\": \"length\", "
                   "\"target\": 4, \"rate\": 2}]}]}",
                   &err) == 0);
  CHECK(s->snapshot->waves[0].length == 0.0f);
  scene_advance(s, 60, 1.0 / 60);
  CHECK_NEAR(s->snapshot->waves[0].length, 2.0, 1e-6);
  scene_destroy(s);
}

/* Sets sim.time to 't' by a patch (so keyframes are applied at commit), returning the value
 * of 'path'. */
static double at_time(scene_t *s, double t, const char *path) {
  char text[96];
  scene_error_t err;
  snprintf(text, sizeof text, "{\"sim\": {\"time\": %.17g}}", t);
  if (patch_text(s, text, &err) != 0) {
    fprintf(stderr, "set time: %s\n", err.message);
    failures++;
  }
  return num_at(s, path);
}

static void test_keys(void) {
  scene_t *s = scene_from("{\"waves\": [{\"length\": 9, \"animate\": [{\"field\": \"length\", "
                          "\"keys\": [{\"t\": 1, \"value\": 0}, {\"t\": 3, \"value\": 2}, "
                          "{\"t\": 5, \"value\": 1}]}]}]}");
  /* Defaults filled, in schema order. */
  CHECK(strcmp(str_at(s, "waves.0.animate.0.interp"), "linear") == 0);
  CHECK(cJSON_IsFalse(sch_path_get(s->doc, "waves.0.animate.0.loop")));
  /* Keyframes own their field: at commit it already has the value of time 0 (held). */
  CHECK(num_at(s, "waves.0.length") == 0);
  CHECK(s->snapshot->waves[0].length == 0.0f);
  CHECK(at_time(s, 0.5, "waves.0.length") == 0);
  CHECK(at_time(s, 1, "waves.0.length") == 0);
  CHECK_NEAR(at_time(s, 2, "waves.0.length"), 1, 1e-12);
  CHECK_NEAR(at_time(s, 2.5, "waves.0.length"), 1.5, 1e-12);
  CHECK(at_time(s, 3, "waves.0.length") == 2);
  CHECK_NEAR(at_time(s, 4.5, "waves.0.length"), 1.25, 1e-12);
  CHECK(at_time(s, 5, "waves.0.length") == 1);
  CHECK(at_time(s, 50, "waves.0.length") == 1); /* Held after the last key. */
  /* Values written by a client are overridden by the keyframes. */
  scene_error_t err;
  CHECK(patch_text(s,
                   "{\"waves\": [{\"length\": 7, \"animate\": [{\"field\": \"length\", "
                   "\"keys\": [{\"t\": 1, \"value\": 0}, {\"t\": 3, \"value\": 2}]}]}]}",
                   &err) == 0);
  CHECK(num_at(s, "waves.0.length") == 2);

  /* Smooth: smoothstep between each pair of keys. */
  CHECK(patch_text(s,
                   "{\"sim\": {\"time\": 0}, \"waves\": [{\"animate\": [{\"field\": \"a\", "
                   "\"keys\": [{\"t\": 0, \"value\": 1}, {\"t\": 2, \"value\": 3}], "
                   "\"interp\": \"smooth\"}]}]}",
                   &err) == 0);
  CHECK(num_at(s, "waves.0.a") == 1);
  /* u = 0.25: 0.25^2 * (3 - 0.5) = 0.15625. */
  CHECK_NEAR(at_time(s, 0.5, "waves.0.a"), 1 + 2 * 0.15625, 1e-12);
  CHECK_NEAR(at_time(s, 1, "waves.0.a"), 2, 1e-12);
  CHECK_NEAR(at_time(s, 1.5, "waves.0.a"), 1 + 2 * 0.84375, 1e-12);
  CHECK(at_time(s, 2, "waves.0.a") == 3);

  /* Loop: wraps over the keys' span; a single key is constant. */
  CHECK(patch_text(s,
                   "{\"sim\": {\"time\": 0}, \"waves\": [{\"animate\": [{\"field\": \"b\", "
                   "\"keys\": [{\"t\": 1, \"value\": 0}, {\"t\": 3, \"value\": 2}], "
                   "\"loop\": true}, {\"field\": \"clamp\", \"keys\": [{\"t\": 4, \"value\": "
                   "6}]}]}]}",
                   &err) == 0);
  CHECK(strcmp(str_at(s, "waves.0.animate.0.interp"), "linear") == 0);
  CHECK(num_at(s, "waves.0.b") == 0 && num_at(s, "waves.0.clamp") == 6);
  CHECK(at_time(s, 0.5, "waves.0.b") == 0); /* Held before the first key, even looping. */
  CHECK_NEAR(at_time(s, 2, "waves.0.b"), 1, 1e-12);
  CHECK_NEAR(at_time(s, 3.5, "waves.0.b"), 0.5, 1e-12);
  CHECK_NEAR(at_time(s, 6, "waves.0.b"), 1, 1e-12);
  CHECK_NEAR(at_time(s, 102.5, "waves.0.b"), 1.5, 1e-9);

  /* Vec3 keys through the clock: a point along straight segments, a direction along arcs. */
  CHECK(patch_text(s,
                   "{\"sim\": {\"time\": 0}, \"waves\": [{\"animate\": [{\"field\": "
                   "\"center\", \"keys\": [{\"t\": 0, \"value\": [0, 0, 0]}, {\"t\": 1, "
                   "\"value\": [2, -4, 6]}]}, {\"field\": \"direction\", \"keys\": [{\"t\": 0, "
                   "\"value\": [1, 0, 0]}, {\"t\": 1, \"value\": [0, 0, 3]}]}]}]}",
                   &err) == 0);
  scene_advance(s, 1, 0.25);
  CHECK_NEAR(num_at(s, "waves.0.center.0"), 0.5, 1e-12);
  CHECK_NEAR(num_at(s, "waves.0.center.1"), -1, 1e-12);
  CHECK_NEAR(num_at(s, "waves.0.center.2"), 1.5, 1e-12);
  CHECK_NEAR(num_at(s, "waves.0.direction.0"), cos(PI / 8), 1e-12);
  CHECK_NEAR(num_at(s, "waves.0.direction.2"), sin(PI / 8), 1e-12);
  CHECK_NEAR(s->snapshot->waves[0].direction[2], sin(PI / 8), 1e-6);
  cJSON *got = scene_get(s, "waves.0.center", &err);
  CHECK(got && fabs(cJSON_GetArrayItem(got, 2)->valuedouble - 1.5) < 1e-12);
  cJSON_Delete(got);
  scene_advance(s, 10, 0.25);
  CHECK(num_at(s, "waves.0.center.1") == -4 && num_at(s, "waves.0.direction.2") == 1);
  scene_destroy(s);
}

/* Many steps cost one compile: a batch is applied in one go, and even single steps only copy
 * the snapshot. */
static void test_many_steps(void) {
  cJSON *doc = J("{\"waves\": []}");
  cJSON *waves = cJSON_GetObjectItem(doc, "waves");
  for (int i = 0; i < 64; i++)
    cJSON_AddItemToArray(
        waves, J("{\"a\": 1, \"animate\": [{\"field\": \"a\", \"target\": 1000, \"rate\": 1}, "
                 "{\"field\": \"center\", \"keys\": [{\"t\": 0, \"value\": [0, 0, 0]}, {\"t\": "
                 "10, \"value\": [10, 0, 0]}], \"loop\": true}]}"));
  scene_error_t err;
  scene_t *s = scene_create("main", doc, &err);
  cJSON_Delete(doc);
  CHECK(s != NULL);
  if (!s)
    return;
  double t0 = now_s();
  scene_advance(s, 10000, 0.01);
  double batch = now_s() - t0;
  CHECK_NEAR(num_at(s, "sim.time"), 100, 1e-9);
  CHECK(num_at(s, "sim.frame") == 10000);
  CHECK_NEAR(num_at(s, "waves.63.a"), 101, 1e-9);
  CHECK(s->snapshot->waves[63].a == 101.0f);
  CHECK_NEAR(num_at(s, "waves.63.center.0"), 0, 1e-6); /* 100 s is 10 loops. */
  t0 = now_s();
  for (int i = 0; i < 10000; i++)
    scene_advance(s, 1, 0.01);
  double single = now_s() - t0;
  CHECK_NEAR(num_at(s, "waves.0.a"), 201, 1e-6);
  CHECK_NEAR(s->snapshot->time, 200, 1e-6);
  /* The value is the same bits however the steps were grouped: one batch of 20000 from the
   * start lands where the batch of 10000 and the 10000 single steps did. */
  scene_t *again = scene_create("again", s->doc, &err);
  CHECK(again != NULL);
  if (again) {
    cJSON_SetNumberValue(sch_path_get(again->doc, "waves.0.a"), 1);
    scene_error_t e2;
    cJSON *reset = J("{\"sim\": {\"frame\": 0, \"time\": 0}}");
    CHECK(scene_patch(again, reset, &e2) == 0);
    cJSON_Delete(reset);
    for (int i = 0; i < 64; i++) {
      char path[32];
      snprintf(path, sizeof path, "waves.%d.a", i);
      cJSON_SetNumberValue(sch_path_get(again->doc, path), 1);
    }
    scene_advance(again, 20000, 0.01);
    CHECK(num_at(again, "waves.0.a") == num_at(s, "waves.0.a"));
    CHECK(num_at(again, "waves.63.a") == num_at(s, "waves.63.a"));
    scene_destroy(again);
  }
  printf("  10000 steps of 64 animated waves: %.3f ms in one call, %.1f ms in single steps\n",
         batch * 1e3, single * 1e3);
  /* Generous bounds that a compile per step (or worse) would still pass for the single steps,
   * but not for the batch: it must be a single step's work. */
  CHECK(batch < 0.05);
  CHECK(single < 20.0);
  scene_destroy(s);
}

/* The published schema carries every wave field's description, default, range and unit. */
static void test_schema(void) {
  cJSON *js = sch_to_json_schema(&scene_schema);
  cJSON *w = sch_path_get(js, "properties.waves.items.properties");
  CHECK(cJSON_IsObject(w));
  CHECK(sch_path_get(js, "properties.waves.maxItems")->valuedouble == 64);
  static const char *const names[] = {"id",    "center", "direction", "a",
                                      "b",     "length", "radius",    "softening",
                                      "clamp", "color",  "animate"};
  for (size_t i = 0; i < sizeof names / sizeof names[0]; i++) {
    cJSON *f = cJSON_GetObjectItemCaseSensitive(w, names[i]);
    CHECK(f && cJSON_IsString(cJSON_GetObjectItem(f, "description")));
    if (strcmp(names[i], "animate") != 0)
      CHECK(f && cJSON_GetObjectItem(f, "default"));
  }
  cJSON *soft = cJSON_GetObjectItem(w, "softening");
  CHECK(cJSON_GetObjectItem(soft, "exclusiveMinimum")->valuedouble == 0);
  CHECK(cJSON_GetObjectItem(soft, "maximum")->valuedouble == 1e6);
  CHECK(cJSON_GetObjectItem(soft, "default")->valuedouble == 0.05);
  CHECK(strcmp(cJSON_GetObjectItem(soft, "x-unit")->valuestring, "world units") == 0);
  CHECK(sch_path_get(w, "a.minimum")->valuedouble == 0);
  CHECK(sch_path_get(w, "direction.default.0")->valuedouble == 1);
  cJSON *anim = sch_path_get(w, "animate.items.properties");
  CHECK(cJSON_IsObject(anim));
  CHECK(strcmp(sch_path_get(anim, "interp.default")->valuestring, "linear") == 0);
  CHECK(cJSON_IsFalse(sch_path_get(anim, "loop.default")));
  CHECK(sch_path_get(anim, "rate.exclusiveMinimum") != NULL);
  CHECK(sch_path_get(anim, "keys.items.properties.t.x-unit") != NULL);
  cJSON *fields = sch_path_get(anim, "field.enum");
  CHECK(cJSON_GetArraySize(fields) == 9);
  cJSON_Delete(js);
}

static cJSON *read_json(const char *path) {
  FILE *f = fopen(path, "rb");
  if (!f)
    return NULL;
  static char buf[1 << 16];
  size_t n = fread(buf, 1, sizeof buf - 1, f);
  fclose(f);
  buf[n] = '\0';
  return cJSON_Parse(buf);
}

/* The thesis' experiment (figs. 4.8-4.13): M's z goes from 280 to -140 at 100 units per
 * second, so the figures' values fall at 0, 1.2, 2.1, 2.7, 3.3 and 4.2 seconds. */
static void test_paper_preset(void) {
  cJSON *doc = read_json("scenes/paper-000.json");
  CHECK(doc != NULL);
  if (!doc)
    return;
  scene_error_t err;
  scene_t *s = scene_create("paper", doc, &err);
  cJSON_Delete(doc);
  CHECK(s != NULL);
  if (!s) {
    fprintf(stderr, "paper-000: %s\n", err.message);
    return;
  }
  CHECK(num_at(s, "camera.eye.2") == 300 && num_at(s, "camera.target.2") == 0);
  CHECK(strcmp(str_at(s, "objects.0.shape"), "tetrahedron") == 0);
  CHECK(strcmp(str_at(s, "objects.1.shape"), "tetrahedron") == 0);
  CHECK(num_at(s, "objects.0.position.2") == 0);
  CHECK(num_at(s, "objects.1.position.0") == 10 && num_at(s, "objects.1.position.2") == 250);
  CHECK(num_at(s, "waves.0.a") == 60 && num_at(s, "waves.0.b") == 30);
  CHECK(num_at(s, "waves.0.direction.0") == 1);
  CHECK(num_at(s, "waves.0.center.2") == 280);
  CHECK(s->snapshot->nwaves == 1 && s->snapshot->waves[0].center[2] == 280.0f);
  CHECK(s->snapshot->nobjects == 2);
  double dt = scene_dt(s);
  scene_advance(s, 72, dt); /* 1.2 s */
  CHECK_NEAR(num_at(s, "waves.0.center.2"), 160, 1e-9);
  CHECK(num_at(s, "waves.0.center.0") == 0 && num_at(s, "waves.0.center.1") == 0);
  scene_advance(s, 54, dt); /* 2.1 s */
  CHECK_NEAR(num_at(s, "waves.0.center.2"), 70, 1e-9);
  scene_advance(s, 36, dt); /* 2.7 s */
  CHECK_NEAR(num_at(s, "waves.0.center.2"), 10, 1e-9);
  scene_advance(s, 36, dt); /* 3.3 s */
  CHECK_NEAR(num_at(s, "waves.0.center.2"), -50, 1e-9);
  scene_advance(s, 54, dt); /* 4.2 s */
  CHECK_NEAR(num_at(s, "waves.0.center.2"), -140, 1e-9);
  CHECK_NEAR(s->snapshot->waves[0].center[2], -140, 1e-4);
  scene_advance(s, 30, dt); /* 4.7 s: held at the end for a second. */
  CHECK(num_at(s, "waves.0.center.2") == -140);
  scene_advance(s, 42, dt); /* 5.4 s: looped to 0.2 s. */
  CHECK_NEAR(num_at(s, "waves.0.center.2"), 260, 1e-6);
  /* A figure is one patch away: set the time. */
  CHECK_NEAR(at_time(s, 2.7, "waves.0.center.2"), 10, 1e-9);
  scene_destroy(s);

  /* The demo scene holds a wave too. */
  doc = read_json("scenes/demo.json");
  CHECK(doc != NULL);
  s = doc ? scene_create("demo", doc, &err) : NULL;
  cJSON_Delete(doc);
  CHECK(s && s->snapshot->nwaves == 1);
  scene_destroy(s);
}

int main(void) {
  test_defaults();
  test_direction();
  test_refused();
  test_compile();
  test_toward();
  test_keys();
  test_many_steps();
  test_schema();
  test_paper_preset();
  if (failures) {
    fprintf(stderr, "test_scene_waves: %d check(s) failed\n", failures);
    return 1;
  }
  printf("test_scene_waves: all checks passed\n");
  return 0;
}
