/*
 * A WebSocket as a connection: the transport (conn_transport_t) that carries a conn_t's
 * requests and replies over libwebsockets, so that dispatch, replies, subscriptions and every
 * limit work as over TCP. Each text message is one request (or batch); each reply line is one
 * text message, and each attachment the binary message right after it. A binary message from
 * the client closes the WebSocket (1003): requests carry no attachments.
 *
 * Replies wait in the link's queue until libwebsockets says the socket is writable, and go out
 * in fragments of WS_CHUNK bytes; a write counts as written (conn_written) once its last
 * fragment is handed over, so the connection's output, the server's budget and the frames'
 * latest-wins see the same numbers as for a TCP socket. Reading pauses with libwebsockets' rx
 * flow control.
 *
 * A message becomes one line for the connection's reader (protocol/ws_text.c): the line breaks
 * JSON allows between tokens become spaces, and one inside a string (which JSON forbids there)
 * a control byte that the parser refuses as it would the raw line break.
 */
#include <stdlib.h>
#include <string.h>

#include "http.h"
#include "log.h"

/* The most bytes handed to libwebsockets at once. */
#define WS_CHUNK 65536

typedef struct ws_part {
  unsigned char *bytes; /* Owned. */
  size_t n;
  int binary;
} ws_part_t;

/* One conn_write: its line and attachments, as messages. */
typedef struct ws_out {
  struct ws_out *next;
  size_t total; /* The bytes net.c counted for it. */
  int nparts, part;
  size_t off; /* Sent of parts[part]. */
  ws_part_t parts[];
} ws_out_t;

typedef struct ws_link {
  server_t *srv;
  conn_t *conn;
  struct lws *wsi; /* NULL once libwebsockets has closed it. */
  ws_out_t *head, *tail;
  size_t queued;          /* Bytes of the queue not yet handed to libwebsockets. */
  int closing;            /* The connection closed: close the WebSocket. */
  proto_ws_text_t text;   /* Where the message read so far stands (protocol/ws_text.c). */
  unsigned char *scratch; /* LWS_PRE + WS_CHUNK bytes to write from. */
} ws_link_t;

typedef struct ws_session {
  ws_link_t *link;
} ws_session_t;

static void free_out(ws_out_t *o) {
  for (int i = 0; i < o->nparts; i++)
    free(o->parts[i].bytes);
  free(o);
}

static int ws_write(conn_t *c, char *line, size_t len, unsigned char **atts, const size_t *lens,
                    int n) {
  ws_link_t *link = c->transport_ctx;
  ws_out_t *o = calloc(1, sizeof *o + (size_t)(n + 1) * sizeof(ws_part_t));
  if (!o || !link->wsi) {
    free(o);
    free(line);
    for (int i = 0; i < n; i++)
      free(atts[i]);
    return -1;
  }
  o->total = len;
  /* The line's '\n' is not sent: a message is its own frame. */
  o->parts[o->nparts++] =
      (ws_part_t){(unsigned char *)line, len && line[len - 1] == '\n' ? len - 1 : len, 0};
  for (int i = 0; i < n; i++)
    if (atts[i]) {
      o->parts[o->nparts++] = (ws_part_t){atts[i], lens[i], 1};
      o->total += lens[i];
    }
  for (int i = 0; i < o->nparts; i++)
    link->queued += o->parts[i].n;
  if (link->tail)
    link->tail->next = o;
  else
    link->head = o;
  link->tail = o;
  lws_callback_on_writable(link->wsi);
  return 0;
}

static void ws_read_stop(conn_t *c) {
  ws_link_t *link = c->transport_ctx;
  if (link->wsi)
    lws_rx_flow_control(link->wsi, 0);
}

static void ws_read_start(conn_t *c) {
  ws_link_t *link = c->transport_ctx;
  if (link->wsi)
    lws_rx_flow_control(link->wsi, 1);
}

static size_t ws_queued(const conn_t *c) {
  const ws_link_t *link = c->transport_ctx;
  return link->queued;
}

/* libwebsockets is done with the link: what is still queued is dropped, and the connection
 * loses the transport's reference. */
static void link_done(ws_link_t *link) {
  conn_t *c = link->conn;
  while (link->head) {
    ws_out_t *o = link->head;
    link->head = o->next;
    size_t total = o->total;
    free_out(o);
    conn_written(c, total, UV_ECANCELED);
  }
  free(link->scratch);
  free(link);
  conn_unref(c);
}

static void ws_close(conn_t *c) {
  ws_link_t *link = c->transport_ctx;
  link->closing = 1;
  if (link->wsi)
    lws_callback_on_writable(link->wsi); /* Which closes it. */
  else
    link_done(link);
}

static const conn_transport_t ws_transport = {.write = ws_write,
                                              .read_stop = ws_read_stop,
                                              .read_start = ws_read_start,
                                              .queued = ws_queued,
                                              .close = ws_close};

