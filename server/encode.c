/*
 * Frame encoders. PNG goes through libpng into memory. The fast default (zlib level 1, no row
 * filter) encodes 512x512 in about 4 ms, where libpng's defaults take 23-44 ms for files
 * perhaps half the size (PERF-NOTES); a request that wants small files asks for a level.
 */
#include <png.h>
#include <setjmp.h>
#include <stdlib.h>
#include <string.h>

#include "render.h"

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
