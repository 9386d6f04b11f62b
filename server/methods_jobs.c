/*
 * Background jobs: render.sequence, job.list and job.cancel.
 *
 * A sequence job renders frames first, first + step, ... up to last of a scene's simulation
 * into numbered files under the data directory. It belongs to the server, not to the
 * connection that started it: it runs on when that connection closes, and any connection may
 * list or cancel it; its job.progress notifications go to the starting connection while that
 * is open.
 *
 * One frame is a chain of callbacks on the loop thread, each waiting on the one before:
 *   advance  the scene's clock moves to the frame (scene_advance, as sim.step does), and the
 *            cloud and fluid steps are queued on the render worker;
 *   barrier  an empty job queued behind those steps: the worker runs jobs in order, so when
 *            its 'done' runs, the stepped particles and cells are in the scene's snapshot;
 *   render   a render job of that snapshot (PNG frames come back encoded);
 *   write    the bytes written atomically on libuv's thread pool, then job.progress.
 * A full render queue delays the chain by a timer instead of failing it. The job holds a
 * reference for every callback it waits on and is freed when the last returns, which may be
 * after it has ended (cancelled, failed, shut down).
 */
#include <errno.h>
#include <limits.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "cloud.h"
#include "datapath.h"
#include "dispatch.h"
#include "files.h"
#include "fluid.h"
#include "frames.h"
#include "jobs.h"
#include "log.h"

/* Finished jobs kept for job.list. */
#define JOBS_KEEP_ENDED 16
/* Delay before trying again when the render queue is full. */
#define JOBS_RETRY_MS 5

typedef enum { JOB_RUNNING, JOB_DONE, JOB_FAILED, JOB_CANCELLED } job_state_t;
static const char *const state_names[] = {"running", "done", "failed", "cancelled"};

struct seq_job {
  seq_job_t *next; /* In the server's list, newest first. */
  server_t *srv;
  uint64_t id;
  conn_t *conn; /* Where progress goes; NULL once that connection has closed. */
  char scene[64];
  cJSON *params; /* The validated render.sequence params, reused for every frame. */
  char dir[256]; /* As the client named it, relative to the data directory. */
  const char *ext;
  uint64_t first, last, step, next_frame;
  uint64_t total, done;
  char last_file[300];
  job_state_t state;
  char error[512];
  uv_timer_t retry;
  int refs; /* The list, the retry timer handle, and each callback waited on. */
};

typedef struct {
  uv_work_t req;
  seq_job_t *job;
  char path[PATH_MAX];
  char file[300];
  unsigned char *bytes;
  size_t n;
  int err;
  const char *step;
} seq_write_t;

static void step_frame(seq_job_t *job);

static void job_unref(seq_job_t *job) {
  if (--job->refs > 0)
    return;
  cJSON_Delete(job->params);
  free(job);
}

static void on_retry_closed(uv_handle_t *h) {
  job_unref(h->data);
}

static cJSON *job_json(const seq_job_t *job) {
  cJSON *o = cJSON_CreateObject();
  cJSON_AddNumberToObject(o, "id", (double)job->id);
  cJSON_AddStringToObject(o, "scene", job->scene);
  cJSON_AddStringToObject(o, "state", state_names[job->state]);
  cJSON_AddNumberToObject(o, "done", (double)job->done);
  cJSON_AddNumberToObject(o, "total", (double)job->total);
  cJSON_AddStringToObject(o, "dir", job->dir);
  cJSON_AddStringToObject(o, "last", job->last_file);
  if (job->state == JOB_FAILED)
    cJSON_AddStringToObject(o, "error", job->error);
  return o;
}

static void notify(seq_job_t *job) {
  if (!job->conn || job->conn->closing)
    return;
  cJSON *n = proto_make_notification("job.progress", job_json(job));
  size_t len;
  char *line = proto_print_line(n, &len);
  cJSON_Delete(n);
  if (line)
    conn_write(job->conn, line, len, NULL, 0);
}

/* Ends a running job: one last job.progress, and no further work is started. */
static void job_end(seq_job_t *job, job_state_t state, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));
static void job_end(seq_job_t *job, job_state_t state, const char *fmt, ...) {
  if (job->state != JOB_RUNNING)
    return;
  job->state = state;
  if (fmt) {
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(job->error, sizeof job->error, fmt, ap);
    va_end(ap);
    LOG(LOG_WARN, "jobs", "job %llu: %s", (unsigned long long)job->id, job->error);
  }
  uv_timer_stop(&job->retry);
  notify(job);
}

