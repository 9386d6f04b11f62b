/*
 * Scene and clock methods: scene.list, scene.create, scene.delete, scene.get, scene.set,
 * sim.step, sim.play and sim.pause.
 */
#include <ctype.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "defer.h"
#include "dispatch.h"
#include "frames.h"
#include "log.h"
#include "play.h"
#include "step_cloud.h"
#include "stepper.h"
#include "worker.h"

static void answer_scene_error(call_t *call, const scene_error_t *err, const char *fallback) {
  const char *path = err->path[0] ? err->path : fallback;
  int code = err->code ? err->code : PROTO_E_INVALID_PARAMS;
  call_error(call, code, path, "%s: %s", proto_err_message(code), err->message);
}

static void scene_list(call_t *call) {
  cJSON *r = cJSON_CreateObject();
  cJSON *arr = cJSON_AddArrayToObject(r, "scenes");
  for (scene_entry_t *e = call->srv->scenes; e; e = e->next) {
    cJSON *o = cJSON_CreateObject();
    cJSON_AddStringToObject(o, "name", e->scene->name);
    cJSON_AddNumberToObject(o, "frame", scene_frame(e->scene));
    cJSON_AddNumberToObject(o, "time", scene_time(e->scene));
    cJSON_AddBoolToObject(o, "playing", e->rate > 0);
    cJSON_AddNumberToObject(o, "version", (double)e->scene->version);
    cJSON_AddStringToObject(o, "preset", e->scene->preset);
    cJSON_AddItemToArray(arr, o);
  }
  call_result(call, r);
}

static int valid_name(const char *s) {
  if (!s[0] || strlen(s) > 63)
    return 0;
  for (; *s; s++)
    if (!isalnum((unsigned char)*s) && *s != '_' && *s != '-' && *s != '.')
      return 0;
  return 1;
}

static void scene_create_m(call_t *call) {
  const char *name = cJSON_GetStringValue(cJSON_GetObjectItem(call->params, "name"));
  const char *preset = cJSON_GetStringValue(cJSON_GetObjectItem(call->params, "preset"));
  if (!valid_name(name)) {
    call_error(call, PROTO_E_INVALID_PARAMS, "name",
               "invalid params: name must be 1-63 characters of A-Z a-z 0-9 _ . -");
    return;
  }
  if (server_find_scene(call->srv, name)) {
    call_error(call, PROTO_E_INVALID_PARAMS, "name", "invalid params: scene '%s' exists", name);
    return;
  }
  if (preset && !valid_name(preset)) {
    call_error(call, PROTO_E_NOT_FOUND, "preset", "not found: no preset named '%s'", preset);
    return;
  }
  scene_error_t err = {0};
  defer_want_t want;
  defer_arm(call, &want);
  scene_entry_t *e = server_add_scene(call->srv, name, preset, &err);
  if (defer_check(call, e ? 0 : -1, &err, &want))
    return;
  if (!e) {
    answer_scene_error(call, &err, "preset");
    return;
  }
  cJSON *r = cJSON_CreateObject();
  cJSON_AddStringToObject(r, "name", name);
  call_result(call, r);
}

static void scene_delete_m(call_t *call) {
  const char *name = cJSON_GetStringValue(cJSON_GetObjectItem(call->params, "name"));
  scene_entry_t *e = server_find_scene(call->srv, name);
  if (!e) {
    call_error(call, PROTO_E_NOT_FOUND, "name", "not found: no scene named '%s'", name);
    return;
  }
  frames_scene_deleted(call->srv, name);
  server_remove_scene(call->srv, e);
  cJSON *r = cJSON_CreateObject();
  cJSON_AddStringToObject(r, "deleted", name);
  call_result(call, r);
}

static void scene_get_m(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  const char *path = cJSON_GetStringValue(cJSON_GetObjectItem(call->params, "path"));
  scene_error_t err = {0};
  cJSON *v = scene_get(e->scene, path, &err);
  if (!v) {
    err.code = err.code ? err.code : PROTO_E_NOT_FOUND;
    call_error(call, err.code, "path", "%s: %s", proto_err_message(err.code), err.message);
    return;
  }
  call_result(call, v);
}

