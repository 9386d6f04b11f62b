/*
 * Connections: accepting on TCP and Unix sockets, reading bytes into the NDJSON reader,
 * handing complete lines to the dispatcher, writing replies in request order, the idle
 * timeout, the output limit, and closing. A connection is freed only when its handles are
 * closed and no call or subscription still points at it ('refs').
 *
 * While a connection is full (conn_full, output.c: its output or its renders over their
 * limits, or the server's output budget spent) no further request is read from it; only a
 * connection whose output stays unsent with nothing taken off the socket for OUT_STALL_MS is
 * closed, as not reading. Before authentication (on a server with a token) a connection runs no
 * batch, it is closed after budget.auth_timeout_s, after budget.auth_failures wrong tokens (each
 * answered after AUTH_DELAY_MS), and at most budget.unauthenticated of them are open at once.
 *
 * The transport names no feature: what hangs off a connection (subscriptions, jobs) registers
 * hooks (conn_hooks_add) that run when it closes, when its socket drains and when the server
 * stops.
 */
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <unistd.h>

#include "dispatch.h"
#include "http.h"
#include "log.h"
#include "server.h"

/* How long output may sit with nothing taken off the socket before the connection closes,
 * and how often that is looked at. */
#define OUT_STALL_MS 10000
#define STALL_CHECK_MS 1000
/* How long the answer to a wrong token is held back. */
#define AUTH_DELAY_MS 100

typedef struct write_req {
  uv_write_t req;
  conn_t *conn;
  char *line;
  size_t total;
  int natt;
  unsigned char *att[]; /* The attachments written after the line, owned. */
} write_req_t;

static void conn_output_changed(conn_t *c, int progress);

int conn_hooks_add(server_t *s, const conn_hooks_t *h) {
  if (s->nconn_hooks >= CONN_HOOKS_MAX) {
    LOG(LOG_ERROR, "net", "no room for the connection hooks of %s (%d at most)", h->name,
        CONN_HOOKS_MAX);
    return -1;
  }
  s->conn_hooks[s->nconn_hooks++] = h;
  return 0;
}

/* Runs the hook 'member' (on_close, on_drain or on_stop) of every conn_hooks_t added, in the
 * order they were added, for 'c'. */
#define RUN_HOOKS(c, member)                                                                       \
  do {                                                                                             \
    for (unsigned i_ = 0; i_ < (c)->srv->nconn_hooks; i_++)                                        \
      if ((c)->srv->conn_hooks[i_]->member)                                                        \
        (c)->srv->conn_hooks[i_]->member(c);                                                       \
  } while (0)

static void free_reply(reply_t *r) {
  for (int i = 0; i < r->nparts; i++) {
    cJSON_Delete(r->parts[i].response);
    free(r->parts[i].line);
    free(r->parts[i].att);
  }
  free(r);
}

void conn_unref(conn_t *c) {
  if (--c->refs > 0)
    return;
  proto_reader_free(&c->reader);
  cJSON_Delete(c->batch);
  while (c->head) {
    reply_t *r = c->head;
    c->head = r->next;
    conn_promise_settle(c, r);
    free_reply(r);
  }
  free(c);
}

static void on_handle_closed(uv_handle_t *h) {
  conn_unref(h->data);
}

void conn_close(conn_t *c) {
  if (c->closing)
    return;
  c->closing = 1;
  server_t *s = c->srv;
  if (c->delayed) { /* A held-back wrong-token answer is given now, or the call would leak. */
    call_t *call = c->delayed;
    c->delayed = NULL;
    call_error(call, PROTO_E_UNAUTHORIZED, "token", "unauthorized: wrong token");
  }
  if (c->unauth_counted && !c->authed)
    s->nunauth--;
  c->unauth_counted = 0;
  RUN_HOOKS(c, on_close);
  if (c->prev)
    c->prev->next = c->next;
  else
    s->conns = c->next;
  if (c->next)
    c->next->prev = c->prev;
  s->nconns--;
  c->transport->close(c);
  uv_close((uv_handle_t *)&c->idle, on_handle_closed);
  uv_close((uv_handle_t *)&c->stall, on_handle_closed);
  uv_close((uv_handle_t *)&c->delay, on_handle_closed);
  LOG(LOG_DEBUG, "net", "connection %llu closed", (unsigned long long)c->id);
}

