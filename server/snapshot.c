/*
 * scene.save and scene.load: snapshots of a scene in the data directory. A snapshot is one
 * JSON header line, {"volfx_snapshot": 1, "scene": {...}, "sections": [...]}, followed by the
 * binary sections it lists (none yet: simulation state that is not in the document will go
 * there). Files are written atomically (temporary file, fsync, rename, fsync of the directory)
 * and all file I/O runs on libuv's thread pool, never on the loop thread.
 */
#include <errno.h>
#include <fcntl.h>
#include <libgen.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "datapath.h"
#include "files.h"
#include "dispatch.h"

#define SNAPSHOT_VERSION 1
#define SNAPSHOT_MAX_BYTES (256u << 20)

typedef struct snap_work {
  uv_work_t req;
  call_t *call;
  char path[PATH_MAX];
  char file[256]; /* The client's name for it. */
  char scene[64];
  char *text; /* save: the bytes to write; load: the bytes read. */
  size_t len;
  int err; /* errno of the failed step, or 0. */
  const char *step;
} snap_work_t;

static int write_all(int fd, const char *p, size_t n) {
  while (n) {
    ssize_t w = write(fd, p, n);
    if (w < 0 && errno == EINTR)
      continue;
    if (w <= 0)
      return -1;
    p += w;
    n -= (size_t)w;
  }
  return 0;
}

/* Thread pool: writes the snapshot next to its final name, then renames it into place. */
static void save_work(uv_work_t *req) {
  snap_work_t *w = req->data;
  char tmp[PATH_MAX + 32];
  snprintf(tmp, sizeof tmp, "%s.tmp%ld", w->path, (long)getpid());
  int fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
  if (fd < 0) {
    w->err = errno;
    w->step = "create";
    return;
  }
  if (write_all(fd, w->text, w->len) != 0 || fsync(fd) != 0) {
    w->err = errno;
    w->step = "write";
    close(fd);
    unlink(tmp);
    return;
  }
  close(fd);
  if (rename(tmp, w->path) != 0) {
    w->err = errno;
    w->step = "rename";
    unlink(tmp);
    return;
  }
  /* The rename is durable once the directory is synced. */
  char dir[PATH_MAX];
  snprintf(dir, sizeof dir, "%s", w->path);
  int dfd = open(dirname(dir), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dfd >= 0) {
    fsync(dfd);
    close(dfd);
  }
}

static void save_done(uv_work_t *req, int status) {
  snap_work_t *w = req->data;
  call_t *call = w->call;
  if (status != 0 || w->err) {
    call_error(call, PROTO_E_INTERNAL, "file", "internal error: cannot %s snapshot \"%s\": %s",
               w->step ? w->step : "write", w->file, strerror(w->err ? w->err : EIO));
  } else {
    cJSON *r = cJSON_CreateObject();
    cJSON_AddStringToObject(r, "file", w->file);
    cJSON_AddNumberToObject(r, "bytes", (double)w->len);
    call_result(call, r);
  }
  free(w->text);
  free(w);
}

static snap_work_t *work_for(call_t *call, int must_exist) {
  const char *file = cJSON_GetStringValue(cJSON_GetObjectItem(call->params, "file"));
  snap_work_t *w = calloc(1, sizeof *w);
  if (!w) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return NULL;
  }
  char why[256];
  int notfound = 0;
  if (datapath_resolve(call->srv->cfg.data_dir, file, must_exist, w->path, sizeof w->path, why,
                       sizeof why, &notfound) != 0) {
    free(w);
    call_error(call, notfound ? PROTO_E_NOT_FOUND : PROTO_E_INVALID_PARAMS, "file", "%s: file: %s",
               proto_err_message(notfound ? PROTO_E_NOT_FOUND : PROTO_E_INVALID_PARAMS), why);
    return NULL;
  }
  snprintf(w->file, sizeof w->file, "%s", file);
  w->call = call;
  w->req.data = w;
  return w;
}

