/*
 * Requests that wait for files or seedings (defer.h): the thread-pool work, the hold on the
 * connection, and what is kept for the call.
 */
#include "defer.h"

#include <stdlib.h>
#include <string.h>

#include "dispatch.h"

/* The files read and the seedings made for one call, referenced until it is answered. */
struct call_files {
  int n;
  scene_pin_t *pins;
  char **paths;                 /* Their resolved paths. */
  int inline_reads;             /* Read any further file on the spot (one changed while waiting). */
  seed_pin_t *seed[SEED_KINDS]; /* The seeding made for the call, by kind, or NULL. */
  int inline_seed[SEED_KINDS];  /* Seed that kind on the spot (its settings changed while
                                   waiting: another client changed the scene). */
};

typedef struct load_job {
  uv_work_t req;
  call_t *call;
  scene_file_t file;
  scene_pin_t pin;
} load_job_t;

typedef struct seed_job {
  uv_work_t req;
  call_t *call;
  seed_want_t want;
  seed_kind_t kind;
  seed_pin_t *pin;
  int rc;
} seed_job_t;

void defer_arm(call_t *call, defer_want_t *want) {
  struct call_files *f = call->files;
  memset(&want->seed, 0, sizeof want->seed);
  scene_files_defer(f && f->inline_reads ? NULL : &want->file);
  seeding_defer(&want->seed, f ? f->inline_seed : NULL);
}

static struct call_files *files_of(call_t *call) {
  if (!call->files)
    call->files = calloc(1, sizeof *call->files);
  return call->files;
}

static int read_before(const call_t *call, const char *real) {
  for (int i = 0; call->files && i < call->files->n; i++)
    if (strcmp(call->files->paths[i], real) == 0)
      return 1;
  return 0;
}

/* Keeps 'pin' for the call (taken). Returns 0, or -1 when out of memory (pin released). */
static int keep(call_t *call, const char *real, scene_pin_t *pin) {
  struct call_files *f = files_of(call);
  if (!f) {
    scene_pin_release(pin);
    return -1;
  }
  scene_pin_t *pins = realloc(f->pins, (size_t)(f->n + 1) * sizeof *pins);
  if (pins)
    f->pins = pins;
  char **paths = pins ? realloc(f->paths, (size_t)(f->n + 1) * sizeof *paths) : NULL;
  if (paths)
    f->paths = paths;
  char *copy = paths ? strdup(real) : NULL;
  if (!copy) {
    scene_pin_release(pin);
    return -1;
  }
  f->pins[f->n] = *pin;
  f->paths[f->n++] = copy;
  return 0;
}

void defer_release(call_t *call) {
  struct call_files *f = call->files;
  if (!f)
    return;
  for (int i = 0; i < f->n; i++) {
    scene_pin_release(&f->pins[i]);
    free(f->paths[i]);
  }
  free(f->pins);
  free(f->paths);
  for (int k = 0; k < SEED_KINDS; k++)
    seeding_unpin(f->seed[k]);
  free(f);
  call->files = NULL;
}

static void load_work(uv_work_t *req) {
  load_job_t *j = req->data;
  /* A fault is cached with the file, where the call's retry finds it. */
  scene_file_load(&j->file, &j->pin, NULL);
}

static void load_done(uv_work_t *req, int status) {
  load_job_t *j = req->data;
  call_t *call = j->call;
  conn_t *c = call->conn;
  c->refs++; /* Answering the call may drop the last reference of a closed connection. */
  if (status != 0) {
    scene_pin_release(&j->pin);
    call_error(call, PROTO_E_INTERNAL, j->file.path, "internal error: %s: \"%s\" was not read",
               j->file.path, j->file.file);
  } else if (keep(call, j->file.real, &j->pin) != 0) {
    call_error(call, PROTO_E_INTERNAL, j->file.path, "internal error: out of memory");
  } else {
    /* Read or refused: either way the call runs again from the start, and finds the contents
     * or the fault in the cache (answering it as it answers any bad field). */
    call->method->handler(call);
  }
  free(j);
  conn_release(c);
  conn_unref(c);
}

static void seed_work(uv_work_t *req) {
  seed_job_t *j = req->data;
  j->rc = seeding_make(&j->want, &j->pin);
}

static const char *seed_path(seed_kind_t kind) {
  return kind == SEED_CLOUD ? "cloud" : "fluid.initial";
}

static void seed_done(uv_work_t *req, int status) {
  seed_job_t *j = req->data;
  call_t *call = j->call;
  conn_t *c = call->conn;
  c->refs++; /* As in load_done. */
  struct call_files *f = status == 0 && j->rc == 0 ? files_of(call) : NULL;
  if (!f) {
    seeding_unpin(j->pin);
    seed_want_clear(&j->want); /* Not run when the work was cancelled. */
    call_error(call, PROTO_E_INTERNAL, seed_path(j->kind), "internal error: out of memory for %s",
               seed_path(j->kind));
  } else {
    f->seed[j->kind] = j->pin;
    call->method->handler(call);
  }
  free(j);
  conn_release(c);
  conn_unref(c);
}

/* Queues the seeding 'want' (taken) for 'call' (defer_check). */
static void queue_seed(call_t *call, seed_want_t *want) {
  seed_kind_t kind = want->kind;
  if (call->files && call->files->seed[kind]) {
    /* Seeded for this call already, with other settings: the scene changed meanwhile. Seed on
     * the spot rather than chase settings that keep changing. */
    seed_want_clear(want);
    call->files->inline_seed[kind] = 1;
    call->method->handler(call);
    return;
  }
  seed_job_t *j = calloc(1, sizeof *j);
  if (!j) {
    seed_want_clear(want);
    call_error(call, PROTO_E_INTERNAL, seed_path(kind), "internal error: out of memory");
    return;
  }
  j->req.data = j;
  j->call = call;
  j->want = *want;
  j->kind = kind;
  want->fluid = NULL;
  if (uv_queue_work(call->srv->loop, &j->req, seed_work, seed_done) != 0) {
    seed_want_clear(&j->want);
    free(j);
    call_error(call, PROTO_E_INTERNAL, seed_path(kind), "internal error: cannot queue the seeding");
    return;
  }
  conn_hold(call->conn);
}

int defer_check(call_t *call, int rc, const scene_error_t *err, defer_want_t *wanted) {
  scene_files_defer(NULL);
  seeding_defer(NULL, NULL);
  if (rc == 0 || err->code != SCENE_DEFERRED_SEED)
    seed_want_clear(&wanted->seed);
  if (rc == 0)
    return 0;
  if (err->code == SCENE_DEFERRED_SEED) {
    queue_seed(call, &wanted->seed);
    return 1;
  }
  if (err->code != SCENE_DEFERRED)
    return 0;
  const scene_file_t *want = &wanted->file;
  if (read_before(call, want->real)) {
    /* Read for this call already, and changed on disk since: read it on the spot, rather than
     * chase a file that keeps changing. */
    call->files->inline_reads = 1;
    call->method->handler(call);
    return 1;
  }
  load_job_t *j = calloc(1, sizeof *j);
  if (!j) {
    call_error(call, PROTO_E_INTERNAL, want->path, "internal error: out of memory");
    return 1;
  }
  j->req.data = j;
  j->call = call;
  j->file = *want;
  if (uv_queue_work(call->srv->loop, &j->req, load_work, load_done) != 0) {
    free(j);
    call_error(call, PROTO_E_INTERNAL, want->path, "internal error: cannot queue the read");
    return 1;
  }
  conn_hold(call->conn);
  return 1;
}