/* Keeps at most JOBS_KEEP_ENDED ended jobs in the list, dropping the oldest. */
static void prune_ended(server_t *s) {
  int kept = 0;
  for (seq_job_t **p = &s->jobs; *p;) {
    seq_job_t *job = *p;
    if (job->state != JOB_RUNNING && ++kept > JOBS_KEEP_ENDED) {
      *p = job->next;
      uv_close((uv_handle_t *)&job->retry, on_retry_closed);
      job_unref(job);
      continue;
    }
    p = &job->next;
  }
}

/* Runs 'fn' again after JOBS_RETRY_MS. */
static void retry_later(seq_job_t *job, uv_timer_cb fn) {
  uv_timer_start(&job->retry, fn, JOBS_RETRY_MS, 0);
}

/* ---- write ---- */

static void write_work(uv_work_t *req) {
  seq_write_t *w = req->data;
  w->err = files_write_atomic(w->path, w->bytes, w->n, &w->step);
}

static void write_done(uv_work_t *req, int status) {
  seq_write_t *w = req->data;
  seq_job_t *job = w->job;
  free(w->bytes);
  if (job->state == JOB_RUNNING) {
    if (status != 0 || w->err) {
      job_end(job, JOB_FAILED, "cannot %s \"%s\": %s", w->step ? w->step : "write", w->file,
              strerror(w->err ? w->err : EIO));
    } else {
      job->done++;
      snprintf(job->last_file, sizeof job->last_file, "%s", w->file);
      if (job->done == job->total) {
        job_end(job, JOB_DONE, NULL);
      } else {
        notify(job);
        job->next_frame += job->step;
        step_frame(job);
      }
    }
  }
  free(w);
  job_unref(job);
}

/* ---- render ---- */

static void render_done(job_t *j) {
  seq_job_t *job = j->ctx;
  render_job_stats(job->srv, j);
  if (job->state != JOB_RUNNING || j->code != 0) {
    if (j->code != 0)
      job_end(job, JOB_FAILED, "frame %llu: %s", (unsigned long long)job->next_frame, j->err);
    free(j->out.bytes);
    free(j);
    job_unref(job);
    return;
  }
  seq_write_t *w = calloc(1, sizeof *w);
  char why[512];
  if (w) {
    snprintf(w->file, sizeof w->file, "%s/frame_%06llu.%s", job->dir,
             (unsigned long long)job->next_frame, job->ext);
    if (datapath_resolve(job->srv->cfg.data_dir, w->file, 0, w->path, sizeof w->path, why,
                         sizeof why, NULL) != 0) {
      job_end(job, JOB_FAILED, "%s", why);
      free(w);
      w = NULL;
    }
  } else {
    job_end(job, JOB_FAILED, "out of memory");
  }
  if (!w) {
    free(j->out.bytes);
    free(j);
    job_unref(job);
    return;
  }
  w->req.data = w;
  w->job = job;
  w->bytes = j->out.bytes;
  w->n = j->out.nbytes;
  free(j);
  /* The reference held for the render passes to the write. */
  if (uv_queue_work(job->srv->loop, &w->req, write_work, write_done) != 0) {
    job_end(job, JOB_FAILED, "cannot queue the write of \"%s\"", w->file);
    free(w->bytes);
    free(w);
    job_unref(job);
  }
}

static void submit_render(seq_job_t *job);

static void on_retry_render(uv_timer_t *t) {
  submit_render(t->data);
}

static void submit_render(seq_job_t *job) {
  server_t *s = job->srv;
  scene_entry_t *e = server_find_scene(s, job->scene);
  if (!e) {
    job_end(job, JOB_FAILED, "scene \"%s\" was deleted", job->scene);
    return;
  }
  job_t *j = calloc(1, sizeof *j);
  if (!j) {
    job_end(job, JOB_FAILED, "out of memory");
    return;
  }
  char path[128], msg[512];
  if (render_job_from_params(s, e, job->params, j, path, sizeof path, msg, sizeof msg) != 0) {
    free(j);
    job_end(job, JOB_FAILED, "%s: %s", path, msg);
    return;
  }
  j->done = render_done;
  j->ctx = job;
  if (worker_submit(s->worker, j) != 0) {
    render_scene_unref(j->scene);
    free(j);
    retry_later(job, on_retry_render);
    return;
  }
  job->refs++;
}