/* Hands the queue to libwebsockets while the socket takes it. Returns -1 to close. */
static int link_writable(ws_link_t *link) {
  while (link->head && !link->closing) {
    if (lws_send_pipe_choked(link->wsi) || lws_partial_buffered(link->wsi)) {
      lws_callback_on_writable(link->wsi);
      return 0;
    }
    ws_out_t *o = link->head;
    ws_part_t *p = &o->parts[o->part];
    size_t n = p->n - o->off < WS_CHUNK ? p->n - o->off : WS_CHUNK;
    int flags = lws_write_ws_flags(p->binary ? LWS_WRITE_BINARY : LWS_WRITE_TEXT, o->off == 0,
                                   o->off + n == p->n);
    memcpy(link->scratch + LWS_PRE, p->bytes + o->off, n);
    if (lws_write(link->wsi, link->scratch + LWS_PRE, n, (enum lws_write_protocol)flags) < (int)n)
      return -1;
    o->off += n;
    link->queued -= n;
    if (o->off < p->n)
      continue;
    o->off = 0;
    if (++o->part < o->nparts)
      continue;
    link->head = o->next;
    if (!link->head)
      link->tail = NULL;
    size_t total = o->total;
    free_out(o);
    /* May queue more (a waiting frame), or close the connection (a drained finish). */
    conn_written(link->conn, total, 0);
  }
  if (link->closing) {
    lws_close_reason(link->wsi, LWS_CLOSE_STATUS_NORMAL, NULL, 0);
    return -1;
  }
  return 0;
}

/* Feeds one fragment of a text message to the connection's reader (see the top). */
static void link_received(ws_link_t *link, const unsigned char *in, size_t len, int last) {
  char buf[4096];
  while (len > 0 && !link->closing) {
    size_t n = len < sizeof buf ? len : sizeof buf;
    proto_ws_text_feed(&link->text, in, n, buf);
    conn_received(link->conn, buf, n);
    in += n;
    len -= n;
  }
  if (last) {
    proto_ws_text_end(&link->text);
    if (!link->closing)
      conn_received(link->conn, "\n", 1);
  }
}

static int ws_callback(struct lws *wsi, enum lws_callback_reasons reason, void *user, void *in,
                       size_t len) {
  ws_session_t *ss = user;
  server_t *s = lws_context_user(lws_get_context(wsi));
  switch (reason) {
  case LWS_CALLBACK_FILTER_PROTOCOL_CONNECTION: {
    char origin[512] = "", host[512] = "";
    int has_origin = lws_hdr_total_length(wsi, WSI_TOKEN_ORIGIN) > 0;
    if (has_origin && lws_hdr_copy(wsi, origin, sizeof origin, WSI_TOKEN_ORIGIN) < 0)
      return 1;
    if (lws_hdr_total_length(wsi, WSI_TOKEN_HOST) > 0)
      lws_hdr_copy(wsi, host, sizeof host, WSI_TOKEN_HOST);
    if (s->stopping || !http_origin_allowed(s, has_origin ? origin : NULL, host)) {
      LOG(LOG_WARN, "http", "refusing a WebSocket from origin '%.200s'%s", origin,
          s->stopping ? " (stopping)" : "; add it with --http-origin to allow it");
      return 1;
    }
    return 0;
  }
  case LWS_CALLBACK_ESTABLISHED: {
    ws_link_t *link = calloc(1, sizeof *link);
    unsigned char *scratch = malloc(LWS_PRE + WS_CHUNK);
    if (!link || !scratch) {
      free(link);
      free(scratch);
      return -1;
    }
    link->srv = s;
    link->wsi = wsi;
    link->scratch = scratch;
    ss->link = link;
    http_ws_opened(s);
    /* Admission may refuse it at once (limits): its error is queued and it closes after. */
    link->conn = conn_open(s, &ws_transport, link);
    if (!link->conn) {
      ss->link = NULL;
      free(scratch);
      free(link);
      http_ws_closed(s);
      return -1;
    }
    return 0;
  }
  case LWS_CALLBACK_RECEIVE:
    if (!ss->link || ss->link->closing)
      return 0;
    if (lws_frame_is_binary(wsi)) {
      static const char why[] = "requests are JSON text messages";
      lws_close_reason(wsi, LWS_CLOSE_STATUS_UNACCEPTABLE_OPCODE, (unsigned char *)why,
                       sizeof why - 1);
      return -1;
    }
    link_received(ss->link, in, len,
                  lws_is_final_fragment(wsi) && lws_remaining_packet_payload(wsi) == 0);
    return 0;
  case LWS_CALLBACK_SERVER_WRITEABLE:
    return ss->link ? link_writable(ss->link) : -1;
  case LWS_CALLBACK_CLOSED: {
    ws_link_t *link = ss->link;
    if (!link)
      return 0;
    ss->link = NULL;
    link->wsi = NULL;
    if (link->closing)
      link_done(link);
    else
      conn_close(link->conn); /* Which ends in ws_close, then link_done. */
    http_ws_closed(s);
    return 0;
  }
  default:
    return lws_callback_http_dummy(wsi, reason, user, in, len);
  }
}

const struct lws_protocols ws_conn_protocol = {
    .name = "volfx",
    .callback = ws_callback,
    .per_session_data_size = sizeof(ws_session_t),
    .rx_buffer_size = 65536,
};
