/*
 * The JSON-RPC 2.0 envelope: parsing one message with the checks the protocol adds to cJSON's
 * (strict UTF-8, a nesting bound, no trailing data, no raw control characters), checking the
 * members of a request, and building and printing requests, notifications, results and errors.
 * Every function here is pure: it allocates only what it returns and never logs.
 */
#include <inttypes.h>
#include <limits.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "proto.h"
#include "proto_error.h"

static int is_json_space(char c) {
  return c == ' ' || c == '\t' || c == '\n' || c == '\r';
}

/*
 * Finds what cJSON would let through but RFC 8259 or the server cannot take: a raw control
 * character (below 0x20) inside a string, one other than whitespace outside strings (cJSON
 * skips any of them as whitespace), or the escape \u0000, which would silently cut the string
 * short for every C consumer. Returns the offset of the first such byte and sets '*what', or
 * returns 'n' when there is none.
 */
/* 1 when the digit at 's[i]' (outside strings) is the first digit of a number's integer part,
 * rather than a later digit, a fraction digit or an exponent digit (where zeros may lead). */
static int starts_integer_part(const char *s, size_t i) {
  if (i == 0)
    return 1;
  char p = s[i - 1];
  if (p == '-')
    return !(i >= 2 && (s[i - 2] == 'e' || s[i - 2] == 'E'));
  return !((p >= '0' && p <= '9') || p == '.' || p == 'e' || p == 'E' || p == '+');
}

static size_t find_bad_byte(const char *s, size_t n, const char **what) {
  int in_string = 0;

  for (size_t i = 0; i < n; i++) {
    unsigned char c = (unsigned char)s[i];
    if (!in_string) {
      if (c == '"') {
        in_string = 1;
      } else if (c < 0x20 && !is_json_space((char)c)) {
        *what = "control character";
        return i;
      } else if (c == '0' && i + 1 < n && s[i + 1] >= '0' && s[i + 1] <= '9' &&
                 starts_integer_part(s, i)) {
        *what = "number with a leading zero"; /* cJSON would read 01 as 1. */
        return i;
      }
      continue;
    }
    if (c == '"') {
      in_string = 0;
    } else if (c < 0x20) {
      *what = "unescaped control character in string";
      return i;
    } else if (c == '\\' && i + 1 < n) {
      if (s[i + 1] == 'u' && n - i >= 6 && memcmp(s + i + 2, "0000", 4) == 0) {
        *what = "\\u0000 in string";
        return i;
      }
      i++; /* The escaped byte cannot end the string; cJSON checks the escape itself. */
    }
  }
  return n;
}

/*
 * Parses one message of 'n' bytes at 's' (no NUL needed). Returns the value, which the caller
 * frees with cJSON_Delete, or NULL with the reason written into 'whybuf' ('whylen' bytes, may
 * be NULL): "invalid UTF-8", "nesting deeper than 64" or "invalid JSON at byte N", the last
 * sometimes followed by ": " and what was found there. Whitespace may follow the value.
 */
cJSON *proto_parse(const char *s, size_t n, char *whybuf, size_t whylen) {
  if (!proto_utf8_valid(s, n)) {
    proto_error_format(whybuf, whylen, "invalid UTF-8");
    return NULL;
  }
  if (!proto_json_depth_ok(s, n, PROTO_MAX_DEPTH)) {
    proto_error_format(whybuf, whylen, "nesting deeper than %d", PROTO_MAX_DEPTH);
    return NULL;
  }
  const char *what = NULL;
  size_t bad = find_bad_byte(s, n, &what);
  if (bad < n) {
    proto_error_format(whybuf, whylen, "invalid JSON at byte %zu: %s", bad, what);
    return NULL;
  }

  const char *end = s;
  cJSON *v = n > 0 ? cJSON_ParseWithLengthOpts(s, n, &end, 0) : NULL;
  if (v == NULL) {
    size_t at = (end != NULL && end >= s && end <= s + n) ? (size_t)(end - s) : 0;
    proto_error_format(whybuf, whylen, "invalid JSON at byte %zu%s", at,
                       n == 0 ? ": empty message" : "");
    return NULL;
  }
  /* cJSON stops after the value; only whitespace may follow it. */
  size_t at = (size_t)(end - s);
  while (at < n && is_json_space(s[at]))
    at++;
  if (at < n) {
    cJSON_Delete(v);
    proto_error_format(whybuf, whylen, "invalid JSON at byte %zu: %s", at, "trailing characters");
    return NULL;
  }
  return v;
}

/* The reason given when a request is a JSON value other than an object. */
static const char *not_object_reason(const cJSON *msg) {
  if (cJSON_IsArray(msg))
    return "request is an array, not an object";
  if (cJSON_IsString(msg))
    return "request is a string, not an object";
  if (cJSON_IsNumber(msg))
    return "request is a number, not an object";
  if (cJSON_IsBool(msg))
    return "request is a boolean, not an object";
  if (cJSON_IsNull(msg))
    return "request is null, not an object";
  return "request is not an object";
}

