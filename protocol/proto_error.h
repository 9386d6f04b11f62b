/*
 * The one error carrier of volfxd's schema, scene, file and render code: a code (a JSON-RPC
 * error code of proto.h, or a module's own positive code such as a deferral), the dotted path
 * of the offending field ("objects.2.scale", "" when none) and a message for the client. A
 * function that fails fills the carrier its caller passed and returns -1; NULL carriers are
 * allowed where a caller does not care why. This header needs nothing else, so the renderer
 * and the server include it alike.
 */
#ifndef VOLFX_PROTO_ERROR_H
#define VOLFX_PROTO_ERROR_H

#include <stdarg.h>
#include <stddef.h>

#define PROTO_ERROR_PATH 256    /* Bytes of a path, its NUL included; longer ones are cut. */
#define PROTO_ERROR_MESSAGE 256 /* Bytes of a message, its NUL included. */

typedef struct proto_error {
  int code;                    /* 0 while nothing failed. */
  char path[PROTO_ERROR_PATH]; /* Offending dotted path, "" when none. */
  char message[PROTO_ERROR_MESSAGE];
} proto_error_t;

/* Empties 'e' (code 0, no path, no message). NULL is fine. */
void proto_error_clear(proto_error_t *e);

/* Fills 'e' with 'code', 'path' (NULL: "") and the message 'fmt' formats. NULL is fine.
 * Returns -1, so that a failing function can end with 'return proto_error_set(...)'. */
int proto_error_set(proto_error_t *e, int code, const char *path, const char *fmt, ...)
    __attribute__((format(printf, 4, 5)));
/* The same with the arguments in 'ap'. */
int proto_error_vset(proto_error_t *e, int code, const char *path, const char *fmt, va_list ap)
    __attribute__((format(printf, 4, 0)));

/*
 * The message alone, formatted into a caller's buffer of 'len' bytes (NULL or 0: nothing): the
 * form the renderer's and the simulations' functions hand a message back in, since theirs (an
 * OpenCL build log) can outgrow the carrier's. The caller turns it into a carrier, or an
 * answer, with the code it knows.
 */
void proto_error_format(char *buf, size_t len, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));

#endif
