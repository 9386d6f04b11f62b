/*
 * libvolfx: the blocking volfxd client behind volfx.h. One socket per connection, made
 * non-blocking so that every wait goes through poll() and can honour a deadline; the framing
 * reader of the protocol library splits the byte stream into lines, and attachment bytes are
 * copied straight from the socket into the caller's buffer. Notifications met while waiting
 * for a response go to a bounded FIFO that volfx_next_notification() drains first; a frame
 * replaces the unread one of its subscription there, so the server's latest-wins holds.
 */
#include "volfx.h"

#include <errno.h>
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <time.h>
#include <unistd.h>

#include "proto.h"

/*
 * Longest response line accepted. Responses are not bound by the server's request line limit:
 * a scene with many objects or the OpenRPC document can be large.
 */
#define MAX_LINE ((size_t)64 << 20)
#define MAX_ATTACHMENT ((size_t)1 << 30) /* 4096² rgbaf32 is 256 MiB; allow headroom. */
#define QUEUE_MAX 256                    /* Notifications kept while nobody reads them. */
#define RECV_CHUNK 65536

typedef struct note {
  struct note *next;
  cJSON *msg;             /* The whole notification. */
  volfx_attachment_t att; /* Its attachment, possibly empty. */
} note_t;

struct volfx_conn {
  int fd;
  int timeout_ms;  /* Per-call budget; 0 or less is none. */
  int broken;      /* 0, or the transport code that made the stream unusable. */
  int64_t next_id; /* Id of the next request. */
  proto_reader_t rd;
  note_t *head; /* Oldest queued notification. */
  note_t *tail;
  size_t queued;
  uint64_t dropped;  /* Notifications evicted from the full queue. */
  uint64_t replaced; /* Frames replaced by a newer one of their subscription. */
};

/* A deadline in CLOCK_MONOTONIC milliseconds; NO_DEADLINE waits forever. */
#define NO_DEADLINE INT64_MAX

static int64_t now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (int64_t)ts.tv_sec * 1000 + ts.tv_nsec / 1000000;
}

static int64_t deadline_after(int timeout_ms) {
  return timeout_ms > 0 ? now_ms() + timeout_ms : NO_DEADLINE;
}

/* Fills 'err' (may be NULL) and returns 'code', so failures read `return fail(err, ...)`. */
static int fail(volfx_error_t *err, int code, const char *message, const char *path) {
  if (err != NULL) {
    err->code = code;
    snprintf(err->message, sizeof(err->message), "%s",
             message != NULL ? message : volfx_strerror(code));
    snprintf(err->path, sizeof(err->path), "%s", path != NULL ? path : "");
  }
  return code;
}

/* Marks the stream unusable: after a lost or half-read message the next line is not ours. */
static int breaks(volfx_conn_t *c, volfx_error_t *err, int code, const char *message) {
  if (c->broken == 0) {
    c->broken = code;
  }
  return fail(err, code, message, NULL);
}

const char *volfx_strerror(int code) {
  switch (code) {
#define XX(name, num, msg)                                                                         \
  case num:                                                                                        \
    return msg;
    VOLFX_ERRNO_MAP(XX)
#undef XX
  default:
    return proto_err_message(code);
  }
}

void volfx_attachment_free(volfx_attachment_t *att) {
  if (att != NULL) {
    free(att->data);
    memset(att, 0, sizeof(*att));
  }
}

/*
 * Waits until 'fd' is ready for 'events' or 'deadline' passes. A signal ends the wait with
 * VOLFX_E_INTR when 'intr_ok' is set and is otherwise ignored. Returns 0 or a VOLFX_E_* code.
 */
static int wait_fd(int fd, short events, int64_t deadline, int intr_ok) {
  for (;;) {
    int ms = -1;
    if (deadline != NO_DEADLINE) {
      int64_t left = deadline - now_ms();
      ms = left < 0 ? 0 : (left > INT32_MAX ? INT32_MAX : (int)left);
    }
    struct pollfd p = {.fd = fd, .events = events};
    int n = poll(&p, 1, ms);
    if (n > 0) {
      return 0;
    }
    if (n == 0) {
      return VOLFX_E_TIMEOUT;
    }
    if (errno != EINTR) {
      return VOLFX_E_IO;
    }
    if (intr_ok) {
      return VOLFX_E_INTR;
    }
  }
}

