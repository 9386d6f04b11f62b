/*
 * The WebP encoder of the "webp" format (render_format.c), through libwebp: quality 1-99 is
 * lossy (VP8, its alpha plane kept losslessly), 100 is lossless (VP8L, every byte of RGBA
 * exact). Both use libwebp's fastest method (0), which keeps a 640x360 frame in a few
 * milliseconds; a fully opaque frame is written without an alpha plane. libwebp allocates its
 * own output, which is copied into a buffer the caller frees with free().
 */
#include <stdlib.h>
#include <string.h>
#include <webp/encode.h>

#include "render.h"

size_t encode_webp_bound(uint32_t width, uint32_t height) {
  /* Lossless WebP of noise can pass the raw size a little; headers and chunks on top. */
  size_t raw = (size_t)width * height * 4;
  return raw + raw / 8 + 4096;
}

int encode_webp(const uint8_t *rgba, uint32_t width, uint32_t height, int level,
                unsigned char **out, size_t *nout) {
  if (level < 1 || level > 100 || width > WEBP_MAX_DIMENSION || height > WEBP_MAX_DIMENSION)
    return -1;
  WebPConfig config;
  WebPPicture pic;
  if (!WebPConfigInit(&config) || !WebPPictureInit(&pic))
    return -1;
  config.method = 0;
  if (level == 100) {
    config.lossless = 1;
    config.exact = 1;
    config.quality = 0; /* For lossless, the effort: the fastest. */
  } else {
    config.quality = (float)level;
  }
  pic.use_argb = config.lossless;
  pic.width = (int)width;
  pic.height = (int)height;
  WebPMemoryWriter writer;
  WebPMemoryWriterInit(&writer);
  pic.writer = WebPMemoryWrite;
  pic.custom_ptr = &writer;
  int ok = WebPPictureImportRGBA(&pic, rgba, (int)width * 4) && WebPEncode(&config, &pic);
  WebPPictureFree(&pic);
  unsigned char *copy =
      ok && writer.size <= encode_webp_bound(width, height) ? malloc(writer.size) : NULL;
  if (copy)
    memcpy(copy, writer.mem, writer.size);
  size_t n = writer.size;
  WebPMemoryWriterClear(&writer);
  if (!copy)
    return -1;
  *out = copy;
  *nout = n;
  return 0;
}
