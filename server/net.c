/*
 * Connections: accepting on TCP and Unix sockets, reading bytes into the NDJSON reader,
 * handing complete lines to the dispatcher, writing replies in request order, the idle
 * timeout, the output limit, and closing. A connection is freed only when its handles are
 * closed and no call or subscription still points at it ('refs').
 *
 * The output limit (limits.output_bytes) is backpressure, not a cut-off: while a connection's
 * unsent output and the answers its queued renders will write pass it, no further request is
 * read from it, so a client that pipelines is slowed to the pace it reads at, and one answer
 * larger than the limit (a 4096² float frame) still goes out whole. Only a connection whose
 * output stays over the limit with nothing taken off the socket for OUT_STALL_MS is closed,
 * as not reading.
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "frames.h"
#include "jobs.h"
#include "log.h"
#include "server.h"

/* How long output over the limit may sit with nothing written before the connection closes. */
#define OUT_STALL_MS 10000

typedef struct write_req {
  uv_write_t req;
  conn_t *conn;
  char *line;
  unsigned char *att;
  size_t total;
} write_req_t;

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
  frames_conn_closed(c);
  jobs_conn_closed(c);
  if (c->prev)
    c->prev->next = c->next;
  else
    s->conns = c->next;
  if (c->next)
    c->next->prev = c->prev;
  s->nconns--;
  uv_close((uv_handle_t *)c->stream, on_handle_closed);
  uv_close((uv_handle_t *)&c->idle, on_handle_closed);
  uv_close((uv_handle_t *)&c->stall, on_handle_closed);
  LOG(LOG_DEBUG, "net", "connection %llu closed", (unsigned long long)c->id);
}

/* Whether the output written and promised passes the limit, or the connection has its share
 * of the render queue: no further request is read. */
static int conn_full(const conn_t *c) {
  return c->out_bytes + c->promised > c->srv->cfg.limits.output_bytes ||
         c->renders >= CONN_RENDERS_MAX;
}

static void pump(conn_t *c);
static void on_read(uv_stream_t *stream, ssize_t nread, const uv_buf_t *buf);
static void on_alloc(uv_handle_t *h, size_t suggested, uv_buf_t *buf);

static void on_stall(uv_timer_t *t) {
  conn_t *c = t->data;
  LOG(LOG_WARN, "net", "connection %llu is not reading: %zu bytes unsent for %d s, closing",
      (unsigned long long)c->id, c->out_bytes, OUT_STALL_MS / 1000);
  conn_close(c);
}

/* After output left or was promised: the stall timer runs while the unsent output is over the
 * limit (restarted by every write that completes), and reading resumes once the output written
 * and promised is back under it. */
static void conn_output_changed(conn_t *c, int progress) {
  if (c->closing)
    return;
  if (c->out_bytes > c->srv->cfg.limits.output_bytes) {
    if (progress || !uv_is_active((uv_handle_t *)&c->stall))
      uv_timer_start(&c->stall, on_stall, OUT_STALL_MS, 0);
  } else {
    uv_timer_stop(&c->stall);
  }
  if (c->out_paused && !conn_full(c)) {
    c->out_paused = 0;
    if (!c->held && !c->draining) {
      pump(c);
      if (!c->held && !c->closing && !c->draining && !c->out_paused)
        uv_read_start(c->stream, on_alloc, on_read);
    }
  }
}

void conn_promise(call_t *call, size_t bytes) {
  call->reply->promised += bytes;
  call->conn->promised += bytes;
}

static void on_write(uv_write_t *req, int status) {
  write_req_t *w = (write_req_t *)req;
  conn_t *c = w->conn;
  c->out_bytes -= w->total;
  free(w->line);
  free(w->att);
  free(w);
  if (!c->closing) {
    if (status < 0 && status != UV_ECANCELED) {
      LOG(LOG_DEBUG, "net", "connection %llu write failed: %s", (unsigned long long)c->id,
          uv_strerror(status));
      conn_close(c);
    } else {
      if (uv_stream_get_write_queue_size(c->stream) == 0) {
        frames_conn_drained(c);
        if (c->draining && !c->head && c->out_bytes == 0)
          conn_close(c);
      }
      conn_output_changed(c, 1);
    }
  }
  conn_unref(c);
}