static double play_rate_default(void);

static void scene_set_m(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  const cJSON *patch = cJSON_GetObjectItem(call->params, "patch");
  const cJSON *path = cJSON_GetObjectItem(call->params, "path");
  const cJSON *value = cJSON_GetObjectItem(call->params, "value");
  const cJSON *changes = cJSON_GetObjectItem(call->params, "changes");
  const cJSON *ops = cJSON_GetObjectItem(call->params, "ops");
  scene_error_t err = {0};
  defer_want_t want;
  int rc;
  /* The cloud before the change: a new metaball radius for the same cells needs their density
   * computed again. */
  scene_cloud_t cloud_before;
  int cloud_was = scene_cloud_config(e->scene, &cloud_before) == 0;
  const cloud_cells_t *cells_before = e->scene->cloud_cells;
  int forms = !!patch + !!(path || value) + !!changes + !!ops;
  if (forms != 1 || (path && !value) || (value && !path)) {
    /* The member that is missing, or the first of the second form given. */
    const char *at = path && !value ? "value" : value && !path ? "path" : "patch";
    if (forms > 1)
      at = patch && (path || value)              ? (path ? "path" : "value")
           : (patch || path || value) && changes ? "changes"
                                                 : "ops";
    call_error(call, PROTO_E_INVALID_PARAMS, at,
               "invalid params: %s: give one of 'patch', 'path' with 'value', 'changes' or "
               "'ops'",
               at);
    return;
  }
  if (patch && !cJSON_IsObject(patch)) {
    call_error(call, PROTO_E_INVALID_PARAMS, "patch",
               "invalid params: patch must be a JSON object (RFC 7386 merge patch)");
    return;
  }
  if (path && (!path->valuestring || !path->valuestring[0])) {
    call_error(call, PROTO_E_INVALID_PARAMS, "path",
               "invalid params: path: a path must name a member of the scene (use a patch for "
               "the whole scene)");
    return;
  }
  defer_arm(call, &want);
  if (patch)
    rc = scene_patch(e->scene, patch, &err);
  else if (path)
    rc = scene_set_path(e->scene, path->valuestring, value, &err);
  else if (changes)
    rc = scene_set_changes(e->scene, changes, &err);
  else
    rc = scene_apply_ops(e->scene, ops, &err);
  if (defer_check(call, rc, &err, &want))
    return;
  if (rc != 0) {
    answer_scene_error(call, &err, NULL);
    return;
  }
  /* sim.playing set in the document plays or pauses the scene, as sim.play at its default
   * rate and sim.pause would. */
  cJSON *playing = scene_get(e->scene, "sim.playing", &err);
  if (playing && cJSON_IsTrue(playing) && !(e->rate > 0))
    play_start(e, play_rate_default());
  else if (playing && !cJSON_IsTrue(playing) && e->rate > 0)
    play_stop(e, NULL, NULL);
  cJSON_Delete(playing);
  scene_cloud_t cloud_after;
  if (cloud_was && cells_before && e->scene->cloud_cells == cells_before &&
      scene_cloud_config(e->scene, &cloud_after) == 0 &&
      cloud_after.radius != cloud_before.radius) {
    /* Answered once the density shows the new radius; the connection's next requests wait. */
    if (cloud_submit_density(call->srv, e, call) == 0) {
      call_hold(call);
      return;
    }
    LOG(LOG_WARN, "scene",
        "scene '%s': the render queue is full; the cloud's density takes the "
        "new metaball radius at its next step",
        e->scene->name);
  }
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "version", (double)e->scene->version);
  call_result(call, r);
}

static cJSON *clock_json(const scene_entry_t *e) {
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "time", scene_time(e->scene));
  cJSON_AddNumberToObject(r, "frame", scene_frame(e->scene));
  return r;
}

