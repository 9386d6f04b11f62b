/*
 * Frame subscriptions (frames.subscribe / frames.update / frames.unsubscribe) and the delivery
 * of their frames. Each subscription owns a timer and a view (its render params); each tick
 * sends one frame of what the scene shows now, unless nothing its frame depends on (the
 * scene's snapshot, its newest tag, the view) changed since its last frame: then it sends
 * nothing. A frame is a shot: one render shared by every subscription showing the same view of
 * the same snapshot, so a tick that finds such a shot in flight waits for it, and one that
 * finds it done takes its bytes without rendering. A subscription has at most two frames in
 * flight: a PNG frame leaves the render worker for the encoder thread, so a second frame lets
 * the worker render it while the first is encoded. A finished frame is written at once when
 * the socket is idle; otherwise it waits, replacing any older waiting frame, until the
 * connection drains. Nothing else is buffered, so a client that never reads costs at most one
 * frame per subscription; and once a frame has waited SUB_STALL_NS, no more are rendered for it
 * until the socket drains (they count as dropped), so a client that stopped reading costs no
 * renders either, while one that reads slowly still gets fresh frames.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dispatch.h"
#include "frames.h"
#include "log.h"

/* What a frame depends on: the scene's snapshot and newest tag, and the subscription's view. */
typedef struct shown {
  uint64_t valid; /* All members 64 bits wide: no padding, so memcmp compares them all. */
  uint64_t scene_id, changes, tag_seq, view_gen;
} shown_t;

typedef struct shot shot_t;

/* A subscription waiting for a shot in flight, with what it attached with. */
typedef struct shot_wait {
  struct shot_wait *next;
  sub_t *sub;
  size_t bound;     /* Counted in the server's output total while it waits. */
  cJSON *tag;       /* The subscription's frames.update tag when it attached (a copy), or NULL. */
  uint64_t tag_seq; /* Its number (0: none). */
} shot_wait_t;

/* One render of a view of one snapshot, shared by the subscriptions that show it. */
struct shot {
  int refs; /* The job in flight, each wait, each subscription's 'last'. */
  server_t *srv;
  char *key;         /* The view key (view_key) it was rendered for. */
  uint64_t scene_id; /* scene_t.id, changes and the scene's tag_seq at the snapshot. */
  uint64_t changes;
  uint64_t tag_seq;
  cJSON *tag;      /* The scene's newest tag at the snapshot (a copy), or NULL. */
  job_t *job;      /* While in flight. */
  int state;       /* SHOT_RENDERING, SHOT_DONE or SHOT_FAILED. */
  size_t bound[2]; /* render_answer_bound: [0] binary, [1] base64. */
  cJSON *info;     /* Done: the notification members every subscriber shares. */
  unsigned char *bytes;
  size_t nbytes;
  int given; /* Subscriptions it was given to. */
  shot_wait_t *waits;
};

enum { SHOT_RENDERING, SHOT_DONE, SHOT_FAILED };

struct sub {
  sub_t *next; /* In the connection's list. */
  uint64_t id;
  server_t *srv;
  conn_t *conn; /* NULL once the subscription has ended. */
  char scene[64];
  cJSON *params;       /* The validated subscribe params (as updated), used for every frame. */
  depth_data_t *depth; /* Their depth param's data, decoded once (or NULL). */
  char *key;           /* Their view key. */
  int base64;
  uint64_t view_gen; /* Counts frames.update calls. */
  cJSON *tag;        /* The newest frames.update tag, or NULL. */
  uint64_t tag_seq;
  shown_t shown; /* What its newest frame (in flight or sent) depends on. */
  shot_t *last;  /* That frame's shot (a reference), or NULL. */
  uv_timer_t timer;
  uint64_t due;        /* The loop time (uv_now) the timer is armed for (sub_arm_at). */
  int refs;            /* The timer handle and the shots it waits for. */
  int in_flight;       /* Shots it waits for, at most SUB_IN_FLIGHT. */
  int owed;            /* A tick found SUB_IN_FLIGHT shots in flight: taken when one ends. */
  char *wait_line;     /* A finished frame waiting for the socket. */
  uint64_t wait_since; /* now_ns() when it began to wait. */
  size_t wait_len;
  unsigned char *wait_att;
  size_t wait_att_len;
  uint64_t frame_ns; /* now_ns() when its newest frame was taken (sub_show). */
  uint64_t sent, dropped;
};

