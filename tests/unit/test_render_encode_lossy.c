/*
 * JPEG and WebP encoding (render/encode_jpeg.c, render/encode_webp.c, reached through the format
 * table), each decoded by its own library's decoder (TurboJPEG's tjDecompress2, libwebp's
 * WebPDecodeRGBA), independent of the encoder's code: lossy frames come back within a stated error
 * of the pixels encoded (PSNR over RGB, and the mean absolute error), lossless WebP exactly, alpha
 * included; a frame's alpha survives lossy WebP exactly; JPEG drops it. Sizes from one pixel to odd
 * ones that do not fill the chroma blocks, and qualities at both ends. Bad qualities are refused.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <turbojpeg.h>
#include <webp/decode.h>

#include "check.h"
#include "render.h"

/* A picture with what frames hold: smooth gradients, a hard-edged disc and a soft alpha ramp
 * (premultiplied: colour never above alpha). */
static uint8_t *image(uint32_t w, uint32_t h) {
  uint8_t *p = malloc((size_t)w * h * 4);
  for (uint32_t y = 0; y < h; y++)
    for (uint32_t x = 0; x < w; x++) {
      uint8_t *q = p + ((size_t)y * w + x) * 4;
      double u = (x + 0.5) / w, v = (y + 0.5) / h;
      double disc = (u - 0.5) * (u - 0.5) + (v - 0.4) * (v - 0.4) < 0.06 ? 1 : 0;
      uint8_t a = (uint8_t)(255 * (0.3 + 0.7 * v));
      double r = 0.2 + 0.6 * u, g = disc ? 0.9 : 0.3 + 0.4 * v, b = 0.5 + 0.4 * sin(6 * u);
      q[0] = (uint8_t)(r * a);
      q[1] = (uint8_t)(g * a);
      q[2] = (uint8_t)(b * a);
      q[3] = a;
    }
  return p;
}

/* PSNR in dB over the RGB of two RGBA images; INFINITY when equal. */
static double psnr_rgb(const uint8_t *a, const uint8_t *b, size_t pixels, double *mean_abs) {
  double se = 0, ae = 0;
  for (size_t i = 0; i < pixels; i++)
    for (int c = 0; c < 3; c++) {
      double d = (double)a[i * 4 + c] - b[i * 4 + c];
      se += d * d;
      ae += fabs(d);
    }
  *mean_abs = ae / (pixels * 3.0);
  return se == 0 ? INFINITY : 10 * log10(255.0 * 255.0 / (se / (pixels * 3.0)));
}

/* The encoders, as the format table holds them. */
static render_encode_fn encode_of(const char *name) {
  return render_format_find(name)->encode;
}

static size_t bound_of(const char *name, uint32_t w, uint32_t h) {
  return render_format_find(name)->encoded_bound(w, h);
}

static void jpeg_case(uint32_t w, uint32_t h, int quality, double min_psnr) {
  uint8_t *src = image(w, h);
  unsigned char *jpg = NULL;
  size_t n = 0;
  int rc = encode_of("jpeg")(src, w, h, quality, &jpg, &n);
  CHECK(rc == 0 && n > 2 && n <= bound_of("jpeg", w, h), "jpeg %ux%u q%d: encode rc %d, %zu bytes",
        w, h, quality, rc, n);
  if (rc == 0) {
    tjhandle tj = tjInitDecompress();
    int dw = 0, dh = 0, sub = 0, space = 0;
    int ok = tjDecompressHeader3(tj, jpg, (unsigned long)n, &dw, &dh, &sub, &space) == 0;
    CHECK(ok && (uint32_t)dw == w && (uint32_t)dh == h, "jpeg %ux%u: header says %dx%d", w, h, dw,
          dh);
    uint8_t *back = malloc((size_t)w * h * 4);
    ok = ok && tjDecompress2(tj, jpg, (unsigned long)n, back, (int)w, (int)w * 4, (int)h, TJPF_RGBA,
                             0) == 0;
    CHECK(ok, "jpeg %ux%u q%d: cannot decode: %s", w, h, quality, tjGetErrorStr2(tj));
    if (ok) {
      double mae;
      double psnr = psnr_rgb(src, back, (size_t)w * h, &mae);
      CHECK(psnr >= min_psnr, "jpeg %ux%u q%d: PSNR %.1f dB < %.1f (mean error %.2f)", w, h,
            quality, psnr, min_psnr, mae);
      int opaque = 1;
      for (size_t i = 0; i < (size_t)w * h; i++)
        opaque &= back[i * 4 + 3] == 255;
      CHECK(opaque, "jpeg %ux%u: decoded alpha is not 255: JPEG has none", w, h);
    }
    free(back);
    tjDestroy(tj);
    free(jpg);
  }
  free(src);
}

