/*
 * Frame subscriptions (frames.subscribe / frames.unsubscribe) and the delivery of their
 * frames. Each subscription owns a timer; each tick renders one frame unless two are still in
 * flight: a PNG frame leaves the render worker for the encoder thread, so a second frame lets
 * the worker render it while the first is encoded. A finished frame is written at once when the
 * socket is idle; otherwise it waits, replacing any older waiting frame, until the connection
 * drains. Nothing else is buffered, so a client that never reads costs at most one frame per
 * subscription; and once a frame has waited SUB_STALL_NS, no more are rendered for it until the
 * socket drains (they count as dropped), so a client that stopped reading costs no renders
 * either, while one that reads slowly still gets fresh frames.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "dispatch.h"
#include "frames.h"
#include "log.h"

struct sub {
  sub_t *next; /* In the connection's list. */
  uint64_t id;
  server_t *srv;
  conn_t *conn; /* NULL once the subscription has ended. */
  char scene[64];
  cJSON *params; /* The validated subscribe params, reused for every frame. */
  int base64;
  uv_timer_t timer;
  int refs;            /* The timer handle and the jobs in flight. */
  int in_flight;       /* Jobs submitted and not yet done, at most SUB_IN_FLIGHT. */
  size_t frame_bound;  /* The most bytes one of its frames takes (counted while in flight). */
  char *wait_line;     /* A finished frame waiting for the socket. */
  uint64_t wait_since; /* now_ns() when it began to wait. */
  size_t wait_len;
  unsigned char *wait_att;
  size_t wait_att_len;
  uint64_t sent, dropped;
};

/* Frames a subscription may have rendering or encoding at once (see above). */
#define SUB_IN_FLIGHT 2
/* How long a frame may wait for the socket before the ticks stop rendering (see above). */
#define SUB_STALL_NS 1000000000ull

static void sub_unref(sub_t *sub) {
  if (--sub->refs > 0)
    return;
  cJSON_Delete(sub->params);
  free(sub->wait_line);
  free(sub->wait_att);
  free(sub);
}

static void on_timer_closed(uv_handle_t *h) {
  sub_unref(h->data);
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

static void on_frame_done(job_t *j) {
  sub_t *sub = j->ctx;
  server_t *s = sub->srv;
  render_job_stats(s, j);
  sub->in_flight--;
  output_total_add(s, -(long long)sub->frame_bound);
  if (!sub->conn || sub->conn->closing || j->code != 0) {
    if (j->code != 0 && sub->conn)
      LOG(LOG_WARN, "frames", "subscription %llu: frame failed: %s", (unsigned long long)sub->id,
          j->err);
    if (sub->conn)
      sub->dropped++;
    free(j->out.bytes);
    free(j);
    sub_unref(sub);
    return;
  }
  cJSON *p = cJSON_CreateObject();
  const char *fmt = proto_format_name(j->params.format);
  cJSON_AddNumberToObject(p, "id", (double)sub->id);
  cJSON_AddNumberToObject(p, "frame", (double)j->frame);
  cJSON_AddNumberToObject(p, "time", j->time);
  cJSON_AddNumberToObject(p, "work_ms", j->out.total_ms);
  cJSON_AddItemToObject(p, "passes", render_job_times(j));
  cJSON_AddNumberToObject(p, "antialias", j->out.antialias);
  /* The frame waiting now, if any, is about to be replaced. */
  cJSON_AddNumberToObject(p, "dropped", (double)(sub->dropped + (sub->wait_line ? 1 : 0)));
  cJSON_AddNumberToObject(p, "width", j->params.width);
  cJSON_AddNumberToObject(p, "height", j->params.height);
  cJSON_AddStringToObject(p, "format", fmt);
  cJSON *att = cJSON_AddObjectToObject(p, "attachment");
  cJSON_AddNumberToObject(att, "bytes", (double)j->out.nbytes);
  cJSON_AddStringToObject(att, "format", fmt);
  cJSON_AddNumberToObject(att, "width", j->params.width);
  cJSON_AddNumberToObject(att, "height", j->params.height);
  unsigned char *bytes = j->out.bytes;
  size_t nbytes = j->out.nbytes;
  if (sub->base64) {
    char *text = malloc(proto_b64_encoded_len(nbytes) + 1);
    if (text) {
      proto_b64_encode(bytes, nbytes, text);
      cJSON_AddStringToObject(p, "data", text);
      free(text);
    }
    free(bytes);
    bytes = NULL;
    nbytes = 0;
  }
  cJSON *n = proto_make_notification("frames", p);
  size_t len;
  char *line = proto_print_line(n, &len);
  cJSON_Delete(n);
  free(j);
  if (!line) {
    free(bytes);
    sub_unref(sub);
    return;
  }
  if (!sub->wait_line)
    sub->wait_since = now_ns();
  drop_waiting(sub);
  sub->wait_line = line;
  sub->wait_len = len;
  sub->wait_att = bytes;
  sub->wait_att_len = nbytes;
  output_total_add(s, (long long)(len + nbytes));
  if (conn_queued(sub->conn) == 0)
    send_frame(sub);
  sub_unref(sub);
}

static void on_tick(uv_timer_t *t) {
  sub_t *sub = t->data;
  if (!sub->conn)
    return;
  if (sub->in_flight >= SUB_IN_FLIGHT) {
    sub->dropped++; /* Earlier frames are still in flight: this one is skipped. */
    return;
  }
  if (sub->wait_line && now_ns() - sub->wait_since > SUB_STALL_NS) {
    sub->dropped++; /* The client has not read for a while: render again once it does. */
    return;
  }
  server_t *s = sub->srv;
  scene_entry_t *e = server_find_scene(s, sub->scene);
  job_t *j = calloc(1, sizeof *j);
  if (!e || !j) {
    free(j);
    return;
  }
  char path[128], msg[512];
  if (render_job_from_params(s, e, sub->params, j, path, sizeof path, msg, sizeof msg) != 0) {
    free(j);
    sub->dropped++;
    return;
  }
  j->done = on_frame_done;
  j->ctx = sub;
  sub->frame_bound = render_answer_bound(j, sub->base64);
  if (!output_total_fits(s, sub->frame_bound)) {
    render_job_release(j);
    free(j);
    sub->dropped++; /* The server's output budget is spent: this frame is skipped. */
    return;
  }
  if (worker_submit(s->worker, j) != 0) {
    render_job_release(j);
    free(j);
    sub->dropped++; /* The render queue is full: this frame is skipped. */
    return;
  }
  output_total_add(s, (long long)sub->frame_bound);
  sub->in_flight++;
  sub->refs++;
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
  job_t probe;
  char path[128], msg[512];
  int code = render_job_from_params(call->srv, e, call->params, &probe, path, sizeof path, msg,
                                    sizeof msg);
  if (code) {
    call_error(call, code, path, "%s", msg);
    return;
  }
  render_job_release(&probe);

  sub_t *sub = calloc(1, sizeof *sub);
  if (!sub) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  server_t *s = call->srv;
  sub->id = ++s->next_sub_id;
  sub->srv = s;
  sub->conn = c;
  snprintf(sub->scene, sizeof sub->scene, "%s", e->scene->name);
  sub->params = cJSON_Duplicate(call->params, 1);
  sub->base64 = strcmp(cJSON_GetObjectItem(call->params, "encoding")->valuestring, "base64") == 0;
  sub->refs = 1;
  c->refs++;
  uv_timer_init(s->loop, &sub->timer);
  sub->timer.data = sub;
  double fps = cJSON_GetObjectItem(call->params, "fps")->valuedouble;
  uint64_t ms = (uint64_t)(1000.0 / fps + 0.5);
  uv_timer_start(&sub->timer, on_tick, 0, ms ? ms : 1);
  sub->next = c->subs;
  c->subs = sub;
  s->nsubs++;

  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "id", (double)sub->id);
  call_result(call, r);
}