/* Frames a subscription may have rendering or encoding at once (see above). */
#define SUB_IN_FLIGHT 2
/* How long a frame may wait for the socket before the ticks stop rendering (see above). */
#define SUB_STALL_NS 1000000000ull

/* Numbers every tag given (scene-wide or frames.update), so that a frame carries the newest. */
static uint64_t tag_counter;

static void shot_unref(shot_t *sh) {
  if (!sh || --sh->refs > 0)
    return;
  free(sh->key);
  cJSON_Delete(sh->tag);
  cJSON_Delete(sh->info);
  free(sh->bytes);
  free(sh);
}

static void sub_unref(sub_t *sub) {
  if (--sub->refs > 0)
    return;
  cJSON_Delete(sub->params);
  free(sub->depth);
  free(sub->key);
  cJSON_Delete(sub->tag);
  shot_unref(sub->last);
  free(sub->wait_line);
  free(sub->wait_att);
  free(sub);
}

static void on_timer_closed(uv_handle_t *h) {
  sub_unref(h->data);
}

static int member_cmp(const void *a, const void *b) {
  return strcmp((*(cJSON *const *)a)->string, (*(cJSON *const *)b)->string);
}

/* Sorts the members of every object inside 'v' by name, so that equal values print alike. */
static int json_sort_members(cJSON *v) {
  int n = 0;
  for (cJSON *it = v->child; it; it = it->next, n++)
    if (json_sort_members(it) != 0)
      return -1;
  if (!cJSON_IsObject(v) || n < 2)
    return 0;
  cJSON **m = malloc((size_t)n * sizeof *m);
  if (!m)
    return -1;
  int i = 0;
  for (cJSON *it = v->child; it; it = it->next)
    m[i++] = it;
  qsort(m, (size_t)n, sizeof *m, member_cmp);
  for (i = 0; i < n; i++) {
    m[i]->prev = m[i ? i - 1 : n - 1]; /* cJSON keeps the last item in the first's 'prev'. */
    m[i]->next = i + 1 < n ? m[i + 1] : NULL;
  }
  v->child = m[0];
  free(m);
  return 0;
}

/* The view key of validated subscribe params: what a frame looks like, printed canonically
 * (members sorted), without what only says when and how it travels. A depth buffer's data is
 * named by its decoded copy 'depth' (its serial) rather than printed: a key compared at every
 * tick stays short, and only subscriptions sharing one decoded buffer share renders. NULL when
 * out of memory. */
static char *view_key(const cJSON *params, const depth_data_t *depth) {
  static const char *const not_view[] = {"fps", "encoding", "repeat", NULL};
  cJSON *v = cJSON_Duplicate(params, 1);
  if (!v)
    return NULL;
  for (int i = 0; not_view[i]; i++)
    cJSON_DeleteItemFromObjectCaseSensitive(v, not_view[i]);
  cJSON *dz = cJSON_GetObjectItem(v, "depth");
  if (dz && depth) {
    char name[32];
    snprintf(name, sizeof name, "#%llu", (unsigned long long)depth->serial);
    cJSON *named = cJSON_CreateString(name);
    if (!named || !cJSON_ReplaceItemInObjectCaseSensitive(dz, "data", named)) {
      cJSON_Delete(named);
      cJSON_Delete(v);
      return NULL;
    }
  }
  char *key = json_sort_members(v) == 0 ? cJSON_PrintUnformatted(v) : NULL;
  cJSON_Delete(v);
  return key;
}

/* The tick interval of validated subscribe params. */
static uint64_t interval_ms(const cJSON *params) {
  uint64_t ms = (uint64_t)(1000.0 / cJSON_GetObjectItem(params, "fps")->valuedouble + 0.5);
  return ms ? ms : 1;
}

static void drop_waiting(sub_t *sub) {
  if (!sub->wait_line)
    return;
  output_total_add(sub->srv, -(long long)(sub->wait_len + sub->wait_att_len));
  free(sub->wait_line);
  free(sub->wait_att);
  sub->wait_line = NULL;
  sub->wait_att = NULL;
  sub->dropped++;
}

/* Ends 'sub': stops its timer, detaches it from its connection (whose list the caller
 * maintains) and releases the connection. */
static void sub_end(sub_t *sub) {
  conn_t *c = sub->conn;
  if (!c)
    return;
  sub->conn = NULL;
  sub->srv->nsubs--;
  drop_waiting(sub);
  uv_timer_stop(&sub->timer);
  uv_close((uv_handle_t *)&sub->timer, on_timer_closed);
  conn_unref(c);
}