static void webp_case(uint32_t w, uint32_t h, int quality, double min_psnr) {
  uint8_t *src = image(w, h);
  unsigned char *webp = NULL;
  size_t n = 0;
  int rc = encode_of("webp")(src, w, h, quality, &webp, &n);
  CHECK(rc == 0 && n > 12 && n <= bound_of("webp", w, h), "webp %ux%u q%d: encode rc %d, %zu bytes",
        w, h, quality, rc, n);
  if (rc == 0) {
    int dw = 0, dh = 0;
    uint8_t *back = WebPDecodeRGBA(webp, n, &dw, &dh);
    CHECK(back && (uint32_t)dw == w && (uint32_t)dh == h, "webp %ux%u q%d: decodes to %dx%d", w, h,
          quality, dw, dh);
    if (back && (uint32_t)dw == w && (uint32_t)dh == h) {
      size_t px = (size_t)w * h;
      if (quality == 100) {
        CHECK(memcmp(src, back, px * 4) == 0, "webp %ux%u lossless: bytes differ", w, h);
      } else {
        double mae;
        double psnr = psnr_rgb(src, back, px, &mae);
        CHECK(psnr >= min_psnr, "webp %ux%u q%d: PSNR %.1f dB < %.1f (mean error %.2f)", w, h,
              quality, psnr, min_psnr, mae);
        int alpha_same = 1;
        for (size_t i = 0; i < px; i++)
          alpha_same &= src[i * 4 + 3] == back[i * 4 + 3];
        CHECK(alpha_same, "webp %ux%u q%d: the alpha plane changed", w, h, quality);
      }
    }
    WebPFree(back);
    free(webp);
  }
  free(src);
}

int main(void) {
  static const uint32_t sizes[][2] = {{1, 1}, {7, 5}, {64, 64}, {333, 197}, {1280, 720}};
  for (size_t i = 0; i < sizeof sizes / sizeof sizes[0]; i++) {
    uint32_t w = sizes[i][0], h = sizes[i][1];
    int big = w * h >= 4096;
    /* Tiny images are mostly block edges: only their decoding is required to be close. */
    jpeg_case(w, h, 85, big ? 34 : 20);
    jpeg_case(w, h, 100, big ? 36 : 25);
    jpeg_case(w, h, 1, 10);
    webp_case(w, h, 80, big ? 32 : 20);
    webp_case(w, h, 100, 0);
    webp_case(w, h, 1, 10);
  }
  unsigned char *out = NULL;
  size_t n = 0;
  uint8_t px[4] = {1, 2, 3, 4};
  CHECK(encode_of("jpeg")(px, 1, 1, 0, &out, &n) == -1 && out == NULL, "jpeg quality 0 accepted");
  CHECK(encode_of("jpeg")(px, 1, 1, 101, &out, &n) == -1 && out == NULL,
        "jpeg quality 101 accepted");
  CHECK(encode_of("webp")(px, 1, 1, 0, &out, &n) == -1 && out == NULL, "webp quality 0 accepted");
  CHECK(encode_of("webp")(px, 20000, 1, 80, &out, &n) == -1 && out == NULL,
        "webp wider than its 16383 pixels accepted");
  printf("test_render_encode_lossy: %d checks, %d failed\n", checks, failures);
  return failures == 0 ? 0 : 1;
}
