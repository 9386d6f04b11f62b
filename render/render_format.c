/*
 * The output formats a frame can be asked for, in one table: each format's wire name, the aovs
 * it serves, the bytes a pixel takes before encoding, the buffer those bytes come from, its
 * encoder (NULL for raw pixels) and its media type. The render method, the worker, sequence
 * jobs and frame subscriptions ask this table; a new format is an entry here and its encoder
 * in a file of its own (encode_png.c, encode_jpeg.c, encode_webp.c).
 */
#include "render_internal.h"

const char *const render_aov_names[] = {
    [AOV_BEAUTY] = "beauty", [AOV_DEPTH] = "depth", [AOV_WAVE_H] = "wave_h", [AOV_COUNT] = NULL};

#define AOV_BIT(a) (1u << (a))

/* The encoders (encode_<name>.c), each with the bound on the bytes it writes. */
int encode_jpeg(const uint8_t *rgba, uint32_t width, uint32_t height, int level,
                unsigned char **out, size_t *nout);
size_t encode_jpeg_bound(uint32_t width, uint32_t height);
int encode_webp(const uint8_t *rgba, uint32_t width, uint32_t height, int level,
                unsigned char **out, size_t *nout);
size_t encode_webp_bound(uint32_t width, uint32_t height);

const render_format_t render_format_table[] = {{.name = "png",
                                                .id = PROTO_FMT_PNG,
                                                .aovs = AOV_BIT(AOV_BEAUTY),
                                                .bytes_per_pixel = 4,
                                                .source = RENDER_SOURCE_DISPLAY,
                                                .encode = encode_png,
                                                .encoded_bound = encode_png_bound,
                                                .alpha = 1,
                                                .mime = "image/png"},
                                               {.name = "rgba8",
                                                .id = PROTO_FMT_RGBA8,
                                                .aovs = AOV_BIT(AOV_BEAUTY),
                                                .bytes_per_pixel = 4,
                                                .source = RENDER_SOURCE_DISPLAY,
                                                .alpha = 1,
                                                .mime = "application/octet-stream"},
                                               {.name = "rgbaf32",
                                                .id = PROTO_FMT_RGBAF32,
                                                .aovs = AOV_BIT(AOV_BEAUTY),
                                                .bytes_per_pixel = 4 * sizeof(float),
                                                .source = RENDER_SOURCE_LINEAR,
                                                .alpha = 1,
                                                .mime = "application/octet-stream"},
                                               {.name = "f32",
                                                .id = PROTO_FMT_F32,
                                                .aovs = AOV_BIT(AOV_DEPTH) | AOV_BIT(AOV_WAVE_H),
                                                .bytes_per_pixel = sizeof(float),
                                                .source = RENDER_SOURCE_AOV,
                                                .mime = "application/octet-stream"},
                                               {.name = "jpeg",
                                                .id = PROTO_FMT_JPEG,
                                                .aovs = AOV_BIT(AOV_BEAUTY),
                                                .bytes_per_pixel = 4,
                                                .source = RENDER_SOURCE_DISPLAY,
                                                .encode = encode_jpeg,
                                                .encoded_bound = encode_jpeg_bound,
                                                .quality = 1,
                                                .mime = "image/jpeg"},
                                               {.name = "webp",
                                                .id = PROTO_FMT_WEBP,
                                                .aovs = AOV_BIT(AOV_BEAUTY),
                                                .bytes_per_pixel = 4,
                                                .source = RENDER_SOURCE_DISPLAY,
                                                .encode = encode_webp,
                                                .encoded_bound = encode_webp_bound,
                                                .quality = 1,
                                                .alpha = 1,
                                                .mime = "image/webp"},
                                               {0}};

/* The names of the table's formats, in its order, for the params' schema. */
const char *const render_format_names[] = {"png", "rgba8", "rgbaf32", "f32", "jpeg", "webp", NULL};