/* Writes all 'n' bytes of 'buf' before 'deadline'. Returns 0 or a VOLFX_E_* code. */
static int send_all(volfx_conn_t *c, const char *buf, size_t n, int64_t deadline) {
  while (n > 0) {
    ssize_t w = send(c->fd, buf, n, MSG_NOSIGNAL);
    if (w > 0) {
      buf += w;
      n -= (size_t)w;
      continue;
    }
    if (w < 0 && errno == EINTR) {
      continue;
    }
    if (w < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
      int rc = wait_fd(c->fd, POLLOUT, deadline, 0);
      if (rc != 0) {
        return rc;
      }
      continue;
    }
    return (w < 0 && (errno == EPIPE || errno == ECONNRESET)) ? VOLFX_E_CLOSED : VOLFX_E_IO;
  }
  return 0;
}

/*
 * Receives at most 'n' bytes into 'dst', waiting until 'deadline'. Returns the count (> 0) or
 * a VOLFX_E_* code; the peer closing the stream is VOLFX_E_CLOSED.
 */
static ssize_t recv_some(volfx_conn_t *c, void *dst, size_t n, int64_t deadline, int intr_ok) {
  for (;;) {
    ssize_t r = recv(c->fd, dst, n, 0);
    if (r > 0) {
      return r;
    }
    if (r == 0) {
      return VOLFX_E_CLOSED;
    }
    if (errno == EINTR) {
      if (intr_ok) {
        return VOLFX_E_INTR;
      }
      continue;
    }
    if (errno != EAGAIN && errno != EWOULDBLOCK) {
      return errno == ECONNRESET ? VOLFX_E_CLOSED : VOLFX_E_IO;
    }
    int rc = wait_fd(c->fd, POLLIN, deadline, intr_ok);
    if (rc != 0) {
      return rc;
    }
  }
}

/* Reads more bytes into the line reader. Returns 0 or a VOLFX_E_* code. */
static int fill(volfx_conn_t *c, int64_t deadline, int intr_ok) {
  char buf[RECV_CHUNK];
  ssize_t r = recv_some(c, buf, sizeof(buf), deadline, intr_ok);
  if (r < 0) {
    return (int)r;
  }
  return proto_reader_feed(&c->rd, buf, (size_t)r) == PROTO_READ_OK ? 0 : VOLFX_E_NOMEM;
}

/*
 * Reads the 'n' raw bytes of an attachment, first from what the reader has buffered, then
 * straight from the socket. 'dst' may be NULL to discard them. Returns 0 or a VOLFX_E_* code.
 */
static int read_raw(volfx_conn_t *c, unsigned char *dst, size_t n, int64_t deadline) {
  char scratch[RECV_CHUNK];
  size_t got = 0;
  while (got < n) {
    size_t pending = proto_reader_pending(&c->rd);
    if (pending > 0) {
      size_t k = pending < n - got ? pending : n - got;
      const char *p;
      if (proto_reader_bytes(&c->rd, k, &p) != PROTO_READ_OK) {
        return VOLFX_E_PROTOCOL;
      }
      if (dst != NULL) {
        memcpy(dst + got, p, k);
      }
      got += k;
      continue;
    }
    size_t want = n - got;
    void *into = dst != NULL ? (void *)(dst + got) : (void *)scratch;
    if (dst == NULL && want > sizeof(scratch)) {
      want = sizeof(scratch);
    }
    ssize_t r = recv_some(c, into, want, deadline, 0);
    if (r < 0) {
      return (int)r;
    }
    got += (size_t)r;
  }
  return 0;
}

/*
 * Takes the attachment described by 'holder' (a result or notification params): the base64
 * "data" (in the attachment or beside it) when present, which is then removed from 'holder',
 * else 'bytes' raw bytes off the stream. 'att' may be NULL to drop the bytes. Returns 0 or a
 * VOLFX_E_* code; a transport error may leave the raw bytes half-read, so the caller must then
 * treat the stream as broken.
 */
