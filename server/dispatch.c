/*
 * From a request line to a handler: parse, check the JSON-RPC envelope, look the method up,
 * check authentication, validate the params against the method's schema, and run the handler.
 * Every request gets a slot in the connection's reply queue before its handler runs, so replies
 * leave in request order whether the handler answers at once or from the render worker.
 */
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "defer.h"
#include "frames.h"
#include "dispatch.h"
#include "log.h"

const method_t *method_find(const char *name) {
  for (const method_t *const *m = method_table; *m; m++)
    if (strcmp((*m)->name, name) == 0)
      return *m;
  return NULL;
}

static reply_t *reply_append(conn_t *c, int nparts, int batch) {
  reply_t *r = calloc(1, sizeof *r + (size_t)nparts * sizeof(reply_part_t));
  if (!r)
    return NULL;
  r->nparts = nparts;
  r->pending = nparts;
  r->batch = batch;
  if (c->tail)
    c->tail->next = r;
  else
    c->head = r;
  c->tail = r;
  return r;
}

/* Echoes the client's 't' (render, frames) in the data of the error 'response', as the results
 * do, so that a client measuring latency can match its failures too. */
static void echo_t(cJSON *response, const cJSON *params) {
  const cJSON *t = cJSON_IsObject(params) ? cJSON_GetObjectItemCaseSensitive(params, "t") : NULL;
  cJSON *error = response ? cJSON_GetObjectItemCaseSensitive(response, "error") : NULL;
  if (!t || !error)
    return;
  cJSON *data = cJSON_GetObjectItemCaseSensitive(error, "data");
  if (!data)
    data = cJSON_AddObjectToObject(error, "data");
  if (cJSON_IsObject(data))
    cJSON_AddItemToObject(data, "t", cJSON_Duplicate(t, 1));
}

/* Whether the method takes a 't' to echo. */
static int takes_t(const method_t *m) {
  for (const sch_field_t *f = m && m->params ? m->params->fields : NULL; f && f->name; f++)
    if (strcmp(f->name, "t") == 0)
      return 1;
  return 0;
}

/* Fills a part that never became a call (envelope errors). 'notification' marks a valid
 * request without an id, which JSON-RPC never answers, not even with an error. */
static void part_error_n(conn_t *c, reply_t *r, int i, const cJSON *id, int notification, int code,
                         const char *msg, const char *path) {
  if (!notification)
    r->parts[i].response = proto_make_error(id, code, msg, path);
  r->parts[i].done = 1;
  r->pending--;
  c->srv->stats.errors++;
}

static void part_error(conn_t *c, reply_t *r, int i, const cJSON *id, int code, const char *msg,
                       const char *path) {
  part_error_n(c, r, i, id, 0, code, msg, path);
}

/* Finishes 'call' with 'response', or with the response already printed in 'line' (both
 * taken), and attachment bytes 'att' (taken; may be NULL). */
static void call_done(call_t *call, cJSON *response, char *line, size_t line_len,
                      unsigned char *att, size_t att_len) {
  conn_t *c = call->conn;
  int holding = call->holding;
  reply_part_t *p = &call->reply->parts[call->part];
  if (call->id) {
    p->response = response;
    p->line = line;
    p->line_len = line_len;
    p->att = att;
    p->att_len = att_len;
  } else {
    cJSON_Delete(response); /* A notification is run but never answered. */
    free(line);
    free(att);
  }
  p->done = 1;
  call->reply->pending--;
  cJSON_Delete(call->id);
  cJSON_Delete(call->params);
  defer_release(call);
  free(call);
  if (!c->closing)
    conn_flush_replies(c);
  if (holding)
    conn_release(c);
  conn_unref(c);
}

void call_hold(call_t *call) {
  if (!call->holding) {
    call->holding = 1;
    conn_hold(call->conn);
  }
}