static void unlink_sub(conn_t *c, sub_t *sub) {
  for (sub_t **p = &c->subs; *p; p = &(*p)->next)
    if (*p == sub) {
      *p = sub->next;
      return;
    }
}

/* The connection closes: its subscriptions end, silently. Safe to call more than once. */
static void conn_closed(conn_t *c) {
  sub_t *sub = c->subs;
  c->subs = NULL;
  while (sub) {
    sub_t *next = sub->next;
    sub_end(sub);
    sub = next;
  }
}

static void send_frame(sub_t *sub) {
  conn_t *c = sub->conn;
  char *line = sub->wait_line;
  unsigned char *att = sub->wait_att;
  sub->wait_line = NULL;
  sub->wait_att = NULL;
  sub->sent++;
  /* The bytes move from the waiting frame to the connection's output. */
  output_total_add(sub->srv, -(long long)(sub->wait_len + sub->wait_att_len));
  conn_write(c, line, sub->wait_len, att, sub->wait_att_len);
}

/* The connection's socket has no queued output: writes the frames waiting. */
static void conn_drained(conn_t *c) {
  for (sub_t *sub = c->subs; sub && !c->closing; sub = sub->next)
    if (sub->wait_line && conn_queued(c) == 0)
      send_frame(sub);
}

/* Ends 'sub' of 'c' (unlinked by the caller) with a last 'frames.ended' notification giving
 * 'reason'. */
static void end_with_notice(conn_t *c, sub_t *sub, const char *reason) {
  cJSON *params = cJSON_CreateObject();
  cJSON_AddNumberToObject(params, "id", (double)sub->id);
  cJSON_AddStringToObject(params, "reason", reason);
  cJSON *n = proto_make_notification("frames.ended", params);
  size_t len;
  char *line = proto_print_line(n, &len);
  cJSON_Delete(n);
  if (line)
    conn_write(c, line, len, NULL, 0);
  sub_end(sub);
}

/* The server is stopping: every subscription of the connection ends with 'frames.ended'
 * (reason "shutdown"), written before the connection closes. */
static void conn_stopping(conn_t *c) {
  sub_t *sub = c->subs;
  c->subs = NULL;
  while (sub) {
    sub_t *next = sub->next;
    end_with_notice(c, sub, "shutdown");
    sub = next;
  }
}

void frames_scene_deleted(server_t *s, const char *scene) {
  for (conn_t *c = s->conns; c; c = c->next) {
    sub_t **p = &c->subs;
    while (*p) {
      sub_t *sub = *p;
      if (strcmp(sub->scene, scene) != 0) {
        p = &sub->next;
        continue;
      }
      *p = sub->next;
      end_with_notice(c, sub, "scene deleted");
    }
  }
}

/* Puts the frame 'line' (with attachment 'att', both taken) in the subscription's waiting
 * slot, replacing an older one, and writes it at once when the socket is idle. */
static void frame_offer(sub_t *sub, char *line, size_t len, unsigned char *att, size_t att_len) {
  if (!sub->wait_line)
    sub->wait_since = now_ns();
  drop_waiting(sub);
  sub->wait_line = line;
  sub->wait_len = len;
  sub->wait_att = att;
  sub->wait_att_len = att_len;
  output_total_add(sub->srv, (long long)(len + att_len));
  if (conn_queued(sub->conn) == 0)
    send_frame(sub);
}

/* Gives the finished shot 'sh' to 'sub' as a 'frames' notification; 'tag' (its frames.update
 * tag when it took the shot, numbered 'tag_seq') is echoed when newer than the scene's. */