static int take_attachment(volfx_conn_t *c, cJSON *holder, volfx_attachment_t *att,
                           int64_t deadline) {
  cJSON *a = cJSON_IsObject(holder) ? cJSON_GetObjectItemCaseSensitive(holder, "attachment") : NULL;
  if (!cJSON_IsObject(a)) {
    return 0;
  }
  const cJSON *bytes = cJSON_GetObjectItemCaseSensitive(a, "bytes");
  if (!cJSON_IsNumber(bytes) || bytes->valuedouble < 0 ||
      bytes->valuedouble > (double)MAX_ATTACHMENT) {
    return VOLFX_E_PROTOCOL;
  }
  size_t n = (size_t)bytes->valuedouble;
  if (att != NULL) {
    const cJSON *f = cJSON_GetObjectItemCaseSensitive(a, "format");
    const cJSON *w = cJSON_GetObjectItemCaseSensitive(a, "width");
    const cJSON *h = cJSON_GetObjectItemCaseSensitive(a, "height");
    snprintf(att->format, sizeof(att->format), "%s", cJSON_IsString(f) ? f->valuestring : "");
    att->width = cJSON_IsNumber(w) ? w->valueint : 0;
    att->height = cJSON_IsNumber(h) ? h->valueint : 0;
  }

  cJSON *owner = a;
  cJSON *b64 = cJSON_GetObjectItemCaseSensitive(a, "data");
  if (!cJSON_IsString(b64)) {
    owner = holder;
    b64 = cJSON_GetObjectItemCaseSensitive(holder, "data");
  }
  if (cJSON_IsString(b64)) {
    /* Inline bytes: nothing follows the line. */
    if (att != NULL) {
      size_t slen = strlen(b64->valuestring);
      unsigned char *buf = malloc(proto_b64_decoded_max(slen) + 1);
      if (buf == NULL) {
        return VOLFX_E_NOMEM;
      }
      long got = proto_b64_decode(b64->valuestring, slen, buf);
      if (got < 0) {
        free(buf);
        return VOLFX_E_PROTOCOL;
      }
      att->data = buf;
      att->len = (size_t)got;
    }
    cJSON_DeleteItemFromObjectCaseSensitive(owner, "data");
    return 0;
  }

  unsigned char *buf = NULL;
  if (att != NULL && n > 0) {
    buf = malloc(n);
    if (buf == NULL) {
      return VOLFX_E_NOMEM;
    }
  }
  int rc = read_raw(c, buf, n, deadline);
  if (rc != 0) {
    free(buf);
    return rc;
  }
  if (att != NULL) {
    att->data = buf;
    att->len = n;
  }
  return 0;
}

/* 1 when 'msg' is a notification: an object with a string "method" and no "id". */
static int is_notification(const cJSON *msg) {
  return cJSON_IsObject(msg) && cJSON_IsString(cJSON_GetObjectItemCaseSensitive(msg, "method")) &&
         !cJSON_HasObjectItem(msg, "id");
}

/*
 * Reads the next message. Waiting for its line ends at 'wait_deadline' (a signal ends it too
 * when 'intr_ok'); once the line is in, its attachment bytes are read under the connection's
 * own timeout, so that a short wait never leaves an attachment half-read. On success '*msg' is
 * the parsed message, and its attachment is in 'note_att' when it is a notification or in
 * 'result_att' when it is a response (either may be NULL to drop the bytes). Returns 0 or a
 * VOLFX_E_* code.
 */
static int read_message(volfx_conn_t *c, int64_t wait_deadline, int intr_ok, cJSON **msg,
                        volfx_attachment_t *note_att, volfx_attachment_t *result_att) {
  char *line;
  size_t len;
  *msg = NULL;
  for (;;) {
    int rc = proto_reader_line(&c->rd, &line, &len);
    if (rc == PROTO_READ_OVERSIZE) {
      return VOLFX_E_PROTOCOL;
    }
    if (rc == PROTO_READ_OK && len == 0) {
      continue; /* Blank lines carry nothing. */
    }
    if (rc == PROTO_READ_OK) {
      break;
    }
    rc = fill(c, wait_deadline, intr_ok);
    if (rc != 0) {
      return rc;
    }
  }

  /*
   * cJSON parses directly rather than proto_parse(): that one enforces the request nesting
   * limit, which a server's response (a deep scene, the OpenRPC schemas) is not bound by.
   */
  cJSON *m = cJSON_ParseWithLength(line, len);
  if (m == NULL) {
    return VOLFX_E_PROTOCOL;
  }
  int64_t body_deadline = deadline_after(c->timeout_ms);
  int rc;
  if (is_notification(m)) {
    rc = take_attachment(c, cJSON_GetObjectItemCaseSensitive(m, "params"), note_att, body_deadline);
  } else {
    rc = take_attachment(c, cJSON_GetObjectItemCaseSensitive(m, "result"), result_att,
                         body_deadline);
  }
  if (rc != 0) {
    cJSON_Delete(m);
    return rc;
  }
  *msg = m;
  return 0;
}

