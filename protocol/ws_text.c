/*
 * WebSocket text messages as request lines (proto.h, proto_ws_text_t): the line breaks a
 * pretty-printed message holds become spaces between tokens and 0x1f inside strings, so that a
 * message is one line for the NDJSON reader and a raw break in a string is refused as over TCP.
 */
#include "proto.h"

void proto_ws_text_feed(proto_ws_text_t *st, const unsigned char *in, size_t n, char *out) {
  for (size_t i = 0; i < n; i++) {
    unsigned char ch = in[i];
    if (ch == '\n' || ch == '\r') {
      /* Always replaced, also right after a backslash: no break reaches the reader. */
      ch = st->in_string ? 0x1f : ' ';
      st->escaped = 0;
    } else if (st->escaped) {
      st->escaped = 0;
    } else if (st->in_string && ch == '\\') {
      st->escaped = 1;
    } else if (ch == '"') {
      st->in_string = !st->in_string;
    }
    out[i] = (char)ch;
  }
}

void proto_ws_text_end(proto_ws_text_t *st) {
  st->in_string = st->escaped = 0;
}