/* The envelope's members, found in one walk over the object so that duplicates show. */
enum { M_JSONRPC, M_METHOD, M_PARAMS, M_ID, M_COUNT };
static const char *const member_names[M_COUNT] = {"jsonrpc", "method", "params", "id"};
static const char *const duplicate_reasons[M_COUNT] = {
    "duplicate member \"jsonrpc\"", "duplicate member \"method\"", "duplicate member \"params\"",
    "duplicate member \"id\""};

/*
 * Checks the envelope of the request 'msg'; see proto.h. Beyond the header's rules, an id that
 * is a number must be finite (cJSON reads 1e999 as infinity, which cannot be echoed), and each
 * of the four members may appear only once, so that the server and a proxy in front of it
 * cannot disagree about which one counts. Other members are ignored. On failure 'out->method'
 * and 'out->params' may hold what was checked before the failure.
 */
int proto_request_check(const cJSON *msg, proto_request_t *out, const char **why) {
  memset(out, 0, sizeof(*out));
  if (msg == NULL || !cJSON_IsObject(msg)) {
    *why = msg == NULL ? "no request" : not_object_reason(msg);
    return PROTO_E_INVALID_REQUEST;
  }

  const cJSON *m[M_COUNT] = {NULL};
  int duplicate = -1;
  for (const cJSON *c = msg->child; c != NULL; c = c->next) {
    if (c->string == NULL)
      continue;
    for (int k = 0; k < M_COUNT; k++) {
      if (strcmp(c->string, member_names[k]) != 0)
        continue;
      if (m[k] == NULL)
        m[k] = c;
      else if (duplicate < 0 || k == M_ID)
        duplicate = k; /* A duplicate id wins: it decides whether the error can echo one. */
      break;
    }
  }

  /* The id first, so that any later failure can still be answered with it. */
  if (duplicate == M_ID) {
    *why = duplicate_reasons[M_ID];
    return PROTO_E_INVALID_REQUEST;
  }
  const cJSON *id = m[M_ID];
  if (id != NULL) {
    if (cJSON_IsNumber(id)) {
      if (!isfinite(id->valuedouble)) {
        *why = "\"id\" must be a finite number";
        return PROTO_E_INVALID_REQUEST;
      }
    } else if (!cJSON_IsString(id) && !cJSON_IsNull(id)) {
      *why = "\"id\" must be a number, a string or null";
      return PROTO_E_INVALID_REQUEST;
    }
    out->id = id;
  }
  if (duplicate >= 0) {
    *why = duplicate_reasons[duplicate];
    return PROTO_E_INVALID_REQUEST;
  }

  const cJSON *version = m[M_JSONRPC];
  if (version == NULL) {
    *why = "missing \"jsonrpc\": \"2.0\"";
    return PROTO_E_INVALID_REQUEST;
  }
  if (!cJSON_IsString(version) || strcmp(version->valuestring, "2.0") != 0) {
    *why = "\"jsonrpc\" must be \"2.0\"";
    return PROTO_E_INVALID_REQUEST;
  }

  const cJSON *method = m[M_METHOD];
  if (method == NULL) {
    *why = "missing \"method\"";
    return PROTO_E_INVALID_REQUEST;
  }
  if (!cJSON_IsString(method)) {
    *why = "\"method\" must be a string";
    return PROTO_E_INVALID_REQUEST;
  }
  out->method = method->valuestring;

  const cJSON *params = m[M_PARAMS];
  if (params != NULL && !cJSON_IsObject(params) && !cJSON_IsArray(params)) {
    *why = "\"params\" must be an object or an array";
    return PROTO_E_INVALID_REQUEST;
  }
  out->params = params;
  return 0;
}

/* Adds 'item' to 'obj' under the string literal 'key'. Returns 0, or -1 when 'item' is NULL
 * (a failed allocation upstream). */
static int add(cJSON *obj, const char *key, cJSON *item) {
  if (item == NULL)
    return -1;
  if (!cJSON_AddItemToObjectCS(obj, key, item)) {
    cJSON_Delete(item);
    return -1;
  }
  return 0;
}

/* A new message holding only "jsonrpc": "2.0", or NULL when out of memory. */
static cJSON *envelope(void) {
  cJSON *msg = cJSON_CreateObject();
  if (msg != NULL && add(msg, "jsonrpc", cJSON_CreateString("2.0")) != 0) {
    cJSON_Delete(msg);
    return NULL;
  }
  return msg;
}

/* 1 when 'text' is made only of characters a JSON number may hold, which is false when a
 * locale other than "C" gave printf a decimal comma. */
