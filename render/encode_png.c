/*
 * The PNG encoder of the "png" format (render_format.c). The fast default PNG (zlib level 1, no row
 * filter) encodes 512x512 in about 3 ms, where libpng's defaults take 23-44 ms for files perhaps
 * half the size (PERF-NOTES); a request that wants small files asks for a level, and goes through
 * libpng. The default is written here: its rows are cut into a part per core, each part deflated on
 * its own as raw deflate blocks ending on a byte boundary (a sync flush, the last part a final
 * block), so that the parts, one after another, are one valid zlib stream; its Adler-32 is the
 * parts' combined.
 */
#include <png.h>
#include <setjmp.h>
#include <stdlib.h>
#include <string.h>
#include <zlib.h>

#include "parallel.h"
#include "render.h"

/* Bytes of a frame from which the fast PNG is deflated on a thread per core (256 x 256). */
#define PNG_SPLIT_MIN ((size_t)1 << 18)

/* The PNG being written: a buffer that doubles as it fills. */
typedef struct png_sink {
  unsigned char *p;
  size_t len, cap;
} png_sink_t;

/* libpng's write callback; running out of memory longjmps back into encode_png. */
static void sink_write(png_structp png, png_bytep data, size_t n) {
  png_sink_t *s = png_get_io_ptr(png);
  if (s->len + n > s->cap) {
    size_t cap = s->cap ? s->cap : 65536;
    while (cap < s->len + n)
      cap *= 2;
    unsigned char *p = realloc(s->p, cap);
    if (p == NULL)
      png_error(png, "out of memory");
    s->p = p, s->cap = cap;
  }
  memcpy(s->p + s->len, data, n);
  s->len += n;
}

static void sink_flush(png_structp png) {
  (void)png;
}

/* Rows [y0, y1) of a fast PNG, each behind its filter byte (0, none), deflated at level 1 into
 * 'out' ('len' bytes); 'adler' is their Adler-32. 'ok' is 0 when zlib failed. */
typedef struct png_part {
  const uint8_t *rgba;
  uint32_t width, y0, y1;
  int last;
  unsigned char *out;
  size_t len;
  uLong adler;
  int ok;
} png_part_t;

static void *deflate_part(void *arg) {
  png_part_t *p = arg;
  static const Bytef none = 0;
  size_t row = (size_t)p->width * 4, rows = p->y1 - p->y0;
  z_stream z;
  memset(&z, 0, sizeof z);
  p->ok = 0;
  if (deflateInit2(&z, 1, Z_DEFLATED, -15, 8, Z_DEFAULT_STRATEGY) != Z_OK)
    return NULL;
  /* Room for the whole part, its sync flush and a few bytes per deflate call. */
  size_t cap = deflateBound(&z, (uLong)((row + 1) * rows)) + 16 + rows;
  p->out = malloc(cap);
  z.next_out = p->out;
  z.avail_out = (uInt)cap;
  p->adler = adler32(0, NULL, 0);
  int ok = p->out != NULL;
  for (uint32_t y = p->y0; ok && y < p->y1; y++) {
    const Bytef *r = p->rgba + (size_t)y * row;
    int flush = y + 1 < p->y1 ? Z_NO_FLUSH : p->last ? Z_FINISH : Z_SYNC_FLUSH;
    z.next_in = (Bytef *)&none;
    z.avail_in = 1;
    ok = deflate(&z, Z_NO_FLUSH) == Z_OK;
    z.next_in = (Bytef *)r;
    z.avail_in = (uInt)row;
    int rc = deflate(&z, flush);
    ok = ok && z.avail_in == 0 && (flush == Z_FINISH ? rc == Z_STREAM_END : rc == Z_OK);
    p->adler = adler32(adler32(p->adler, &none, 1), r, (uInt)row);
  }
  p->len = cap - z.avail_out;
  p->ok = ok;
  deflateEnd(&z);
  return NULL;
}

static void put32(unsigned char *b, uint32_t v) {
  b[0] = (unsigned char)(v >> 24), b[1] = (unsigned char)(v >> 16);
  b[2] = (unsigned char)(v >> 8), b[3] = (unsigned char)v;
}

/* Writes a chunk of 'type' holding 'n' bytes at 'data' (none when n is 0) at 'o'; returns its
 * end. */
static unsigned char *chunk(unsigned char *o, const char *type, const unsigned char *data,
                            size_t n) {
  put32(o, (uint32_t)n);
  memcpy(o + 4, type, 4);
  if (n)
    memcpy(o + 8, data, n);
  put32(o + 8 + n, (uint32_t)crc32(0, o + 4, (uInt)(4 + n)));
  return o + 12 + n;
}

/* The fast PNG of encode_png (level -1), its rows deflated in parts on a thread per core: one
 * IDAT chunk per part, the zlib header in the first and the Adler-32 in the last. Returns 0, or
 * -1 when out of memory or zlib failed, with nothing allocated. */
