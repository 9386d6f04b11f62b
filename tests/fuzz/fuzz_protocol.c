/*
 * libFuzzer target for the protocol library. The input's first four bytes choose the line limit
 * and seed the chunk sizes; the rest is a byte stream fed to an NDJSON reader in random-sized
 * pieces, the way a socket delivers it. Every line is parsed, checked as a request (or as a
 * batch of them), answered, printed, and also run through base64 in both directions; a line
 * "#N" announces an attachment of N bytes, taken raw. Properties that must hold whatever the
 * input are checked with abort(), so the fuzzer reports them as crashes.
 *
 * Build with -DVOLFX_FUZZ=ON -DCMAKE_C_COMPILER=clang, then run ./bin/fuzz_protocol CORPUS_DIR.
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "fuzz.h"
#include "proto.h"

/* Chunk sizes come from a generator seeded by the input, so each input replays exactly. */
static uint32_t next_random(uint32_t *state) {
  *state ^= *state << 13;
  *state ^= *state >> 17;
  *state ^= *state << 5;
  return *state;
}

/* Prints 'msg' as a line, checks its framing and that it parses back, and frees both. When
 * 'want_id' is a number, the printed "id" must read back as the same number. */
static void print_and_reparse(cJSON *msg, const cJSON *want_id) {
  REQUIRE(msg != NULL);
  size_t len = 0;
  char *line = proto_print_line(msg, &len);
  REQUIRE(line != NULL);
  REQUIRE(len >= 1 && len == strlen(line) && line[len - 1] == '\n');
  REQUIRE(memchr(line, '\n', len - 1) == NULL);
  cJSON *back = cJSON_ParseWithLength(line, len - 1);
  REQUIRE(back != NULL);
  if (want_id != NULL && cJSON_IsNumber(want_id)) {
    const cJSON *id = cJSON_GetObjectItemCaseSensitive(back, "id");
    REQUIRE(cJSON_IsNumber(id) && id->valuedouble == want_id->valuedouble);
  }
  cJSON_Delete(back);
  free(line);
  cJSON_Delete(msg);
}

/* Checks one request the way volfxd's dispatcher starts, and answers it. */
static void answer(const cJSON *msg) {
  proto_request_t req;
  const char *why = NULL;
  int rc = proto_request_check(msg, &req, &why);
  if (rc != 0) {
    REQUIRE(rc == PROTO_E_INVALID_REQUEST && why != NULL);
    print_and_reparse(proto_make_error(req.id, rc, why, NULL), req.id);
    return;
  }
  REQUIRE(req.method != NULL);
  REQUIRE(req.params == NULL || cJSON_IsObject(req.params) || cJSON_IsArray(req.params));
  cJSON *result = req.params != NULL ? cJSON_Duplicate(req.params, 1) : NULL;
  print_and_reparse(proto_make_result(req.id, result), req.id);
  print_and_reparse(proto_make_error(req.id, PROTO_E_INVALID_PARAMS, NULL, req.method), req.id);
}

/* Base64 both ways: whatever decodes must encode back to the same text (the decoder accepts
 * one encoding per byte string), and any bytes must survive an encode and decode. */
static void check_base64(const char *s, size_t n) {
  size_t max = proto_b64_decoded_max(n);
  unsigned char *bytes = malloc(max + 1);
  REQUIRE(bytes != NULL);
  long got = proto_b64_decode(s, n, bytes);
  if (got >= 0) {
    REQUIRE((size_t)got <= max);
    char *text = malloc(proto_b64_encoded_len((size_t)got) + 1);
    REQUIRE(text != NULL);
    proto_b64_encode(bytes, (size_t)got, text);
    REQUIRE(strlen(text) == n && memcmp(text, s, n) == 0);
    free(text);
  }
  free(bytes);

  size_t elen = proto_b64_encoded_len(n);
  char *text = malloc(elen + 1);
  bytes = malloc(proto_b64_decoded_max(elen) + 1);
  REQUIRE(text != NULL && bytes != NULL);
  proto_b64_encode(s, n, text);
  REQUIRE(text[elen] == '\0');
  REQUIRE(proto_b64_decode(text, elen, bytes) == (long)n && memcmp(bytes, s, n) == 0);
  free(bytes);
  free(text);
}

/* Handles one line; returns the size of the attachment it announces, or 0. */
static size_t handle_line(const char *line, size_t len) {
  char why[96];
  cJSON *msg = proto_parse(line, len, why, sizeof(why));
  if (msg != NULL) {
    REQUIRE(proto_utf8_valid(line, len));
    REQUIRE(proto_json_depth_ok(line, len, PROTO_MAX_DEPTH));
    if (cJSON_IsArray(msg)) {
      for (const cJSON *item = msg->child; item != NULL; item = item->next)
        answer(item);
    } else {
      answer(msg);
    }
    print_and_reparse(msg, NULL);
  } else {
    REQUIRE(why[0] != '\0');
  }

  check_base64(line, len);

  if (len >= 2 && line[0] == '#') {
    size_t n = 0;
    for (size_t i = 1; i < len && i < 6 && line[i] >= '0' && line[i] <= '9'; i++)
      n = n * 10 + (size_t)(line[i] - '0');
    return n;
  }
  return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  if (size < 4)
    return 0;
  uint32_t state =
      ((uint32_t)data[0] << 24 | (uint32_t)data[1] << 16 | (uint32_t)data[2] << 8 | data[3]) | 1;
  /* Mostly small limits, so that the oversize paths are reached; sometimes the default. */
  size_t max_line = data[0] < 32 ? (size_t)1 << 20 : (size_t)data[0] * 4;
  data += 4;
  size -= 4;

  proto_reader_t r;
  proto_reader_init(&r, max_line);
  size_t off = 0, attachment = 0;
  int done = 0;
  while (off < size && !done) {
    uint32_t k = next_random(&state);
    size_t chunk = (k & 3) == 0 ? 1 : 1 + (k >> 8) % ((k & 4) ? 4096 : 32);
    if (chunk > size - off)
      chunk = size - off;
    size_t before = proto_reader_pending(&r);
    REQUIRE(proto_reader_feed(&r, data + off, chunk) == PROTO_READ_OK);
    REQUIRE(proto_reader_pending(&r) == before + chunk);
    off += chunk;

    for (;;) {
      if (attachment > 0) {
        const char *bytes;
        if (proto_reader_bytes(&r, attachment, &bytes) != PROTO_READ_OK)
          break;
        REQUIRE(memcmp(bytes, data + off - proto_reader_pending(&r) - attachment, attachment) == 0);
        attachment = 0;
        continue;
      }
      char *line;
      size_t len;
      int rc = proto_reader_line(&r, &line, &len);
      if (rc == PROTO_READ_MORE) {
        REQUIRE(proto_reader_pending(&r) <= max_line + 1);
        break;
      }
      if (rc == PROTO_READ_OVERSIZE) {
        done = 1;
        break;
      }
      REQUIRE(rc == PROTO_READ_OK && len <= max_line && line[len] == '\0');
      REQUIRE(memchr(line, '\n', len) == NULL);
      attachment = handle_line(line, len);
    }
  }
  proto_reader_free(&r);
  return 0;
}
