/*
 * The volfx wire protocol, shared by volfxd and its clients: NDJSON framing with a line
 * limit, the JSON-RPC 2.0 envelope, error codes, limits, attachment formats and base64.
 * This library never logs and never touches sockets; it turns bytes into messages and back.
 */
#ifndef VOLFX_PROTO_H
#define VOLFX_PROTO_H

#include <stddef.h>
#include <stdint.h>

#include <cjson/cJSON.h>

#define PROTO_VERSION "1"
#define PROTO_DEFAULT_HOST "127.0.0.1"
#define PROTO_DEFAULT_PORT 7878
#define PROTO_MAX_DEPTH 64 /* Deepest JSON nesting accepted in one message. */

/* Error codes of SPEC §3: JSON-RPC's own, then volfx's. */
#define PROTO_ERROR_MAP(XX)                                                                        \
  XX(PARSE, -32700, "parse error")                                                                 \
  XX(INVALID_REQUEST, -32600, "invalid request")                                                   \
  XX(METHOD_NOT_FOUND, -32601, "method not found")                                                 \
  XX(INVALID_PARAMS, -32602, "invalid params")                                                     \
  XX(INTERNAL, -32603, "internal error")                                                           \
  XX(UNAUTHORIZED, -32001, "unauthorized")                                                         \
  XX(BUSY, -32002, "busy")                                                                         \
  XX(LIMIT, -32003, "limit exceeded")                                                              \
  XX(NOT_FOUND, -32004, "not found")                                                               \
  XX(DEVICE, -32005, "device error")

typedef enum {
#define XX(name, code, msg) PROTO_E_##name = code,
  PROTO_ERROR_MAP(XX)
#undef XX
} proto_errcode_t;

/* The default message of an error code, or "unknown error". */
const char *proto_err_message(int code);
/* The symbolic name of an error code ("INVALID_PARAMS"), or NULL. */
const char *proto_err_name(int code);

/* Limits of SPEC §3, configurable in volfxd and reported by server.info. */
typedef struct proto_limits {
  size_t line_bytes;    /* Longest request line, without its '\n'. */
  uint32_t frame_side;  /* Largest width or height of a frame. */
  uint32_t particles;   /* Most fluid particles per scene. */
  uint32_t cloud_side;  /* Largest cloud grid side. */
  uint32_t connections; /* Most open connections. */
  size_t output_bytes;  /* Most bytes queued for writing on one connection. */
} proto_limits_t;

void proto_limits_default(proto_limits_t *l);

/* Attachment formats (SPEC §3): X(ID, wire name) gives PROTO_FMT_<ID>. A frame format also has
 * an entry in the renderer's format table (render/render_format.c). */
#define PROTO_FORMATS(X)                                                                           \
  X(PNG, "png")         /* 8-bit RGBA PNG file. */                                                 \
  X(RGBA8, "rgba8")     /* Raw 8-bit RGBA, rows top to bottom. */                                  \
  X(RGBAF32, "rgbaf32") /* Raw linear float RGBA before tone mapping, little-endian. */            \
  X(F32, "f32")         /* One little-endian float per pixel or element. */                        \
  X(U8, "u8")           /* One byte per element. */                                                \
  X(JPEG, "jpeg")       /* 8-bit RGB JPEG file (no alpha). */                                      \
  X(WEBP, "webp")       /* 8-bit RGBA WebP file, lossy or lossless. */

#define PROTO_FORMAT_ENUM(id, name) PROTO_FMT_##id,
typedef enum { PROTO_FORMATS(PROTO_FORMAT_ENUM) PROTO_FMT_COUNT } proto_format_t;

/* "png", "rgba8", ... ; NULL for an out-of-range value. */
const char *proto_format_name(proto_format_t f);
/* The format named 's', or -1. */
int proto_format_parse(const char *s);

/*
 * NDJSON reader. Bytes are fed in as they arrive; complete lines and attachment payloads are
 * taken out in order. A line longer than 'max_line' bytes (not counting '\n') is an error that
 * the reader reports as soon as it is certain, without buffering the rest of the line.
 */
typedef struct proto_reader {
  char *buf;       /* Buffered bytes: [start, len) are unread. */
  size_t start;    /* First unread byte. */
  size_t len;      /* End of the buffered bytes. */
  size_t cap;      /* Allocated size of 'buf'. */
  size_t scanned;  /* Bytes after 'start' already known to hold no '\n'. */
  size_t max_line; /* Line limit. */
} proto_reader_t;

enum {
  PROTO_READ_MORE = 0,      /* Nothing complete yet: feed more bytes. */
  PROTO_READ_OK = 1,        /* A line or payload was returned. */
  PROTO_READ_OVERSIZE = -1, /* The pending line is over the limit; the stream is unusable. */
  PROTO_READ_NOMEM = -2
};

void proto_reader_init(proto_reader_t *r, size_t max_line);
void proto_reader_free(proto_reader_t *r);
/* Appends 'n' bytes. Returns PROTO_READ_OK or PROTO_READ_NOMEM. */
int proto_reader_feed(proto_reader_t *r, const void *data, size_t n);
/*
 * Takes the next line. On PROTO_READ_OK '*line' points at it inside the reader's buffer,
 * NUL-terminated in place of the '\n' (a '\r' before it is removed too), valid until the next
 * feed. Returns PROTO_READ_MORE, PROTO_READ_OK or PROTO_READ_OVERSIZE.
 */
int proto_reader_line(proto_reader_t *r, char **line, size_t *len);
/*
 * Takes the next 'n' raw bytes (an attachment). On PROTO_READ_OK '*data' is valid until the
 * next feed. Returns PROTO_READ_MORE or PROTO_READ_OK.
 */
