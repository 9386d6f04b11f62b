/*
 * Unit tests of the protocol library (volfx_proto): the NDJSON reader, UTF-8 and nesting
 * checks, message parsing, the JSON-RPC envelope check, the message builders, base64, and the
 * error, limit and format tables. A self-contained program: each CHECK that fails prints its
 * file and line, the run goes on, and the exit status is 1 when anything failed.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "proto.h"

static int checks;
static int failures;

#define CHECK(cond)                                                                                \
  do {                                                                                             \
    checks++;                                                                                      \
    if (!(cond)) {                                                                                 \
      failures++;                                                                                  \
      fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond);                     \
    }                                                                                              \
  } while (0)

/* Compares two C strings, either of which may be NULL, and prints both when they differ. */
#define CHECK_STR(got, want)                                                                       \
  do {                                                                                             \
    const char *got_ = (got), *want_ = (want);                                                     \
    checks++;                                                                                      \
    if (got_ == NULL || want_ == NULL ? got_ != want_ : strcmp(got_, want_) != 0) {                \
      failures++;                                                                                  \
      fprintf(stderr, "%s:%d: CHECK_STR failed: %s is \"%s\", want \"%s\"\n", __FILE__, __LINE__,  \
              #got, got_ ? got_ : "(null)", want_ ? want_ : "(null)");                             \
    }                                                                                              \
  } while (0)

/* A small deterministic generator (xorshift64), so that failures reproduce. */
static uint64_t rng_state = 0x9E3779B97F4A7C15u;

static uint32_t rng(void) {
  rng_state ^= rng_state << 13;
  rng_state ^= rng_state >> 7;
  rng_state ^= rng_state << 17;
  return (uint32_t)(rng_state >> 32);
}

/* ---------------------------------------------------------------------------------------------
 * Errors, limits and formats.
 */

static void test_errors(void) {
  CHECK(PROTO_E_PARSE == -32700);
  CHECK(PROTO_E_INVALID_REQUEST == -32600);
  CHECK(PROTO_E_METHOD_NOT_FOUND == -32601);
  CHECK(PROTO_E_INVALID_PARAMS == -32602);
  CHECK(PROTO_E_INTERNAL == -32603);
  CHECK(PROTO_E_UNAUTHORIZED == -32001);
  CHECK(PROTO_E_BUSY == -32002);
  CHECK(PROTO_E_LIMIT == -32003);
  CHECK(PROTO_E_NOT_FOUND == -32004);
  CHECK(PROTO_E_DEVICE == -32005);

  CHECK_STR(proto_err_name(-32700), "PARSE");
  CHECK_STR(proto_err_name(-32602), "INVALID_PARAMS");
  CHECK_STR(proto_err_name(-32005), "DEVICE");
  CHECK_STR(proto_err_name(0), NULL);
  CHECK_STR(proto_err_name(-32000), NULL);
  CHECK_STR(proto_err_message(-32700), "parse error");
  CHECK_STR(proto_err_message(-32600), "invalid request");
  CHECK_STR(proto_err_message(-32601), "method not found");
  CHECK_STR(proto_err_message(-32003), "limit exceeded");
  CHECK_STR(proto_err_message(-32001), "unauthorized");
  CHECK_STR(proto_err_message(42), "unknown error");

  /* Every code in the map has a name and a message of its own. */
#define XX(name, code, msg)                                                                        \
  CHECK_STR(proto_err_name(code), #name);                                                          \
  CHECK_STR(proto_err_message(code), msg);
  PROTO_ERROR_MAP(XX)
#undef XX
}

static void test_limits_and_formats(void) {
  proto_limits_t l;
  memset(&l, 0xAB, sizeof(l));
  proto_limits_default(&l);
  CHECK(l.line_bytes == 1048576);
  CHECK(l.frame_side == 4096);
  CHECK(l.particles == 1u << 20);
  CHECK(l.cloud_side == 256);
  CHECK(l.connections == 256);
  CHECK(l.output_bytes == (size_t)64 << 20);

  static const char *const names[] = {"png", "rgba8", "rgbaf32", "f32", "u8", "jpeg", "webp"};
  for (int f = 0; f < PROTO_FMT_COUNT; f++) {
    CHECK_STR(proto_format_name((proto_format_t)f), names[f]);
    CHECK(proto_format_parse(names[f]) == f);
  }
  CHECK(proto_format_parse("rgbaf32") == PROTO_FMT_RGBAF32);
  CHECK(proto_format_parse("PNG") == -1);
  CHECK(proto_format_parse("") == -1);
  CHECK(proto_format_parse("png ") == -1);
  CHECK(proto_format_parse(NULL) == -1);
  CHECK_STR(proto_format_name(PROTO_FMT_COUNT), NULL);
  CHECK_STR(proto_format_name((proto_format_t)-1), NULL);
}

/* ---------------------------------------------------------------------------------------------
 * The NDJSON reader.
 */

/* Takes every complete line out of 'r' and appends each, followed by '|', to 'acc'. Returns the
 * last status of proto_reader_line. */
static int drain(proto_reader_t *r, char *acc, size_t cap) {
  char *line;
  size_t len;
  int rc;
  while ((rc = proto_reader_line(r, &line, &len)) == PROTO_READ_OK) {
    CHECK(strlen(line) == len || memchr(line, '\0', len) != NULL);
    CHECK(line[len] == '\0');
    size_t used = strlen(acc);
    if (used + len + 2 <= cap) {
      memcpy(acc + used, line, len);
      acc[used + len] = '|';
      acc[used + len + 1] = '\0';
    }
  }
  return rc;
}

static void test_reader_byte_at_a_time(void) {
  static const char input[] = "{\"id\":1}\n\nabc\r\n{\"method\":\"x\"}\n\xc3\xa9\n";
  proto_reader_t r;
  char acc[256] = "";
  proto_reader_init(&r, 64);
  for (size_t i = 0; i < sizeof(input) - 1; i++) {
    CHECK(proto_reader_feed(&r, input + i, 1) == PROTO_READ_OK);
    CHECK(drain(&r, acc, sizeof(acc)) == PROTO_READ_MORE);
  }
  CHECK_STR(acc, "{\"id\":1}||abc|{\"method\":\"x\"}|\xc3\xa9|");
  CHECK(proto_reader_pending(&r) == 0);
  proto_reader_free(&r);
  CHECK(r.buf == NULL);
}

static void test_reader_many_in_one_feed(void) {
  enum { COUNT = 5000 };
  size_t cap = COUNT * 32;
  char *input = malloc(cap);
  size_t n = 0;
  for (int i = 0; i < COUNT; i++)
    n += (size_t)snprintf(input + n, cap - n, "{\"id\":%d}\n", i);

  proto_reader_t r;
  proto_reader_init(&r, 1024);
  CHECK(proto_reader_feed(&r, input, n) == PROTO_READ_OK);
  CHECK(proto_reader_pending(&r) == n);
  int seen = 0, in_order = 1;
  char *line;
  size_t len;
  char want[32];
  while (proto_reader_line(&r, &line, &len) == PROTO_READ_OK) {
    snprintf(want, sizeof(want), "{\"id\":%d}", seen);
    if (strcmp(line, want) != 0 || len != strlen(want))
      in_order = 0;
    seen++;
  }
  CHECK(seen == COUNT);
  CHECK(in_order);
  CHECK(proto_reader_pending(&r) == 0);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_MORE);
  proto_reader_free(&r);
  free(input);
}

static void test_reader_split_lines(void) {
  proto_reader_t r;
  char acc[256] = "";
  proto_reader_init(&r, 64);
  CHECK(proto_reader_feed(&r, "hel", 3) == PROTO_READ_OK);
  CHECK(drain(&r, acc, sizeof(acc)) == PROTO_READ_MORE);
  CHECK_STR(acc, "");
  CHECK(proto_reader_feed(&r, "lo\nwor", 6) == PROTO_READ_OK);
  CHECK(drain(&r, acc, sizeof(acc)) == PROTO_READ_MORE);
  CHECK_STR(acc, "hello|");
  CHECK(proto_reader_pending(&r) == 3);
  CHECK(proto_reader_feed(&r, "", 0) == PROTO_READ_OK);
  CHECK(proto_reader_feed(&r, "ld", 2) == PROTO_READ_OK);
  CHECK(proto_reader_feed(&r, "\n!", 2) == PROTO_READ_OK);
  CHECK(drain(&r, acc, sizeof(acc)) == PROTO_READ_MORE);
  CHECK_STR(acc, "hello|world|");
  CHECK(proto_reader_pending(&r) == 1);
  proto_reader_free(&r);
}

static void test_reader_crlf(void) {
  proto_reader_t r;
  char acc[256] = "";
  char *line;
  size_t len;
  proto_reader_init(&r, 64);
  CHECK(proto_reader_feed(&r, "abc\r\n\r\na\rb\n", 11) == PROTO_READ_OK);
  CHECK(drain(&r, acc, sizeof(acc)) == PROTO_READ_MORE);
  CHECK_STR(acc, "abc||a\rb|"); /* Only a '\r' right before the '\n' goes. */

  /* A '\r' and its '\n' in different feeds. */
  CHECK(proto_reader_feed(&r, "xy\r", 3) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_MORE);
  CHECK(proto_reader_feed(&r, "\n", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK(len == 2 && strcmp(line, "xy") == 0);

  /* "\r\r\n" loses one '\r' only. */
  CHECK(proto_reader_feed(&r, "z\r\r\n", 4) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK(len == 2 && memcmp(line, "z\r", 3) == 0);
  proto_reader_free(&r);
}

static void test_reader_oversize(void) {
  enum { MAX = 16 };
  char text[MAX + 8];
  memset(text, 'a', sizeof(text));
  proto_reader_t r;
  char *line;
  size_t len;

  /* Exactly the limit, then '\n': accepted. */
  proto_reader_init(&r, MAX);
  CHECK(proto_reader_feed(&r, text, MAX) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_MORE);
  CHECK(proto_reader_feed(&r, "\n", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK(len == MAX);
  /* Exactly the limit with "\r\n", the '\r' arriving alone: accepted. */
  CHECK(proto_reader_feed(&r, text, MAX) == PROTO_READ_OK);
  CHECK(proto_reader_feed(&r, "\r", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_MORE);
  CHECK(proto_reader_feed(&r, "\n", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK(len == MAX);
  /* One byte over, no '\n' yet: refused at once, and from then on. */
  CHECK(proto_reader_feed(&r, text, MAX + 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OVERSIZE);
  CHECK(proto_reader_feed(&r, "\n", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OVERSIZE);
  proto_reader_free(&r);

  /* The limit plus a '\r' that the next byte shows is not a line ending. */
  proto_reader_init(&r, MAX);
  CHECK(proto_reader_feed(&r, text, MAX) == PROTO_READ_OK);
  CHECK(proto_reader_feed(&r, "\r", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_MORE);
  CHECK(proto_reader_feed(&r, "x", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OVERSIZE);
  proto_reader_free(&r);

  /* An over-long line whose '\n' is already buffered, after a good line. */
  proto_reader_init(&r, MAX);
  CHECK(proto_reader_feed(&r, "ok\n", 3) == PROTO_READ_OK);
  CHECK(proto_reader_feed(&r, text, MAX + 1) == PROTO_READ_OK);
  CHECK(proto_reader_feed(&r, "\n", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK_STR(line, "ok");
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OVERSIZE);
  proto_reader_free(&r);

  /* The default limit, fed in 4 KiB pieces: no error up to the limit, an error on the byte
   * after it, long before any '\n'. */
  proto_limits_t l;
  proto_limits_default(&l);
  proto_reader_init(&r, l.line_bytes);
  char chunk[4096];
  memset(chunk, 'b', sizeof(chunk));
  size_t fed = 0;
  int early = 0;
  while (fed < l.line_bytes) {
    CHECK(proto_reader_feed(&r, chunk, sizeof(chunk)) == PROTO_READ_OK);
    fed += sizeof(chunk);
    if (proto_reader_line(&r, &line, &len) != PROTO_READ_MORE)
      early = 1;
  }
  CHECK(!early);
  CHECK(fed == l.line_bytes);
  CHECK(proto_reader_feed(&r, "b", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OVERSIZE);
  CHECK(r.cap <= 2 * l.line_bytes + 8192); /* Nothing beyond the limit was kept. */
  proto_reader_free(&r);

  /* A zero limit takes empty lines only. */
  proto_reader_init(&r, 0);
  CHECK(proto_reader_feed(&r, "\n\r\nx", 4) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK && len == 0);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK && len == 0);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OVERSIZE);
  proto_reader_free(&r);
}

static void test_reader_attachments(void) {
  static const char payload[10] = {'\n', 0, 'x', '\r', '\n', (char)0xFF, '{', '}', '\n', 7};
  char input[64];
  size_t n = 0;
  memcpy(input + n, "{\"attachment\":{\"bytes\":10}}\n", 28);
  n += 28;
  memcpy(input + n, payload, sizeof(payload));
  n += sizeof(payload);
  memcpy(input + n, "next\n", 5);
  n += 5;

  /* All at once. */
  proto_reader_t r;
  char *line;
  size_t len;
  const char *data;
  proto_reader_init(&r, 64);
  CHECK(proto_reader_feed(&r, input, n) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK_STR(line, "{\"attachment\":{\"bytes\":10}}");
  CHECK(proto_reader_bytes(&r, 10, &data) == PROTO_READ_OK);
  CHECK(memcmp(data, payload, 10) == 0);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK_STR(line, "next");
  CHECK(proto_reader_bytes(&r, 0, &data) == PROTO_READ_OK);
  CHECK(proto_reader_bytes(&r, 1, &data) == PROTO_READ_MORE);
  proto_reader_free(&r);

  /* One byte at a time. */
  proto_reader_init(&r, 64);
  int state = 0, got_payload = 0, got_next = 0;
  for (size_t i = 0; i < n; i++) {
    CHECK(proto_reader_feed(&r, input + i, 1) == PROTO_READ_OK);
    for (;;) {
      if (state == 1) {
        if (proto_reader_bytes(&r, 10, &data) != PROTO_READ_OK)
          break;
        got_payload = memcmp(data, payload, 10) == 0;
        state = 2;
      } else {
        if (proto_reader_line(&r, &line, &len) != PROTO_READ_OK)
          break;
        if (state == 0)
          state = 1;
        else
          got_next = strcmp(line, "next") == 0;
      }
    }
  }
  CHECK(got_payload);
  CHECK(got_next);
  CHECK(proto_reader_pending(&r) == 0);
  proto_reader_free(&r);

  /* A line scan that ran into bytes later taken as an attachment must not hide a later '\n'. */
  proto_reader_init(&r, 64);
  CHECK(proto_reader_feed(&r, "hdr\nabcdef", 10) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_MORE);
  CHECK(proto_reader_bytes(&r, 3, &data) == PROTO_READ_OK);
  CHECK(memcmp(data, "abc", 3) == 0);
  CHECK(proto_reader_feed(&r, "\n", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK_STR(line, "def");
  proto_reader_free(&r);

  /* An attachment far larger than the line limit. */
  enum { BIG = 300000 };
  char *big = malloc(BIG);
  for (size_t i = 0; i < BIG; i++)
    big[i] = (char)rng();
  proto_reader_init(&r, 64);
  CHECK(proto_reader_feed(&r, "h\n", 2) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  for (size_t off = 0; off < BIG; off += 7000) {
    size_t k = BIG - off < 7000 ? BIG - off : 7000;
    CHECK(proto_reader_bytes(&r, BIG, &data) == PROTO_READ_MORE);
    CHECK(proto_reader_feed(&r, big + off, k) == PROTO_READ_OK);
  }
  CHECK(proto_reader_bytes(&r, BIG, &data) == PROTO_READ_OK);
  CHECK(memcmp(data, big, BIG) == 0);
  /* Once it is taken, the large buffer is given back on the next feed. */
  CHECK(proto_reader_feed(&r, "t\n", 2) == PROTO_READ_OK);
  CHECK(r.cap < BIG);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK_STR(line, "t");
  proto_reader_free(&r);
  free(big);
}

static void test_reader_compaction(void) {
  /* Many lines in pieces that never line up with line ends: the buffer stays small because
   * taken bytes are reclaimed instead of the buffer growing. */
  proto_reader_t r;
  char text[1000];
  for (size_t i = 0; i < sizeof(text); i++)
    text[i] = (i % 100 == 99) ? '\n' : (char)('a' + i % 26);
  proto_reader_init(&r, 1024);
  size_t lines = 0, maxcap = 0;
  for (int round = 0; round < 2000; round++) {
    size_t k = 1 + rng() % sizeof(text);
    CHECK(proto_reader_feed(&r, text, k) == PROTO_READ_OK);
    char *line;
    size_t len;
    int rc;
    while ((rc = proto_reader_line(&r, &line, &len)) == PROTO_READ_OK)
      lines++;
    CHECK(rc == PROTO_READ_MORE);
    if (r.cap > maxcap)
      maxcap = r.cap;
  }
  CHECK(lines > 1000);
  CHECK(maxcap <= 8192);
  proto_reader_free(&r);

  /* A long line fed a byte at a time costs linear time, since no byte is scanned twice. A
   * rescanning reader would take some 10^11 steps here and time the test out. */
  enum { LONG = 512 * 1024 };
  proto_reader_init(&r, LONG);
  char *line;
  size_t len;
  int more = 1;
  for (size_t i = 0; i < LONG; i++) {
    proto_reader_feed(&r, "z", 1);
    more &= proto_reader_line(&r, &line, &len) == PROTO_READ_MORE;
  }
  CHECK(more);
  CHECK(proto_reader_feed(&r, "\n", 1) == PROTO_READ_OK);
  CHECK(proto_reader_line(&r, &line, &len) == PROTO_READ_OK);
  CHECK(len == LONG);
  proto_reader_free(&r);
}

/* ---------------------------------------------------------------------------------------------
 * UTF-8 and nesting.
 */

/* A reference validator written from the bit patterns of RFC 3629 rather than its table. */
static int ref_utf8_valid(const unsigned char *s, size_t n) {
  size_t i = 0;
  while (i < n) {
    unsigned c = s[i];
    size_t len;
    uint32_t cp, min;
    if (c < 0x80) {
      i++;
      continue;
    } else if ((c & 0xE0) == 0xC0) {
      len = 2, cp = c & 0x1F, min = 0x80;
    } else if ((c & 0xF0) == 0xE0) {
      len = 3, cp = c & 0x0F, min = 0x800;
    } else if ((c & 0xF8) == 0xF0) {
      len = 4, cp = c & 0x07, min = 0x10000;
    } else {
      return 0;
    }
    if (n - i < len)
      return 0;
    for (size_t k = 1; k < len; k++) {
      if ((s[i + k] & 0xC0) != 0x80)
        return 0;
      cp = cp << 6 | (s[i + k] & 0x3F);
    }
    if (cp < min || cp > 0x10FFFF || (cp >= 0xD800 && cp <= 0xDFFF))
      return 0;
    i += len;
  }
  return 1;
}

#define UTF8_OK(lit) CHECK(proto_utf8_valid(lit, sizeof(lit) - 1) == 1)
#define UTF8_BAD(lit) CHECK(proto_utf8_valid(lit, sizeof(lit) - 1) == 0)

static void test_utf8(void) {
  UTF8_OK("");
  UTF8_OK("plain ASCII text, long enough for the fast path");
  UTF8_OK("\xc3\xa9");                  /* é */
  UTF8_OK("\xe2\x82\xac");              /* € */
  UTF8_OK("\xf0\x9d\x84\x9e");          /* U+1D11E */
  UTF8_OK("\xf4\x8f\xbf\xbf");          /* U+10FFFF */
  UTF8_OK("\xed\x9f\xbf");              /* U+D7FF, just below the surrogates */
  UTF8_OK("\xee\x80\x80");              /* U+E000, just above them */
  UTF8_OK("\xef\xbf\xbf");              /* U+FFFF */
  UTF8_OK("\xc2\x80");                  /* U+0080, the smallest two-byte value */
  UTF8_OK("\xe0\xa0\x80");              /* U+0800 */
  UTF8_OK("\xf0\x90\x80\x80");          /* U+10000 */
  UTF8_OK("abcdefgh\xc3\xa9xyz");       /* A sequence right after an eight-byte block. */
  UTF8_BAD("\xc0\x80");                 /* Overlong NUL. */
  UTF8_BAD("\xc1\xbf");                 /* Overlong U+007F. */
  UTF8_BAD("\xe0\x80\x80");             /* Overlong three-byte. */
  UTF8_BAD("\xe0\x9f\xbf");             /* Overlong U+07FF. */
  UTF8_BAD("\xf0\x80\x80\x80");         /* Overlong four-byte. */
  UTF8_BAD("\xf0\x8f\xbf\xbf");         /* Overlong U+FFFF. */
  UTF8_BAD("\xed\xa0\x80");             /* U+D800, a surrogate. */
  UTF8_BAD("\xed\xbf\xbf");             /* U+DFFF. */
  UTF8_BAD("\xed\xa0\xbd\xed\xb2\xa9"); /* A CESU-8 surrogate pair. */
  UTF8_BAD("\xf4\x90\x80\x80");         /* U+110000. */
  UTF8_BAD("\xf5\x80\x80\x80");
  UTF8_BAD("\xff");
  UTF8_BAD("\xfe");
  UTF8_BAD("abc\xff");
  UTF8_BAD("\x80"); /* A lone continuation byte. */
  UTF8_BAD("\xc3"); /* Truncated. */
  UTF8_BAD("\xe2\x82");
  UTF8_BAD("\xf0\x9d\x84");
  UTF8_BAD("\xe2\x82"
           "A"); /* Cut short by an ASCII byte. */
  UTF8_BAD("\xc3\xa9\xc3");
  UTF8_BAD("0123456789abc\xff"
           "0123456789");

  /* A truncated sequence must be caught even when the byte after the given length would
   * complete it. */
  CHECK(proto_utf8_valid("\xc3\xa9", 1) == 0);

  /* Every string of one to three bytes, against the reference. */
  int agree = 1;
  unsigned char b[4];
  for (unsigned x = 0; x < 256; x++) {
    b[0] = (unsigned char)x;
    agree &= proto_utf8_valid((char *)b, 1) == ref_utf8_valid(b, 1);
    for (unsigned y = 0; y < 256; y++) {
      b[1] = (unsigned char)y;
      agree &= proto_utf8_valid((char *)b, 2) == ref_utf8_valid(b, 2);
      /* Three bytes only where the first two start a sequence, which keeps this fast. */
      if (x < 0xC0)
        continue;
      for (unsigned z = 0; z < 256; z++) {
        b[2] = (unsigned char)z;
        agree &= proto_utf8_valid((char *)b, 3) == ref_utf8_valid(b, 3);
      }
    }
  }
  CHECK(agree);

  /* Random four-byte strings leaning on the interesting lead bytes, and random longer text. */
  agree = 1;
  for (int i = 0; i < 200000; i++) {
    b[0] = (unsigned char)(0xE0 + rng() % 32);
    b[1] = (unsigned char)(0x70 + rng() % 0x60);
    b[2] = (unsigned char)(0x70 + rng() % 0x60);
    b[3] = (unsigned char)(0x70 + rng() % 0x60);
    agree &= proto_utf8_valid((char *)b, 4) == ref_utf8_valid(b, 4);
  }
  unsigned char text[40];
  for (int i = 0; i < 100000; i++) {
    size_t n = rng() % sizeof(text);
    for (size_t k = 0; k < n; k++)
      text[k] = (unsigned char)(rng() % 8 == 0 ? rng() : rng() % 128);
    agree &= proto_utf8_valid((char *)text, n) == ref_utf8_valid(text, n);
  }
  CHECK(agree);

  /* Scrubbing: valid text is left alone; any text comes out valid, with only bytes that were
   * not part of a well-formed sequence turned into '?'. */
  char fixed[] = "caf\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80";
  proto_utf8_scrub(fixed, sizeof(fixed) - 1);
  CHECK(strcmp(fixed, "caf\xc3\xa9 \xe2\x82\xac \xf0\x9f\x98\x80") == 0);
  char cut[] = "ab\xc3\xa9\xc3";
  proto_utf8_scrub(cut, sizeof(cut) - 1);
  CHECK(strcmp(cut, "ab\xc3\xa9?") == 0);
  char stray[] = "\x80x\xed\xa0\x80\xc0\xaf";
  proto_utf8_scrub(stray, sizeof(stray) - 1);
  CHECK(strcmp(stray, "?x?????") == 0);
  int scrubbed_ok = 1;
  for (int i = 0; i < 100000; i++) {
    unsigned char orig[40];
    size_t n = rng() % sizeof(text);
    for (size_t k = 0; k < n; k++)
      orig[k] = text[k] = (unsigned char)(rng() % 4 == 0 ? rng() : rng() % 128);
    proto_utf8_scrub((char *)text, n);
    scrubbed_ok &= ref_utf8_valid(text, n);
    for (size_t k = 0; k < n; k++)
      scrubbed_ok &= text[k] == orig[k] || (text[k] == '?' && orig[k] >= 0x80);
    if (ref_utf8_valid(orig, n))
      scrubbed_ok &= memcmp(text, orig, n) == 0;
  }
  CHECK(scrubbed_ok);
}

/* Writes 'depth' nested arrays around 'inner' into 'buf' (open brackets, inner, close). */
static size_t nested(char *buf, int depth, const char *open, const char *inner, const char *close) {
  size_t n = 0;
  for (int i = 0; i < depth; i++)
    n += (size_t)sprintf(buf + n, "%s", open);
  n += (size_t)sprintf(buf + n, "%s", inner);
  for (int i = 0; i < depth; i++)
    n += (size_t)sprintf(buf + n, "%s", close);
  return n;
}

static void test_depth(void) {
  char buf[4096], why[128];
  size_t n;
  cJSON *v;

  n = nested(buf, 64, "[", "", "]");
  CHECK(proto_json_depth_ok(buf, n, 64) == 1);
  v = proto_parse(buf, n, why, sizeof(why));
  CHECK(v != NULL);
  cJSON_Delete(v);

  n = nested(buf, 65, "[", "", "]");
  CHECK(proto_json_depth_ok(buf, n, 64) == 0);
  CHECK(proto_json_depth_ok(buf, n, 65) == 1);
  v = proto_parse(buf, n, why, sizeof(why));
  CHECK(v == NULL);
  CHECK_STR(why, "nesting deeper than 64");

  /* Objects count as well as arrays. */
  n = nested(buf, 64, "{\"a\":", "1", "}");
  v = proto_parse(buf, n, why, sizeof(why));
  CHECK(v != NULL);
  cJSON_Delete(v);
  n = nested(buf, 65, "{\"a\":[", "1", "]}");
  CHECK(proto_json_depth_ok(buf, n, 64) == 0);
  n = nested(buf, 32, "{\"a\":[", "1", "]}");
  CHECK(proto_json_depth_ok(buf, n, 64) == 1);

  /* Brackets in strings do not count, escaped quotes do not end strings, and an escaped
   * backslash does not escape the quote after it. */
  n = (size_t)sprintf(buf, "[\"%0200d\"]", 0);
  memset(buf + 2, '[', 200);
  CHECK(proto_json_depth_ok(buf, n, 2) == 1);
  v = proto_parse(buf, n, why, sizeof(why));
  CHECK(v != NULL);
  cJSON_Delete(v);
  static const char esc[] = "[\"\\\"[[[[{{{{\", 1]";
  CHECK(proto_json_depth_ok(esc, sizeof(esc) - 1, 1) == 1);
  static const char bs[] = "[\"\\\\\", [[1]]]";
  CHECK(proto_json_depth_ok(bs, sizeof(bs) - 1, 2) == 0);
  CHECK(proto_json_depth_ok(bs, sizeof(bs) - 1, 3) == 1);
  /* Closing brackets bring the depth back down. */
  static const char flat[] = "[[[1]],[[2]],[[3]]]";
  CHECK(proto_json_depth_ok(flat, sizeof(flat) - 1, 3) == 1);
  CHECK(proto_json_depth_ok(flat, sizeof(flat) - 1, 2) == 0);
}

/* ---------------------------------------------------------------------------------------------
 * Parsing and the envelope.
 */

/* Parses the string literal 'text' and returns the value (NULL on failure), leaving the reason
 * in 'why'. The bytes are copied into a buffer of exactly their size, so a parser that reads
 * past the given length is caught by AddressSanitizer. */
static cJSON *parse_exact(const char *text, size_t n, char *why, size_t whylen) {
  char *copy = malloc(n ? n : 1);
  memcpy(copy, text, n);
  why[0] = '\0';
  cJSON *v = proto_parse(copy, n, why, whylen);
  free(copy);
  return v;
}
#define PARSE(lit) parse_exact(lit, sizeof(lit) - 1, why, sizeof(why))

static void test_parse(void) {
  char why[128];
  cJSON *v;

  v = PARSE("{\"s\":\"\xc3\xa9\xe2\x82\xac\xf0\x9d\x84\x9e\",\"n\":[1,2.5,-3e2]}");
  CHECK(v != NULL);
  CHECK_STR(cJSON_GetStringValue(cJSON_GetObjectItem(v, "s")),
            "\xc3\xa9\xe2\x82\xac\xf0\x9d\x84\x9e");
  cJSON_Delete(v);

  v = PARSE("{\"s\":\"\xc0\x80\"}");
  CHECK(v == NULL);
  CHECK_STR(why, "invalid UTF-8");
  v = PARSE("{\"s\":\"\xed\xa0\x80\"}");
  CHECK(v == NULL);
  CHECK_STR(why, "invalid UTF-8");
  v = PARSE("{\"s\":\"\xe2\x82\"}");
  CHECK(v == NULL);
  CHECK_STR(why, "invalid UTF-8");
  v = PARSE("\xff");
  CHECK(v == NULL);
  CHECK_STR(why, "invalid UTF-8");

  /* Whitespace may follow the value; anything else is an error naming its offset. */
  v = PARSE("{\"a\":1} \t\r\n ");
  CHECK(v != NULL);
  cJSON_Delete(v);
  v = PARSE(" \t{\"a\":1}");
  CHECK(v != NULL);
  cJSON_Delete(v);
  v = PARSE("{} x");
  CHECK(v == NULL);
  CHECK_STR(why, "invalid JSON at byte 3: trailing characters");
  /* Leading zeros are not JSON, though cJSON alone would accept them; zeros after the
   * first digit, in fractions and in exponents are fine. */
  v = PARSE("{\"id\":01}");
  CHECK(v == NULL);
  CHECK_STR(why, "invalid JSON at byte 6: number with a leading zero");
  v = PARSE("[-00.5]");
  CHECK(v == NULL);
  v = PARSE("[0, -0, 10, 100.005, 1e05, 2E-007, 0.0, -0.01, \"01\"]");
  CHECK(v != NULL);
  cJSON_Delete(v);
  v = PARSE("{}{}");
  CHECK(v == NULL);
  CHECK_STR(why, "invalid JSON at byte 2: trailing characters");
  v = PARSE("1 2");
  CHECK(v == NULL);
  CHECK(strstr(why, "invalid JSON at byte 2") == why);
  v = PARSE("{\"a\":1}}");
  CHECK(v == NULL);
  CHECK(strstr(why, "invalid JSON at byte 7") == why);

  /* Not JSON at all. */
  v = PARSE("");
  CHECK(v == NULL);
  CHECK(strstr(why, "invalid JSON at byte 0") == why);
  v = PARSE("   ");
  CHECK(v == NULL);
  CHECK(strstr(why, "invalid JSON at byte ") == why);
  v = PARSE("{\"a\":}");
  CHECK(v == NULL);
  CHECK(strstr(why, "invalid JSON at byte ") == why);
  v = PARSE("{\"a\":1,}");
  CHECK(v == NULL);
  v = PARSE("{\"a\"");
  CHECK(v == NULL);
  v = PARSE("\"unterminated");
  CHECK(v == NULL);
  v = PARSE("\"ends in a backslash\\");
  CHECK(v == NULL);
  v = PARSE("[\"\\u12\"]");
  CHECK(v == NULL);
  v = PARSE("nul");
  CHECK(v == NULL);
  v = PARSE("tru");
  CHECK(v == NULL);
  v = PARSE("-");
  CHECK(v == NULL);

  /* Control characters: a raw NUL, a raw tab in a string, \u0000. */
  v = parse_exact("{}\0", 3, why, sizeof(why));
  CHECK(v == NULL);
  CHECK_STR(why, "invalid JSON at byte 2: control character");
  v = parse_exact("{\"a\":\"x\0y\"}", 11, why, sizeof(why));
  CHECK(v == NULL);
  CHECK_STR(why, "invalid JSON at byte 7: unescaped control character in string");
  v = PARSE("{\"a\":\"x\ty\"}");
  CHECK(v == NULL);
  v = PARSE("{\"a\":\x01 1}");
  CHECK(v == NULL);
  v = PARSE("{\"method\":\"auth\\u0000x\"}");
  CHECK(v == NULL);
  CHECK_STR(why, "invalid JSON at byte 15: \\u0000 in string");
  v = PARSE("{\"a\":\"\\\\u0000\"}"); /* An escaped backslash, then plain text. */
  CHECK(v != NULL);
  CHECK_STR(cJSON_GetStringValue(cJSON_GetObjectItem(v, "a")), "\\u0000");
  cJSON_Delete(v);
  v = PARSE("{\"a\":\"\\u00e9\\n\\t\"}");
  CHECK(v != NULL);
  CHECK_STR(cJSON_GetStringValue(cJSON_GetObjectItem(v, "a")), "\xc3\xa9\n\t");
  cJSON_Delete(v);

  /* A length shorter than the buffer: only the given bytes count. */
  v = proto_parse("{}garbage", 2, why, sizeof(why));
  CHECK(v != NULL);
  cJSON_Delete(v);
  /* No reason buffer at all. */
  CHECK(proto_parse("{", 1, NULL, 0) == NULL);
  /* A short reason buffer is truncated, not overrun. */
  char small[8];
  CHECK(proto_parse("{} x", 4, small, sizeof(small)) == NULL);
  CHECK_STR(small, "invalid");
}

/* Parses 'text' (which must be valid JSON) and runs proto_request_check on it. Returns its
 * result; 'req' and 'why' get its outputs and '*msg' the parsed value, which the caller frees. */
static int check_text(const char *text, cJSON **msg, proto_request_t *req, const char **why) {
  char pwhy[128];
  *msg = proto_parse(text, strlen(text), pwhy, sizeof(pwhy));
  if (*msg == NULL) {
    fprintf(stderr, "unexpected parse failure of %s: %s\n", text, pwhy);
    failures++;
    return -1;
  }
  *why = NULL;
  return proto_request_check(*msg, req, why);
}

/* Expects 'text' to be refused as an invalid request with a reason containing 'reason'. */
#define REFUSED(text, reason)                                                                      \
  do {                                                                                             \
    cJSON *msg_;                                                                                   \
    proto_request_t req_;                                                                          \
    const char *why_;                                                                              \
    CHECK(check_text(text, &msg_, &req_, &why_) == PROTO_E_INVALID_REQUEST);                       \
    CHECK(why_ != NULL && strstr(why_, reason) != NULL);                                           \
    cJSON_Delete(msg_);                                                                            \
  } while (0)

static void test_request_check(void) {
  cJSON *msg;
  proto_request_t req;
  const char *why;

  /* Good requests. */
  CHECK(check_text("{\"jsonrpc\":\"2.0\",\"method\":\"render\",\"params\":{\"width\":4},\"id\":1}",
                   &msg, &req, &why) == 0);
  CHECK(why == NULL);
  CHECK_STR(req.method, "render");
  CHECK(cJSON_IsObject(req.params));
  CHECK(cJSON_IsNumber(req.id) && req.id->valuedouble == 1);
  cJSON_Delete(msg);

  CHECK(check_text("{\"method\":\"a\",\"params\":[1,2],\"jsonrpc\":\"2.0\",\"id\":\"abc\"}", &msg,
                   &req, &why) == 0);
  CHECK(cJSON_IsArray(req.params));
  CHECK(cJSON_IsString(req.id));
  cJSON_Delete(msg);

  /* A notification: no id at all; and an explicit null id, which is not a notification. */
  CHECK(check_text("{\"jsonrpc\":\"2.0\",\"method\":\"stats\"}", &msg, &req, &why) == 0);
  CHECK(req.id == NULL && req.params == NULL);
  CHECK_STR(req.method, "stats");
  cJSON_Delete(msg);
  CHECK(check_text("{\"jsonrpc\":\"2.0\",\"method\":\"stats\",\"id\":null}", &msg, &req, &why) ==
        0);
  CHECK(cJSON_IsNull(req.id));
  cJSON_Delete(msg);
  CHECK(check_text("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"id\":1.5}", &msg, &req, &why) == 0);
  CHECK(cJSON_IsNumber(req.id) && req.id->valuedouble == 1.5);
  cJSON_Delete(msg);
  /* Unknown members are ignored. */
  CHECK(check_text("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"extra\":[]}", &msg, &req, &why) == 0);
  cJSON_Delete(msg);

  /* Not objects. */
  REFUSED("42", "not an object");
  REFUSED("[{\"jsonrpc\":\"2.0\",\"method\":\"x\"}]", "array");
  REFUSED("\"str\"", "string");
  REFUSED("null", "not an object");
  REFUSED("true", "not an object");
  CHECK(proto_request_check(NULL, &req, &why) == PROTO_E_INVALID_REQUEST && why != NULL);

  /* The envelope's members. */
  REFUSED("{\"method\":\"x\",\"id\":1}", "jsonrpc");
  REFUSED("{\"jsonrpc\":\"1.0\",\"method\":\"x\",\"id\":1}", "\"2.0\"");
  REFUSED("{\"jsonrpc\":2.0,\"method\":\"x\",\"id\":1}", "\"2.0\"");
  REFUSED("{\"jsonrpc\":\"2.0 \",\"method\":\"x\"}", "\"2.0\"");
  REFUSED("{\"JSONRPC\":\"2.0\",\"method\":\"x\"}", "jsonrpc");
  REFUSED("{\"jsonrpc\":\"2.0\",\"id\":1}", "method");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":5,\"id\":1}", "\"method\" must be a string");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":null}", "\"method\" must be a string");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"params\":3}", "params");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"params\":\"a\"}", "params");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"params\":null}", "params");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"id\":{}}", "id");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"id\":[1]}", "id");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"id\":true}", "id");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"id\":1e999}", "finite");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":\"a\",\"method\":\"b\"}", "duplicate member \"method\"");
  REFUSED("{\"jsonrpc\":\"2.0\",\"method\":\"a\",\"id\":1,\"id\":2}", "duplicate member \"id\"");

  /* A usable id is reported even when the request fails, so the error can echo it; an unusable
   * one is not. */
  CHECK(check_text("{\"jsonrpc\":\"2.0\",\"method\":3,\"id\":7}", &msg, &req, &why) ==
        PROTO_E_INVALID_REQUEST);
  CHECK(cJSON_IsNumber(req.id) && req.id->valuedouble == 7);
  cJSON_Delete(msg);
  CHECK(check_text("{\"id\":\"q\"}", &msg, &req, &why) == PROTO_E_INVALID_REQUEST);
  CHECK(cJSON_IsString(req.id));
  cJSON_Delete(msg);
  CHECK(check_text("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"id\":{\"a\":1}}", &msg, &req, &why) ==
        PROTO_E_INVALID_REQUEST);
  CHECK(req.id == NULL);
  cJSON_Delete(msg);
  CHECK(check_text("{\"jsonrpc\":\"2.0\",\"method\":\"x\",\"id\":1,\"id\":2}", &msg, &req, &why) ==
        PROTO_E_INVALID_REQUEST);
  CHECK(req.id == NULL);
  cJSON_Delete(msg);
}

/* ---------------------------------------------------------------------------------------------
 * Builders and printing.
 */

/* Prints 'msg' with proto_print_line, checks the framing, frees 'msg', and returns the text
 * without its '\n' in 'out'. */
static void print_into(cJSON *msg, char *out, size_t cap) {
  size_t len = 0;
  char *line = proto_print_line(msg, &len);
  cJSON_Delete(msg);
  out[0] = '\0';
  CHECK(line != NULL);
  if (line == NULL)
    return;
  CHECK(len == strlen(line));
  CHECK(len >= 1 && line[len - 1] == '\n');
  CHECK(memchr(line, '\n', len - 1) == NULL);
  CHECK(memchr(line, '\r', len) == NULL);
  if (len - 1 < cap) {
    memcpy(out, line, len - 1);
    out[len - 1] = '\0';
  }
  free(line);
}

static void test_builders(void) {
  char text[512];

  cJSON *params = cJSON_CreateObject();
  cJSON_AddNumberToObject(params, "width", 64);
  print_into(proto_make_request("render", params, 5), text, sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"id\":5,\"method\":\"render\",\"params\":{\"width\":64}}");
  print_into(proto_make_request("stats", NULL, 9007199254740992), text, sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"id\":9007199254740992,\"method\":\"stats\"}");
  print_into(proto_make_request("x", NULL, INT64_MAX), text, sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"id\":9223372036854775807,\"method\":\"x\"}");
  print_into(proto_make_request("x", NULL, -2147483648), text, sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"id\":-2147483648,\"method\":\"x\"}");
  CHECK(proto_make_request(NULL, cJSON_CreateObject(), 1) == NULL); /* Params freed: see ASan. */

  /* Number ids come back exactly as they were sent, even where cJSON would round them. */
  static const char *const ids[] = {"1",
                                    "-7",
                                    "1.5",
                                    "0.1",
                                    "0.30000000000000004",
                                    "1e300",
                                    "2147483648",
                                    "9007199254740993",
                                    "1234567890123456",
                                    "1.0000000000000002",
                                    "-0.5",
                                    "1e-7"};
  static const char *const echoed[] = {"1",
                                       "-7",
                                       "1.5",
                                       "0.1",
                                       "0.30000000000000004",
                                       "1e+300",
                                       "2147483648",
                                       "9007199254740992",
                                       "1234567890123456",
                                       "1.0000000000000002",
                                       "-0.5",
                                       "1e-07"};
  for (size_t i = 0; i < sizeof(ids) / sizeof(ids[0]); i++) {
    char req_text[128], want[160], why[128];
    snprintf(req_text, sizeof(req_text), "{\"jsonrpc\":\"2.0\",\"method\":\"m\",\"id\":%s}",
             ids[i]);
    cJSON *m = proto_parse(req_text, strlen(req_text), why, sizeof(why));
    proto_request_t rq;
    const char *reason;
    CHECK(m != NULL && proto_request_check(m, &rq, &reason) == 0);
    print_into(proto_make_result(rq.id, NULL), text, sizeof(text));
    snprintf(want, sizeof(want), "{\"jsonrpc\":\"2.0\",\"id\":%s,\"result\":null}", echoed[i]);
    CHECK_STR(text, want);
    cJSON *back = proto_parse(text, strlen(text), why, sizeof(why));
    CHECK(back != NULL && cJSON_GetObjectItem(back, "id")->valuedouble ==
                              cJSON_GetObjectItem(m, "id")->valuedouble);
    cJSON_Delete(back);
    cJSON_Delete(m);
  }

  params = cJSON_CreateObject();
  cJSON_AddNumberToObject(params, "frame", 3);
  print_into(proto_make_notification("frames", params), text, sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"method\":\"frames\",\"params\":{\"frame\":3}}");

  /* Results: ids are copied; a missing id or result is null. */
  cJSON *id = cJSON_CreateString("req-1");
  cJSON *result = cJSON_CreateObject();
  cJSON_AddStringToObject(result, "text", "two\nlines\r\u2028");
  cJSON_AddNumberToObject(result, "nan", NAN);
  print_into(proto_make_result(id, result), text, sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"id\":\"req-1\",\"result\":{\"text\":\"two\\nlines\\r"
                  "\xe2\x80\xa8\",\"nan\":null}}");
  CHECK_STR(cJSON_GetStringValue(id), "req-1"); /* Still the caller's. */
  cJSON_Delete(id);
  print_into(proto_make_result(NULL, NULL), text, sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"id\":null,\"result\":null}");
  cJSON *bad_id = cJSON_CreateArray();
  print_into(proto_make_result(bad_id, cJSON_CreateTrue()), text, sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"id\":null,\"result\":true}");
  cJSON_Delete(bad_id);

  /* Errors, with and without a path and a message. */
  id = cJSON_CreateNumber(12);
  print_into(proto_make_error(id, PROTO_E_INVALID_PARAMS, "width out of range", "width"), text,
             sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"id\":12,\"error\":{\"code\":-32602,\"message\":"
                  "\"width out of range\",\"data\":{\"path\":\"width\"}}}");
  print_into(proto_make_error(id, PROTO_E_METHOD_NOT_FOUND, NULL, NULL), text, sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"id\":12,\"error\":{\"code\":-32601,\"message\":"
                  "\"method not found\"}}");
  cJSON_Delete(id);
  print_into(proto_make_error(NULL, PROTO_E_LIMIT, NULL, NULL), text, sizeof(text));
  CHECK_STR(text, "{\"jsonrpc\":\"2.0\",\"id\":null,\"error\":{\"code\":-32003,\"message\":"
                  "\"limit exceeded\"}}");

  CHECK(proto_print_line(NULL, NULL) == NULL);

  /* Every number prints so that it reads back exactly, at any depth: cJSON alone gives 0.3 and
   * 9.00719925474099e+15 for these; 2.5 and 1e300 print as cJSON prints them. */
  cJSON *nums = cJSON_Parse("{\"t\":[0.30000000000000004,{\"s\":9007199254740991}],"
                            "\"a\":1796182484.5305502,\"b\":2.5,\"c\":1e300,\"d\":-3}");
  CHECK(nums != NULL);
  print_into(nums, text, sizeof(text));
  CHECK_STR(text, "{\"t\":[0.30000000000000004,{\"s\":9007199254740991}],"
                  "\"a\":1796182484.5305502,\"b\":2.5,\"c\":1e+300,\"d\":-3}");
  print_into(cJSON_CreateNumber(9007199254740991.0), text, sizeof(text));
  CHECK_STR(text, "9007199254740991"); /* A number alone, as the CLI prints one. */

  /* A request built here survives the trip through print, reader, parse and check. */
  params = cJSON_CreateObject();
  cJSON_AddStringToObject(params, "scene", "main \xc3\xa9");
  cJSON *req_msg = proto_make_request("scene.get", params, 77);
  size_t len;
  char *line = proto_print_line(req_msg, &len);
  cJSON_Delete(req_msg);
  proto_reader_t r;
  proto_reader_init(&r, 1024);
  CHECK(proto_reader_feed(&r, line, len) == PROTO_READ_OK);
  free(line);
  char *got;
  size_t got_len;
  CHECK(proto_reader_line(&r, &got, &got_len) == PROTO_READ_OK);
  char why[128];
  cJSON *back = proto_parse(got, got_len, why, sizeof(why));
  CHECK(back != NULL);
  proto_request_t req;
  const char *reason = NULL;
  CHECK(proto_request_check(back, &req, &reason) == 0);
  CHECK_STR(req.method, "scene.get");
  CHECK(req.id != NULL && req.id->valuedouble == 77);
  CHECK_STR(cJSON_GetStringValue(cJSON_GetObjectItem(req.params, "scene")), "main \xc3\xa9");
  cJSON_Delete(back);
  proto_reader_free(&r);
}

/* ---------------------------------------------------------------------------------------------
 * Base64.
 */

/* Decodes the string literal 'lit' into a buffer of exactly proto_b64_decoded_max bytes. */
static long decode_exact(const char *text, size_t n, unsigned char *out, size_t cap) {
  size_t max = proto_b64_decoded_max(n);
  unsigned char *buf = malloc(max ? max : 1);
  long got = proto_b64_decode(text, n, buf);
  if (got > 0 && (size_t)got <= cap)
    memcpy(out, buf, (size_t)got);
  free(buf);
  return got;
}
#define DECODE(lit) decode_exact(lit, sizeof(lit) - 1, out, sizeof(out))

static void test_base64(void) {
  static const struct {
    const char *plain, *encoded;
  } vectors[] = {{"", ""},
                 {"f", "Zg=="},
                 {"fo", "Zm8="},
                 {"foo", "Zm9v"},
                 {"foob", "Zm9vYg=="},
                 {"fooba", "Zm9vYmE="},
                 {"foobar", "Zm9vYmFy"}};
  char enc[256];
  unsigned char out[256];
  for (size_t i = 0; i < sizeof(vectors) / sizeof(vectors[0]); i++) {
    size_t n = strlen(vectors[i].plain);
    CHECK(proto_b64_encoded_len(n) == strlen(vectors[i].encoded));
    proto_b64_encode(vectors[i].plain, n, enc);
    CHECK_STR(enc, vectors[i].encoded);
    long got = decode_exact(vectors[i].encoded, strlen(vectors[i].encoded), out, sizeof(out));
    CHECK(got == (long)n);
    CHECK(got >= 0 && memcmp(out, vectors[i].plain, n) == 0);
  }
  unsigned char all[3] = {0xFB, 0xFF, 0xBF};
  proto_b64_encode(all, 3, enc);
  CHECK_STR(enc, "+/+/");

  /* Round trips of every length from 0 to 64, and of larger random buffers. */
  unsigned char src[4096], back[4096];
  char *text = malloc(proto_b64_encoded_len(sizeof(src)) + 1);
  int ok = 1;
  for (size_t n = 0; n <= 64; n++) {
    for (int rep = 0; rep < 20; rep++) {
      for (size_t k = 0; k < n; k++)
        src[k] = (unsigned char)rng();
      size_t elen = proto_b64_encoded_len(n);
      text[elen] = 'X';
      proto_b64_encode(src, n, text);
      ok &= text[elen] == '\0' && strlen(text) == elen && elen % 4 == 0;
      ok &= proto_b64_decoded_max(elen) >= n;
      long got = proto_b64_decode(text, elen, back);
      ok &= got == (long)n && memcmp(src, back, n) == 0;
    }
  }
  for (int rep = 0; rep < 50; rep++) {
    size_t n = rng() % sizeof(src);
    for (size_t k = 0; k < n; k++)
      src[k] = (unsigned char)rng();
    proto_b64_encode(src, n, text);
    long got = proto_b64_decode(text, strlen(text), back);
    ok &= got == (long)n && memcmp(src, back, n) == 0;
  }
  CHECK(ok);
  free(text);

  /* Refused: lengths, characters outside the alphabet (whitespace included), misplaced or
   * excess padding, and nonzero bits under the padding. */
  CHECK(DECODE("Zg=") == -1);
  CHECK(DECODE("Zg") == -1);
  CHECK(DECODE("Z") == -1);
  CHECK(DECODE("Zm9vY") == -1);
  CHECK(DECODE("Z===") == -1);
  CHECK(DECODE("====") == -1);
  CHECK(DECODE("=Zg=") == -1);
  CHECK(DECODE("Zm=v") == -1);
  CHECK(DECODE("Zg==Zg==") == -1);
  CHECK(DECODE("Zm9v====") == -1);
  CHECK(DECODE("Zh==") == -1);
  CHECK(DECODE("Zm9=") == -1);
  CHECK(DECODE("Zm9v Zm9v") == -1);
  CHECK(DECODE("Zm9v\n") == -1);
  CHECK(DECODE("Zm9vYmFy\r\n") == -1);
  CHECK(DECODE(" Zm9") == -1);
  CHECK(DECODE("Zm9-") == -1);
  CHECK(DECODE("Zm9_") == -1);
  CHECK(DECODE("Zm9.") == -1);
  CHECK(DECODE("Zm\xff"
               "v") == -1);
  CHECK(decode_exact("Zm\0v", 4, out, sizeof(out)) == -1);
  /* Accepted limits of the above. */
  CHECK(DECODE("Zg==") == 1 && out[0] == 'f');
  CHECK(DECODE("Zm8=") == 2);
  CHECK(DECODE("") == 0);

  /* Every byte value as a symbol in every position of a final group. */
  int agree = 1;
  for (int pos = 0; pos < 4; pos++) {
    for (int c = 0; c < 256; c++) {
      char g[4] = {'Q', 'U', 'J', 'D'}; /* "QUJD" is "ABC". */
      g[pos] = (char)c;
      /* Only the alphabet: even '=' in the last place fails, since "QUJ=" leaves the nonzero
       * low bits of 'J' under the padding. */
      int valid = (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') ||
                  c == '+' || c == '/';
      long got = decode_exact(g, 4, out, sizeof(out));
      agree &= (got == 3) == valid && (got == -1) == !valid;
    }
  }
  CHECK(agree);

  CHECK(proto_b64_encoded_len(0) == 0);
  CHECK(proto_b64_encoded_len(1) == 4);
  CHECK(proto_b64_encoded_len(3) == 4);
  CHECK(proto_b64_encoded_len(4) == 8);
  CHECK(proto_b64_decoded_max(0) == 0);
  CHECK(proto_b64_decoded_max(4) == 3);
  CHECK(proto_b64_decoded_max(8) == 6);
}

/* WebSocket messages as lines: breaks between tokens become spaces, breaks in strings 0x1f
 * (also right after a backslash, where a kept break would split the message in two), and the
 * state carries across fragments but not across messages. */
static void test_ws_text(void) {
  static const struct {
    const char *in, *out;
  } cases[] = {
      {"{\"a\":\n1}", "{\"a\": 1}"},  {"[1,\r\n2]", "[1,  2]"},
      {"\"x\ny\"", "\"x\x1fy\""},     {"\"x\\\ny\"", "\"x\\\x1fy\""},
      {"\"\\\"\n\"", "\"\\\"\x1f\""}, {"[\"a\", \n \"b\"]", "[\"a\",   \"b\"]"},
  };
  for (size_t k = 0; k < sizeof cases / sizeof cases[0]; k++) {
    size_t n = strlen(cases[k].in);
    /* Byte by byte, so that the state crosses every fragment boundary. */
    proto_ws_text_t st = {0};
    char out[64] = {0};
    for (size_t i = 0; i < n; i++)
      proto_ws_text_feed(&st, (const unsigned char *)cases[k].in + i, 1, out + i);
    proto_ws_text_end(&st);
    CHECK_STR(out, cases[k].out);
    CHECK(st.in_string == 0 && st.escaped == 0);
    char why[128];
    cJSON *v = proto_parse(out, n, why, sizeof why);
    CHECK((v != NULL) == (strchr(cases[k].out, 0x1f) == NULL));
    cJSON_Delete(v);
  }
  /* A message left inside a string does not carry into the next. */
  proto_ws_text_t st = {0};
  char out[8];
  proto_ws_text_feed(&st, (const unsigned char *)"\"ab", 3, out);
  proto_ws_text_end(&st);
  proto_ws_text_feed(&st, (const unsigned char *)"\n", 1, out);
  CHECK(out[0] == ' ');
}

int main(void) {
  test_errors();
  test_limits_and_formats();
  test_reader_byte_at_a_time();
  test_reader_many_in_one_feed();
  test_reader_split_lines();
  test_reader_crlf();
  test_reader_oversize();
  test_reader_attachments();
  test_reader_compaction();
  test_utf8();
  test_depth();
  test_parse();
  test_request_check();
  test_builders();
  test_base64();
  test_ws_text();

  printf("test_protocol: %d checks, %d failed\n", checks, failures);
  return failures == 0 ? 0 : 1;
}
