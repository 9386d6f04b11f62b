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
 * A bake job (sim.bake) runs the same chain with a snapshot in place of the render: it visits
 * the frames that are multiples of 'every' and the last, and writes each as a snapshot in
 * scene.save's format. Before its first frame the bake's manifest (bake.json) is checked on
 * the thread pool, or written when the directory has none: a directory holding a bake of
 * another scene is refused, and sim.bake is answered only then.
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

#include "datapath.h"
#include "dispatch.h"
#include "files.h"
#include "render_job.h"
#include "jobs.h"
#include "log.h"
#include "reserve.h"
#include "snapshot.h"
#include "stepper.h"

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
  int bake; /* sim.bake: snapshots every 'every' frames and at 'last' instead of renders. */
  uint64_t every;
  uint64_t written;   /* Bytes of the files written, held to limits.job_bytes. */
  stepper_t *stepper; /* Stepping the scene to next_frame, or NULL. */
};

typedef struct {
  uv_work_t req;
  seq_job_t *job;
  char file[300];       /* Under the data directory, opened beneath its descriptor. */
  unsigned char *bytes; /* A frame's bytes, or NULL for 'snap'. */
  size_t n;             /* The frame's bytes; after the write, the file's. */
  uint64_t size;        /* What the file will take: n, or a snapshot's estimate. */
  snapshot_out_t *snap; /* A bake's snapshot. */
  char dir[PATH_MAX];   /* The data directory, for the reserve. */
  uint64_t reserve;     /* limits.data_reserve_bytes */
  char short_of[400];   /* Why the reserve refused the write; "" when it did not. */
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
  cJSON_AddStringToObject(o, "kind", job->bake ? "bake" : "sequence");
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
  if (job->stepper)
    stepper_cancel(job->stepper); /* Its callback drops the job's reference later. */
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
  if (reserve_check(w->dir, w->size, w->reserve, w->short_of, sizeof w->short_of) != 0)
    return;
  if (w->snap)
    w->err = snapshot_out_write(w->snap, w->file, &w->n, &w->step);
  else
    w->err = files_write_atomic(w->file, w->bytes, w->n, &w->step);
}

/* The frame after 'f' that the job visits; f itself when there is none. */
static uint64_t next_of(const seq_job_t *job, uint64_t f) {
  if (!job->bake)
    return f + job->step;
  uint64_t m = (f / job->every + 1) * job->every;
  return m <= job->last ? m : f < job->last ? job->last : f;
}

/* The frames a bake from 'from' visits: the multiples of 'every' up to 'last', and 'last'. */
static uint64_t bake_total(uint64_t from, uint64_t last, uint64_t every) {
  uint64_t m = (from + every - 1) / every * every;
  return (m <= last ? (last - m) / every + 1 : 0) + (last % every != 0);
}

static void write_done(uv_work_t *req, int status) {
  seq_write_t *w = req->data;
  seq_job_t *job = w->job;
  free(w->bytes);
  snapshot_out_free(w->snap);
  if (job->state == JOB_RUNNING) {
    if (w->short_of[0]) {
      job_end(job, JOB_FAILED, "cannot write \"%s\": %s", w->file, w->short_of);
    } else if (status != 0 || w->err) {
      job_end(job, JOB_FAILED, "cannot %s \"%s\": %s", w->step ? w->step : "write", w->file,
              strerror(w->err ? w->err : EIO));
    } else {
      job->written += w->n;
      job->done++;
      snprintf(job->last_file, sizeof job->last_file, "%s", w->file);
      if (job->done == job->total) {
        job_end(job, JOB_DONE, NULL);
      } else {
        notify(job);
        job->next_frame = next_of(job, job->next_frame);
        step_frame(job);
      }
    }
  }
  free(w);
  job_unref(job);
}

/* Queues the write of 'w' (bytes or a snapshot of about w->size bytes) to the file w->file
 * names; the job's reference held by the caller passes to it. The job fails instead when the
 * file would take its bytes past limits.job_bytes. */