static void frame_give(sub_t *sub, shot_t *sh, const cJSON *tag, uint64_t tag_seq) {
  if (sh->given++ > 0)
    sub->srv->stats.frames_shared++;
  cJSON *p = cJSON_CreateObject();
  cJSON_AddNumberToObject(p, "id", (double)sub->id);
  for (const cJSON *it = sh->info->child; it; it = it->next)
    cJSON_AddItemToObject(p, it->string, cJSON_Duplicate(it, 1));
  /* The frame waiting now, if any, is about to be replaced. */
  cJSON_AddNumberToObject(p, "dropped", (double)(sub->dropped + (sub->wait_line ? 1 : 0)));
  const cJSON *newest = tag_seq > sh->tag_seq ? tag : sh->tag;
  if (newest)
    cJSON_AddItemToObject(p, "tag", cJSON_Duplicate(newest, 1));
  unsigned char *bytes = NULL;
  size_t nbytes = 0;
  if (sub->base64) {
    char *text = malloc(proto_b64_encoded_len(sh->nbytes) + 1);
    if (text) {
      proto_b64_encode(sh->bytes, sh->nbytes, text);
      cJSON_AddStringToObject(p, "data", text);
      free(text);
    }
  } else if (sh->nbytes) {
    bytes = malloc(sh->nbytes);
    if (!bytes) {
      cJSON_Delete(p);
      sub->dropped++;
      return;
    }
    memcpy(bytes, sh->bytes, sh->nbytes);
    nbytes = sh->nbytes;
  }
  cJSON *n = proto_make_notification("frames", p);
  size_t len;
  char *line = proto_print_line(n, &len);
  cJSON_Delete(n);
  if (!line) {
    free(bytes);
    sub->dropped++;
    return;
  }
  frame_offer(sub, line, len, bytes, nbytes);
}

/* The members of a finished job's notification that every subscriber shares. */
static cJSON *shot_info(const job_t *j) {
  cJSON *p = cJSON_CreateObject();
  const char *fmt = proto_format_name(j->params.format);
  cJSON_AddNumberToObject(p, "frame", (double)j->frame);
  cJSON_AddNumberToObject(p, "time", j->time);
  render_job_sync(p, j);
  cJSON_AddNumberToObject(p, "work_ms", j->out.total_ms);
  cJSON_AddItemToObject(p, "passes", render_job_times(j));
  cJSON_AddNumberToObject(p, "antialias", j->out.antialias);
  cJSON_AddNumberToObject(p, "width", j->params.width);
  cJSON_AddNumberToObject(p, "height", j->params.height);
  cJSON_AddStringToObject(p, "format", fmt);
  cJSON *att = cJSON_AddObjectToObject(p, "attachment");
  cJSON_AddNumberToObject(att, "bytes", (double)j->out.nbytes);
  cJSON_AddStringToObject(att, "format", fmt);
  cJSON_AddNumberToObject(att, "width", j->params.width);
  cJSON_AddNumberToObject(att, "height", j->params.height);
  return p;
}

static void on_tick(uv_timer_t *t);
static void on_timer(uv_timer_t *t);

/* Arms the subscription's timer for the loop time 'due', from which ticks follow at whole
 * intervals (on_timer). */
static void sub_arm_at(sub_t *sub, uint64_t due) {
  uint64_t now = uv_now(sub->timer.loop);
  sub->due = due > now ? due : now;
  uv_timer_start(&sub->timer, on_timer, sub->due - now, 0);
}

/* The subscription's tick timer. Each tick is armed for a whole number of intervals after the
 * one before, not an interval after the callback ran (as a repeating libuv timer is), so that
 * the loop's lateness does not add up and a stream keeps its rate. */
static void on_timer(uv_timer_t *t) {
  sub_t *sub = t->data;
  uint64_t ms = interval_ms(sub->params), now = uv_now(t->loop), next = sub->due + ms;
  if (next <= now) /* Late by an interval or more: the ticks missed are not made up. */
    next += ((now - next) / ms + 1) * ms;
  sub_arm_at(sub, next);
  on_tick(t);
}

static void on_shot_done(job_t *j) {
  shot_t *sh = j->ctx;
  server_t *s = sh->srv;
  render_job_stats(s, j);
  sh->info = j->code == 0 ? shot_info(j) : NULL;
  sh->state = sh->info ? SHOT_DONE : SHOT_FAILED;
  if (sh->state == SHOT_DONE) {
    sh->bytes = j->out.bytes;
    sh->nbytes = j->out.nbytes;
  } else {
    free(j->out.bytes);
  }
  shot_wait_t *w = sh->waits;
  sh->waits = NULL;
  if (j->code != 0 && w && w->sub->conn)
    LOG(LOG_WARN, "frames", "subscription %llu: frame failed: %s", (unsigned long long)w->sub->id,
        j->err);
  sh->job = NULL;
  free(j);
  while (w) {
    shot_wait_t *next = w->next;
    sub_t *sub = w->sub;
    sub->in_flight--;
    output_total_add(s, -(long long)w->bound);
    if (sub->conn && !sub->conn->closing && sh->state == SHOT_DONE) {
      frame_give(sub, sh, w->tag, w->tag_seq);
    } else if (sub->conn) {
      sub->dropped++;
      sub->shown.valid = 0; /* Not shown after all: the next tick renders again. */
    }
    cJSON_Delete(w->tag);
    free(w);
    if (sub->owed && sub->conn && !sub->conn->closing)
      on_tick(&sub->timer);
    sub_unref(sub);
    shot_unref(sh);
    w = next;
  }
  shot_unref(sh); /* The job's reference. */
}

