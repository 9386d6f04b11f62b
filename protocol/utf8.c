/*
 * Byte-level checks run on every message before the JSON parser sees it: strict UTF-8
 * validation (RFC 3629) and a bound on how deeply arrays and objects nest, so that a hostile
 * line can neither smuggle malformed text into the server nor make the recursive parser dig
 * deep. Both are single linear passes with no allocation.
 */
#include <string.h>

#include "proto.h"

/*
 * The length of the well-formed UTF-8 sequence that starts 'p' ('left' bytes available, at
 * least one), or 0 when none does: the sequence must be the shortest encoding of its code
 * point, no UTF-16 surrogate (U+D800-U+DFFF) and not above U+10FFFF.
 */
static size_t seq_len(const unsigned char *p, size_t left) {
  unsigned char c = p[0];
  if (c < 0x80)
    return 1;
  /* The table of RFC 3629 §4: the lead byte fixes the length and the range of the first
   * continuation byte, which is where overlongs, surrogates and values past U+10FFFF show. */
  size_t len;
  unsigned char lo = 0x80, hi = 0xBF;
  if (c >= 0xC2 && c <= 0xDF) {
    len = 2;
  } else if (c == 0xE0) {
    len = 3;
    lo = 0xA0;
  } else if (c == 0xED) {
    len = 3;
    hi = 0x9F;
  } else if (c >= 0xE1 && c <= 0xEF) {
    len = 3;
  } else if (c == 0xF0) {
    len = 4;
    lo = 0x90;
  } else if (c == 0xF4) {
    len = 4;
    hi = 0x8F;
  } else if (c >= 0xF1 && c <= 0xF3) {
    len = 4;
  } else {
    return 0; /* A stray continuation byte, an overlong lead C0/C1, or F5-FF. */
  }
  if (left < len || p[1] < lo || p[1] > hi)
    return 0;
  for (size_t k = 2; k < len; k++) {
    if ((p[k] & 0xC0) != 0x80)
      return 0;
  }
  return len;
}

/*
 * 1 when the 'n' bytes at 's' are well-formed UTF-8 (see seq_len) and the text does not end
 * inside a sequence. NUL bytes are valid UTF-8 and are accepted.
 */
int proto_utf8_valid(const char *s, size_t n) {
  const unsigned char *p = (const unsigned char *)s;
  size_t i = 0;

  while (i < n) {
    /* Most protocol text is ASCII: skip it eight bytes at a time. */
    while (n - i >= 8) {
      uint64_t w;
      memcpy(&w, p + i, sizeof(w));
      if (w & UINT64_C(0x8080808080808080))
        break;
      i += 8;
    }
    if (i == n)
      break;
    size_t len = seq_len(p + i, n - i);
    if (len == 0)
      return 0;
    i += len;
  }
  return 1;
}

void proto_utf8_scrub(char *s, size_t n) {
  unsigned char *p = (unsigned char *)s;
  for (size_t i = 0; i < n;) {
    size_t len = seq_len(p + i, n - i);
    if (len == 0) {
      p[i] = '?';
      len = 1;
    }
    i += len;
  }
}

/*
 * 1 when no array or object in the JSON text at 's' ('n' bytes) lies deeper than 'max_depth'
 * levels: "[[]]" has depth 2. Brackets inside strings do not count; a backslash inside a string
 * escapes the byte after it, so "\"" does not end the string. The text is not otherwise
 * validated: unbalanced brackets are left for the parser to refuse.
 */
int proto_json_depth_ok(const char *s, size_t n, int max_depth) {
  int depth = 0;
  int in_string = 0;

  for (size_t i = 0; i < n; i++) {
    char c = s[i];
    if (in_string) {
      if (c == '\\')
        i++;
      else if (c == '"')
        in_string = 0;
      continue;
    }
    switch (c) {
    case '"':
      in_string = 1;
      break;
    case '[':
    case '{':
      if (++depth > max_depth)
        return 0;
      break;
    case ']':
    case '}':
      if (depth > 0)
        depth--;
      break;
    default:
      break;
    }
  }
  return 1;
}