void conn_finish(conn_t *c) {
  if (c->closing)
    return;
  c->transport->read_stop(c);
  c->draining = 1;
  if (!c->head && c->out_bytes == 0)
    conn_close(c);
}

static void pump(conn_t *c);
static void on_read(uv_stream_t *stream, ssize_t nread, const uv_buf_t *buf);
static void on_alloc(uv_handle_t *h, size_t suggested, uv_buf_t *buf);

/* Looks at the socket's write queue every STALL_CHECK_MS while output is unsent: any byte
 * taken off it since the last look is progress (a slow reader is not stalled); none for
 * OUT_STALL_MS closes the connection. */
static void on_stall(uv_timer_t *t) {
  conn_t *c = t->data;
  size_t queued = conn_queued(c);
  uint64_t now = now_ns();
  if (queued < c->stall_mark) {
    c->stall_mark = queued;
    c->stall_since_ns = now;
    return;
  }
  if (now - c->stall_since_ns < (uint64_t)OUT_STALL_MS * 1000000u)
    return;
  LOG(LOG_WARN, "net", "connection %llu is not reading: %zu bytes unsent for %d s, closing",
      (unsigned long long)c->id, c->out_bytes, OUT_STALL_MS / 1000);
  conn_close(c);
}

/* After output left or was promised: the stall check runs while output is unsent (a write
 * that completes is progress), and reading resumes once the connection is no longer full. */
static void conn_output_changed(conn_t *c, int progress) {
  if (c->closing)
    return;
  if (c->out_bytes > 0) {
    if (progress || !uv_is_active((uv_handle_t *)&c->stall)) {
      c->stall_mark = conn_queued(c);
      c->stall_since_ns = now_ns();
    }
    if (!uv_is_active((uv_handle_t *)&c->stall))
      uv_timer_start(&c->stall, on_stall, STALL_CHECK_MS, STALL_CHECK_MS);
  } else {
    uv_timer_stop(&c->stall);
  }
  if (c->out_paused && !conn_full(c)) {
    c->out_paused = 0;
    if (!c->held && !c->draining) {
      pump(c);
      if (!c->held && !c->closing && !c->draining && !c->out_paused)
        c->transport->read_start(c);
    }
  }
}

void conn_resume(conn_t *c) {
  conn_output_changed(c, 0);
}

static void on_write(uv_write_t *req, int status) {
  write_req_t *w = (write_req_t *)req;
  conn_t *c = w->conn;
  size_t total = w->total;
  free(w->line);
  for (int i = 0; i < w->natt; i++)
    free(w->att[i]);
  free(w);
  conn_written(c, total, status);
}

void conn_written(conn_t *c, size_t total, int status) {
  conn_output_written(c, total);
  if (!c->closing) {
    if (status < 0 && status != UV_ECANCELED) {
      LOG(LOG_DEBUG, "net", "connection %llu write failed: %s", (unsigned long long)c->id,
          uv_strerror(status));
      conn_close(c);
    } else {
      if (conn_queued(c) == 0) {
        RUN_HOOKS(c, on_drain);
        if (c->draining && !c->head && c->out_bytes == 0)
          conn_close(c);
      }
      conn_output_changed(c, 1);
    }
  }
  /* The server's total drops last, so that connections its budget paused go on after this
   * one has reacted to its own write. */
  output_total_add(c->srv, -(long long)total);
  conn_unref(c);
}

/* The stream transport's write: 'line' and the attachments after it in one uv_write, without
 * copying them. */
static int stream_write(conn_t *c, char *line, size_t len, unsigned char **atts, const size_t *lens,
                        int n) {
  write_req_t *w = malloc(sizeof *w + (size_t)n * sizeof *atts);
  uv_buf_t stack[9], *bufs = n < 9 ? stack : malloc((size_t)(n + 1) * sizeof *bufs);
  if (!w || !bufs) {
    free(line);
    for (int i = 0; i < n; i++)
      free(atts[i]);
    free(w);
    if (bufs != stack)
      free(bufs);
    return -1;
  }
  w->conn = c;
  w->line = line;
  w->total = len;
  w->natt = 0;
  bufs[0] = uv_buf_init(line, (unsigned)len);
  for (int i = 0; i < n; i++) {
    if (!atts[i])
      continue;
    w->att[w->natt++] = atts[i];
    bufs[w->natt] = uv_buf_init((char *)atts[i], (unsigned)lens[i]);
    w->total += lens[i];
  }
  int rc = uv_write(&w->req, c->stream, bufs, (unsigned)w->natt + 1, on_write);
  if (bufs != stack)
    free(bufs);
  if (rc < 0) {
    free(line);
    for (int i = 0; i < w->natt; i++)
      free(w->att[i]);
    free(w);
    return -1;
  }
  return 0;
}