/* A shot of the view 'key' at 'now' that a subscription of the server has in flight or has
 * shown last, or NULL. */
static shot_t *shot_find(server_t *s, const char *key, const shown_t *now) {
  for (conn_t *c = s->conns; c; c = c->next)
    for (sub_t *sub = c->subs; sub; sub = sub->next) {
      shot_t *sh = sub->last;
      if (sh && sh->state != SHOT_FAILED && sh->scene_id == now->scene_id &&
          sh->changes == now->changes && sh->tag_seq == now->tag_seq && strcmp(sh->key, key) == 0)
        return sh;
    }
  return NULL;
}

/* A new shot of what 'sub' shows of 'e' now, its job made but not submitted; NULL (counted as
 * a drop by the caller) when the params no longer make a job or memory ran out. */
static shot_t *shot_new(sub_t *sub, scene_entry_t *e, const shown_t *now) {
  shot_t *sh = calloc(1, sizeof *sh);
  job_t *j = calloc(1, sizeof *j);
  char *key = strdup(sub->key);
  cJSON *tag = e->tag ? cJSON_Duplicate(e->tag, 1) : NULL;
  char path[128], msg[512];
  if (!sh || !j || !key || (e->tag && !tag) ||
      render_job_from_params(sub->srv, e, sub->params, &sub->depth, j, path, sizeof path, msg,
                             sizeof msg) != 0) {
    free(sh);
    free(j);
    free(key);
    cJSON_Delete(tag);
    return NULL;
  }
  j->done = on_shot_done;
  j->ctx = sh;
  *sh = (shot_t){.refs = 1,
                 .srv = sub->srv,
                 .key = key,
                 .scene_id = now->scene_id,
                 .changes = now->changes,
                 .tag_seq = now->tag_seq,
                 .tag = tag,
                 .job = j,
                 .state = SHOT_RENDERING,
                 .bound = {render_answer_bound(j, 0), render_answer_bound(j, 1)}};
  return sh;
}

/* Drops a shot that was never submitted. */
static void shot_discard(shot_t *sh) {
  render_job_release(sh->job);
  free(sh->job);
  sh->job = NULL;
  shot_unref(sh);
}

/* 'sub' shows 'sh' from now on. */
static void sub_show(sub_t *sub, shot_t *sh, const shown_t *now) {
  sub->shown = *now;
  sub->frame_ns = now_ns();
  sh->refs++;
  shot_unref(sub->last);
  sub->last = sh;
}

static void on_tick(uv_timer_t *t) {
  sub_t *sub = t->data;
  if (!sub->conn)
    return;
  server_t *s = sub->srv;
  scene_entry_t *e = server_find_scene(s, sub->scene);
  if (!e)
    return;
  shown_t now = {.valid = 1,
                 .scene_id = e->scene->id,
                 .changes = e->scene->changes,
                 .tag_seq = e->tag_seq,
                 .view_gen = sub->view_gen};
  int same = memcmp(&now, &sub->shown, sizeof now) == 0;
  int owed = sub->owed; /* Any tick takes an owed one. */
  sub->owed = 0;
  if (same && !cJSON_IsTrue(cJSON_GetObjectItem(sub->params, "repeat")))
    return; /* Nothing the frame shows changed since the last one: nothing new to send. */
  if (sub->in_flight >= SUB_IN_FLIGHT) {
    /* Earlier frames are still in flight: this one is owed until one of them ends
     * (on_shot_done), so that a moment's queue on the worker delays a frame rather than
     * losing it. A second tick while one is owed loses one. */
    sub->dropped += (uint64_t)owed;
    sub->owed = 1;
    return;
  }
  if (sub->wait_line && now_ns() - sub->wait_since > SUB_STALL_NS) {
    sub->dropped++; /* The client has not read for a while: render again once it does. */
    return;
  }
  /* A repeated frame is rendered again; any other may be another subscription's. */
  shot_t *sh = same ? NULL : shot_find(s, sub->key, &now);
  if (sh && sh->state == SHOT_DONE) {
    sub_show(sub, sh, &now);
    frame_give(sub, sh, sub->tag, sub->tag_seq);
    return;
  }
  int fresh = !sh;
  if (fresh && !(sh = shot_new(sub, e, &now))) {
    sub->dropped++;
    return;
  }
  shot_wait_t *w = calloc(1, sizeof *w);
  cJSON *tag = sub->tag ? cJSON_Duplicate(sub->tag, 1) : NULL;
  size_t bound = sh->bound[sub->base64 ? 1 : 0];
  /* Skipped when out of memory, past the server's output budget, or (a new render) when the
   * render queue is full. */
  if (!w || (sub->tag && !tag) || !output_total_fits(s, bound) ||
      (fresh && worker_submit(s->worker, sh->job) != 0)) {
    free(w);
    cJSON_Delete(tag);
    if (fresh)
      shot_discard(sh);
    sub->dropped++;
    return;
  }
  *w = (shot_wait_t){
      .next = sh->waits, .sub = sub, .bound = bound, .tag = tag, .tag_seq = sub->tag_seq};
  sh->waits = w;
  sh->refs++;
  output_total_add(s, (long long)bound);
  sub->in_flight++;
  sub->refs++;
  sub_show(sub, sh, &now);
}