static void queue_write(seq_job_t *job, seq_write_t *w) {
  char why[512];
  const budget_t *b = &job->srv->cfg.budget;
  snprintf(w->dir, sizeof w->dir, "%s", job->srv->cfg.data_dir);
  w->reserve = b->data_reserve_bytes;
  if (job->written + w->size > b->job_bytes) {
    job_end(job, JOB_FAILED,
            "cannot write \"%s\": its %llu bytes would take the job's files past %llu bytes, the "
            "limit (limits.job_bytes)",
            w->file, (unsigned long long)w->size, (unsigned long long)b->job_bytes);
  } else if (datapath_check(w->file, why, sizeof why) != 0) {
    job_end(job, JOB_FAILED, "%s", why);
  } else {
    w->req.data = w;
    w->job = job;
    if (uv_queue_work(job->srv->loop, &w->req, write_work, write_done) == 0)
      return;
    job_end(job, JOB_FAILED, "cannot queue the write of \"%s\"", w->file);
  }
  free(w->bytes);
  snapshot_out_free(w->snap);
  free(w);
  job_unref(job);
}

/* ---- snapshot (sim.bake) ---- */

/*
 * About the bytes a snapshot of 's' takes, before it is written (scene.save's format,
 * docs/protocol.md): the header line, about the document's length, and the sections, the
 * cloud's planes and density and the fluid's positions and velocities.
 */
static uint64_t snapshot_bytes(const scene_t *s) {
  uint64_t n = 4096; /* The header's members besides the document. */
  char *doc = cJSON_PrintUnformatted(s->doc);
  n += doc ? strlen(doc) : 0;
  free(doc);
  const cloud_cells_t *c = s->cloud_cells;
  if (c)
    n += 3 * 8 * (uint64_t)c->words * c->n[1] * c->n[2] + 4 * (uint64_t)cloud_cells_count(c);
  if (s->particles)
    n += 24 * (uint64_t)s->particles->count;
  return n;
}

