/*
 * The NDJSON reader: a growable byte buffer that bytes are fed into as they arrive from a
 * socket, and that complete lines and raw attachment payloads are taken out of, in order.
 *
 * Each byte is searched for '\n' once: 'scanned' remembers how much of the unread data is
 * already known to hold none, so a long line that arrives in many small pieces costs linear
 * time. Taken data is not moved at once; the unread bytes are moved to the front of the buffer
 * only when a feed finds the taken prefix large, or when it would otherwise have to grow. A
 * line over the limit is reported as soon as the buffered bytes prove it, so a peer cannot make
 * the reader hold more than about 'max_line' bytes of one line plus what one feed brings.
 */
#include <stdlib.h>
#include <string.h>

#include "proto.h"

/* Smallest allocation, so that short messages do not cause a chain of tiny reallocations. */
#define READER_MIN_CAP 4096
/* An empty reader whose buffer is larger than this (and than twice the line limit) gives the
 * buffer back, so that one large attachment does not pin its memory for the connection's life. */
#define READER_KEEP_CAP ((size_t)256 << 10)

void proto_reader_init(proto_reader_t *r, size_t max_line) {
  memset(r, 0, sizeof(*r));
  r->max_line = max_line;
}

void proto_reader_free(proto_reader_t *r) {
  free(r->buf);
  r->buf = NULL;
  r->start = r->len = r->cap = r->scanned = 0;
}

size_t proto_reader_pending(const proto_reader_t *r) {
  return r->len - r->start;
}

/* Grows the buffer so that 'need' bytes fit from offset 0. Returns 0, or -1 when out of memory
 * (the buffer is then unchanged). */
static int reserve(proto_reader_t *r, size_t need) {
  if (need <= r->cap)
    return 0;
  size_t cap = r->cap < READER_MIN_CAP ? READER_MIN_CAP : r->cap;
  while (cap < need) {
    if (cap > SIZE_MAX / 2) {
      cap = need;
      break;
    }
    cap *= 2;
  }
  char *buf = realloc(r->buf, cap);
  if (buf == NULL)
    return -1;
  r->buf = buf;
  r->cap = cap;
  return 0;
}

/*
 * Appends 'n' bytes from 'data'. Pointers handed out by proto_reader_line and
 * proto_reader_bytes become invalid, since the buffer may move. Returns PROTO_READ_OK, or
 * PROTO_READ_NOMEM with the reader unchanged except for where its unread bytes lie.
 */
int proto_reader_feed(proto_reader_t *r, const void *data, size_t n) {
  if (n == 0)
    return PROTO_READ_OK;

  if (r->start == r->len) {
    /* Nothing unread: start over at the front, and drop a buffer that an earlier large
     * message left behind when this feed does not need it. */
    r->start = r->len = r->scanned = 0;
    size_t keep = READER_KEEP_CAP;
    if (r->max_line > keep / 2)
      keep = r->max_line > SIZE_MAX / 2 ? SIZE_MAX : r->max_line * 2;
    if (r->cap > keep && n <= keep) {
      free(r->buf);
      r->buf = NULL;
      r->cap = 0;
    }
  } else if (r->start > 0 && (r->start >= r->cap / 2 || n > r->cap - r->len)) {
    /* The taken prefix is half the buffer, or the new bytes do not fit behind the unread ones:
     * move the unread bytes to the front. 'scanned' counts from 'start', so it stays valid. */
    memmove(r->buf, r->buf + r->start, r->len - r->start);
    r->len -= r->start;
    r->start = 0;
  }

  if (n > SIZE_MAX - r->len)
    return PROTO_READ_NOMEM;
  if (reserve(r, r->len + n) != 0)
    return PROTO_READ_NOMEM;
  memcpy(r->buf + r->len, data, n);
  r->len += n;
  return PROTO_READ_OK;
}

/*
 * Takes the next line; see proto.h. The limit applies to the line as returned, so a line of
 * exactly 'max_line' bytes is accepted with "\n" or "\r\n" after it. Once PROTO_READ_OVERSIZE
 * has been returned the reader keeps returning it: the rest of the stream cannot be framed.
 */
int proto_reader_line(proto_reader_t *r, char **line, size_t *len) {
  size_t avail = r->len - r->start;
  char *nl = NULL;

  if (avail == 0)
    return PROTO_READ_MORE; /* Also keeps arithmetic off a reader that has no buffer yet. */
  char *base = r->buf + r->start;

  if (avail > r->scanned)
    nl = memchr(base + r->scanned, '\n', avail - r->scanned);
  if (nl == NULL) {
    r->scanned = avail;
    /* Without a '\n' the line is at least 'avail' bytes long, or 'avail' - 1 when the last
     * byte is a '\r' that the next byte may turn into a line ending. */
    if (avail > r->max_line && (avail - r->max_line > 1 || base[avail - 1] != '\r'))
      return PROTO_READ_OVERSIZE;
    return PROTO_READ_MORE;
  }

  size_t n = (size_t)(nl - base);
  size_t taken = n + 1;
  if (n > 0 && base[n - 1] == '\r')
    n--;
  if (n > r->max_line) {
    r->scanned = (size_t)(nl - base); /* The next call finds the same '\n' at once. */
    return PROTO_READ_OVERSIZE;
  }
  base[n] = '\0';
  r->start += taken;
  r->scanned = 0;
  *line = base;
  if (len != NULL)
    *len = n;
  return PROTO_READ_OK;
}

/* Takes the next 'n' raw bytes, whatever they hold; see proto.h. The line limit does not apply:
 * the caller has already checked 'n' against its own limits. */
int proto_reader_bytes(proto_reader_t *r, size_t n, const char **data) {
  if (r->len - r->start < n)
    return PROTO_READ_MORE;
  *data = r->buf == NULL ? "" : r->buf + r->start;
  r->start += n;
  /* Bytes known to hold no '\n' stay known after the taken ones. */
  r->scanned = r->scanned > n ? r->scanned - n : 0;
  return PROTO_READ_OK;
}
