/*
 * Base64 of RFC 4648 §4 (standard alphabet, '=' padding), used for attachments sent inline as
 * "data" and for binary request params such as fluid.set_particles' positions. The decoder is
 * strict: the length must be a multiple of four, no whitespace or other byte outside the
 * alphabet is skipped, '=' may only end the text, and the bits a final symbol leaves unused must
 * be zero. Every byte string therefore has exactly one accepted encoding.
 */
#include <string.h>

#include "proto.h"

static const char alphabet[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

/* The value of each byte as a base64 symbol, or BAD, computed at compile time from the same
 * ranges as 'alphabet'. The cast keeps clang from warning about the arms not taken. */
#define BAD 0xFF
#define SYM(c)                                                                                     \
  (unsigned char)((c) >= 'A' && (c) <= 'Z'   ? (c) - 'A'                                           \
                  : (c) >= 'a' && (c) <= 'z' ? (c) - 'a' + 26                                      \
                  : (c) >= '0' && (c) <= '9' ? (c) - '0' + 52                                      \
                  : (c) == '+'               ? 62                                                  \
                  : (c) == '/'               ? 63                                                  \
                                             : BAD)
#define SYM4(c) SYM(c), SYM((c) + 1), SYM((c) + 2), SYM((c) + 3)
#define SYM16(c) SYM4(c), SYM4((c) + 4), SYM4((c) + 8), SYM4((c) + 12)
#define SYM64(c) SYM16(c), SYM16((c) + 16), SYM16((c) + 32), SYM16((c) + 48)
static const unsigned char symbol_value[256] = {SYM64(0), SYM64(64), SYM64(128), SYM64(192)};

/* Four characters for every started group of three bytes. 'n' must be below about 3/4 of
 * SIZE_MAX, which any buffer in memory is. */
size_t proto_b64_encoded_len(size_t n) {
  return n / 3 * 4 + (n % 3 != 0 ? 4 : 0);
}

void proto_b64_encode(const void *src, size_t n, char *dst) {
  const unsigned char *p = src;
  size_t i = 0;

  for (; n - i >= 3; i += 3) {
    uint32_t v = (uint32_t)p[i] << 16 | (uint32_t)p[i + 1] << 8 | p[i + 2];
    *dst++ = alphabet[v >> 18];
    *dst++ = alphabet[(v >> 12) & 63];
    *dst++ = alphabet[(v >> 6) & 63];
    *dst++ = alphabet[v & 63];
  }
  if (n - i == 1) {
    uint32_t v = (uint32_t)p[i] << 16;
    *dst++ = alphabet[v >> 18];
    *dst++ = alphabet[(v >> 12) & 63];
    *dst++ = '=';
    *dst++ = '=';
  } else if (n - i == 2) {
    uint32_t v = (uint32_t)p[i] << 16 | (uint32_t)p[i + 1] << 8;
    *dst++ = alphabet[v >> 18];
    *dst++ = alphabet[(v >> 12) & 63];
    *dst++ = alphabet[(v >> 6) & 63];
    *dst++ = '=';
  }
  *dst = '\0';
}

/* Three bytes for every four characters. proto_b64_decode refuses a length that is not a
 * multiple of four before writing anything, so no input makes it write more than this. */
size_t proto_b64_decoded_max(size_t n) {
  return n / 4 * 3;
}

/*
 * Decodes the 'n' characters at 'src' (no NUL needed) into 'dst', which has room for
 * proto_b64_decoded_max(n) bytes. Returns the number of bytes written, or -1 for a length that
 * is not a multiple of four, a byte outside the alphabet, misplaced or excess '=', or nonzero
 * unused bits before the padding. On -1, 'dst' may hold part of the output.
 */
long proto_b64_decode(const char *src, size_t n, void *dst) {
  const unsigned char *s = (const unsigned char *)src;
  unsigned char *out = dst;

  if (n % 4 != 0)
    return -1;
  if (n == 0)
    return 0;

  /* Every group but the last is four plain symbols. */
  size_t last = n - 4;
  for (size_t i = 0; i < last; i += 4) {
    unsigned a = symbol_value[s[i]], b = symbol_value[s[i + 1]];
    unsigned c = symbol_value[s[i + 2]], d = symbol_value[s[i + 3]];
    if ((a | b | c | d) > 63) /* Any BAD sets bits above the six of a symbol. */
      return -1;
    uint32_t v = (uint32_t)a << 18 | (uint32_t)b << 12 | (uint32_t)c << 6 | d;
    *out++ = (unsigned char)(v >> 16);
    *out++ = (unsigned char)(v >> 8);
    *out++ = (unsigned char)v;
  }

  /* The last group: "xxxx", "xxx=" or "xx==". */
  unsigned a = symbol_value[s[last]], b = symbol_value[s[last + 1]];
  if (a == BAD || b == BAD)
    return -1;
  uint32_t v = (uint32_t)a << 18 | (uint32_t)b << 12;
  if (s[last + 2] == '=') {
    if (s[last + 3] != '=' || (v & 0xFFFF) != 0)
      return -1;
    *out++ = (unsigned char)(v >> 16);
  } else {
    unsigned c = symbol_value[s[last + 2]];
    if (c == BAD)
      return -1;
    v |= (uint32_t)c << 6;
    if (s[last + 3] == '=') {
      if ((v & 0xFF) != 0)
        return -1;
      *out++ = (unsigned char)(v >> 16);
      *out++ = (unsigned char)(v >> 8);
    } else {
      unsigned d = symbol_value[s[last + 3]];
      if (d == BAD)
        return -1;
      v |= d;
      *out++ = (unsigned char)(v >> 16);
      *out++ = (unsigned char)(v >> 8);
      *out++ = (unsigned char)v;
    }
  }
  return (long)(out - (unsigned char *)dst);
}
