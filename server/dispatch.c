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

static void call_finish(call_t *call, cJSON *response, unsigned char *att, size_t att_len) {
  conn_t *c = call->conn;
  reply_part_t *p = &call->reply->parts[call->part];
  if (call->id) {
    p->response = response;
    p->att = att;
    p->att_len = att_len;
  } else {
    cJSON_Delete(response); /* A notification is run but never answered. */
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
  conn_unref(c);
}

void call_result(call_t *call, cJSON *result) {
  call_finish(call, proto_make_result(call->id, result), NULL, 0);
}

void call_result_bytes(call_t *call, cJSON *result, unsigned char *bytes, size_t n,
                       const char *format, uint32_t width, uint32_t height, int base64) {
  cJSON *att = cJSON_AddObjectToObject(result, "attachment");
  cJSON_AddNumberToObject(att, "bytes", (double)n);
  cJSON_AddStringToObject(att, "format", format);
  if (width)
    cJSON_AddNumberToObject(att, "width", width);
  if (height)
    cJSON_AddNumberToObject(att, "height", height);
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

void call_error(call_t *call, int code, const char *path, const char *fmt, ...) {
  char msg[512];
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(msg, sizeof msg, fmt, ap);
  va_end(ap);
  call->srv->stats.errors++;
  call_finish(call, proto_make_error(call->id, code, msg, path), NULL, 0);
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
  if (!m) {
    char text[256];
    snprintf(text, sizeof text, "method not found: '%.128s'", req.method);
    part_error_n(c, r, i, req.id, !req.id, PROTO_E_METHOD_NOT_FOUND, text, NULL);
    return;
  }
  if (!c->authed && !(m->flags & METHOD_NO_AUTH)) {
    part_error_n(c, r, i, req.id, !req.id, PROTO_E_UNAUTHORIZED,
                 "unauthorized: this server needs 'auth' with its token first", NULL);
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
  while (c->batch_next && !c->held) {
    const cJSON *it = c->batch_next;
    c->batch_next = it->next;
    dispatch_one(c, c->batch_reply, c->batch_part++, it);
  }
  if (c->batch_next)
    return; /* Held part-way: the rest waits for conn_release. */
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