static void call_finish(call_t *call, cJSON *response, unsigned char *att, size_t att_len) {
  call_done(call, response, NULL, 0, att, att_len);
}

void call_result(call_t *call, cJSON *result) {
  if (call->method && (call->method->flags & METHOD_SCENE_TAG))
    frames_scene_changed(call);
  call_finish(call, proto_make_result(call->id, result), NULL, 0);
}

static void attachment_of(cJSON *result, size_t n, const char *format, uint32_t width,
                          uint32_t height) {
  cJSON *att = cJSON_AddObjectToObject(result, "attachment");
  cJSON_AddNumberToObject(att, "bytes", (double)n);
  cJSON_AddStringToObject(att, "format", format);
  if (width)
    cJSON_AddNumberToObject(att, "width", width);
  if (height)
    cJSON_AddNumberToObject(att, "height", height);
}

/* An answer whose bytes are made, base64-encoded and printed on the thread pool. */
typedef struct made_job {
  uv_work_t req;
  call_t *call;
  cJSON *result; /* Becomes the response. */
  cJSON *id;     /* A copy of the call's, to print the response with off the loop. */
  call_bytes_fn make;
  void (*drop)(void *);
  void *ctx;
  const char *format;
  uint32_t width, height;
  int base64;
  unsigned char *bytes; /* Made, or given (make NULL). */
  size_t n;
  char *line; /* The response printed, when base64. */
  size_t len;
  int ok;
} made_job_t;

static void made_work(uv_work_t *req) {
  made_job_t *j = req->data;
  if (j->make)
    j->bytes = j->make(j->ctx, &j->n);
  if (!j->bytes)
    return;
  attachment_of(j->result, j->n, j->format, j->width, j->height);
  if (!j->base64) {
    j->ok = 1;
    return;
  }
  char *text = malloc(proto_b64_encoded_len(j->n) + 1);
  if (!text)
    return;
  proto_b64_encode(j->bytes, j->n, text);
  free(j->bytes);
  j->bytes = NULL;
  /* A reference: the text is not copied into cJSON, and cJSON does not free it. */
  cJSON_AddItemToObject(j->result, "data", cJSON_CreateStringReference(text));
  cJSON *response = proto_make_result(j->id, j->result);
  j->result = NULL;
  j->line = proto_print_line(response, &j->len);
  cJSON_Delete(response);
  free(text);
  j->ok = j->line != NULL;
}

static void made_done(uv_work_t *req, int status) {
  made_job_t *j = req->data;
  call_t *call = j->call;
  if (j->drop)
    j->drop(j->ctx);
  if (status != 0 || !j->ok) {
    free(j->bytes);
    cJSON_Delete(j->result);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory for the answer");
  } else if (j->line) {
    call_done(call, NULL, j->line, j->len, NULL, 0);
  } else {
    call_finish(call, proto_make_result(call->id, j->result), j->bytes, j->n);
  }
  cJSON_Delete(j->id);
  free(j);
}

/* Queues 'j' (filled but for its request); on failure answers the call at once. */
static void made_queue(made_job_t *j) {
  j->req.data = j;
  j->id = j->call->id ? cJSON_Duplicate(j->call->id, 1) : NULL;
  if ((j->call->id && !j->id) ||
      uv_queue_work(j->call->srv->loop, &j->req, made_work, made_done) != 0)
    made_done(&j->req, UV_ENOMEM);
}

