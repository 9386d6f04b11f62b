/*
 * PNG encoding (render/encode_png.c): every image encoded at the fast default (deflated in parts on
 * several threads) and at explicit levels (libpng) is decoded by libpng, an independent reader,
 * back to exactly the bytes encoded; sizes from one pixel to frames large enough to be split
 * into parts of uneven height, and images that compress well and badly.
 */
#include <png.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "check.h"
#include "render.h"

static uint32_t rng = 12345;

static uint32_t next(void) {
  rng ^= rng << 13;
  rng ^= rng >> 17;
  rng ^= rng << 5;
  return rng;
}

/* An image of gradients with a share 'noise' (0-100) of random pixels. */
static uint8_t *image(uint32_t w, uint32_t h, int noise) {
  uint8_t *p = malloc((size_t)w * h * 4);
  for (uint32_t y = 0; y < h; y++)
    for (uint32_t x = 0; x < w; x++) {
      uint8_t *q = p + ((size_t)y * w + x) * 4;
      if ((int)(next() % 100) < noise) {
        uint32_t r = next();
        memcpy(q, &r, 4);
      } else {
        q[0] = (uint8_t)(x * 255 / (w > 1 ? w - 1 : 1));
        q[1] = (uint8_t)(y * 255 / (h > 1 ? h - 1 : 1));
        q[2] = (uint8_t)((x + y) & 0xff);
        q[3] = 255;
      }
    }
  return p;
}

static void round_trip(uint32_t w, uint32_t h, int noise, int level) {
  uint8_t *src = image(w, h, noise);
  unsigned char *png = NULL;
  size_t n = 0;
  int rc = encode_png(src, w, h, level, &png, &n);
  CHECK(rc == 0 && png != NULL && n > 8, "%ux%u level %d: encode failed", w, h, level);
  if (rc == 0) {
    png_image img;
    memset(&img, 0, sizeof img);
    img.version = PNG_IMAGE_VERSION;
    int ok = png_image_begin_read_from_memory(&img, png, n);
    CHECK(ok && img.width == w && img.height == h, "%ux%u level %d: libpng reads %ux%u (%s)", w, h,
          level, img.width, img.height, img.message);
    if (ok && img.width == w && img.height == h) {
      img.format = PNG_FORMAT_RGBA;
      uint8_t *back = malloc((size_t)w * h * 4);
      ok = png_image_finish_read(&img, NULL, back, 0, NULL);
      CHECK(ok, "%ux%u level %d: libpng cannot decode it: %s", w, h, level, img.message);
      size_t bad = 0;
      for (size_t i = 0; ok && i < (size_t)w * h * 4; i++)
        bad += back[i] != src[i];
      CHECK(ok && bad == 0, "%ux%u level %d: %zu bytes differ after decoding", w, h, level, bad);
      free(back);
    }
    png_image_free(&img);
  }
  printf("%ux%u noise %d%% level %d: %zu bytes\n", w, h, noise, level, n);
  free(png);
  free(src);
}

int main(void) {
  uint32_t sizes[][2] = {{1, 1},     {3, 7},       {256, 256}, {257, 255}, {512, 512},
                         {960, 541}, {1024, 1024}, {4096, 3},  {2, 2000}};
  for (size_t i = 0; i < sizeof sizes / sizeof sizes[0]; i++) {
    round_trip(sizes[i][0], sizes[i][1], 0, -1);
    round_trip(sizes[i][0], sizes[i][1], 30, -1);
  }
  round_trip(640, 480, 100, -1); /* Incompressible. */
  round_trip(300, 200, 10, 6);
  round_trip(300, 200, 10, 0);
  unsigned char *png = NULL;
  size_t n = 0;
  uint8_t px[4] = {0};
  CHECK(encode_png(px, 0, 1, -1, &png, &n) != 0 && png == NULL, "a zero width is refused");
  CHECK(encode_png(px, 1, 1, 10, &png, &n) != 0 && png == NULL, "level 10 is refused");
  printf("%d checks, %d failures\n", checks, failures);
  return failures != 0;
}