static void scene_save(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  snap_work_t *w = work_for(call, 0);
  if (!w)
    return;
  cJSON *head = cJSON_CreateObject();
  cJSON_AddNumberToObject(head, "volfx_snapshot", SNAPSHOT_VERSION);
  cJSON_AddStringToObject(head, "name", e->scene->name);
  cJSON_AddItemToObject(head, "scene", cJSON_Duplicate(e->scene->doc, 1));
  cJSON_AddArrayToObject(head, "sections");
  w->text = proto_print_line(head, &w->len);
  cJSON_Delete(head);
  if (!w->text) {
    free(w);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  uv_queue_work(call->srv->loop, &w->req, save_work, save_done);
}

/* Thread pool: reads the whole file. */
static void load_work(uv_work_t *req) {
  snap_work_t *w = req->data;
  w->text = files_read(w->path, SNAPSHOT_MAX_BYTES, &w->len);
  if (!w->text) {
    w->err = errno;
    w->step = "read";
  }
}

static void load_done(uv_work_t *req, int status) {
  snap_work_t *w = req->data;
  call_t *call = w->call;
  scene_entry_t *e = server_find_scene(call->srv, w->scene);
  char why[160] = "";
  cJSON *head = NULL;
  if (status != 0 || w->err) {
    call_error(call, PROTO_E_INTERNAL, "file", "internal error: cannot %s \"%s\": %s",
               w->step ? w->step : "read", w->file, strerror(w->err ? w->err : EIO));
  } else if (!e) {
    call_error(call, PROTO_E_NOT_FOUND, "scene", "not found: scene '%s' was deleted", w->scene);
  } else {
    char *nl = memchr(w->text, '\n', w->len);
    head = proto_parse(w->text, nl ? (size_t)(nl - w->text) : w->len, why, sizeof why);
    const cJSON *doc = cJSON_GetObjectItem(head, "scene");
    if (!head || !cJSON_IsNumber(cJSON_GetObjectItem(head, "volfx_snapshot")) ||
        cJSON_GetObjectItem(head, "volfx_snapshot")->valuedouble != SNAPSHOT_VERSION ||
        !cJSON_IsObject(doc)) {
      call_error(call, PROTO_E_INVALID_PARAMS, "file",
                 "invalid params: file: \"%s\" is not a volfx snapshot (version %d)%s%s", w->file,
                 SNAPSHOT_VERSION, why[0] ? ": " : "", why);
    } else {
      scene_error_t err = {0};
      if (scene_replace(e->scene, doc, &err) != 0) {
        call_error(call, PROTO_E_INVALID_PARAMS, err.path[0] ? err.path : "file",
                   "invalid params: snapshot \"%s\": %s", w->file, err.message);
      } else {
        /* Playing is the server's state, not the file's. */
        cJSON *patch = cJSON_CreateObject();
        cJSON_AddBoolToObject(cJSON_AddObjectToObject(patch, "sim"), "playing", e->rate > 0);
        scene_patch(e->scene, patch, &err);
        cJSON_Delete(patch);
        cJSON *r = cJSON_CreateObject();
        cJSON_AddStringToObject(r, "file", w->file);
        cJSON_AddNumberToObject(r, "version", (double)e->scene->version);
        cJSON_AddNumberToObject(r, "frame", scene_frame(e->scene));
        cJSON_AddNumberToObject(r, "time", scene_time(e->scene));
        call_result(call, r);
      }
    }
  }
  cJSON_Delete(head);
  free(w->text);
  free(w);
}

static void scene_load(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  snap_work_t *w = work_for(call, 1);
  if (!w)
    return;
  snprintf(w->scene, sizeof w->scene, "%s", e->scene->name);
  uv_queue_work(call->srv->loop, &w->req, load_work, load_done);
}

static const sch_field_t file_params[] = {
    PARAM_SCENE,
    {.name = "file",
     .type = SCH_STRING,
     .desc = "Snapshot file, relative to the data directory (its directory must exist).",
     .max = 255,
     .flags = SCH_REQUIRED},
    {0}};

static const int save_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, 0};

const method_t method_scene_save = {
    .name = "scene.save",
    .summary = "Writes a snapshot of the scene (JSON plus binary state) atomically under the "
               "data directory.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = file_params},
    .result = "{file, bytes}",
    .errors = save_errors,
    .handler = scene_save};

const method_t method_scene_load = {
    .name = "scene.load",
    .summary = "Replaces the scene with a snapshot from the data directory; on any error "
               "nothing changes.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = file_params},
    .result = "{file, version, frame, time}",
    .errors = save_errors,
    .handler = scene_load};