void call_result_bytes(call_t *call, cJSON *result, unsigned char *bytes, size_t n,
                       const char *format, uint32_t width, uint32_t height, int base64) {
  made_job_t *j = base64 && n >= CALL_BYTES_OFF_LOOP ? calloc(1, sizeof *j) : NULL;
  if (j) {
    *j = (made_job_t){.call = call,
                      .result = result,
                      .format = format,
                      .width = width,
                      .height = height,
                      .base64 = 1,
                      .bytes = bytes,
                      .n = n};
    made_queue(j);
    return;
  }
  attachment_of(result, n, format, width, height);
  if (base64) {
    char *text = malloc(proto_b64_encoded_len(n) + 1);
    if (!text) {
      free(bytes);
      cJSON_Delete(result);
      call_error(call, PROTO_E_INTERNAL, NULL, "out of memory encoding base64");
      return;
    }
    proto_b64_encode(bytes, n, text);
    free(bytes);
    cJSON_AddStringToObject(result, "data", text);
    free(text);
    call_finish(call, proto_make_result(call->id, result), NULL, 0);
    return;
  }
  call_finish(call, proto_make_result(call->id, result), bytes, n);
}

void call_result_made(call_t *call, cJSON *result, call_bytes_fn make, void (*drop)(void *),
                      void *ctx, size_t size, const char *format, int base64) {
  /* Counted towards the connection's output now, so that the requests behind wait while
   * the answers queued pass the limit (net.c). */
  conn_promise(call, (base64 ? proto_b64_encoded_len(size) : size) + 4096);
  made_job_t *j = size >= CALL_BYTES_OFF_LOOP ? calloc(1, sizeof *j) : NULL;
  if (j) {
    *j = (made_job_t){.call = call,
                      .result = result,
                      .make = make,
                      .drop = drop,
                      .ctx = ctx,
                      .format = format,
                      .base64 = base64};
    made_queue(j);
    return;
  }
  size_t n = 0;
  unsigned char *bytes = make(ctx, &n);
  if (drop)
    drop(ctx);
  if (!bytes) {
    cJSON_Delete(result);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  call_result_bytes(call, result, bytes, n, format, 0, 0, base64);
}

void call_error(call_t *call, int code, const char *path, const char *fmt, ...) {
  char msg[512];
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(msg, sizeof msg, fmt, ap);
  va_end(ap);
  call->srv->stats.errors++;
  cJSON *response = proto_make_error(call->id, code, msg, path);
  echo_t(response, call->params);
  call_finish(call, response, NULL, 0);
}

scene_entry_t *call_scene(call_t *call) {
  const char *name = cJSON_GetStringValue(cJSON_GetObjectItem(call->params, "scene"));
  scene_entry_t *e = name ? server_find_scene(call->srv, name) : NULL;
  if (!e)
    call_error(call, PROTO_E_NOT_FOUND, "scene", "not found: no scene named '%s'",
               name ? name : "");
  return e;
}

/* Runs one request of a line: part 'i' of reply 'r'. */
static void dispatch_one(conn_t *c, reply_t *r, int i, const cJSON *msg) {
  server_t *s = c->srv;
  proto_request_t req;
  const char *why = NULL;
  s->stats.requests++;
  c->requests++;
  if (proto_request_check(msg, &req, &why) != 0) {
    char text[256];
    snprintf(text, sizeof text, "invalid request: %s", why);
    part_error(c, r, i, req.id, PROTO_E_INVALID_REQUEST, text, NULL);
    return;
  }
  const method_t *m = method_find(req.method);
  /* Before 'auth', unknown methods are unauthorized too, so method names cannot be probed. */
  if (!c->authed && !(m && (m->flags & METHOD_NO_AUTH))) {
    part_error_n(c, r, i, req.id, !req.id, PROTO_E_UNAUTHORIZED,
                 "unauthorized: this server needs 'auth' with its token first", NULL);
    return;
  }
  if (!m) {
    char text[256];
    snprintf(text, sizeof text, "method not found: '%.128s'", req.method);
    part_error_n(c, r, i, req.id, !req.id, PROTO_E_METHOD_NOT_FOUND, text, NULL);
    return;
  }
  if (req.params && !cJSON_IsObject(req.params)) {
    part_error_n(c, r, i, req.id, !req.id, PROTO_E_INVALID_PARAMS,
                 "invalid params: params must be an object of named params", "params");
    return;
  }
  cJSON *params = req.params ? cJSON_Duplicate(req.params, 1) : cJSON_CreateObject();
  sch_error_t err;
  if (!params || sch_validate(m->params, params, "", &err) != 0) {
    cJSON_Delete(params);
    char text[600];
    snprintf(text, sizeof text, "invalid params: %s", params ? err.message : "out of memory");
    part_error_n(c, r, i, req.id, !req.id, PROTO_E_INVALID_PARAMS, text, params ? err.path : NULL);
    if (takes_t(m))
      echo_t(r->parts[i].response, req.params);
    return;
  }
  call_t *call = calloc(1, sizeof *call);
  if (!call) {
    cJSON_Delete(params);
    part_error_n(c, r, i, req.id, !req.id, PROTO_E_INTERNAL, "internal error: out of memory", NULL);
    return;
  }
  call->srv = s;
  call->conn = c;
  call->reply = r;
  call->part = i;
  call->id = req.id ? cJSON_Duplicate(req.id, 1) : NULL;
  call->params = params;
  call->method = m;
  call->t_start_ns = now_ns();
  c->refs++;
  m->handler(call);
}

void dispatch_resume(conn_t *c) {
  if (!c->batch)
    return;
  /* A batch obeys the limits of a line each: its parts wait while the connection is full
   * (its output, its share of the render queue, the server's output budget). */
  while (c->batch_next && !c->held && !conn_full(c)) {
    const cJSON *it = c->batch_next;
    c->batch_next = it->next;
    dispatch_one(c, c->batch_reply, c->batch_part++, it);
  }
  if (c->batch_next)
    return; /* Held or full part-way: the rest waits for conn_release or pump. */
  cJSON_Delete(c->batch);
  c->batch = NULL;
  if (!c->closing)
    conn_flush_replies(c);
}

void dispatch_line(conn_t *c, char *line, size_t len) {
  char why[160];
  cJSON *msg = proto_parse(line, len, why, sizeof why);
  if (!msg) {
    reply_t *r = reply_append(c, 1, 0);
    if (!r) {
      conn_close(c);
      return;
    }
    char text[200];
    snprintf(text, sizeof text, "parse error: %s", why);
    c->srv->stats.requests++;
    part_error(c, r, 0, NULL, PROTO_E_PARSE, text, NULL);
    conn_flush_replies(c);
    return;
  }
  if (cJSON_IsArray(msg) && !c->authed) {
    /* Before authentication a line gets one small answer: a batch is refused whole. */
    cJSON_Delete(msg);
    reply_t *r = reply_append(c, 1, 0);
    if (!r) {
      conn_close(c);
      return;
    }
    c->srv->stats.requests++;
    part_error(c, r, 0, NULL, PROTO_E_UNAUTHORIZED,
               "unauthorized: this server needs 'auth' with its token first; batches come after",
               NULL);
    conn_flush_replies(c);
    return;
  }
  if (cJSON_IsArray(msg)) {
    int n = cJSON_GetArraySize(msg);
    reply_t *r = reply_append(c, n ? n : 1, n ? 1 : 0);
    if (!r) {
      cJSON_Delete(msg);
      conn_close(c);
      return;
    }
    if (n == 0) {
      c->srv->stats.requests++;
      part_error(c, r, 0, NULL, PROTO_E_INVALID_REQUEST, "invalid request: empty batch", NULL);
    } else {
      c->batch = msg;
      c->batch_next = msg->child;
      c->batch_reply = r;
      c->batch_part = 0;
      dispatch_resume(c);
      return;
    }
  } else {
    reply_t *r = reply_append(c, 1, 0);
    if (!r) {
      cJSON_Delete(msg);
      conn_close(c);
      return;
    }
    dispatch_one(c, r, 0, msg);
  }
  cJSON_Delete(msg);
  if (!c->closing)
    conn_flush_replies(c);
}