static size_t purge_frames(volfx_conn_t *c, int64_t id);
static int method_is(const cJSON *msg, const char *method);

/*
 * Appends a notification to the queue, evicting the oldest when it is full; a frame first
 * removes the unread frame of its subscription. Takes 'msg'.
 */
static void enqueue(volfx_conn_t *c, cJSON *msg, volfx_attachment_t *att) {
  if (method_is(msg, "frames")) {
    const cJSON *p = cJSON_GetObjectItemCaseSensitive(msg, "params");
    const cJSON *id = cJSON_GetObjectItemCaseSensitive(p, "id");
    if (cJSON_IsNumber(id)) {
      c->replaced += purge_frames(c, (int64_t)id->valuedouble);
    }
  }
  note_t *n = calloc(1, sizeof(*n));
  if (n == NULL) {
    cJSON_Delete(msg);
    volfx_attachment_free(att);
    c->dropped++;
    return;
  }
  n->msg = msg;
  n->att = *att;
  memset(att, 0, sizeof(*att));
  if (c->tail != NULL) {
    c->tail->next = n;
  } else {
    c->head = n;
  }
  c->tail = n;
  c->queued++;
  while (c->queued > QUEUE_MAX) {
    note_t *old = c->head;
    c->head = old->next;
    cJSON_Delete(old->msg);
    volfx_attachment_free(&old->att);
    free(old);
    c->queued--;
    c->dropped++;
  }
}

/* 1 when notification 'msg' has method 'method' (NULL matches any). */
static int method_is(const cJSON *msg, const char *method) {
  if (method == NULL) {
    return 1;
  }
  const cJSON *m = cJSON_GetObjectItemCaseSensitive(msg, "method");
  return cJSON_IsString(m) && strcmp(m->valuestring, method) == 0;
}

/* Unlinks and returns the oldest queued notification of 'method', or NULL. */
static note_t *dequeue(volfx_conn_t *c, const char *method) {
  note_t *prev = NULL;
  for (note_t *n = c->head; n != NULL; prev = n, n = n->next) {
    if (!method_is(n->msg, method)) {
      continue;
    }
    if (prev != NULL) {
      prev->next = n->next;
    } else {
      c->head = n->next;
    }
    if (c->tail == n) {
      c->tail = prev;
    }
    c->queued--;
    n->next = NULL;
    return n;
  }
  return NULL;
}

static volfx_conn_t *conn_new(int fd, int timeout_ms) {
  volfx_conn_t *c = calloc(1, sizeof(*c));
  if (c == NULL) {
    return NULL;
  }
  c->fd = fd;
  c->timeout_ms = timeout_ms;
  c->next_id = 1;
  proto_reader_init(&c->rd, MAX_LINE);
  return c;
}

/*
 * Connects the non-blocking socket 'fd' to 'addr' before 'deadline'. Returns 0 or a
 * VOLFX_E_* code with errno describing a refusal.
 */
static int connect_wait(int fd, const struct sockaddr *addr, socklen_t alen, int64_t deadline) {
  if (connect(fd, addr, alen) == 0) {
    return 0;
  }
  if (errno != EINPROGRESS && errno != EINTR) {
    return VOLFX_E_CONNECT;
  }
  int rc = wait_fd(fd, POLLOUT, deadline, 0);
  if (rc != 0) {
    errno = ETIMEDOUT;
    return rc;
  }
  int soerr = 0;
  socklen_t slen = sizeof(soerr);
  if (getsockopt(fd, SOL_SOCKET, SO_ERROR, &soerr, &slen) != 0 || soerr != 0) {
    errno = soerr != 0 ? soerr : errno;
    return VOLFX_E_CONNECT;
  }
  return 0;
}