/* ---- barrier ---- */

static void barrier_run(renderer_t *r, job_t *j) {
  (void)r;
  (void)j;
}

static void barrier_done(job_t *j) {
  seq_job_t *job = j->ctx;
  int code = j->code;
  free(j);
  if (job->state == JOB_RUNNING) {
    if (code != 0)
      job_end(job, JOB_FAILED, "the server is shutting down");
    else
      submit_render(job);
  }
  job_unref(job);
}

static void submit_barrier(seq_job_t *job);

static void on_retry_barrier(uv_timer_t *t) {
  submit_barrier(t->data);
}

static void submit_barrier(seq_job_t *job) {
  job_t *j = calloc(1, sizeof *j);
  if (!j) {
    job_end(job, JOB_FAILED, "out of memory");
    return;
  }
  j->run = barrier_run;
  j->done = barrier_done;
  j->ctx = job;
  if (worker_submit(job->srv->worker, j) != 0) {
    free(j);
    retry_later(job, on_retry_barrier);
    return;
  }
  job->refs++;
}

/* ---- advance ---- */

static void on_retry_step(uv_timer_t *t) {
  step_frame(t->data);
}

/* Moves the scene to job->next_frame, then renders it. */
static void step_frame(seq_job_t *job) {
  server_t *s = job->srv;
  scene_entry_t *e = server_find_scene(s, job->scene);
  if (!e) {
    job_end(job, JOB_FAILED, "scene \"%s\" was deleted", job->scene);
    return;
  }
  double now = scene_frame(e->scene);
  if (now > (double)job->next_frame) {
    job_end(job, JOB_FAILED, "the scene moved past frame %llu (now at %.0f) while the job ran",
            (unsigned long long)job->next_frame, now);
    return;
  }
  unsigned steps = (unsigned)((double)job->next_frame - now);
  if (steps == 0) {
    submit_barrier(job);
    return;
  }
  int cloud = cloud_wants_step(e), fluid = fluid_wants_step(e);
  /* The steps, the barrier and the render must all find room, or none is queued yet. */
  if (worker_queue_depth(s->worker) + cloud + fluid + 2 > s->cfg.render_queue) {
    retry_later(job, on_retry_step);
    return;
  }
  scene_advance(e->scene, steps, scene_dt(e->scene));
  if ((cloud && cloud_submit_step(s, e, steps, NULL) != 0) ||
      (fluid && fluid_submit_step(s, e, steps, scene_dt(e->scene), NULL) != 0)) {
    job_end(job, JOB_FAILED, "frame %llu: the render queue filled while stepping",
            (unsigned long long)job->next_frame);
    return;
  }
  submit_barrier(job);
}

/* ---- methods ---- */

/* Makes 'dir' and each missing directory above it, all under the data directory. Returns 0,
 * or -1 with 'why' set. */
static int make_dirs(const char *data_dir, const char *dir, char *why, size_t whylen) {
  char part[256], path[PATH_MAX];
  size_t n = strlen(dir);
  for (size_t i = 1; i <= n; i++) {
    if (dir[i] != '/' && dir[i] != '\0')
      continue;
    snprintf(part, sizeof part, "%.*s", (int)i, dir);
    int missing = 0;
    if (datapath_resolve(data_dir, part, 1, path, sizeof path, why, whylen, &missing) != 0) {
      if (!missing ||
          datapath_resolve(data_dir, part, 0, path, sizeof path, why, whylen, NULL) != 0)
        return -1;
      if (mkdir(path, 0755) != 0 && errno != EEXIST) {
        snprintf(why, whylen, "cannot create directory \"%s\": %s", part, strerror(errno));
        return -1;
      }
    }
    struct stat st;
    if (stat(path, &st) != 0 || !S_ISDIR(st.st_mode)) {
      snprintf(why, whylen, "\"%s\" is not a directory", part);
      return -1;
    }
  }
  return 0;
}