void frames_scene_changed(call_t *call) {
  const cJSON *scene = cJSON_GetObjectItem(call->params, "scene");
  server_t *s = call->srv;
  scene_entry_t *e = scene ? server_find_scene(s, scene->valuestring) : NULL;
  if (!e)
    return;
  const cJSON *tag = cJSON_GetObjectItem(call->params, "tag");
  cJSON *copy = tag ? cJSON_Duplicate(tag, 1) : NULL;
  if (copy) {
    cJSON_Delete(e->tag);
    e->tag = copy;
    e->tag_seq = ++tag_counter;
  }
  /* A subscription whose newest frame is an interval old or more ticks now rather than up to
   * an interval later, and keeps that phase: the change shows as soon as it can, and frames
   * stay an interval apart. */
  uint64_t now = now_ns();
  for (conn_t *c = s->conns; c; c = c->next)
    for (sub_t *sub = c->subs; sub; sub = sub->next) {
      uint64_t ms = interval_ms(sub->params);
      if (strcmp(sub->scene, e->scene->name) != 0 || now - sub->frame_ns < ms * 1000000ull)
        continue;
      sub_arm_at(sub, uv_now(sub->timer.loop) + ms);
      on_tick(&sub->timer);
    }
}

/* The subscription 'id' names among the connection's; answers -32004 and returns NULL when
 * there is none. */
static sub_t *call_sub(call_t *call) {
  double id = cJSON_GetObjectItem(call->params, "id")->valuedouble;
  sub_t *sub = call->conn->subs;
  while (sub && (double)sub->id != id)
    sub = sub->next;
  if (!sub)
    call_error(call, PROTO_E_NOT_FOUND, "id", "not found: no subscription %.0f on this connection",
               id);
  return sub;
}

static const sch_field_t subscribe_params[] = {RENDER_PARAMS_COMMON,
                                               {.name = "fps",
                                                .type = SCH_NUMBER,
                                                .desc = "Frames per second to push.",
                                                .unit = "frames/second",
                                                .min = 0,
                                                .max = 240,
                                                .def = 30,
                                                .flags = SCH_POSITIVE},
                                               {.name = "repeat",
                                                .type = SCH_BOOL,
                                                .desc = "true: render and send a frame at every "
                                                        "tick, even when nothing it shows "
                                                        "changed (a steady stream).",
                                                .def = 0},
                                               {0}};
static const sch_field_t subscribe_schema = {.type = SCH_OBJECT, .fields = subscribe_params};
static const sch_field_t unsubscribe_params[] = {{.name = "id",
                                                  .type = SCH_INTEGER,
                                                  .desc = "The id frames.subscribe returned.",
                                                  .min = 1,
                                                  .max = 9007199254740991.0,
                                                  .flags = SCH_REQUIRED},
                                                 {0}};

/* Checks validated subscribe 'params' against the scene and the limits, answering the call when
 * they fail, with their depth data from '*depth' when set, else decoded into it. Returns 0 when
 * a frame can be made of them. */