int volfx_connect_tcp(volfx_conn_t **out, const char *host, int port, int timeout_ms,
                      volfx_error_t *err) {
  if (out == NULL || port < 0 || port > 65535) {
    return fail(err, VOLFX_E_INVAL, NULL, NULL);
  }
  *out = NULL;
  if (host == NULL || host[0] == '\0') {
    host = VOLFX_DEFAULT_HOST;
  }
  char portstr[8];
  snprintf(portstr, sizeof(portstr), "%d", port > 0 ? port : VOLFX_DEFAULT_PORT);
  struct addrinfo hints = {.ai_family = AF_UNSPEC, .ai_socktype = SOCK_STREAM};
  struct addrinfo *res = NULL;
  int gai = getaddrinfo(host, portstr, &hints, &res);
  if (gai != 0) {
    char msg[300];
    snprintf(msg, sizeof(msg), "cannot resolve %s: %s", host, gai_strerror(gai));
    return fail(err, VOLFX_E_CONNECT, msg, NULL);
  }

  int64_t deadline = deadline_after(timeout_ms);
  int rc = VOLFX_E_CONNECT;
  int fd = -1;
  int why = ECONNREFUSED;
  for (struct addrinfo *ai = res; ai != NULL; ai = ai->ai_next) {
    fd = socket(ai->ai_family, ai->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, ai->ai_protocol);
    if (fd < 0) {
      why = errno;
      continue;
    }
    rc = connect_wait(fd, ai->ai_addr, ai->ai_addrlen, deadline);
    if (rc == 0) {
      break;
    }
    why = errno;
    close(fd);
    fd = -1;
  }
  freeaddrinfo(res);
  if (fd < 0) {
    char msg[400];
    snprintf(msg, sizeof(msg), "cannot connect to %s:%s: %s", host, portstr,
             rc == VOLFX_E_TIMEOUT ? "timed out" : strerror(why));
    return fail(err, rc == VOLFX_E_TIMEOUT ? VOLFX_E_TIMEOUT : VOLFX_E_CONNECT, msg, NULL);
  }
  /* Requests are small and each waits for its answer: do not let Nagle delay them. */
  int one = 1;
  setsockopt(fd, IPPROTO_TCP, TCP_NODELAY, &one, sizeof(one));
  *out = conn_new(fd, timeout_ms);
  if (*out == NULL) {
    close(fd);
    return fail(err, VOLFX_E_NOMEM, NULL, NULL);
  }
  return 0;
}

