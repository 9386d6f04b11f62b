/*
 * The error carrier (proto_error.h): clearing it and filling it from a format; and the message
 * alone formatted into a caller's buffer.
 */
#include "proto_error.h"

#include <stdio.h>

void proto_error_clear(proto_error_t *e) {
  if (!e)
    return;
  e->code = 0;
  e->path[0] = '\0';
  e->message[0] = '\0';
}

int proto_error_vset(proto_error_t *e, int code, const char *path, const char *fmt, va_list ap) {
  if (!e)
    return -1;
  e->code = code;
  snprintf(e->path, sizeof e->path, "%s", path ? path : "");
  vsnprintf(e->message, sizeof e->message, fmt, ap);
  return -1;
}

int proto_error_set(proto_error_t *e, int code, const char *path, const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  proto_error_vset(e, code, path, fmt, ap);
  va_end(ap);
  return -1;
}

void proto_error_format(char *buf, size_t len, const char *fmt, ...) {
  if (buf == NULL || len == 0)
    return;
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(buf, len, fmt, ap);
  va_end(ap);
}