static int is_number_text(const char *text) {
  return text[0] != '\0' && strspn(text, "0123456789+-.eE") == strlen(text);
}

/*
 * A JSON number that prints as exactly 'd'. cJSON prints integers that fit an int exactly, and
 * anything else with 15 significant digits whenever those come within a relative DBL_EPSILON
 * of the value, so an id such as 9007199254740993 or 0.30000000000000004 would come back
 * changed, and a client would not recognise its response. Such values become a raw item holding
 * the shortest text that reads back as 'd' (cJSON_IsRaw, not cJSON_IsNumber). NaN and the
 * infinities, which JSON cannot hold, become null.
 */
static cJSON *number_exact(double d) {
  char text[32];

  if (!isfinite(d))
    return cJSON_CreateNull();
  if (d >= INT_MIN && d <= INT_MAX && d == (double)(int)d)
    return cJSON_CreateNumber(d);
  for (int digits = 15; digits <= 17; digits++) {
    snprintf(text, sizeof(text), "%1.*g", digits, d);
    if (strtod(text, NULL) == d)
      break;
  }
  if (strtod(text, NULL) != d || !is_number_text(text))
    return cJSON_CreateNumber(d); /* Cannot happen in the C locale; better close than invalid. */
  char cjson_text[32];
  snprintf(cjson_text, sizeof(cjson_text), "%1.15g", d);
  if (strcmp(text, cjson_text) == 0)
    return cJSON_CreateNumber(d); /* cJSON will print the same text. */
  return cJSON_CreateRaw(text);
}

/* A copy of the request id 'id' for a response: strings are copied, numbers are copied so that
 * they print exactly as received (see number_exact), and anything else (NULL, null, or a value
 * a request may not use as an id) becomes null. */
static cJSON *copy_id(const cJSON *id) {
  if (id != NULL && cJSON_IsString(id))
    return cJSON_CreateString(id->valuestring);
  if (id != NULL && cJSON_IsNumber(id))
    return number_exact(id->valuedouble);
  if (id != NULL && cJSON_IsRaw(id) && id->valuestring != NULL && is_number_text(id->valuestring))
    return cJSON_CreateRaw(id->valuestring); /* An id that number_exact made earlier. */
  return cJSON_CreateNull();
}

/* A JSON number for the integer 'id', printed with all its digits (see number_exact); beyond
 * 2^53, where a double cannot hold every integer, a raw item with the decimal digits. */
static cJSON *int_exact(int64_t id) {
  const int64_t exact = INT64_C(1) << 53;
  if (id >= -exact && id <= exact)
    return number_exact((double)id);
  char text[32];
  snprintf(text, sizeof(text), "%" PRId64, id);
  return cJSON_CreateRaw(text);
}

/*
 * Builds {"jsonrpc": "2.0", "id": 'id', "method": 'method', "params": 'params'}, without
 * "params" when it is NULL, or a notification (no "id") when 'with_id' is 0. 'params' is taken
 * even when this fails. Returns NULL when out of memory or when 'method' is NULL.
 */
static cJSON *make_call(const char *method, cJSON *params, int with_id, int64_t id) {
  cJSON *msg = method != NULL ? envelope() : NULL;
  if (msg == NULL)
    goto fail;
  if (with_id && add(msg, "id", int_exact(id)) != 0)
    goto fail;
  if (add(msg, "method", cJSON_CreateString(method)) != 0)
    goto fail;
  if (params != NULL && add(msg, "params", params) != 0) {
    params = NULL; /* add() freed it. */
    goto fail;
  }
  return msg;

fail:
  cJSON_Delete(params);
  cJSON_Delete(msg);
  return NULL;
}

/* A request with the numeric 'id', printed with all its digits. A peer that reads numbers as
 * doubles sees ids beyond 2^53 rounded, so clients should count from 1. */
cJSON *proto_make_request(const char *method, cJSON *params, int64_t id) {
  return make_call(method, params, 1, id);
}

cJSON *proto_make_notification(const char *method, cJSON *params) {
  return make_call(method, params, 0, 0);
}

/*
 * Builds {"jsonrpc": "2.0", "id": 'id', "result": 'result'}. 'result' is taken, even when this
 * fails; NULL gives "result": null. Returns NULL when out of memory.
 */
cJSON *proto_make_result(const cJSON *id, cJSON *result) {
  cJSON *msg = envelope();
  if (msg == NULL || add(msg, "id", copy_id(id)) != 0) {
    cJSON_Delete(result);
    cJSON_Delete(msg);
    return NULL;
  }
  if (add(msg, "result", result != NULL ? result : cJSON_CreateNull()) != 0) {
    cJSON_Delete(msg); /* add() freed 'result'. */
    return NULL;
  }
  return msg;
}