static int params_check(call_t *call, scene_entry_t *e, const cJSON *params, depth_data_t **depth) {
  job_t probe;
  char path[128], msg[512];
  int code = render_job_from_params(call->srv, e, params, depth, &probe, path, sizeof path, msg,
                                    sizeof msg);
  if (code) {
    call_error(call, code, path, "%s", msg);
    return -1;
  }
  render_job_release(&probe);
  return 0;
}

static int is_base64(const cJSON *params) {
  return strcmp(cJSON_GetObjectItem(params, "encoding")->valuestring, "base64") == 0;
}

/* Another subscription of the server ticking at 'ms' for the same view of the same scene, so
 * that a new one can tick with it and share its renders; or NULL. */
static sub_t *sub_twin(server_t *s, const char *scene, const char *key, uint64_t ms) {
  for (conn_t *c = s->conns; c; c = c->next)
    for (sub_t *sub = c->subs; sub; sub = sub->next)
      if (strcmp(sub->scene, scene) == 0 && strcmp(sub->key, key) == 0 &&
          interval_ms(sub->params) == ms)
        return sub;
  return NULL;
}

static void subscribe(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  conn_t *c = call->conn;
  int n = 0;
  for (sub_t *it = c->subs; it; it = it->next)
    n++;
  if (n >= FRAMES_MAX_PER_CONN) {
    call_error(call, PROTO_E_LIMIT, NULL, "limit exceeded: at most %d subscriptions per connection",
               FRAMES_MAX_PER_CONN);
    return;
  }
  /* Check the params once now, so that a bad subscription is refused rather than dropping
   * every frame. */
  depth_data_t *depth = NULL;
  if (params_check(call, e, call->params, &depth) != 0) {
    free(depth);
    return;
  }
  sub_t *sub = calloc(1, sizeof *sub);
  if (sub) {
    sub->params = cJSON_Duplicate(call->params, 1);
    sub->key = view_key(call->params, depth);
    sub->depth = depth;
  }
  if (!sub || !sub->params || !sub->key) {
    if (sub) {
      cJSON_Delete(sub->params);
      free(sub->key);
      free(sub);
    }
    free(depth);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  server_t *s = call->srv;
  sub->id = ++s->next_sub_id;
  sub->srv = s;
  sub->conn = c;
  snprintf(sub->scene, sizeof sub->scene, "%s", e->scene->name);
  sub->base64 = is_base64(call->params);
  sub->refs = 1;
  c->refs++;
  uv_timer_init(s->loop, &sub->timer);
  sub->timer.data = sub;
  uint64_t ms = interval_ms(call->params);
  sub_t *twin = sub_twin(s, sub->scene, sub->key, ms);
  sub_arm_at(sub, twin ? twin->due : uv_now(s->loop));
  sub->next = c->subs;
  c->subs = sub;
  s->nsubs++;

  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "id", (double)sub->id);
  call_result(call, r);
}

/*
 * Changes a subscription's view: the update's params replace the subscription's, the result is
 * validated as frames.subscribe validates its params, and only then applied, so a bad update
 * changes nothing. The timer goes on; a new fps re-arms it, due no later than before.
 */