static void unsubscribe(call_t *call) {
  double id = cJSON_GetObjectItem(call->params, "id")->valuedouble;
  conn_t *c = call->conn;
  sub_t *sub = c->subs;
  while (sub && (double)sub->id != id)
    sub = sub->next;
  if (!sub) {
    call_error(call, PROTO_E_NOT_FOUND, "id", "not found: no subscription %.0f on this connection",
               id);
    return;
  }
  unlink_sub(c, sub);
  uint64_t sent = sub->sent;
  sub_end(sub); /* A frame still waiting counts as dropped. */
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "id", id);
  cJSON_AddNumberToObject(r, "sent", (double)sent);
  cJSON_AddNumberToObject(r, "dropped", (double)sub->dropped);
  call_result(call, r);
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
                                               {0}};
static const sch_field_t unsubscribe_params[] = {{.name = "id",
                                                  .type = SCH_INTEGER,
                                                  .desc = "The id frames.subscribe returned.",
                                                  .min = 1,
                                                  .max = 9007199254740991.0,
                                                  .flags = SCH_REQUIRED},
                                                 {0}};

static const int subscribe_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_LIMIT, PROTO_E_NOT_FOUND, 0};
static const int unsubscribe_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, 0};

const method_t method_frames_subscribe = {
    .name = "frames.subscribe",
    .summary = "Pushes 'frames' notifications with attachments at up to 'fps'; latest frame "
               "wins and drops are counted.",
    .params = METHOD_PARAMS(subscribe_params),
    .result = "{id}",
    .errors = subscribe_errors,
    .handler = subscribe};

const method_t method_frames_unsubscribe = {.name = "frames.unsubscribe",
                                            .summary = "Ends a subscription of this connection.",
                                            .params = METHOD_PARAMS(unsubscribe_params),
                                            .result = "{id, sent, dropped}",
                                            .errors = unsubscribe_errors,
                                            .handler = unsubscribe};

static const conn_hooks_t frames_hooks = {
    .name = "frames", .on_close = conn_closed, .on_drain = conn_drained, .on_stop = conn_stopping};

void frames_register(server_t *s) {
  conn_hooks_add(s, &frames_hooks);
}