int volfx_connect_unix(volfx_conn_t **out, const char *path, int timeout_ms, volfx_error_t *err) {
  if (out == NULL || path == NULL) {
    return fail(err, VOLFX_E_INVAL, NULL, NULL);
  }
  *out = NULL;
  struct sockaddr_un sa = {.sun_family = AF_UNIX};
  if (strlen(path) >= sizeof(sa.sun_path)) {
    return fail(err, VOLFX_E_INVAL, "unix socket path too long", NULL);
  }
  memcpy(sa.sun_path, path, strlen(path) + 1);
  int fd = socket(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (fd < 0) {
    return fail(err, VOLFX_E_CONNECT, strerror(errno), NULL);
  }
  int rc = connect_wait(fd, (const struct sockaddr *)&sa, sizeof(sa), deadline_after(timeout_ms));
  if (rc != 0) {
    char msg[400];
    snprintf(msg, sizeof(msg), "cannot connect to %s: %s", path,
             rc == VOLFX_E_TIMEOUT ? "timed out" : strerror(errno));
    close(fd);
    return fail(err, rc, msg, NULL);
  }
  *out = conn_new(fd, timeout_ms);
  if (*out == NULL) {
    close(fd);
    return fail(err, VOLFX_E_NOMEM, NULL, NULL);
  }
  return 0;
}

void volfx_set_timeout(volfx_conn_t *conn, int timeout_ms) {
  if (conn != NULL) {
    conn->timeout_ms = timeout_ms;
  }
}

/* Turns the "error" member of a response into a return code and 'err'. */
static int server_error(const cJSON *e, volfx_error_t *err) {
  const cJSON *code = cJSON_GetObjectItemCaseSensitive(e, "code");
  const cJSON *message = cJSON_GetObjectItemCaseSensitive(e, "message");
  const cJSON *data = cJSON_GetObjectItemCaseSensitive(e, "data");
  const cJSON *path = cJSON_IsObject(data) ? cJSON_GetObjectItemCaseSensitive(data, "path") : NULL;
  int c = cJSON_IsNumber(code) ? code->valueint : PROTO_E_INTERNAL;
  if (c == 0) {
    c = PROTO_E_INTERNAL; /* 0 would read as success. */
  }
  return fail(err, c, cJSON_IsString(message) ? message->valuestring : proto_err_message(c),
              cJSON_IsString(path) ? path->valuestring : NULL);
}

/* 1 when response 'msg' answers request 'id': same id, or a null id (a parse error of ours). */
static int answers(const cJSON *msg, int64_t id) {
  const cJSON *rid = cJSON_GetObjectItemCaseSensitive(msg, "id");
  if (cJSON_IsNumber(rid)) {
    return rid->valuedouble == (double)id;
  }
  return cJSON_IsNull(rid) && cJSON_HasObjectItem(msg, "error");
}

int volfx_call(volfx_conn_t *conn, const char *method, cJSON *params, cJSON **result,
               volfx_attachment_t *att, volfx_error_t *err) {
  if (result != NULL) {
    *result = NULL;
  }
  if (att != NULL) {
    memset(att, 0, sizeof(*att));
  }
  if (conn == NULL || method == NULL) {
    cJSON_Delete(params);
    return fail(err, VOLFX_E_INVAL, NULL, NULL);
  }
  if (conn->broken != 0) {
    cJSON_Delete(params);
    return fail(err, conn->broken, "connection unusable after an earlier error", NULL);
  }

  int64_t id = conn->next_id++;
  cJSON *req = proto_make_request(method, params, id);
  size_t len = 0;
  char *line = req != NULL ? proto_print_line(req, &len) : NULL;
  cJSON_Delete(req);
  if (line == NULL) {
    return fail(err, VOLFX_E_NOMEM, NULL, NULL);
  }
  int64_t deadline = deadline_after(conn->timeout_ms);
  int rc = send_all(conn, line, len, deadline);
  free(line);
  if (rc != 0) {
    return breaks(conn, err, rc, NULL);
  }

  for (;;) {
    cJSON *msg = NULL;
    volfx_attachment_t note_att = {0};
    volfx_attachment_t res_att = {0};
    rc = read_message(conn, deadline, 0, &msg, &note_att, &res_att);
    if (rc != 0) {
      return breaks(conn, err, rc, NULL);
    }
    if (is_notification(msg)) {
      enqueue(conn, msg, &note_att);
      continue;
    }
    if (!cJSON_IsObject(msg) || !answers(msg, id)) {
      /* A stray response (not ours): its bytes are already consumed; drop it. */
      volfx_attachment_free(&res_att);
      cJSON_Delete(msg);
      continue;
    }
    const cJSON *e = cJSON_GetObjectItemCaseSensitive(msg, "error");
    cJSON *r = cJSON_GetObjectItemCaseSensitive(msg, "result");
    if (cJSON_IsObject(e)) {
      rc = server_error(e, err);
    } else if (r == NULL) {
      rc = breaks(conn, err, VOLFX_E_PROTOCOL, "response without result or error");
    } else if (result != NULL) {
      *result = cJSON_DetachItemViaPointer(msg, r);
    }
    if (rc == 0 && att != NULL) {
      *att = res_att;
    } else {
      volfx_attachment_free(&res_att);
    }
    cJSON_Delete(msg);
    return rc;
  }
}

int volfx_auth(volfx_conn_t *conn, const char *token, volfx_error_t *err) {
  if (token == NULL) {
    return fail(err, VOLFX_E_INVAL, NULL, NULL);
  }
  cJSON *p = cJSON_CreateObject();
  if (p == NULL || cJSON_AddStringToObject(p, "token", token) == NULL) {
    cJSON_Delete(p);
    return fail(err, VOLFX_E_NOMEM, NULL, NULL);
  }
  return volfx_call(conn, "auth", p, NULL, NULL, err);
}

int volfx_subscribe(volfx_conn_t *conn, cJSON *params, int64_t *id, volfx_error_t *err) {
  cJSON *r = NULL;
  int rc = volfx_call(conn, "frames.subscribe", params, &r, NULL, err);
  if (rc != 0) {
    return rc;
  }
  const cJSON *jid = cJSON_GetObjectItemCaseSensitive(r, "id");
  if (!cJSON_IsNumber(jid)) {
    cJSON_Delete(r);
    return fail(err, VOLFX_E_PROTOCOL, "frames.subscribe result has no numeric id", NULL);
  }
  if (id != NULL) {
    *id = (int64_t)jid->valuedouble;
  }
  cJSON_Delete(r);
  return 0;
}

/* Drops queued "frames" notifications of subscription 'id'; returns how many. */
static size_t purge_frames(volfx_conn_t *c, int64_t id) {
  size_t purged = 0;
  note_t *prev = NULL;
  note_t *n = c->head;
  while (n != NULL) {
    const cJSON *p = cJSON_GetObjectItemCaseSensitive(n->msg, "params");
    const cJSON *nid = cJSON_GetObjectItemCaseSensitive(p, "id");
    note_t *next = n->next;
    if (method_is(n->msg, "frames") && cJSON_IsNumber(nid) && nid->valuedouble == (double)id) {
      if (prev != NULL) {
        prev->next = next;
      } else {
        c->head = next;
      }
      if (c->tail == n) {
        c->tail = prev;
      }
      c->queued--;
      purged++;
      cJSON_Delete(n->msg);
      volfx_attachment_free(&n->att);
      free(n);
    } else {
      prev = n;
    }
    n = next;
  }
  return purged;
}

int volfx_unsubscribe(volfx_conn_t *conn, int64_t id, cJSON **result, volfx_error_t *err) {
  cJSON *p = cJSON_CreateObject();
  if (p == NULL || cJSON_AddNumberToObject(p, "id", (double)id) == NULL) {
    cJSON_Delete(p);
    return fail(err, VOLFX_E_NOMEM, NULL, NULL);
  }
  int rc = volfx_call(conn, "frames.unsubscribe", p, result, NULL, err);
  if (conn != NULL) {
    purge_frames(conn, id);
  }
  return rc;
}

int volfx_next_notification(volfx_conn_t *conn, const char *method, int timeout_ms, cJSON **msg,
                            volfx_attachment_t *att) {
  if (msg != NULL) {
    *msg = NULL;
  }
  if (att != NULL) {
    memset(att, 0, sizeof(*att));
  }
  if (conn == NULL || msg == NULL) {
    return VOLFX_E_INVAL;
  }
  note_t *n = dequeue(conn, method);
  if (n != NULL) {
    *msg = n->msg;
    if (att != NULL) {
      *att = n->att;
    } else {
      volfx_attachment_free(&n->att);
    }
    free(n);
    return 0;
  }
  if (conn->broken != 0) {
    return conn->broken;
  }

  int64_t deadline = timeout_ms < 0 ? NO_DEADLINE : now_ms() + timeout_ms;
  for (;;) {
    cJSON *m = NULL;
    volfx_attachment_t note_att = {0};
    int rc = read_message(conn, deadline, 1, &m, &note_att, NULL);
    if (rc == VOLFX_E_TIMEOUT || rc == VOLFX_E_INTR) {
      return rc; /* Only the wait for a line ended: the stream is intact. */
    }
    if (rc != 0) {
      conn->broken = rc;
      return rc;
    }
    if (!is_notification(m)) {
      cJSON_Delete(m); /* No request is outstanding: a stray response. */
      continue;
    }
    if (!method_is(m, method)) {
      enqueue(conn, m, &note_att);
      continue;
    }
    *msg = m;
    if (att != NULL) {
      *att = note_att;
    } else {
      volfx_attachment_free(&note_att);
    }
    return 0;
  }
}

int volfx_next_frame(volfx_conn_t *conn, int timeout_ms, cJSON **params, volfx_attachment_t *att) {
  cJSON *msg = NULL;
  if (params != NULL) {
    *params = NULL;
  }
  int rc = volfx_next_notification(conn, "frames", timeout_ms, &msg, att);
  if (rc != 0) {
    return rc;
  }
  if (params != NULL) {
    cJSON *p = cJSON_DetachItemFromObjectCaseSensitive(msg, "params");
    *params = p != NULL ? p : cJSON_CreateObject();
  }
  cJSON_Delete(msg);
  return 0;
}

uint64_t volfx_queue_dropped(const volfx_conn_t *conn) {
  return conn != NULL ? conn->dropped : 0;
}

uint64_t volfx_frames_replaced(const volfx_conn_t *conn) {
  return conn != NULL ? conn->replaced : 0;
}

void volfx_close(volfx_conn_t *conn) {
  if (conn == NULL) {
    return;
  }
  while (conn->head != NULL) {
    note_t *n = conn->head;
    conn->head = n->next;
    cJSON_Delete(n->msg);
    volfx_attachment_free(&n->att);
    free(n);
  }
  proto_reader_free(&conn->rd);
  close(conn->fd);
  free(conn);
}