/* Writes 'line' and the 'n' attachments 'atts' of 'lens' bytes after it through the
 * connection's transport; takes every buffer (free()). */
static void write_buffers(conn_t *c, char *line, size_t len, unsigned char **atts,
                          const size_t *lens, int n) {
  if (c->closing) {
    free(line);
    for (int i = 0; i < n; i++)
      free(atts[i]);
    return;
  }
  size_t total = len;
  for (int i = 0; i < n; i++)
    total += atts[i] ? lens[i] : 0;
  conn_output_queued(c, total);
  c->refs++;
  if (c->transport->write(c, line, len, atts, lens, n) != 0) {
    conn_output_written(c, total);
    output_total_add(c->srv, -(long long)total);
    c->refs--;
    conn_close(c);
    return;
  }
  conn_output_changed(c, 0);
}

void conn_write(conn_t *c, char *line, size_t len, unsigned char *att, size_t att_len) {
  write_buffers(c, line, len, &att, &att_len, att ? 1 : 0);
}

/* The response of part 'p' printed, with its newline, into '*len' bytes: its own line when it
 * has one (taken), else its cJSON printed. NULL when out of memory. */
static char *part_text(reply_part_t *p, size_t *len) {
  char *text = p->line;
  *len = p->line_len;
  p->line = NULL;
  return text ? text : proto_print_line(p->response, len);
}

/* The line of a finished reply: one response, or the array answering a batch; NULL (with
 * '*empty' set) when nothing is answered (notifications only) or when out of memory. */
static char *reply_line(reply_t *r, size_t *len, int *empty) {
  if (!r->batch) {
    *empty = !r->parts[0].response && !r->parts[0].line;
    return *empty ? NULL : part_text(&r->parts[0], len);
  }
  size_t total = 0, answered = 0;
  char **texts = calloc((size_t)r->nparts, sizeof *texts);
  size_t *lens = calloc((size_t)r->nparts, sizeof *lens);
  int ok = texts && lens;
  for (int i = 0; ok && i < r->nparts; i++) {
    if (!r->parts[i].response && !r->parts[i].line)
      continue;
    ok = (texts[i] = part_text(&r->parts[i], &lens[i])) != NULL;
    if (ok)
      lens[i]--; /* Joined without their newlines. */
    total += lens[i] + 1;
    answered++;
  }
  *empty = ok && answered == 0;
  /* '[', the texts with a comma after all but the last, ']', '\n' and a NUL. */
  char *line = ok && answered ? malloc(total + 3) : NULL;
  if (line) {
    size_t at = 0;
    line[at++] = '[';
    for (int i = 0; i < r->nparts; i++) {
      if (!texts[i])
        continue;
      if (at > 1)
        line[at++] = ',';
      memcpy(line + at, texts[i], lens[i]);
      at += lens[i];
    }
    line[at++] = ']';
    line[at++] = '\n';
    line[at] = '\0';
    *len = at;
  }
  for (int i = 0; texts && i < r->nparts; i++)
    free(texts[i]);
  free(texts);
  free(lens);
  return line;
}

/* Serialises a finished reply: one response line, or one array line for a batch, followed by
 * the attachments in response order, each written from its own buffer. */
