/*
 * The JPEG encoder of the "jpeg" format (render_format.c), through libjpeg-turbo's TurboJPEG
 * API: 4:2:0 chroma, its fast integer DCT, quality 1-100 from the request. The frame's alpha is
 * dropped: a premultiplied frame over a transparent background becomes the effects over black.
 * The output buffer is sized by tjBufSize and allocated here, so the library never reallocates
 * it and the caller frees it with free().
 */
#include <stdlib.h>
#include <turbojpeg.h>

#include "render.h"

size_t encode_jpeg_bound(uint32_t width, uint32_t height) {
  unsigned long n = tjBufSize((int)width, (int)height, TJSAMP_420);
  return n == (unsigned long)-1 ? 0 : (size_t)n;
}

int encode_jpeg(const uint8_t *rgba, uint32_t width, uint32_t height, int level,
                unsigned char **out, size_t *nout) {
  size_t cap = encode_jpeg_bound(width, height);
  if (cap == 0 || level < 1 || level > 100)
    return -1;
  tjhandle tj = tjInitCompress();
  unsigned char *buf = malloc(cap);
  if (!tj || !buf) {
    if (tj)
      tjDestroy(tj);
    free(buf);
    return -1;
  }
  unsigned long n = cap;
  /* RGBX: the fourth byte of each pixel, the alpha, is skipped. */
  int rc = tjCompress2(tj, rgba, (int)width, (int)width * 4, (int)height, TJPF_RGBX, &buf, &n,
                       TJSAMP_420, level, TJFLAG_NOREALLOC | TJFLAG_FASTDCT);
  tjDestroy(tj);
  if (rc != 0) {
    free(buf);
    return -1;
  }
  *out = buf;
  *nout = n;
  return 0;
}