const render_format_t *render_format_get(proto_format_t id) {
  for (const render_format_t *f = render_format_table; f->name; f++)
    if (f->id == id)
      return f;
  return NULL;
}

const render_format_t *render_format_find(const char *name) {
  for (const render_format_t *f = render_format_table; name && f->name; f++)
    if (strcmp(f->name, name) == 0)
      return f;
  return NULL;
}

int render_aov_parse(const char *name) {
  for (int a = 0; name && a < AOV_COUNT; a++)
    if (strcmp(render_aov_names[a], name) == 0)
      return a;
  return -1;
}

/* The formats that serve aov 'a', as a bit per table entry. */
static unsigned formats_of(int a) {
  unsigned set = 0, bit = 1;
  for (const render_format_t *f = render_format_table; f->name; f++, bit <<= 1)
    if (f->aovs & AOV_BIT(a))
      set |= bit;
  return set;
}

/* Writes to 'buf' which formats go with which aovs, aovs that take the same formats together:
 * "beauty: png, rgba8, rgbaf32; depth and wave_h: f32". */
static void list_pairs(char *buf, size_t len) {
  size_t at = 0;
  buf[0] = '\0';
  for (int a = 0; a < AOV_COUNT && at < len; a++) {
    unsigned set = formats_of(a);
    int seen = 0;
    for (int b = 0; b < a; b++)
      seen |= formats_of(b) == set;
    if (seen)
      continue;
    at += (size_t)snprintf(buf + at, len - at, "%s%s", at ? "; " : "", render_aov_names[a]);
    for (int b = a + 1; b < AOV_COUNT && at < len; b++)
      if (formats_of(b) == set)
        at += (size_t)snprintf(buf + at, len - at, " and %s", render_aov_names[b]);
    const char *sep = ": ";
    unsigned bit = 1;
    for (const render_format_t *f = render_format_table; f->name && at < len; f++, bit <<= 1)
      if (set & bit) {
        at += (size_t)snprintf(buf + at, len - at, "%s%s", sep, f->name);
        sep = ", ";
      }
  }
}

int render_format_check(proto_format_t id, int aov, char *err, size_t errlen) {
  const render_format_t *f = render_format_get(id);
  if (f && aov >= 0 && aov < AOV_COUNT && (f->aovs & AOV_BIT(aov)))
    return 0;
  if (err && errlen) {
    char pairs[160];
    list_pairs(pairs, sizeof pairs);
    const char *name = proto_format_name(id);
    snprintf(err, errlen, "format '%s' does not go with aov '%s' (%s)", name ? name : "unknown",
             aov >= 0 && aov < AOV_COUNT ? render_aov_names[aov] : "unknown", pairs);
  }
  return PROTO_E_INVALID_PARAMS;
}

size_t render_format_bound(const render_format_t *f, uint32_t width, uint32_t height) {
  size_t raw = f->bytes_per_pixel * (size_t)width * height;
  return f->encoded_bound ? f->encoded_bound(width, height) : raw;
}

int render_output_encode(const render_format_t *f, const render_params_t *p, render_output_t *out,
                         char *err, size_t errlen) {
  if (f->encode == NULL)
    return 0;
  double t0 = now_ms();
  unsigned char *bytes = NULL;
  size_t n = 0;
  int level = f->quality ? p->quality : p->png_level;
  if (f->encode(out->bytes, p->width, p->height, level, &bytes, &n) != 0) {
    proto_error_format(err, errlen, "%s encoding of a %ux%u frame failed", f->name, p->width,
                       p->height);
    free(out->bytes);
    out->bytes = NULL;
    out->nbytes = 0;
    return PROTO_E_INTERNAL;
  }
  free(out->bytes);
  out->bytes = bytes;
  out->nbytes = n;
  double ms = now_ms() - t0;
  if (out->npasses < RENDER_MAX_PASSES) {
    out->passes[out->npasses].name = "encode";
    out->passes[out->npasses++].ms = ms;
  }
  out->total_ms += ms;
  return 0;
}