static void write_reply(conn_t *c, reply_t *r) {
  size_t len = 0;
  int empty;
  char *line = reply_line(r, &len, &empty);
  conn_promise_settle(c, r);
  if (empty) {
    free_reply(r);
    return;
  }
  if (!line) {
    free_reply(r);
    conn_close(c);
    return;
  }
  unsigned char *stack_att[8], **atts = stack_att;
  size_t stack_len[8], *lens = stack_len;
  if (r->nparts > 8) {
    atts = malloc((size_t)r->nparts * sizeof *atts);
    lens = malloc((size_t)r->nparts * sizeof *lens);
  }
  if (!atts || !lens) {
    if (atts != stack_att)
      free(atts);
    if (lens != stack_len)
      free(lens);
    free(line);
    free_reply(r);
    conn_close(c);
    return;
  }
  int n = 0;
  for (int i = 0; i < r->nparts; i++)
    if (r->parts[i].att_len) {
      atts[n] = r->parts[i].att;
      lens[n++] = r->parts[i].att_len;
      r->parts[i].att = NULL;
    }
  free_reply(r);
  write_buffers(c, line, len, atts, lens, n);
  if (atts != stack_att)
    free(atts);
  if (lens != stack_len)
    free(lens);
}

void conn_flush_replies(conn_t *c) {
  while (c->head && c->head->pending == 0 && !c->closing) {
    reply_t *r = c->head;
    c->head = r->next;
    if (!c->head)
      c->tail = NULL;
    write_reply(c, r);
  }
  if (c->draining && !c->closing && !c->head && c->out_bytes == 0)
    conn_close(c);
}

static void on_alloc(uv_handle_t *h, size_t suggested, uv_buf_t *buf) {
  (void)h;
  (void)suggested;
  static char slab[65536]; /* Reads are copied into the reader at once: one slab suffices. */
  *buf = uv_buf_init(slab, sizeof slab);
}

static void on_idle_timeout(uv_timer_t *t) {
  conn_t *c = t->data;
  if (!c->authed) {
    LOG(LOG_DEBUG, "net", "connection %llu did not authenticate in time, closing",
        (unsigned long long)c->id);
    conn_close(c);
    return;
  }
  if (c->subs || c->head)
    return; /* A subscriber or a connection waiting for work is not idle. */
  LOG(LOG_DEBUG, "net", "connection %llu idle, closing", (unsigned long long)c->id);
  conn_close(c);
}

/* Starts the idle timer: the idle timeout, or before authentication budget.auth_timeout_s when
 * that is shorter. */
static void idle_start(conn_t *c) {
  const config_t *cfg = &c->srv->cfg;
  double s = cfg->idle_timeout_s;
  if (!c->authed && (!(s > 0) || cfg->budget.auth_timeout_s < s))
    s = cfg->budget.auth_timeout_s;
  if (!(s > 0)) {
    uv_timer_stop(&c->idle);
    return;
  }
  uint64_t ms = (uint64_t)(s * 1000.0);
  uv_timer_start(&c->idle, on_idle_timeout, ms ? ms : 1, ms ? ms : 1);
}

void conn_authenticated(conn_t *c) {
  if (c->authed)
    return;
  c->authed = 1;
  if (c->unauth_counted)
    c->srv->nunauth--;
  c->unauth_counted = 0;
  if (!c->closing)
    idle_start(c);
}

static void on_auth_delay(uv_timer_t *t) {
  conn_t *c = t->data;
  call_t *call = c->delayed;
  c->delayed = NULL;
  if (!call)
    return;
  int last = c->auth_failures >= c->srv->cfg.budget.auth_failures;
  if (last)
    conn_finish(c); /* The answer below is its last. */
  call_error(call, PROTO_E_UNAUTHORIZED, "token",
             last ? "unauthorized: wrong token; %u wrong tokens close the connection"
                  : "unauthorized: wrong token",
             c->srv->cfg.budget.auth_failures);
}

void conn_auth_failed(call_t *call) {
  conn_t *c = call->conn;
  c->auth_failures++;
  if (c->closing || c->delayed) {
    call_error(call, PROTO_E_UNAUTHORIZED, "token", "unauthorized: wrong token");
    return;
  }
  /* The connection waits: nothing else it sent runs before the answer. */
  call_hold(call);
  c->delayed = call;
  uv_timer_start(&c->delay, on_auth_delay, AUTH_DELAY_MS, 0);
}

/* Appends an error reply with a null id after any pending replies, and closes the connection
 * once everything queued is written. Used when the connection cannot go on. */
static void finish_with_error(conn_t *c, int code, const char *msg, const char *path) {
  c->transport->read_stop(c);
  c->draining = 1;
  c->srv->stats.errors++;
  reply_t *r = calloc(1, sizeof *r + sizeof(reply_part_t));
  if (!r) {
    conn_close(c);
    return;
  }
  r->nparts = 1;
  r->parts[0].response = proto_make_error(NULL, code, msg, path);
  r->parts[0].done = 1;
  if (c->tail)
    c->tail->next = r;
  else
    c->head = r;
  c->tail = r;
  conn_flush_replies(c);
}