/* The answer to a sim.step: the clock where the stepping ended, and why, when it ended early. */
static void step_answer(void *ctx, const stepper_end_t *end) {
  call_t *call = ctx;
  if (end->code != 0) {
    call_error(call, end->code, NULL, "%s: %s", proto_err_message(end->code), end->err);
    return;
  }
  cJSON *r = clock_json(end->scene);
  if (end->cut)
    cJSON_AddStringToObject(r, "cut_short", end->cut);
  call_result(call, r);
}

/* Whether 'steps' simulation steps of the cloud of 'e' fit limits.automaton_steps; answers
 * the call when not. */
static int automaton_fits(call_t *call, const scene_entry_t *e, uint64_t steps) {
  scene_cloud_t cfg;
  uint32_t limit = call->srv->cfg.budget.automaton_steps;
  if (!cloud_wants_step(e) || scene_cloud_config(e->scene, &cfg) != 0 ||
      steps * cfg.steps_per_frame <= limit)
    return 1;
  call_error(call, PROTO_E_LIMIT, "steps",
             "%s: steps: %llu steps of %u automaton steps each (cloud.steps_per_frame) is over "
             "the limit of %u automaton steps (limits.automaton_steps)",
             proto_err_message(PROTO_E_LIMIT), (unsigned long long)steps, cfg.steps_per_frame,
             limit);
  return 0;
}

/*
 * Steps the clock, the cloud and the fluid (stepper.c: slices on the render worker, so other
 * scenes' renders run between them). The answer waits for the last slice, and so do the
 * connection's next requests, which see the steps taken.
 */
static void sim_step(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  uint64_t steps = (uint64_t)cJSON_GetObjectItem(call->params, "steps")->valuedouble;
  const cJSON *dt = cJSON_GetObjectItem(call->params, "dt");
  double step_dt = dt ? dt->valuedouble : scene_dt(e->scene);
  if (!automaton_fits(call, e, steps))
    return;
  int rc = stepper_start(call->srv, e, steps, step_dt, step_answer, call, NULL);
  if (rc < 0)
    call_error(call, PROTO_E_BUSY, NULL, "%s: the render queue is full",
               proto_err_message(PROTO_E_BUSY));
  else if (rc == 0)
    call_hold(call);
}

static void sim_play(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  play_start(e, cJSON_GetObjectItem(call->params, "rate")->valuedouble);
  cJSON *r = clock_json(e);
  cJSON_AddBoolToObject(r, "playing", 1);
  cJSON_AddNumberToObject(r, "rate", e->rate);
  call_result(call, r);
}

/* A job behind the simulations' last steps that answers sim.pause. */
typedef struct pause_job {
  job_t job;
  call_t *call;
  cJSON *result;
  int starting; /* Inside sim_pause, which queues the job itself when the catch-up ends at once. */
} pause_job_t;

static void pause_run(renderer_t *r, job_t *j) {
  (void)r;
  (void)j;
}

static void pause_done(job_t *j) {
  pause_job_t *pj = (pause_job_t *)j;
  call_result(pj->call, pj->result);
  free(pj);
}

/* Queues the job that answers the pause behind every job of the scene, or answers at once
 * when the worker takes no more. Returns 0 when the answer comes later. */
static int pause_queue(pause_job_t *pj, server_t *srv) {
  pj->job.run = pause_run;
  pj->job.done = pause_done;
  pj->job.continues = 1;
  if (srv->worker && worker_submit(srv->worker, &pj->job) == 0)
    return 0;
  call_result(pj->call, pj->result);
  free(pj);
  return -1;
}

/* The steps owed are taken (or the catch-up ended otherwise): the answer follows them. */
static void pause_caught_up(void *ctx, const stepper_end_t *end) {
  (void)end;
  pause_job_t *pj = ctx;
  if (!pj->starting)
    pause_queue(pj, pj->call->srv);
}