void conn_write(conn_t *c, char *line, size_t len, unsigned char *att, size_t att_len) {
  if (c->closing) {
    free(line);
    free(att);
    return;
  }
  write_req_t *w = malloc(sizeof *w);
  if (!w) {
    free(line);
    free(att);
    conn_close(c);
    return;
  }
  w->conn = c;
  w->line = line;
  w->att = att;
  w->total = len + att_len;
  uv_buf_t bufs[2] = {uv_buf_init(line, (unsigned)len),
                      uv_buf_init((char *)att, (unsigned)att_len)};
  c->out_bytes += w->total;
  c->refs++;
  int rc = uv_write(&w->req, c->stream, bufs, att_len ? 2 : 1, on_write);
  if (rc < 0) {
    c->out_bytes -= w->total;
    c->refs--;
    free(line);
    free(att);
    free(w);
    conn_close(c);
    return;
  }
  conn_output_changed(c, 0);
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
 * the attachments in response order. */
static void write_reply(conn_t *c, reply_t *r) {
  size_t len = 0;
  int empty;
  char *line = reply_line(r, &len, &empty);
  if (empty) {
    free_reply(r);
    return;
  }
  size_t att_len = 0;
  for (int i = 0; i < r->nparts; i++)
    att_len += r->parts[i].att_len;
  unsigned char *att = NULL;
  if (att_len) {
    if (r->nparts == 1) {
      att = r->parts[0].att;
      r->parts[0].att = NULL;
    } else if ((att = malloc(att_len)) != NULL) {
      size_t off = 0;
      for (int i = 0; i < r->nparts; i++) {
        if (!r->parts[i].att_len)
          continue;
        memcpy(att + off, r->parts[i].att, r->parts[i].att_len);
        off += r->parts[i].att_len;
      }
    }
  }
  c->promised -= r->promised;
  free_reply(r);
  if (!line || (att_len && !att)) {
    free(line);
    free(att);
    conn_close(c);
    return;
  }
  conn_write(c, line, len, att, att_len);
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
  if (c->subs || c->head)
    return; /* A subscriber or a connection waiting for work is not idle. */
  LOG(LOG_DEBUG, "net", "connection %llu idle, closing", (unsigned long long)c->id);
  conn_close(c);
}

/* Appends an error reply with a null id after any pending replies, and closes the connection
 * once everything queued is written. Used when the connection cannot go on. */
static void finish_with_error(conn_t *c, int code, const char *msg, const char *path) {
  uv_read_stop(c->stream);
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
    uv_read_stop(c->stream);
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
  if (nread == 0 || c->closing || c->draining)
    return;
  /* Only an authenticated connection's traffic keeps it open: one that never authenticates is
   * closed after the idle timeout whatever it sends, so blank lines cannot hold the slots. */
  if (c->srv->cfg.idle_timeout_s > 0 && c->authed)
    uv_timer_again(&c->idle);
  if (proto_reader_feed(&c->reader, buf->base, (size_t)nread) != PROTO_READ_OK) {
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
      uv_read_start(c->stream, on_alloc, on_read);
  }
  conn_unref(c);
}

static void on_connection(uv_stream_t *listener, int status) {
  server_t *s = listener->data;
  if (status < 0) {
    LOG(LOG_WARN, "net", "accept failed: %s", uv_strerror(status));
    return;
  }
  conn_t *c = calloc(1, sizeof *c);
  if (!c)
    return;
  c->srv = s;
  if (listener == (uv_stream_t *)&s->tcp) {
    uv_tcp_init(s->loop, &c->h.tcp);
    uv_tcp_nodelay(&c->h.tcp, 1);
  } else {
    uv_pipe_init(s->loop, &c->h.pipe, 0);
  }
  c->stream = (uv_stream_t *)&c->h;
  c->stream->data = c;
  uv_timer_init(s->loop, &c->idle);
  c->idle.data = c;
  uv_timer_init(s->loop, &c->stall);
  c->stall.data = c;
  c->refs = 3; /* The stream, the idle timer and the stall timer. */
  c->id = ++s->next_conn_id;
  c->authed = s->cfg.token[0] == '\0';
  proto_reader_init(&c->reader, s->cfg.limits.line_bytes);
  c->next = s->conns;
  if (s->conns)
    s->conns->prev = c;
  s->conns = c;
  s->nconns++;
  s->stats.connections_total++;

  if (uv_accept(listener, c->stream) != 0) {
    conn_close(c);
    return;
  }
  if (s->stopping) {
    conn_close(c);
    return;
  }
  if (s->nconns > s->cfg.limits.connections) {
    LOG(LOG_WARN, "net", "connection limit (%u) reached, refusing a client",
        s->cfg.limits.connections);
    char msg[128];
    snprintf(msg, sizeof msg, "limit exceeded: too many connections (limit %u)",
             s->cfg.limits.connections);
    finish_with_error(c, PROTO_E_LIMIT, msg, "connections");
    return;
  }
  if (s->cfg.idle_timeout_s > 0) {
    uint64_t ms = (uint64_t)(s->cfg.idle_timeout_s * 1000.0);
    uv_timer_start(&c->idle, on_idle_timeout, ms, ms);
  }
  uv_read_start(c->stream, on_alloc, on_read);
}

int net_listen(server_t *s) {
  config_t *cfg = &s->cfg;
  int rc;
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
    /* A stale socket file from a previous run would make bind fail. */
    unlink(cfg->unix_path);
    if ((rc = uv_pipe_bind(&s->pipe, cfg->unix_path)) != 0 ||
        (rc = uv_listen((uv_stream_t *)&s->pipe, 511, on_connection)) != 0) {
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
  if (s->has_tcp) {
    uv_close((uv_handle_t *)&s->tcp, on_listener_closed);
    s->has_tcp = 0;
  }
  if (s->has_pipe) {
    uv_close((uv_handle_t *)&s->pipe, on_listener_closed);
    s->has_pipe = 0;
    unlink(s->cfg.unix_path);
  }
  conn_t *c = s->conns;
  while (c) {
    conn_t *next = c->next;
    uv_read_stop(c->stream);
    frames_conn_closed(c);
    c->draining = 1;
    if (!c->head && c->out_bytes == 0)
      conn_close(c);
    c = next;
  }
}