static void submit_snapshot(seq_job_t *job) {
  scene_entry_t *e = server_find_scene(job->srv, job->scene);
  if (!e) {
    job_end(job, JOB_FAILED, "scene \"%s\" was deleted", job->scene);
    return;
  }
  seq_write_t *w = calloc(1, sizeof *w);
  if (w)
    w->snap = snapshot_out_new(e->scene);
  if (!w || !w->snap) {
    free(w);
    job_end(job, JOB_FAILED, "out of memory");
    return;
  }
  w->size = snapshot_bytes(e->scene);
  snprintf(w->file, sizeof w->file, "%s/" PROTO_BAKE_FILE, job->dir,
           (unsigned long long)job->next_frame);
  job->refs++;
  queue_write(job, w);
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
  if (!w) {
    job_end(job, JOB_FAILED, "out of memory");
    free(j->out.bytes);
    free(j);
    job_unref(job);
    return;
  }
  snprintf(w->file, sizeof w->file, "%s/frame_%06llu.%s", job->dir,
           (unsigned long long)job->next_frame, job->ext);
  w->bytes = j->out.bytes;
  w->n = j->out.nbytes;
  w->size = w->n;
  free(j);
  /* The reference held for the render passes to the write. */
  queue_write(job, w);
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
  if (render_job_from_params(s, e, job->params, NULL, j, path, sizeof path, msg, sizeof msg) != 0) {
    free(j);
    job_end(job, JOB_FAILED, "%s: %s", path, msg);
    return;
  }
  j->done = render_done;
  j->ctx = job;
  if (worker_submit(s->worker, j) != 0) {
    render_job_release(j);
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
  scene_entry_t *e = server_find_scene(job->srv, job->scene);
  if (job->state == JOB_RUNNING) {
    if (code != 0)
      job_end(job, JOB_FAILED, "the server is shutting down");
    else if (e && scene_frame(e->scene) != (double)job->next_frame)
      job_end(job, JOB_FAILED, "the scene moved to frame %.0f, off frame %llu, while the job ran",
              scene_frame(e->scene), (unsigned long long)job->next_frame);
    else if (job->bake)
      submit_snapshot(job);
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

/* The stepping to job->next_frame ended: on to the barrier, or the job fails. */
static void stepped(void *ctx, const stepper_end_t *end) {
  seq_job_t *job = ctx;
  job->stepper = NULL;
  if (job->state == JOB_RUNNING) {
    if (end->code != 0)
      job_end(job, JOB_FAILED, "frame %llu: %s", (unsigned long long)job->next_frame, end->err);
    else if (end->cut)
      job_end(job, JOB_FAILED, "frame %llu: the stepping was cut short (%s)",
              (unsigned long long)job->next_frame, end->cut);
    else
      submit_barrier(job);
  }
  job_unref(job);
}

/*
 * Moves the scene to job->next_frame, then renders it. The steps are taken in slices
 * (stepper.c), 64-bit all the way: a frame past 2^32 is reached, not wrapped.
 */
static void step_frame(seq_job_t *job) {
  server_t *s = job->srv;
  scene_entry_t *e = server_find_scene(s, job->scene);
  if (!e) {
    job_end(job, JOB_FAILED, "scene \"%s\" was deleted", job->scene);
    return;
  }
  /* Frames are whole numbers below 2^53, exact in a double. */
  uint64_t now = (uint64_t)scene_frame(e->scene);
  if (now > job->next_frame) {
    job_end(job, JOB_FAILED, "the scene moved past frame %llu (now at %llu) while the job ran",
            (unsigned long long)job->next_frame, (unsigned long long)now);
    return;
  }
  if (now == job->next_frame) {
    submit_barrier(job);
    return;
  }
  job->refs++; /* Held by the stepping until its callback, which may come at once. */
  int rc =
      stepper_start(s, e, job->next_frame - now, scene_dt(e->scene), stepped, job, &job->stepper);
  if (rc < 0) {
    job->refs--;
    retry_later(job, on_retry_step);
  }
}

/* ---- methods ---- */

/* Whether a job of 'frames' files fits limits.job_frames; answers the call when not. */
static int frames_fit(call_t *call, uint64_t frames) {
  uint64_t limit = call->srv->cfg.budget.job_frames;
  if (frames <= limit)
    return 1;
  call_error(call, PROTO_E_LIMIT, "last",
             "%s: last: the job would write %llu files, over the limit of %llu a job "
             "(limits.job_frames)",
             proto_err_message(PROTO_E_LIMIT), (unsigned long long)frames,
             (unsigned long long)limit);
  return 0;
}

static int running_jobs(const server_t *s, const char *scene) {
  int n = 0;
  for (const seq_job_t *job = s->jobs; job; job = job->next)
    if (job->state == JOB_RUNNING && (!scene || strcmp(job->scene, scene) == 0))
      n++;
  return n;
}

/* Whether a job of the scene of 'e' may start: the scene paused and without a running job, and
 * room for one more job. Returns 0, or -1 with the call answered. */
static int job_admit(call_t *call, scene_entry_t *e) {
  server_t *s = call->srv;
  if (uv_is_active((uv_handle_t *)&e->play)) {
    call_error(call, PROTO_E_INVALID_PARAMS, "scene",
               "invalid params: scene \"%s\" is playing; sim.pause it first", e->scene->name);
    return -1;
  }
  if (running_jobs(s, e->scene->name) > 0) {
    call_error(call, PROTO_E_BUSY, "scene", "busy: scene \"%s\" already has a running job",
               e->scene->name);
    return -1;
  }
  if (running_jobs(s, NULL) >= JOBS_MAX_RUNNING) {
    call_error(call, PROTO_E_LIMIT, NULL,
               "limit exceeded: at most %d jobs run at once (limits.jobs_running)",
               JOBS_MAX_RUNNING);
    return -1;
  }
  return 0;
}

/* Makes the job's 'dir' under the data directory. Returns 0, or -1 with the call answered. */
static int job_dir(call_t *call, const char *dir) {
  char why[512];
  if (!dir[0]) {
    call_error(call, PROTO_E_INVALID_PARAMS, "dir",
               "invalid params: dir: must name a directory under the data directory");
    return -1;
  }
  if (!call->srv->cfg.data_dir[0]) {
    call_error(call, PROTO_E_INVALID_PARAMS, "dir",
               "invalid params: the server has no data directory (--data) to write files to");
    return -1;
  }
  int code = datapath_check(dir, why, sizeof why);
  if (code != 0) {
    call_error(call, code, "dir", "%s: dir: %s", proto_err_message(code), why);
    return -1;
  }
  /* Made beneath the data directory's descriptor, component by component, following no link
   * out of it. */
  int err = datapath_mkdirs(dir);
  if (err != 0) {
    code = datapath_error(err, dir, 1, 0, why, sizeof why);
    call_error(call, code, "dir", "%s: dir: %s", proto_err_message(code), why);
    return -1;
  }
  return 0;
}

/* A new running job of the scene of 'e' writing into 'dir', listed; NULL (answered) on OOM. */
static seq_job_t *job_new(call_t *call, scene_entry_t *e, const char *dir) {
  server_t *s = call->srv;
  seq_job_t *job = calloc(1, sizeof *job);
  cJSON *params = cJSON_Duplicate(call->params, 1);
  if (!job || !params) {
    free(job);
    cJSON_Delete(params);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return NULL;
  }
  job->srv = s;
  job->id = ++s->next_job_id;
  job->conn = call->conn;
  snprintf(job->scene, sizeof job->scene, "%s", e->scene->name);
  snprintf(job->dir, sizeof job->dir, "%s", dir);
  job->params = params;
  job->refs = 2; /* The list and the retry timer. */
  uv_timer_init(s->loop, &job->retry);
  job->retry.data = job;
  job->next = s->jobs;
  s->jobs = job;
  prune_ended(s);
  return job;
}

/* The answer to the call that started 'job': {id, total, files}. */
static cJSON *job_started(const seq_job_t *job) {
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "id", (double)job->id);
  cJSON_AddNumberToObject(r, "total", (double)job->total);
  char pattern[300];
  if (job->bake)
    snprintf(pattern, sizeof pattern, "%s/frame_%%06d.snap", job->dir);
  else
    snprintf(pattern, sizeof pattern, "%s/frame_%%06d.%s", job->dir, job->ext);
  cJSON_AddStringToObject(r, "files", pattern);
  return r;
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
  uint64_t frames = (last - first) / step + 1;
  if (!frames_fit(call, frames))
    return;
  double now = scene_frame(e->scene);
  if ((double)first < now) {
    call_error(call, PROTO_E_INVALID_PARAMS, "first",
               "invalid params: scene \"%s\" is at frame %.0f, past first (%llu); load or "
               "re-create it to render earlier frames",
               e->scene->name, now, (unsigned long long)first);
    return;
  }
  if (job_admit(call, e) != 0)
    return;
  /* Check the frame params once now, so that a bad job is refused rather than failing later. */
  job_t probe;
  char path[128], msg[512];
  int code = render_job_from_params(s, e, p, NULL, &probe, path, sizeof path, msg, sizeof msg);
  if (code) {
    call_error(call, code, path, "%s", msg);
    return;
  }
  render_job_release(&probe);
  if (job_dir(call, dir) != 0)
    return;
  seq_job_t *job = job_new(call, e, dir);
  if (!job)
    return;
  /* A frame's file is named after its format (render_format_table). */
  job->ext = render_format_find(cJSON_GetObjectItem(p, "format")->valuestring)->name;
  job->first = job->next_frame = first;
  job->last = last;
  job->step = step;
  job->total = frames;
  call_result(call, job_started(job));
  step_frame(job);
}

/* ---- sim.bake: the manifest, checked or written on the thread pool ---- */

typedef struct {
  uv_work_t req;
  seq_job_t *job;
  call_t *call;
  char file[300];  /* The manifest's name under the data directory. */
  cJSON *manifest; /* What bake.json must hold. */
  int err;         /* errno of a failed read or write. */
  const char *step;
  char bad[400]; /* Why the directory is refused; "" when it is fine. */
} bake_prep_t;

static void prep_work(uv_work_t *req) {
  bake_prep_t *bp = req->data;
  size_t len = 0;
  char *text = datapath_read(bp->file, 64u << 20, &len);
  if (!text) {
    if (errno != ENOENT) {
      bp->err = errno;
      bp->step = "read";
      return;
    }
    char *line = proto_print_line(bp->manifest, &len);
    if (!line) {
      bp->err = ENOMEM;
      bp->step = "encode";
      return;
    }
    bp->err = files_write_atomic(bp->file, line, len, &bp->step);
    free(line);
    return;
  }
  cJSON *have = proto_parse(text, len, NULL, 0);
  free(text);
  const cJSON *ver = cJSON_GetObjectItem(have, "volfx_bake");
  const cJSON *every = cJSON_GetObjectItem(have, "every");
  const cJSON *want_every = cJSON_GetObjectItem(bp->manifest, "every");
  if (!cJSON_IsNumber(ver) || ver->valuedouble != PROTO_BAKE_VERSION)
    snprintf(bp->bad, sizeof bp->bad, "%s is not a volfx bake manifest (version %d)",
             PROTO_BAKE_MANIFEST, PROTO_BAKE_VERSION);
  else if (!cJSON_Compare(cJSON_GetObjectItem(have, "scene"),
                          cJSON_GetObjectItem(bp->manifest, "scene"), 1))
    snprintf(bp->bad, sizeof bp->bad,
             "the directory holds a bake of another scene (its %s differs from this scene's "
             "document); bake into another directory",
             PROTO_BAKE_MANIFEST);
  else if (!cJSON_IsNumber(every) || every->valuedouble != want_every->valuedouble)
    snprintf(bp->bad, sizeof bp->bad,
             "the directory holds a bake every %.0f frames, not every %.0f",
             cJSON_IsNumber(every) ? every->valuedouble : 0, want_every->valuedouble);
  cJSON_Delete(have);
}

static void prep_done(uv_work_t *req, int status) {
  bake_prep_t *bp = req->data;
  seq_job_t *job = bp->job;
  if (status != 0 || bp->err) {
    char why[400];
    int code = datapath_error(bp->err ? bp->err : EIO, bp->file,
                              bp->step && strcmp(bp->step, "read"), 64u << 20, why, sizeof why);
    call_error(bp->call, code, "dir", "%s: dir: cannot %s the manifest: %s",
               proto_err_message(code), bp->step ? bp->step : "read", why);
    job_end(job, JOB_FAILED, "cannot %s its manifest: %s", bp->step ? bp->step : "read", why);
  } else if (bp->bad[0]) {
    call_error(bp->call, PROTO_E_INVALID_PARAMS, "dir", "invalid params: dir \"%s\": %s", job->dir,
               bp->bad);
    job_end(job, JOB_FAILED, "%s", bp->bad);
  } else if (job->state != JOB_RUNNING) {
    call_result(bp->call, job_started(job)); /* Cancelled meanwhile: job.list says so. */
  } else {
    call_result(bp->call, job_started(job));
    step_frame(job);
  }
  cJSON_Delete(bp->manifest);
  free(bp);
  job_unref(job);
}

static void sim_bake(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  const cJSON *p = call->params;
  uint64_t last = (uint64_t)cJSON_GetObjectItem(p, "last")->valuedouble;
  uint64_t every = (uint64_t)cJSON_GetObjectItem(p, "every")->valuedouble;
  const char *dir = cJSON_GetObjectItem(p, "dir")->valuestring;
  double now = scene_frame(e->scene);
  if ((double)last < now) {
    call_error(call, PROTO_E_INVALID_PARAMS, "last",
               "invalid params: scene \"%s\" is at frame %.0f, past last (%llu); load an "
               "earlier snapshot or re-create it",
               e->scene->name, now, (unsigned long long)last);
    return;
  }
  if (!frames_fit(call, bake_total((uint64_t)now, last, every)) || job_admit(call, e) != 0 ||
      job_dir(call, dir) != 0)
    return;
  bake_prep_t *bp = calloc(1, sizeof *bp);
  char file[300], why[512];
  snprintf(file, sizeof file, "%s/%s", dir, PROTO_BAKE_MANIFEST);
  if (bp) {
    bp->manifest = cJSON_CreateObject();
    cJSON_AddNumberToObject(bp->manifest, "volfx_bake", PROTO_BAKE_VERSION);
    cJSON_AddNumberToObject(bp->manifest, "every", (double)every);
    cJSON *key = proto_bake_key(e->scene->doc);
    if (!key || !cJSON_AddItemToObject(bp->manifest, "scene", key)) {
      cJSON_Delete(key);
      cJSON_Delete(bp->manifest);
      free(bp);
      bp = NULL;
    }
  }
  if (!bp) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  int code = datapath_check(file, why, sizeof why);
  if (code != 0) {
    cJSON_Delete(bp->manifest);
    free(bp);
    call_error(call, code, "dir", "%s: dir: %s", proto_err_message(code), why);
    return;
  }
  snprintf(bp->file, sizeof bp->file, "%s", file);
  seq_job_t *job = job_new(call, e, dir);
  if (!job) {
    cJSON_Delete(bp->manifest);
    free(bp);
    return;
  }
  job->bake = 1;
  job->every = every;
  job->last = last;
  job->first = (uint64_t)now;
  job->total = bake_total((uint64_t)now, last, every);
  job->next_frame = (uint64_t)now % every == 0 ? (uint64_t)now : next_of(job, (uint64_t)now);
  job->refs++; /* Held by the manifest's check. */
  bp->job = job;
  bp->call = call;
  bp->req.data = bp;
  if (uv_queue_work(call->srv->loop, &bp->req, prep_work, prep_done) != 0) {
    bp->err = EAGAIN;
    prep_done(&bp->req, 0);
  }
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

/* The connection closed: its jobs run on, without progress notifications. */
static void conn_closed(conn_t *c) {
  for (seq_job_t *job = c->srv->jobs; job; job = job->next)
    if (job->conn == c)
      job->conn = NULL;
}

static const conn_hooks_t jobs_hooks = {.name = "jobs", .on_close = conn_closed};

void jobs_register(server_t *s) {
  conn_hooks_add(s, &jobs_hooks);
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
             "number in six or more digits, EXT the format's name: png, jpeg, webp, rgba8, rgbaf32 "
             "or f32); "
             "created when missing.",
     .max = 200,
     .flags = SCH_REQUIRED},
    {0}};
static const sch_field_t bake_params[] = {
    PARAM_SCENE,
    {.name = "dir",
     .type = SCH_STRING,
     .desc = "Directory under the data directory for the bake: bake.json and the snapshots "
             "dir/frame_NNNNNN.snap (six or more digits); created when missing.",
     .max = 200,
     .flags = SCH_REQUIRED},
    {.name = "last",
     .type = SCH_INTEGER,
     .desc = "The shot's last frame: the scene is stepped from its current frame to it.",
     .unit = "frames",
     .min = 0,
     .max = 9007199254740991.0,
     .flags = SCH_REQUIRED},
    {.name = "every",
     .type = SCH_INTEGER,
     .desc = "A snapshot at every frame that is a multiple of this, and at last.",
     .unit = "frames",
     .min = 1,
     .max = 1e6,
     .def = PROTO_DEFAULT_BAKE_EVERY},
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

static const int bake_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, PROTO_E_BUSY,
                                  PROTO_E_LIMIT, 0};

const method_t method_sim_bake = {
    .name = "sim.bake",
    .summary = "Starts a job that steps the scene to last, writing a snapshot every 'every' "
               "frames and at last, with the bake's manifest; job.progress notifications follow.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = bake_params},
    .result = "{id, total, files}: the job's id, the number of snapshots, their name pattern",
    .errors = bake_errors,
    .handler = sim_bake};

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