/*
 * Builds {"jsonrpc": "2.0", "id": 'id', "error": {"code": 'code', "message": 'message',
 * "data": {"path": 'path'}}}. A NULL 'message' gives the code's default message; a NULL 'path'
 * leaves "data" out. Returns NULL when out of memory.
 */
cJSON *proto_make_error(const cJSON *id, int code, const char *message, const char *path) {
  cJSON *msg = envelope();
  cJSON *err = cJSON_CreateObject();
  if (msg == NULL || err == NULL)
    goto fail;
  if (add(err, "code", cJSON_CreateNumber(code)) != 0)
    goto fail;
  if (add(err, "message",
          cJSON_CreateString(message != NULL ? message : proto_err_message(code))) != 0)
    goto fail;
  if (path != NULL) {
    cJSON *data = cJSON_CreateObject();
    if (data == NULL || add(data, "path", cJSON_CreateString(path)) != 0 ||
        !cJSON_AddItemToObjectCS(err, "data", data)) {
      cJSON_Delete(data);
      goto fail;
    }
  }
  if (add(msg, "id", copy_id(id)) != 0)
    goto fail;
  if (!cJSON_AddItemToObjectCS(msg, "error", err))
    goto fail;
  return msg;

fail:
  cJSON_Delete(err);
  cJSON_Delete(msg);
  return NULL;
}

/*
 * Prints 'msg' without whitespace, followed by one '\n'; cJSON escapes every control character
 * inside strings, so the line holds no other newline. The result is NUL-terminated, '*len'
 * (may be NULL) gets its length including the '\n', and the caller frees it with free(). The
 * copy out of cJSON's buffer keeps that true even when cJSON has been given other allocation
 * hooks. Returns NULL when out of memory or when 'msg' is NULL.
 */
/* Whether cJSON prints the number 'd' so that it reads back as 'd' (see number_exact). */
static int prints_exactly(double d) {
  if (!isfinite(d) || (d >= INT_MIN && d <= INT_MAX && d == (double)(int)d))
    return 1;
  char text[32];
  snprintf(text, sizeof(text), "%1.15g", d);
  return strtod(text, NULL) == d;
}

/* Whether 'v' or anything under it is a number that cJSON would print changed. */
static int needs_exact(const cJSON *v) {
  if (cJSON_IsNumber(v))
    return !prints_exactly(v->valuedouble);
  for (const cJSON *c = (cJSON_IsArray(v) || cJSON_IsObject(v)) ? v->child : NULL; c; c = c->next)
    if (needs_exact(c))
      return 1;
  return 0;
}

/*
 * A copy of 'v' to print, whose numbers print exactly (number_exact). Strings are referenced,
 * not copied, so that a message carrying megabytes of base64 costs only its small nodes.
 * NULL when out of memory.
 */
static cJSON *exact_copy(const cJSON *v) {
  if (cJSON_IsNumber(v))
    return number_exact(v->valuedouble);
  if (cJSON_IsString(v))
    return cJSON_CreateStringReference(v->valuestring);
  if (!cJSON_IsArray(v) && !cJSON_IsObject(v))
    return cJSON_Duplicate(v, 0);
  cJSON *out = cJSON_IsArray(v) ? cJSON_CreateArray() : cJSON_CreateObject();
  for (const cJSON *c = v->child; out != NULL && c != NULL; c = c->next) {
    cJSON *item = exact_copy(c);
    if (item == NULL || (cJSON_IsArray(v) ? !cJSON_AddItemToArray(out, item)
                                          : !cJSON_AddItemToObject(out, c->string, item))) {
      cJSON_Delete(item);
      cJSON_Delete(out);
      out = NULL;
    }
  }
  return out;
}

char *proto_print_line(const cJSON *msg, size_t *len) {
  if (msg == NULL)
    return NULL;
  /* Numbers are printed so that they read back exactly: an echoed 't', a document's
   * 0.30000000000000004 or a seed of 2^53 - 1 come back as sent. Only a message that holds
   * such a number is copied for it, its strings by reference. */
  cJSON *copy = NULL;
  if (needs_exact(msg)) {
    if ((copy = exact_copy(msg)) == NULL)
      return NULL;
    msg = copy;
  }
  char *text = cJSON_PrintUnformatted(msg);
  cJSON_Delete(copy);
  if (text == NULL)
    return NULL;
  size_t n = strlen(text);
  char *line = malloc(n + 2);
  if (line != NULL) {
    memcpy(line, text, n);
    /* Bytes >= 0x80 occur only inside strings, where '?' keeps the JSON what it was. */
    if (!proto_utf8_valid(line, n))
      proto_utf8_scrub(line, n);
    line[n] = '\n';
    line[n + 1] = '\0';
    if (len != NULL)
      *len = n + 1;
  }
  cJSON_free(text);
  return line;
}