int proto_reader_bytes(proto_reader_t *r, size_t n, const char **data);
/* Bytes buffered and not yet taken. */
size_t proto_reader_pending(const proto_reader_t *r);

/* 1 when 's' is well-formed UTF-8 (no overlongs, no surrogates, nothing above U+10FFFF). */
int proto_utf8_valid(const char *s, size_t n);
/*
 * Makes the 'n' bytes at 's' well-formed UTF-8 in place: each byte that does not start a
 * well-formed sequence becomes '?'. Text the server writes passes through it when it is not
 * valid already, so a message that quotes a client's string cut short by a size limit (in the
 * middle of a character) still reaches the client as UTF-8.
 */
void proto_utf8_scrub(char *s, size_t n);
/* 1 when the JSON text nests arrays/objects no deeper than 'max_depth' (strings skipped). */
int proto_json_depth_ok(const char *s, size_t n, int max_depth);

/*
 * Parses one message. Checks UTF-8 and nesting depth first. Returns the value or NULL with
 * 'whybuf' holding a description ("invalid UTF-8", "nesting deeper than 64", "invalid
 * JSON at byte 17" written into 'whybuf').
 */
cJSON *proto_parse(const char *s, size_t n, char *whybuf, size_t whylen);

/* A checked JSON-RPC 2.0 request. Pointers are borrowed from the message. */
typedef struct proto_request {
  const cJSON *id;     /* NULL for a notification (no "id" member). */
  const char *method;  /* Never NULL after a successful check. */
  const cJSON *params; /* NULL when absent; otherwise an object or an array. */
} proto_request_t;

/*
 * Checks the envelope of one request: an object with "jsonrpc": "2.0", a string "method",
 * "params" absent or an object/array, "id" absent, null, a number or a string. Returns 0, or
 * PROTO_E_INVALID_REQUEST with a static reason in '*why'. 'out->id' is set whenever the id is
 * usable, even on failure, so the error can echo it.
 */
int proto_request_check(const cJSON *msg, proto_request_t *out, const char **why);

/* Builders. Arguments marked 'taken' become part of the returned message. */
cJSON *proto_make_request(const char *method, cJSON *params /* taken, may be NULL */, int64_t id);
cJSON *proto_make_notification(const char *method, cJSON *params /* taken */);
cJSON *proto_make_result(const cJSON *id /* copied; NULL means null */, cJSON *result /* taken */);
/* An error response; 'path' (may be NULL) becomes "data": {"path": path}. */
cJSON *proto_make_error(const cJSON *id, int code, const char *message, const char *path);

/* Prints 'msg' compactly followed by '\n'. The caller frees the result with free(). */
char *proto_print_line(const cJSON *msg, size_t *len);

/* Base64 (RFC 4648, with padding). */
size_t proto_b64_encoded_len(size_t n); /* Without the NUL. */
/* Writes proto_b64_encoded_len(n) characters and a NUL into 'dst'. */
void proto_b64_encode(const void *src, size_t n, char *dst);
/* Upper bound of the decoded size of 'n' characters. */
size_t proto_b64_decoded_max(size_t n);
/* Decodes; returns the byte count, or -1 on a character outside the alphabet or bad padding. */
long proto_b64_decode(const char *src, size_t n, void *dst);

/*
 * Bakes (bake.c). A bake directory holds a manifest, bake.json,
 * {"volfx_bake": PROTO_BAKE_VERSION, "every": K, "scene": KEY}, and snapshots named
 * PROTO_BAKE_FILE of its frame. KEY is proto_bake_key of the scene document: the document
 * without what the clock moves (sim.frame, sim.time, sim.playing, fluid.count and the wave
 * fields an animation drives), so a document at any frame of the shot has the same key.
 */
#define PROTO_BAKE_VERSION 1
#define PROTO_BAKE_MANIFEST "bake.json"
#define PROTO_BAKE_FILE "frame_%06llu.snap" /* The frame as unsigned long long. */

/*
 * Defaults that the server's method table gives and a C client also needs before it can ask the
 * server (the batch sizes raw frames and checks finished files before it starts one): defined
 * once here, and used as the table's .def.
 */
#define PROTO_DEFAULT_SCENE "main"   /* Every method's 'scene', and volfxd's first scene. */
#define PROTO_DEFAULT_FRAME_SIDE 512 /* A frame's 'width' and 'height'. */
#define PROTO_DEFAULT_BAKE_EVERY 24  /* sim.bake's 'every'. */
/* A new copy of 'doc' reduced to its key, or NULL (not an object, or out of memory). */
cJSON *proto_bake_key(const cJSON *doc);
/* Whether documents 'a' and 'b' have equal keys. */
int proto_bake_same(const cJSON *a, const cJSON *b);

/*
 * WebSocket text messages as request lines. A message is one request (or batch) and may hold
 * the line breaks JSON allows between tokens; the connection's reader splits on '\n', so each
 * fragment is copied with those breaks made spaces, and a break inside a string (which JSON
 * forbids there) made the control byte 0x1f, which proto_parse refuses as it would the raw
 * break. The state carries over fragments of one message; proto_ws_text_end resets it.
 */
typedef struct proto_ws_text {
  int in_string; /* The message so far ends inside a JSON string, */
  int escaped;   /* after a backslash. */
} proto_ws_text_t;
/* Copies the 'n' bytes at 'in' to 'out' (n bytes), converted as above. */
void proto_ws_text_feed(proto_ws_text_t *st, const unsigned char *in, size_t n, char *out);
/* The message ended: the next byte starts a new one. */
void proto_ws_text_end(proto_ws_text_t *st);

#endif
