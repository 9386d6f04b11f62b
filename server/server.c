/*
 * The server's scene registry and life cycle: adding, finding and removing named scenes,
 * loading presets, and the graceful stop (stop accepting, answer what is pending, let the
 * render worker finish, close every handle, leave the loop).
 */
#include <ctype.h>
#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "files.h"
#include "frames.h"
#include "jobs.h"
#include "log.h"
#include "server.h"
#include "step_fluid.h"
#include "worker.h"

uint64_t now_ns(void) {
  return uv_hrtime();
}

scene_entry_t *server_find_scene(server_t *s, const char *name) {
  for (scene_entry_t *e = s->scenes; e; e = e->next)
    if (strcmp(e->scene->name, name) == 0)
      return e;
  return NULL;
}

/* The largest preset or --scene file read. */
#define PRESET_MAX_BYTES (16u << 20)

/* Whether 'name' can name a preset: 1-63 characters of [A-Za-z0-9_.-]. */
static int preset_name_ok(const char *name) {
  size_t n = strlen(name);
  if (n == 0 || n > 63)
    return 0;
  for (const char *p = name; *p; p++)
    if (!isalnum((unsigned char)*p) && *p != '_' && *p != '-' && *p != '.')
      return 0;
  return 1;
}

cJSON *server_load_preset(server_t *s, const char *name, scene_error_t *err) {
  /* Only the operator's --scene, which start-up passes as s->cfg.scene itself, may name a file
   * by its path (one with a '/' or ending in ".json"). Any other name, a client's scene.create
   * above all, is a preset, read only as PRESETS_DIR/NAME.json in that directory without
   * following a link: a client learns nothing of other files, not even whether they exist. */
  size_t n = strlen(name);
  int is_file =
      name == s->cfg.scene && (strchr(name, '/') || (n > 5 && strcmp(name + n - 5, ".json") == 0));
  char *text = NULL;
  int e = ENOENT;
  if (is_file) {
    text = files_read(name, PRESET_MAX_BYTES, NULL);
    e = errno;
  } else if (preset_name_ok(name)) {
    char file[80];
    snprintf(file, sizeof file, "%s.json", name);
    int dir = open(s->cfg.presets_dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    text = dir >= 0 ? files_read_at(dir, file, PRESET_MAX_BYTES, NULL) : NULL;
    e = errno;
    if (dir >= 0)
      close(dir);
  }
  snprintf(err->path, sizeof err->path, "preset");
  if (!text) {
    err->code = e == ENOENT || is_file ? PROTO_E_NOT_FOUND : PROTO_E_INVALID_PARAMS;
    if (is_file)
      snprintf(err->message, sizeof err->message, "no preset '%.63s' (%.120s: %.40s)", name, name,
               strerror(e));
    else if (e == ENOENT)
      snprintf(err->message, sizeof err->message, "no preset '%.63s'", name);
    else
      snprintf(err->message, sizeof err->message, "preset '%.63s' cannot be read: %s", name,
               e == EISDIR   ? "it is a directory"
               : e == ENODEV ? "it is not a regular file"
               : e == ELOOP  ? "it is a link, which is not followed"
               : e == EFBIG  ? "it is larger than 16 MiB"
                             : strerror(e));
    return NULL;
  }
  cJSON *doc = cJSON_Parse(text);
  free(text);
  if (!cJSON_IsObject(doc)) {
    cJSON_Delete(doc);
    err->code = PROTO_E_INVALID_PARAMS;
    snprintf(err->message, sizeof err->message, "preset '%.63s' is not a JSON object", name);
    return NULL;
  }
  return doc;
}

/* The scenes the server holds. */
static uint32_t scene_count(const server_t *s) {
  uint32_t n = 0;
  for (const scene_entry_t *e = s->scenes; e; e = e->next)
    n++;
  return n;
}

scene_entry_t *server_add_scene(server_t *s, const char *name, const char *preset,
                                scene_error_t *err) {
  if (scene_count(s) >= s->cfg.budget.scenes) {
    err->code = PROTO_E_LIMIT;
    snprintf(err->path, sizeof err->path, "name");
    snprintf(err->message, sizeof err->message,
             "name: the server holds %u scenes, the limit (limits.scenes); delete one first",
             s->cfg.budget.scenes);
    return NULL;
  }
  /* Every scene is made here, so the scene model takes its budgets from the configuration here
   * (read-only once the server runs). */
  scene_set_budget(s->cfg.budget.scene_bytes, s->cfg.budget.keyframes);
  cJSON *doc = NULL;
  if (preset && preset[0] && !(doc = server_load_preset(s, preset, err)))
    return NULL;
  scene_t *sc = scene_create(name, doc, err);
  cJSON_Delete(doc);
  if (!sc) {
    if (preset && preset[0]) {
      /* The preset itself is broken: say which one. */
      char inner[256];
      snprintf(inner, sizeof inner, "%s", err->message);
      snprintf(err->message, sizeof err->message, "preset '%.40s': %.200s", preset, inner);
    }
    return NULL;
  }
  scene_entry_t *e = calloc(1, sizeof *e);
  if (!e) {
    scene_destroy(sc);
    err->code = PROTO_E_INTERNAL;
    snprintf(err->message, sizeof err->message, "out of memory");
    return NULL;
  }
  e->srv = s;
  e->scene = sc;
  snprintf(sc->preset, sizeof sc->preset, "%s", preset ? preset : "");
  uv_timer_init(s->loop, &e->play);
  e->play.data = e;
  /* A preset saved while playing starts paused: play is always an explicit request. */
  if (cJSON_IsTrue(cJSON_GetObjectItem(cJSON_GetObjectItem(sc->doc, "sim"), "playing"))) {
    cJSON *patch = cJSON_Parse("{\"sim\":{\"playing\":false}}");
    scene_error_t ignored;
    scene_patch(sc, patch, &ignored);
    cJSON_Delete(patch);
  }
  e->next = s->scenes;
  s->scenes = e;
  return e;
}

static void on_play_closed(uv_handle_t *h) {
  scene_entry_t *e = h->data;
  scene_destroy(e->scene);
  cJSON_Delete(e->tag);
  free(e);
}

void server_remove_scene(server_t *s, scene_entry_t *e) {
  for (scene_entry_t **p = &s->scenes; *p; p = &(*p)->next)
    if (*p == e) {
      *p = e->next;
      break;
    }
  uv_timer_stop(&e->play);
  fluid_scene_removed(s, e);
  uv_close((uv_handle_t *)&e->play, on_play_closed);
}

static void on_closed_nothing(uv_handle_t *h) {
  (void)h;
}

static void on_stop_timeout(uv_timer_t *t) {
  server_t *s = t->data;
  if (s->conns)
    LOG(LOG_WARN, "server", "closing %u connections that did not drain", s->nconns);
  while (s->conns)
    conn_close(s->conns);
  uv_close((uv_handle_t *)t, on_closed_nothing);
}

/* Runs once, from the idle handle, outside any request callback. */
static void do_stop(uv_idle_t *idle) {
  server_t *s = idle->data;
  uv_idle_stop(idle);
  uv_close((uv_handle_t *)idle, on_closed_nothing);
  LOG(LOG_INFO, "server", "stopping");
  /* The jobs end first, so that their clients' last job.progress (failed) is queued before
   * net_stop closes the connections that have nothing left to write. */
  jobs_server_stopping(s);
  net_stop(s);
  while (s->scenes)
    server_remove_scene(s, s->scenes);
  uv_close((uv_handle_t *)&s->sigint, on_closed_nothing);
  uv_close((uv_handle_t *)&s->sigterm, on_closed_nothing);
  /* Answers every queued render; the replies are written before the connections close. */
  worker_stop(s->worker);
  s->worker = NULL;
  uv_timer_init(s->loop, &s->stop_timer);
  s->stop_timer.data = s;
  uv_timer_start(&s->stop_timer, on_stop_timeout, 2000, 0);
  uv_unref((uv_handle_t *)&s->stop_timer);
}

void server_features_register(server_t *s) {
  frames_register(s);
  jobs_register(s);
}

void server_request_stop(server_t *s) {
  if (s->stopping)
    return;
  s->stopping = 1;
  uv_idle_init(s->loop, &s->stopper);
  s->stopper.data = s;
  uv_idle_start(&s->stopper, do_stop);
}