/* The file name extension of each format. */
static const char *ext_of(const char *format) {
  static const char *const exts[] = {"png", "rgba8", "rgbaf32", "f32"};
  for (size_t i = 0; i < sizeof exts / sizeof *exts; i++)
    if (strcmp(format, exts[i]) == 0)
      return exts[i];
  return "bin";
}

static int running_jobs(const server_t *s, const char *scene) {
  int n = 0;
  for (const seq_job_t *job = s->jobs; job; job = job->next)
    if (job->state == JOB_RUNNING && (!scene || strcmp(job->scene, scene) == 0))
      n++;
  return n;
}

static void render_sequence(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  server_t *s = call->srv;
  const cJSON *p = call->params;
  uint64_t first = (uint64_t)cJSON_GetObjectItem(p, "first")->valuedouble;
  uint64_t last = (uint64_t)cJSON_GetObjectItem(p, "last")->valuedouble;
  uint64_t step = (uint64_t)cJSON_GetObjectItem(p, "step")->valuedouble;
  const char *dir = cJSON_GetObjectItem(p, "dir")->valuestring;
  if (last < first) {
    call_error(call, PROTO_E_INVALID_PARAMS, "last",
               "invalid params: last (%llu) is before first (%llu)", (unsigned long long)last,
               (unsigned long long)first);
    return;
  }
  double now = scene_frame(e->scene);
  if ((double)first < now) {
    call_error(call, PROTO_E_INVALID_PARAMS, "first",
               "invalid params: scene \"%s\" is at frame %.0f, past first (%llu); load or "
               "re-create it to render earlier frames",
               e->scene->name, now, (unsigned long long)first);
    return;
  }
  if (uv_is_active((uv_handle_t *)&e->play)) {
    call_error(call, PROTO_E_INVALID_PARAMS, "scene",
               "invalid params: scene \"%s\" is playing; sim.pause it first", e->scene->name);
    return;
  }
  if (running_jobs(s, e->scene->name) > 0) {
    call_error(call, PROTO_E_BUSY, "scene", "busy: scene \"%s\" already has a running job",
               e->scene->name);
    return;
  }
  if (running_jobs(s, NULL) >= JOBS_MAX_RUNNING) {
    call_error(call, PROTO_E_LIMIT, NULL,
               "limit exceeded: at most %d jobs run at once (limits.jobs_running)",
               JOBS_MAX_RUNNING);
    return;
  }
  /* Check the frame params once now, so that a bad job is refused rather than failing later. */
  job_t probe;
  char path[128], msg[512];
  int code = render_job_from_params(s, e, p, &probe, path, sizeof path, msg, sizeof msg);
  if (code) {
    call_error(call, code, path, "%s", msg);
    return;
  }
  render_scene_unref(probe.scene);
  char why[512];
  if (!dir[0]) {
    call_error(call, PROTO_E_INVALID_PARAMS, "dir",
               "invalid params: dir: must name a directory under the data directory");
    return;
  }
  if (!s->cfg.data_dir[0]) {
    call_error(call, PROTO_E_INVALID_PARAMS, "dir",
               "invalid params: the server has no data directory (--data) to write frames to");
    return;
  }
  if (make_dirs(s->cfg.data_dir, dir, why, sizeof why) != 0) {
    call_error(call, PROTO_E_INVALID_PARAMS, "dir", "invalid params: dir: %s", why);
    return;
  }

  seq_job_t *job = calloc(1, sizeof *job);
  cJSON *params = cJSON_Duplicate(p, 1);
  if (!job || !params) {
    free(job);
    cJSON_Delete(params);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  job->srv = s;
  job->id = ++s->next_job_id;
  job->conn = call->conn;
  snprintf(job->scene, sizeof job->scene, "%s", e->scene->name);
  snprintf(job->dir, sizeof job->dir, "%s", dir);
  job->params = params;
  job->ext = ext_of(cJSON_GetObjectItem(p, "format")->valuestring);
  job->first = job->next_frame = first;
  job->last = last;
  job->step = step;
  job->total = (last - first) / step + 1;
  job->refs = 2; /* The list and the retry timer. */
  uv_timer_init(s->loop, &job->retry);
  job->retry.data = job;
  job->next = s->jobs;
  s->jobs = job;
  prune_ended(s);

  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "id", (double)job->id);
  cJSON_AddNumberToObject(r, "total", (double)job->total);
  char pattern[300];
  snprintf(pattern, sizeof pattern, "%s/frame_%%06d.%s", dir, job->ext);
  cJSON_AddStringToObject(r, "files", pattern);
  call_result(call, r);
  step_frame(job);
}