/* Dispatches the complete lines the reader holds, in order, until none is left or a call
 * holds the connection: then reading stops, so a client pipelining behind a held request is
 * slowed by TCP rather than buffered here without bound. */
/* Whether a line holds only JSON's insignificant whitespace (RFC 8259: space, tab, CR, LF). */
static int blank(const char *line, size_t len) {
  for (size_t i = 0; i < len; i++)
    if (line[i] != ' ' && line[i] != '\t' && line[i] != '\r' && line[i] != '\n')
      return 0;
  return 1;
}

static void pump(conn_t *c) {
  /* Calls may close the connection; hold a reference while lines are dispatched. */
  c->refs++;
  while (!c->held && !(c->out_paused = conn_full(c))) {
    if (c->batch) { /* A batch stopped part-way by the limits goes on first. */
      dispatch_resume(c);
      if (c->closing || c->draining)
        break;
      continue;
    }
    char *line;
    size_t len;
    int rc = proto_reader_line(&c->reader, &line, &len);
    if (rc == PROTO_READ_MORE)
      break;
    if (rc == PROTO_READ_OVERSIZE) {
      char msg[128];
      snprintf(msg, sizeof msg, "limit exceeded: line longer than %zu bytes",
               c->srv->cfg.limits.line_bytes);
      finish_with_error(c, PROTO_E_LIMIT, msg, "line_bytes");
      break;
    }
    if (blank(line, len))
      continue; /* Blank lines, of nothing or only JSON whitespace, are keep-alives. */
    dispatch_line(c, line, len);
    if (c->closing || c->draining)
      break;
  }
  if ((c->held || c->out_paused) && !c->closing)
    c->transport->read_stop(c);
  conn_unref(c);
}

static void on_read(uv_stream_t *stream, ssize_t nread, const uv_buf_t *buf) {
  conn_t *c = stream->data;
  if (nread == UV_EOF && !c->closing) {
    /* The client will send nothing more but may still be reading (a half-close, as from
     * `nc -N`): answer what it sent, a last line without its newline included, then close. */
    uv_read_stop(stream);
    if (!c->draining && !c->held && proto_reader_feed(&c->reader, "\n", 1) == PROTO_READ_OK)
      pump(c);
    if (c->closing)
      return;
    c->draining = 1;
    if (!c->head && c->out_bytes == 0)
      conn_close(c);
    return;
  }
  if (nread < 0) {
    conn_close(c);
    return;
  }
  if (nread > 0)
    conn_received(c, buf->base, (size_t)nread);
}

void conn_received(conn_t *c, const char *data, size_t n) {
  if (n == 0 || c->closing || c->draining)
    return;
  /* Only an authenticated connection's traffic keeps it open: one that never authenticates is
   * closed after the idle timeout whatever it sends, so blank lines cannot hold the slots. */
  if (c->srv->cfg.idle_timeout_s > 0 && c->authed)
    uv_timer_again(&c->idle);
  if (proto_reader_feed(&c->reader, data, n) != PROTO_READ_OK) {
    conn_close(c);
    return;
  }
  pump(c);
}

void conn_hold(conn_t *c) {
  c->held++;
}

void conn_release(conn_t *c) {
  if (--c->held > 0 || c->closing)
    return;
  c->refs++;
  dispatch_resume(c);
  if (!c->held && !c->closing && !c->draining) {
    pump(c);
    if (!c->held && !c->closing && !c->draining && !c->out_paused)
      c->transport->read_start(c);
  }
  conn_unref(c);
}

static void stream_read_stop(conn_t *c) {
  uv_read_stop(c->stream);
}

static void stream_read_start(conn_t *c) {
  uv_read_start(c->stream, on_alloc, on_read);
}

static size_t stream_queued(const conn_t *c) {
  return uv_stream_get_write_queue_size(c->stream);
}

static void stream_close(conn_t *c) {
  uv_close((uv_handle_t *)c->stream, on_handle_closed);
}