static int encode_fast(const uint8_t *rgba, uint32_t width, uint32_t height, unsigned char **out,
                       size_t *nout) {
  size_t raw = ((size_t)width * 4 + 1) * height;
  int n = par_parts(raw, PNG_SPLIT_MIN);
  if ((uint32_t)n > height)
    n = (int)height;
  png_part_t parts[PAR_MAX];
  for (int i = 0; i < n; i++)
    parts[i] = (png_part_t){.rgba = rgba,
                            .width = width,
                            .y0 = (uint32_t)((uint64_t)height * i / n),
                            .y1 = (uint32_t)((uint64_t)height * (i + 1) / n),
                            .last = i == n - 1};
  par_run(deflate_part, parts, sizeof *parts, n);
  int ok = 1;
  size_t total = 8 + 25 + 12; /* Signature, IHDR, IEND. */
  uLong adler = adler32(0, NULL, 0);
  for (int i = 0; i < n; i++) {
    ok &= parts[i].ok;
    total += 12 + parts[i].len + (i == 0 ? 2 : 0) + (i == n - 1 ? 4 : 0);
    adler = adler32_combine(adler, parts[i].adler,
                            (z_off_t)(((size_t)width * 4 + 1) * (parts[i].y1 - parts[i].y0)));
  }
  unsigned char *buf = ok ? malloc(total) : NULL;
  if (buf) {
    static const unsigned char sig[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
    /* zlib header: deflate, 32 KiB window, fastest level; the check bits make it 0x7801. */
    static const unsigned char zhead[2] = {0x78, 0x01};
    unsigned char ihdr[13] = {0}, tail[4], *o = buf;
    put32(ihdr, width);
    put32(ihdr + 4, height);
    ihdr[8] = 8; /* Bits per channel. */
    ihdr[9] = 6; /* RGBA. Compression, filter and interlace methods 0. */
    put32(tail, (uint32_t)adler);
    memcpy(o, sig, 8);
    o = chunk(o + 8, "IHDR", ihdr, 13);
    for (int i = 0; i < n; i++) {
      const unsigned char *pre = i == 0 ? zhead : NULL, *post = i == n - 1 ? tail : NULL;
      /* The zlib header before the first part, the Adler-32 after the last. */
      size_t np = pre ? 2 : 0, nq = post ? 4 : 0, nd = np + parts[i].len + nq;
      put32(o, (uint32_t)nd);
      memcpy(o + 4, "IDAT", 4);
      if (np)
        memcpy(o + 8, pre, np);
      memcpy(o + 8 + np, parts[i].out, parts[i].len);
      if (nq)
        memcpy(o + 8 + np + parts[i].len, post, nq);
      put32(o + 8 + nd, (uint32_t)crc32(0, o + 4, (uInt)(4 + nd)));
      o += 12 + nd;
    }
    o = chunk(o, "IEND", NULL, 0);
    *out = buf;
    *nout = (size_t)(o - buf);
  }
  for (int i = 0; i < n; i++)
    free(parts[i].out);
  return buf ? 0 : -1;
}

/*
 * Encodes 'rgba' (rows top to bottom, 4 bytes a pixel) as an 8-bit RGBA PNG into a malloc'd
 * buffer '*out' of '*nout' bytes, which the caller frees. 'level' is a zlib level 0-9 with
 * libpng's default filters, or -1 for level 1 without filtering. Returns 0, or -1 on bad
 * arguments or any libpng error, with nothing allocated.
 */
int encode_png(const uint8_t *rgba, uint32_t width, uint32_t height, int level, unsigned char **out,
               size_t *nout) {
  *out = NULL;
  *nout = 0;
  if (rgba == NULL || width == 0 || height == 0 || width > PNG_USER_WIDTH_MAX ||
      height > PNG_USER_HEIGHT_MAX || level < -1 || level > 9)
    return -1;
  if (level < 0 && encode_fast(rgba, width, height, out, nout) == 0)
    return 0;
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, NULL, NULL, NULL);
  if (png == NULL)
    return -1;
  png_infop info = png_create_info_struct(png);
  png_sink_t *sink = calloc(1, sizeof *sink);
  if (info == NULL || sink == NULL || setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    if (sink)
      free(sink->p);
    free(sink);
    return -1;
  }
  png_set_write_fn(png, sink, sink_write, sink_flush);
  png_set_IHDR(png, info, width, height, 8, PNG_COLOR_TYPE_RGB_ALPHA, PNG_INTERLACE_NONE,
               PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  if (level < 0) {
    png_set_compression_level(png, 1);
    png_set_filter(png, PNG_FILTER_TYPE_BASE, PNG_FILTER_NONE);
  } else {
    png_set_compression_level(png, level);
  }
  png_write_info(png, info);
  for (uint32_t y = 0; y < height; y++)
    png_write_row(png, (png_const_bytep)(rgba + (size_t)y * width * 4));
  png_write_end(png, NULL);
  png_destroy_write_struct(&png, &info);

  *out = sink->p;
  *nout = sink->len;
  free(sink);
  return 0;
}

/* A PNG is at worst a little over the raw pixels: stored deflate blocks, a filter byte a row,
 * the chunks. */
size_t encode_png_bound(uint32_t width, uint32_t height) {
  size_t npix = (size_t)width * height;
  return 4 * npix + npix / 64 + height;
}