static void job_list(call_t *call) {
  cJSON *r = cJSON_CreateObject();
  cJSON *a = cJSON_AddArrayToObject(r, "jobs");
  for (const seq_job_t *job = call->srv->jobs; job; job = job->next)
    cJSON_AddItemToArray(a, job_json(job));
  call_result(call, r);
}

static void job_cancel(call_t *call) {
  double id = cJSON_GetObjectItem(call->params, "id")->valuedouble;
  seq_job_t *job = call->srv->jobs;
  while (job && (double)job->id != id)
    job = job->next;
  if (!job) {
    call_error(call, PROTO_E_NOT_FOUND, "id", "not found: no job %.0f", id);
    return;
  }
  /* Work in flight finishes, but nothing after it is started or written. */
  job_end(job, JOB_CANCELLED, NULL);
  call_result(call, job_json(job));
}

int jobs_running(const server_t *s) {
  return running_jobs(s, NULL);
}

void jobs_conn_closed(conn_t *c) {
  for (seq_job_t *job = c->srv->jobs; job; job = job->next)
    if (job->conn == c)
      job->conn = NULL;
}

void jobs_server_stopping(server_t *s) {
  while (s->jobs) {
    seq_job_t *job = s->jobs;
    s->jobs = job->next;
    job_end(job, JOB_FAILED, "the server is shutting down");
    uv_close((uv_handle_t *)&job->retry, on_retry_closed);
    job_unref(job);
  }
}

static const sch_field_t sequence_params[] = {
    RENDER_PARAMS_FRAME,
    {.name = "first",
     .type = SCH_INTEGER,
     .desc = "Simulation frame of the first file; the scene is stepped to it from its current "
             "frame, which must not be past it.",
     .unit = "frames",
     .min = 0,
     .max = 9007199254740991.0,
     .flags = SCH_REQUIRED},
    {.name = "last",
     .type = SCH_INTEGER,
     .desc = "Last simulation frame that may be rendered; at least first.",
     .unit = "frames",
     .min = 0,
     .max = 9007199254740991.0,
     .flags = SCH_REQUIRED},
    {.name = "step",
     .type = SCH_INTEGER,
     .desc = "Simulation steps from one rendered frame to the next.",
     .unit = "frames",
     .min = 1,
     .max = 1e6,
     .def = 1},
    {.name = "dir",
     .type = SCH_STRING,
     .desc = "Directory under the data directory for the files dir/frame_NNNNNN.EXT (the frame "
             "number in six or more digits, EXT the format: png, rgba8, rgbaf32 or f32); "
             "created when missing.",
     .max = 200,
     .flags = SCH_REQUIRED},
    {0}};
static const sch_field_t list_params[] = {{0}};
static const sch_field_t cancel_params[] = {{.name = "id",
                                             .type = SCH_INTEGER,
                                             .desc = "The id render.sequence returned.",
                                             .min = 1,
                                             .max = 9007199254740991.0,
                                             .flags = SCH_REQUIRED},
                                            {0}};

static const int sequence_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, PROTO_E_BUSY,
                                      PROTO_E_LIMIT, 0};
static const int list_errors[] = {PROTO_E_UNAUTHORIZED, 0};
static const int cancel_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, 0};

const method_t method_render_sequence = {
    .name = "render.sequence",
    .summary = "Starts a job that steps the scene and writes frames first..last (every step-th) "
               "as numbered files under the data directory; job.progress notifications follow.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = sequence_params},
    .result = "{id, total, files}: the job's id, the number of frames, the files' name pattern",
    .errors = sequence_errors,
    .handler = render_sequence};

const method_t method_job_list = {
    .name = "job.list",
    .summary = "Running jobs and the last ended ones, newest first.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = list_params},
    .result = "{jobs: [{id, scene, state, done, total, dir, last, error?}]}",
    .errors = list_errors,
    .handler = job_list};

const method_t method_job_cancel = {
    .name = "job.cancel",
    .summary = "Stops a running job after the work in flight; files already written stay.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = cancel_params},
    .result = "{id, scene, state, done, total, dir, last}",
    .errors = cancel_errors,
    .handler = job_cancel};