static const conn_transport_t stream_transport = {.write = stream_write,
                                                  .read_stop = stream_read_stop,
                                                  .read_start = stream_read_start,
                                                  .queued = stream_queued,
                                                  .close = stream_close};

size_t conn_queued(const conn_t *c) {
  return c->transport->queued(c);
}

/* A connection with its timers, in the server's list; its transport not yet started. */
static conn_t *conn_new(server_t *s, const conn_transport_t *transport, void *ctx) {
  conn_t *c = calloc(1, sizeof *c);
  if (!c)
    return NULL;
  c->srv = s;
  c->transport = transport;
  c->transport_ctx = ctx;
  uv_timer_init(s->loop, &c->idle);
  c->idle.data = c;
  uv_timer_init(s->loop, &c->stall);
  c->stall.data = c;
  uv_timer_init(s->loop, &c->delay);
  c->delay.data = c;
  c->refs = 4; /* The transport and the idle, stall and delay timers. */
  c->id = ++s->next_conn_id;
  c->authed = s->cfg.token[0] == '\0';
  proto_reader_init(&c->reader, s->cfg.limits.line_bytes);
  c->next = s->conns;
  if (s->conns)
    s->conns->prev = c;
  s->conns = c;
  s->nconns++;
  s->stats.connections_total++;
  return c;
}

/* Applies the connection and authentication limits to a new connection and starts it: returns
 * 0, or -1 when it was refused (it closes once the error is written) or the server stops. */
static int conn_admit(conn_t *c) {
  server_t *s = c->srv;
  if (s->stopping) {
    conn_close(c);
    return -1;
  }
  if (s->nconns > s->cfg.limits.connections) {
    LOG(LOG_WARN, "net", "connection limit (%u) reached, refusing a client",
        s->cfg.limits.connections);
    char msg[128];
    snprintf(msg, sizeof msg, "limit exceeded: too many connections (limit %u)",
             s->cfg.limits.connections);
    finish_with_error(c, PROTO_E_LIMIT, msg, "connections");
    return -1;
  }
  if (!c->authed) {
    if (s->nunauth >= s->cfg.budget.unauthenticated) {
      LOG(LOG_WARN, "net", "%u connections are waiting to authenticate, refusing a client",
          s->nunauth);
      char msg[160];
      snprintf(msg, sizeof msg,
               "limit exceeded: too many connections waiting to authenticate (limit %u)",
               s->cfg.budget.unauthenticated);
      finish_with_error(c, PROTO_E_LIMIT, msg, "unauthenticated");
      return -1;
    }
    s->nunauth++;
    c->unauth_counted = 1;
  }
  idle_start(c);
  c->transport->read_start(c);
  return 0;
}

conn_t *conn_open(server_t *s, const conn_transport_t *transport, void *ctx) {
  conn_t *c = conn_new(s, transport, ctx);
  if (c)
    conn_admit(c);
  return c;
}

static void on_connection(uv_stream_t *listener, int status) {
  server_t *s = listener->data;
  if (status < 0) {
    LOG(LOG_WARN, "net", "accept failed: %s", uv_strerror(status));
    return;
  }
  conn_t *c = conn_new(s, &stream_transport, NULL);
  if (!c)
    return;
  if (listener == (uv_stream_t *)&s->tcp) {
    uv_tcp_init(s->loop, &c->h.tcp);
    uv_tcp_nodelay(&c->h.tcp, 1);
  } else {
    uv_pipe_init(s->loop, &c->h.pipe, 0);
  }
  c->stream = (uv_stream_t *)&c->h;
  c->stream->data = c;
  if (uv_accept(listener, c->stream) != 0) {
    conn_close(c);
    return;
  }
  conn_admit(c);
}

/*
 * Makes room for the Unix socket at 'path': nothing there is fine; a socket nobody listens on
 * (left by a process that died) is removed; anything else (a regular file, a directory, a
 * socket another server is listening on) is left alone and refused. Returns 0 or -1 (logged).
 */