/*
 * Stops playing and cuts short any stepping of the scene (sim.step, a job's): each stops after
 * its slice in flight. The steps the fluid and the cloud still owe the clock (ticks that found
 * a job running) are taken now, and the answer waits behind them and behind every job of the
 * scene in flight, as do the connection's next requests: what they read is the state at the
 * frame the answer reports.
 */
static void sim_pause(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  pause_job_t *pj = calloc(1, sizeof *pj);
  if (!pj) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  pj->call = call;
  pj->starting = 1;
  int rc = play_stop(e, pause_caught_up, pj);
  pj->starting = 0;
  pj->result = clock_json(e);
  cJSON_AddBoolToObject(pj->result, "playing", 0);
  if (rc == 0 || pause_queue(pj, call->srv) == 0)
    call_hold(call);
}

static const sch_field_t list_params[] = {{0}};
static const sch_field_t create_params[] = {
    {.name = "name",
     .type = SCH_STRING,
     .desc = "Name of the new scene: [A-Za-z0-9_.-]{1,63}.",
     .max = 63,
     .flags = SCH_REQUIRED},
    {.name = "preset",
     .type = SCH_STRING,
     .desc = "A preset from scenes/ (\"demo\", ...); omitted for the default scene.",
     .max = 63,
     .flags = SCH_NO_DEFAULT},
    {0}};
static const sch_field_t delete_params[] = {{.name = "name",
                                             .type = SCH_STRING,
                                             .desc = "Name of the scene to delete.",
                                             .max = 63,
                                             .flags = SCH_REQUIRED},
                                            {0}};
static const sch_field_t get_params[] = {
    PARAM_SCENE,
    {.name = "path",
     .type = SCH_STRING,
     .desc = "Dotted path of a sub-tree (\"camera.eye\", \"objects.0.color\", "
             "\"objects.orb.color\": array items by index or id); omitted for all.",
     .max = 255,
     .flags = SCH_NO_DEFAULT},
    {0}};
static const sch_field_t set_params[] = {
    PARAM_SCENE,
    {.name = "patch",
     .type = SCH_ANY,
     .desc = "An RFC 7386 merge patch of the scene document; an array whose items all have an "
             "id updates the items of objects, waves or volumes with those ids (adding new "
             "ones), any other array replaces the array whole.",
     .flags = SCH_NO_DEFAULT},
    {.name = "path",
     .type = SCH_STRING,
     .desc = "Dotted path of one value to set (with 'value'), array items by index or id "
             "(\"objects.orb.scale\"); an index equal to an array's length appends, null "
             "deletes.",
     .max = 255,
     .flags = SCH_NO_DEFAULT},
    {.name = "value",
     .type = SCH_ANY,
     .desc = "The value to set at 'path'.",
     .flags = SCH_NO_DEFAULT},
    {.name = "changes",
     .type = SCH_ARRAY,
     .desc = "Changes applied in order and committed as one version, or not at all: each "
             "{path, value} (as the path form) or {path, patch} (a merge patch of the value at "
             "path).",
     .max = 1024,
     .items = &(sch_field_t){.type = SCH_ANY},
     .flags = SCH_NO_DEFAULT},
    {.name = "ops",
     .type = SCH_ARRAY,
     .desc = "An RFC 6902 JSON Patch (add, remove, replace, move, copy, test; JSON Pointer "
             "paths, array items by index or id), applied as one version, or not at all.",
     .max = 1024,
     .items = &(sch_field_t){.type = SCH_ANY},
     .flags = SCH_NO_DEFAULT},
    PARAM_TAG,
    {0}};
static const sch_field_t step_params[] = {PARAM_SCENE,
                                          {.name = "steps",
                                           .type = SCH_INTEGER,
                                           .desc = "Number of simulation steps.",
                                           .min = 1,
                                           .max = 100000,
                                           .def = 1},
                                          {.name = "dt",
                                           .type = SCH_NUMBER,
                                           .desc = "Step length; default the scene's sim.dt.",
                                           .unit = "seconds",
                                           .min = 0,
                                           .max = 1,
                                           .flags = SCH_POSITIVE | SCH_NO_DEFAULT},
                                          PARAM_TAG,
                                          {0}};
