/*
 * Error codes, limits and attachment formats of the volfx protocol: the tables that turn the
 * PROTO_ERROR_MAP X-macro into names and messages, the default limits of SPEC §3, and the
 * names of the attachment formats as they appear on the wire.
 */
#include <string.h>

#include "proto.h"

/* The default message of 'code' from PROTO_ERROR_MAP, or "unknown error" for any other code. */
const char *proto_err_message(int code) {
  switch (code) {
#define XX(name, value, msg)                                                                       \
  case value:                                                                                      \
    return msg;
    PROTO_ERROR_MAP(XX)
#undef XX
  default:
    return "unknown error";
  }
}

/* The symbolic name of 'code' ("INVALID_PARAMS"), or NULL when the map has no such code. */
const char *proto_err_name(int code) {
  switch (code) {
#define XX(name, value, msg)                                                                       \
  case value:                                                                                      \
    return #name;
    PROTO_ERROR_MAP(XX)
#undef XX
  default:
    return NULL;
  }
}

/* Fills 'l' with the defaults of SPEC §3; volfxd overrides them from its configuration. */
void proto_limits_default(proto_limits_t *l) {
  l->line_bytes = (size_t)1 << 20;
  l->frame_side = 4096;
  l->particles = (uint32_t)1 << 20;
  l->cloud_side = 256;
  l->connections = 256;
  l->output_bytes = (size_t)64 << 20;
}

/* Wire names, indexed by proto_format_t. */
#define PROTO_FORMAT_NAME(id, name) [PROTO_FMT_##id] = name,
static const char *const format_names[PROTO_FMT_COUNT] = {PROTO_FORMATS(PROTO_FORMAT_NAME)};

/* The wire name of 'f', or NULL when 'f' is not a format. */
const char *proto_format_name(proto_format_t f) {
  /* The enum's underlying type may be unsigned, so compare as int to catch negative values. */
  if ((int)f < 0 || (int)f >= PROTO_FMT_COUNT)
    return NULL;
  return format_names[f];
}

/* The format whose wire name is exactly 's' (case-sensitive), or -1; 's' may be NULL. */
int proto_format_parse(const char *s) {
  if (s == NULL)
    return -1;
  for (int f = 0; f < PROTO_FMT_COUNT; f++) {
    if (strcmp(s, format_names[f]) == 0)
      return f;
  }
  return -1;
}