static void update(call_t *call) {
  sub_t *sub = call_sub(call);
  if (!sub)
    return;
  scene_entry_t *e = server_find_scene(call->srv, sub->scene);
  cJSON *next = cJSON_Duplicate(sub->params, 1);
  if (!e || !next) {
    cJSON_Delete(next);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  for (const cJSON *it = call->params->child; it; it = it->next) {
    if (strcmp(it->string, "id") == 0 || strcmp(it->string, "tag") == 0)
      continue;
    cJSON_DeleteItemFromObjectCaseSensitive(next, it->string);
    cJSON_AddItemToObject(next, it->string, cJSON_Duplicate(it, 1));
  }
  sch_error_t err;
  if (sch_validate(&subscribe_schema, next, "", &err) != 0) {
    cJSON_Delete(next);
    call_error(call, PROTO_E_INVALID_PARAMS, err.path, "invalid params: %s", err.message);
    return;
  }
  /* A new depth buffer is decoded once here; without one, the subscription's stays. */
  depth_data_t *depth = cJSON_GetObjectItem(call->params, "depth") ? NULL : sub->depth;
  int bad = params_check(call, e, next, &depth);
  depth_data_t *fresh = depth != sub->depth ? depth : NULL;
  if (bad) {
    free(fresh);
    cJSON_Delete(next);
    return;
  }
  const cJSON *tag = cJSON_GetObjectItem(call->params, "tag");
  cJSON *tag_copy = tag ? cJSON_Duplicate(tag, 1) : NULL;
  char *key = view_key(next, depth);
  if (!key || (tag && !tag_copy)) {
    free(key);
    free(fresh);
    cJSON_Delete(tag_copy);
    cJSON_Delete(next);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  uint64_t ms = interval_ms(next);
  if (ms != interval_ms(sub->params)) {
    uint64_t now = uv_now(sub->timer.loop);
    sub_arm_at(sub, sub->due < now + ms ? sub->due : now + ms);
  }
  cJSON_Delete(sub->params);
  sub->params = next;
  if (fresh) {
    free(sub->depth);
    sub->depth = fresh;
  }
  free(sub->key);
  sub->key = key;
  sub->base64 = is_base64(next);
  sub->view_gen++;
  if (tag_copy) {
    cJSON_Delete(sub->tag);
    sub->tag = tag_copy;
    sub->tag_seq = ++tag_counter;
  }
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "id", (double)sub->id);
  call_result(call, r);
}

static void unsubscribe(call_t *call) {
  sub_t *sub = call_sub(call);
  if (!sub)
    return;
  conn_t *c = call->conn;
  unlink_sub(c, sub);
  uint64_t sent = sub->sent;
  sub_end(sub); /* A frame still waiting counts as dropped. */
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "id", (double)sub->id);
  cJSON_AddNumberToObject(r, "sent", (double)sent);
  cJSON_AddNumberToObject(r, "dropped", (double)sub->dropped);
  call_result(call, r);
}

/* frames.update's params: the id, every subscribe param but the scene, optional and without
 * defaults, and a tag. Filled from subscribe_params by frames_register, so that a param added
 * to subscriptions can be updated too. */
#define UPDATE_FIELDS_MAX 64
static sch_field_t update_params[UPDATE_FIELDS_MAX];
static const sch_field_t update_schema = {.type = SCH_OBJECT, .fields = update_params};

static void update_params_fill(void) {
  static const sch_field_t tag = {
      .name = "tag",
      .type = SCH_ANY,
      .desc = "Any JSON value of at most 256 bytes, echoed as 'tag' by this subscription's "
              "frames from the first that shows the update.",
      .max = 256,
      .flags = SCH_NO_DEFAULT};
  int n = 0;
  update_params[n++] = unsubscribe_params[0];
  for (const sch_field_t *f = subscribe_params; f->name && n < UPDATE_FIELDS_MAX - 2; f++) {
    if (strcmp(f->name, "scene") == 0)
      continue;
    update_params[n] = *f;
    update_params[n++].flags = (f->flags & ~(SCH_REQUIRED | SCH_SHOW_DEFAULT)) | SCH_NO_DEFAULT;
  }
  update_params[n++] = tag;
  update_params[n] = (sch_field_t){0};
}

static const int subscribe_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_LIMIT, PROTO_E_NOT_FOUND, 0};
static const int unsubscribe_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, 0};
static const int update_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_LIMIT, PROTO_E_NOT_FOUND, 0};

const method_t method_frames_subscribe = {
    .name = "frames.subscribe",
    .summary = "Pushes 'frames' notifications with attachments at up to 'fps' while what they "
               "show changes; latest frame wins and drops are counted.",
    .params = &subscribe_schema,
    .result = "{id}",
    .errors = subscribe_errors,
    .handler = subscribe};

const method_t method_frames_update = {
    .name = "frames.update",
    .summary = "Changes a subscription's view (camera, size, fps, format, ...) from its next "
               "frame, atomically: a bad update changes nothing.",
    .params = &update_schema,
    .result = "{id}",
    .errors = update_errors,
    .handler = update};

const method_t method_frames_unsubscribe = {.name = "frames.unsubscribe",
                                            .summary = "Ends a subscription of this connection.",
                                            .params = METHOD_PARAMS(unsubscribe_params),
                                            .result = "{id, sent, dropped}",
                                            .errors = unsubscribe_errors,
                                            .handler = unsubscribe};

static const conn_hooks_t frames_hooks = {
    .name = "frames", .on_close = conn_closed, .on_drain = conn_drained, .on_stop = conn_stopping};

void frames_register(server_t *s) {
  if (!update_params[0].name)
    update_params_fill();
  conn_hooks_add(s, &frames_hooks);
}