static int clear_stale_socket(const char *path) {
  struct stat st;
  if (lstat(path, &st) != 0) {
    if (errno == ENOENT)
      return 0;
    LOG(LOG_ERROR, "net", "cannot use %s: %s", path, strerror(errno));
    return -1;
  }
  if (!S_ISSOCK(st.st_mode)) {
    LOG(LOG_ERROR, "net", "refusing to listen on %s: it exists and is not a socket", path);
    return -1;
  }
  struct sockaddr_un addr = {.sun_family = AF_UNIX};
  if (strlen(path) >= sizeof addr.sun_path) {
    LOG(LOG_ERROR, "net", "the Unix socket path %s is too long", path);
    return -1;
  }
  strcpy(addr.sun_path, path);
  int fd = socket(AF_UNIX, SOCK_STREAM | SOCK_CLOEXEC, 0);
  if (fd < 0) {
    LOG(LOG_ERROR, "net", "cannot check %s: %s", path, strerror(errno));
    return -1;
  }
  int live = connect(fd, (struct sockaddr *)&addr, sizeof addr) == 0;
  int err = errno;
  close(fd);
  if (live) {
    LOG(LOG_ERROR, "net", "refusing to listen on %s: another server is listening there", path);
    return -1;
  }
  if (err != ECONNREFUSED) {
    LOG(LOG_ERROR, "net", "cannot check %s: %s", path, strerror(err));
    return -1;
  }
  if (unlink(path) != 0 && errno != ENOENT) {
    LOG(LOG_ERROR, "net", "cannot remove the stale socket %s: %s", path, strerror(errno));
    return -1;
  }
  return 0;
}

int net_listen(server_t *s) {
  config_t *cfg = &s->cfg;
  int rc;
  if (http_listen(s) != 0)
    return -1;
  if (cfg->listen_host[0]) {
    struct sockaddr_storage addr;
    if (uv_ip4_addr(cfg->listen_host, cfg->listen_port, (struct sockaddr_in *)&addr) != 0 &&
        uv_ip6_addr(cfg->listen_host, cfg->listen_port, (struct sockaddr_in6 *)&addr) != 0) {
      if (strcmp(cfg->listen_host, "localhost") == 0)
        uv_ip4_addr("127.0.0.1", cfg->listen_port, (struct sockaddr_in *)&addr);
      else {
        LOG(LOG_ERROR, "net", "cannot parse listen address '%s'", cfg->listen_host);
        return -1;
      }
    }
    uv_tcp_init(s->loop, &s->tcp);
    s->tcp.data = s;
    s->has_tcp = 1;
    if ((rc = uv_tcp_bind(&s->tcp, (struct sockaddr *)&addr, 0)) != 0 ||
        (rc = uv_listen((uv_stream_t *)&s->tcp, 511, on_connection)) != 0) {
      LOG(LOG_ERROR, "net", "cannot listen on %s:%d: %s", cfg->listen_host, cfg->listen_port,
          uv_strerror(rc));
      return -1;
    }
  }
  if (cfg->unix_path[0]) {
    uv_pipe_init(s->loop, &s->pipe, 0);
    s->pipe.data = s;
    s->has_pipe = 1;
    if (clear_stale_socket(cfg->unix_path) != 0)
      return -1;
    if ((rc = uv_pipe_bind(&s->pipe, cfg->unix_path)) == 0)
      s->pipe_bound = 1; /* Ours now: removed at the stop. */
    if (rc != 0 || (rc = uv_listen((uv_stream_t *)&s->pipe, 511, on_connection)) != 0) {
      LOG(LOG_ERROR, "net", "cannot listen on %s: %s", cfg->unix_path, uv_strerror(rc));
      return -1;
    }
  }
  return 0;
}

static void on_listener_closed(uv_handle_t *h) {
  (void)h;
}

void net_stop(server_t *s) {
  http_stop(s);
  if (s->has_tcp) {
    uv_close((uv_handle_t *)&s->tcp, on_listener_closed);
    s->has_tcp = 0;
  }
  if (s->has_pipe) {
    uv_close((uv_handle_t *)&s->pipe, on_listener_closed);
    s->has_pipe = 0;
    if (s->pipe_bound)
      unlink(s->cfg.unix_path);
    s->pipe_bound = 0;
  }
  conn_t *c = s->conns;
  while (c) {
    conn_t *next = c->next;
    c->transport->read_stop(c);
    /* Draining first, so that what the hooks write does not start the reading again. */
    c->draining = 1;
    RUN_HOOKS(c, on_stop);
    if (!c->closing && !c->head && c->out_bytes == 0)
      conn_close(c);
    c = next;
  }
}