static const sch_field_t play_params[] = {PARAM_SCENE,
                                          {.name = "rate",
                                           .type = SCH_NUMBER,
                                           .desc = "Simulation steps per second of wall time.",
                                           .unit = "steps/second",
                                           .min = 0,
                                           .max = 1000,
                                           .def = 60,
                                           .flags = SCH_POSITIVE},
                                          PARAM_TAG,
                                          {0}};
static const sch_field_t pause_params[] = {PARAM_SCENE, PARAM_TAG, {0}};

/* sim.play's rate when left out: the default of its param above. */
static double play_rate_default(void) {
  static const sch_field_t play = {.type = SCH_OBJECT, .fields = play_params};
  return sch_path_field(&play, "rate")->def;
}

static const int auth_errors[] = {PROTO_E_UNAUTHORIZED, 0};
static const int scene_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, 0};
static const int step_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, PROTO_E_BUSY,
                                  PROTO_E_LIMIT,        PROTO_E_DEVICE,    0};
static const int create_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, PROTO_E_LIMIT, 0};
static const int set_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, PROTO_E_LIMIT, 0};

const method_t method_scene_list = {
    .name = "scene.list",
    .summary = "The named scenes with their clocks.",
    .params = METHOD_PARAMS(list_params),
    .result = "{scenes: [{name, frame, time, playing, version, preset}]}: preset is "
              "what the scene was created from, \"\" for "
              "defaults",
    .errors = auth_errors,
    .handler = scene_list};
const method_t method_scene_create = {
    .name = "scene.create",
    .summary = "Creates a named scene, with its own state and clock, from a preset or defaults.",
    .params = METHOD_PARAMS(create_params),
    .result = "{name}",
    .errors = create_errors,
    .handler = scene_create_m};
const method_t method_scene_delete = {.name = "scene.delete",
                                      .summary = "Deletes a scene; its subscriptions end.",
                                      .params = METHOD_PARAMS(delete_params),
                                      .result = "{deleted}",
                                      .errors = scene_errors,
                                      .handler = scene_delete_m};
const method_t method_scene_get = {.name = "scene.get",
                                   .summary =
                                       "The scene document, or the sub-tree at a dotted path.",
                                   .params = METHOD_PARAMS(get_params),
                                   .result = "The document or the value at 'path'.",
                                   .errors = scene_errors,
                                   .handler = scene_get_m};
const method_t method_scene_set = {
    .name = "scene.set",
    .summary = "Applies a merge patch, one path, a list of changes or a JSON Patch; validated "
               "as a whole, applied atomically as one version; errors name the offending path.",
    .params = METHOD_PARAMS(set_params),
    .result = "{version}",
    .errors = set_errors,
    .handler = scene_set_m,
    .flags = METHOD_SCENE_TAG};
const method_t method_sim_step = {.name = "sim.step",
                                  .summary = "Advances the scene's simulations by 'steps' steps, "
                                             "in slices that other scenes' renders run between.",
                                  .params = METHOD_PARAMS(step_params),
                                  .result = "{time, frame, cut_short?}: the clock where the "
                                            "stepping ended, and why when it ended early",
                                  .errors = step_errors,
                                  .handler = sim_step,
                                  .flags = METHOD_SCENE_TAG};
const method_t method_sim_play = {
    .name = "sim.play",
    .summary = "Runs the simulation freely inside the server at 'rate' steps per second.",
    .params = METHOD_PARAMS(play_params),
    .result = "{playing, rate, time, frame}",
    .errors = scene_errors,
    .handler = sim_play,
    .flags = METHOD_SCENE_TAG};
const method_t method_sim_pause = {.name = "sim.pause",
                                   .summary = "Stops the free-running simulation.",
                                   .params = METHOD_PARAMS(pause_params),
                                   .result = "{playing, time, frame}",
                                   .errors = scene_errors,
                                   .handler = sim_pause,
                                   .flags = METHOD_SCENE_TAG};
