/*
 * libFuzzer target for WebSocket text messages as request lines (protocol/ws_text.c), the way
 * volfxd's WebSocket transport hands them to a connection's reader. The input is a sequence of
 * messages separated by 0xff bytes; each is cut into fragments of random sizes (seeded by its
 * first byte), converted fragment by fragment and fed to an NDJSON reader with a newline at
 * the message's end, as the transport does. Properties checked with abort():
 * - each message gives exactly one line, of its own length, holding no line break;
 * - the line differs from the message only where the message had a line break;
 * - a message that is valid JSON (cJSON) reads back from its line as the same value, and one
 *   with a raw line break inside a string is refused by proto_parse;
 * - the state a message leaves does not leak into the next one.
 *
 * Build with -DVOLFX_FUZZ=ON -DCMAKE_C_COMPILER=clang, then run ./bin/fuzz_websocket CORPUS_DIR.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "fuzz.h"
#include "proto.h"

/* Whether 'msg' holds a line break inside a JSON string, scanning as a JSON tokenizer would. */
static int break_in_string(const uint8_t *msg, size_t n) {
  int in_string = 0, escaped = 0;
  for (size_t i = 0; i < n; i++) {
    if (in_string && (msg[i] == '\n' || msg[i] == '\r'))
      return 1;
    if (escaped)
      escaped = 0;
    else if (in_string && msg[i] == '\\')
      escaped = 1;
    else if (msg[i] == '"')
      in_string = !in_string;
  }
  return 0;
}

static void one_message(proto_ws_text_t *st, const uint8_t *msg, size_t n) {
  proto_reader_t reader;
  proto_reader_init(&reader, n + 1);
  char *converted = malloc(n + 1);
  REQUIRE(converted != NULL);
  /* Fragments of sizes 1..16, seeded by the message's first byte. */
  uint32_t seed = n ? msg[0] * 2654435761u + 1 : 1;
  for (size_t at = 0; at < n;) {
    seed = seed * 1103515245u + 12345u;
    size_t take = 1 + (seed >> 16) % 16;
    if (take > n - at)
      take = n - at;
    proto_ws_text_feed(st, msg + at, take, converted + at);
    REQUIRE(proto_reader_feed(&reader, converted + at, take) == PROTO_READ_OK);
    at += take;
  }
  proto_ws_text_end(st);
  REQUIRE(proto_reader_feed(&reader, "\n", 1) == PROTO_READ_OK);

  char *line = NULL;
  size_t len = 0;
  REQUIRE(proto_reader_line(&reader, &line, &len) == PROTO_READ_OK);
  REQUIRE(len == n && memcmp(line, converted, n) == 0);
  for (size_t i = 0; i < n; i++) {
    REQUIRE(line[i] != '\n' && line[i] != '\r');
    if (msg[i] != '\n' && msg[i] != '\r')
      REQUIRE((uint8_t)line[i] == msg[i]);
  }
  REQUIRE(proto_reader_line(&reader, &line, &len) == PROTO_READ_MORE);

  cJSON *want = cJSON_ParseWithLength((const char *)msg, n);
  char why[128];
  cJSON *got = proto_parse(converted, n, why, sizeof why);
  if (break_in_string(msg, n))
    REQUIRE(got == NULL);
  if (want && got) {
    /* Compared printed, so that numbers past a double's range (printed null) compare too. */
    char *a = cJSON_PrintUnformatted(want), *b = cJSON_PrintUnformatted(got);
    REQUIRE(a && b && strcmp(a, b) == 0);
    cJSON_free(a);
    cJSON_free(b);
  }
  cJSON_Delete(want);
  cJSON_Delete(got);
  free(converted);
  proto_reader_free(&reader);
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  proto_ws_text_t st = {0};
  size_t start = 0;
  for (size_t i = 0; i <= size; i++) {
    if (i < size && data[i] != 0xff)
      continue;
    one_message(&st, data + start, i - start);
    REQUIRE(st.in_string == 0 && st.escaped == 0);
    start = i + 1;
  }
  return 0;
}
