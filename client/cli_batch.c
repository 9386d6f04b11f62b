/*
 * volfx batch and volfx bake: render-farm commands that need no running server. Each starts a
 * private volfxd (farm_server.c), drives its main scene over one connection and always stops it,
 * also after an error and on SIGINT or SIGTERM.
 *
 * `batch` renders frames FIRST..LAST to files named by a #### pattern. Each frame goes to a
 * temporary file beside its target, is fsynced and renamed into place, so a file under its
 * final name is always whole; frames whose files are whole already are skipped, and no server
 * starts when none is missing. `bake` simulates a shot once with the server's sim.bake job,
 * which saves a snapshot every K frames into a bake directory; `batch --bake DIR` then starts
 * from the snapshot nearest before the frames it needs instead of simulating from the start.
 */
#include <dirent.h>
#include <errno.h>
#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "cli_batch.h"
#include "farm.h"
#include "proto.h"

#define FRAME_MAX 9007199254740991ULL /* 2^53 - 1, the largest sim.frame. */
#define STEPS_MAX 100000              /* The most steps one sim.step takes. */

/* Options of both commands, parsed into one table of values (flags get ""). */
enum {
  A_FIRST,
  A_LAST,
  A_STEP,
  A_OUT,
  A_BAKE,
  A_EVERY,
  A_WIDTH,
  A_HEIGHT,
  A_FORMAT,
  A_AOV,
  A_LAYERS,
  A_CAMERA,
  A_PNG_LEVEL,
  A_QUALITY,
  A_ANTIALIAS,
  A_PRESETS,
  A_DEVICE,
  A_OVERWRITE,
  A_VERBOSE,
  A_COUNT
};

static const struct {
  const char *name, *alias;
  int flag; /* 1: takes no value. */
} options[A_COUNT] = {
    [A_FIRST] = {"--start", "-s", 0},         [A_LAST] = {"--end", "-e", 0},
    [A_STEP] = {"--jump", "-j", 0},           [A_OUT] = {"--output", "-o", 0},
    [A_BAKE] = {"--bake", NULL, 0},           [A_EVERY] = {"--every", "-k", 0},
    [A_WIDTH] = {"--width", "-W", 0},         [A_HEIGHT] = {"--height", "-H", 0},
    [A_FORMAT] = {"--format", "-f", 0},       [A_AOV] = {"--aov", NULL, 0},
    [A_LAYERS] = {"--layers", NULL, 0},       [A_CAMERA] = {"--camera", NULL, 0},
    [A_PNG_LEVEL] = {"--png-level", NULL, 0}, [A_ANTIALIAS] = {"--antialias", NULL, 0},
    [A_QUALITY] = {"--quality", "-q", 0},     [A_PRESETS] = {"--presets", NULL, 0},
    [A_DEVICE] = {"--device", NULL, 0},       [A_OVERWRITE] = {"--overwrite", NULL, 1},
    [A_VERBOSE] = {"--verbose", "-v", 1},
};

#define BIT(a) (1u << (a))
#define BATCH_OPTS                                                                                 \
  (BIT(A_FIRST) | BIT(A_LAST) | BIT(A_STEP) | BIT(A_OUT) | BIT(A_BAKE) | BIT(A_WIDTH) |            \
   BIT(A_HEIGHT) | BIT(A_FORMAT) | BIT(A_AOV) | BIT(A_LAYERS) | BIT(A_CAMERA) | BIT(A_PNG_LEVEL) | \
   BIT(A_QUALITY) | BIT(A_ANTIALIAS) | BIT(A_PRESETS) | BIT(A_DEVICE) | BIT(A_OVERWRITE) |         \
   BIT(A_VERBOSE))
#define BAKE_OPTS                                                                                  \
  (BIT(A_LAST) | BIT(A_EVERY) | BIT(A_OUT) | BIT(A_PRESETS) | BIT(A_DEVICE) | BIT(A_VERBOSE))

/* Reports a command-line mistake about 'arg' and returns EXIT_USAGE. */
static int usage(const farm_t *f, const char *fmt, const char *arg) {
  fprintf(stderr, "volfx %s: ", f->cmd);
  fprintf(stderr, fmt, arg != NULL ? arg : "");
  fputs(" (see volfx --help)\n", stderr);
  return EXIT_USAGE;
}

/*
 * Reads the command's words into 'val' (indexed by A_*; NULL when absent, "" for a flag given)
 * and its one positional word into '*scene'. Only the options in 'accepted' are known.
 * "--name=VALUE" works for long names. Returns 0 or EXIT_USAGE after saying why.
 */
static int parse_args(const farm_t *f, int argc, char **argv, unsigned accepted,
                      const char *val[A_COUNT], const char **scene) {
  for (int i = 1; i < argc; i++) {
    const char *a = argv[i];
    int k = 0;
    const char *inline_val = NULL;
    for (; k < A_COUNT; k++) {
      size_t n = strlen(options[k].name);
      if (!(accepted & BIT(k))) {
        continue;
      }
      if (strcmp(a, options[k].name) == 0 ||
          (options[k].alias != NULL && strcmp(a, options[k].alias) == 0)) {
        break;
      }
      if (!options[k].flag && strncmp(a, options[k].name, n) == 0 && a[n] == '=') {
        inline_val = a + n + 1;
        break;
      }
    }
    if (k < A_COUNT && options[k].flag) {
      val[k] = "";
    } else if (k < A_COUNT && inline_val != NULL) {
      val[k] = inline_val;
    } else if (k < A_COUNT) {
      if (i + 1 >= argc) {
        return usage(f, "%s needs a value", a);
      }
      val[k] = argv[++i];
    } else if (a[0] == '-' && a[1] != '\0') {
      return usage(f, "unknown option '%s'", a);
    } else if (*scene == NULL) {
      *scene = a;
    } else {
      return usage(f, "unexpected '%s': give one PRESET, SCENE.json or SNAPSHOT", a);
    }
  }
  if (*scene == NULL) {
    return usage(f, "needs a PRESET, SCENE.json or SNAPSHOT%s", NULL);
  }
  return 0;
}

/* ---------------------------------------------------------------------------------------- */
/* Scenes, snapshots and bakes */

/* The scene's current frame from its document. */
static uint64_t doc_frame(const cJSON *doc) {
  double v = farm_num(cJSON_GetObjectItemCaseSensitive(doc, "sim"), "frame", 0);
  return v > 0 ? (uint64_t)v : 0;
}

/* Loads snapshot 'file' (relative to the data directory) into the main scene and sets
 * 'f->frame' to its frame. Returns 0 or the call's code with 'f->why' set. */
static int load_snapshot(farm_t *f, const char *file) {
  cJSON *p = farm_main_params();
  cJSON_AddStringToObject(p, "file", file);
  cJSON *r = NULL;
  int rc = farm_call(f, "scene.load", p, &r, NULL);
  if (rc == 0) {
    double v = farm_num(r, "frame", 0);
    f->frame = v > 0 ? (uint64_t)v : 0;
  }
  cJSON_Delete(r);
  return rc;
}

static int cmp_u64(const void *a, const void *b) {
  uint64_t x = *(const uint64_t *)a, y = *(const uint64_t *)b;
  return x < y ? -1 : x > y;
}

/*
 * Lists the snapshots of bake directory 'dir' into 'f->snaps' (frames, ascending). Names that
 * are not exactly PROTO_BAKE_FILE of a frame are ignored. Returns 0 or -1 with errno set.
 */
static int list_snapshots(farm_t *f, const char *dir) {
  DIR *d = opendir(dir);
  if (d == NULL) {
    return -1;
  }
  size_t cap = 0;
  struct dirent *e;
  while ((e = readdir(d)) != NULL) {
    uint64_t frame;
    char digits[32], again[64];
    const char *name = e->d_name;
    size_t n = strlen(name);
    if (n < 12 || n - 11 >= sizeof(digits) || strncmp(name, "frame_", 6) != 0) {
      continue;
    }
    snprintf(digits, sizeof(digits), "%.*s", (int)(n - 11), name + 6);
    if (!farm_parse_u64(digits, 0, FRAME_MAX, &frame)) {
      continue;
    }
    snprintf(again, sizeof(again), PROTO_BAKE_FILE, (unsigned long long)frame);
    if (strcmp(again, name) != 0) {
      continue;
    }
    if (f->nsnaps == cap) {
      cap = cap != 0 ? cap * 2 : 64;
      uint64_t *bigger = realloc(f->snaps, cap * sizeof(*bigger));
      if (bigger == NULL) {
        closedir(d);
        errno = ENOMEM;
        return -1;
      }
      f->snaps = bigger;
    }
    f->snaps[f->nsnaps++] = frame;
  }
  closedir(d);
  if (f->nsnaps > 1) {
    qsort(f->snaps, f->nsnaps, sizeof(*f->snaps), cmp_u64);
  }
  return 0;
}

/* The index of the latest snapshot at or before 'frame', or -1. */
static long snapshot_before(const farm_t *f, uint64_t frame) {
  long k = -1;
  for (size_t i = 0; i < f->nsnaps && f->snaps[i] <= frame; i++) {
    k = (long)i;
  }
  return k;
}

/* The bake snapshot of 'frame' as the server names it: "BASE/frame_NNNNNN.snap". */
static void snapshot_file(const farm_t *f, uint64_t frame, char *out, size_t cap) {
  char name[64];
  snprintf(name, sizeof(name), PROTO_BAKE_FILE, (unsigned long long)frame);
  snprintf(out, cap, "%s/%s", f->bake_base, name);
}

/*
 * Reads 'dir'/bake.json into '*manifest' (owned by the caller; left NULL when there is none
 * and that is 'optional'). Returns 0 or EXIT_FAIL after saying why.
 */
static int read_manifest(const farm_t *f, const char *dir, int optional, cJSON **manifest) {
  char path[FARM_PATH_CAP];
  snprintf(path, sizeof(path), "%s/%s", dir, PROTO_BAKE_MANIFEST);
  char *text = farm_read_text(path);
  *manifest = NULL;
  if (text == NULL && errno == ENOENT && optional) {
    return 0;
  }
  if (text == NULL) {
    return farm_say(f, EXIT_FAIL, "cannot read %s: %s", path, strerror(errno));
  }
  *manifest = cJSON_Parse(text);
  free(text);
  const cJSON *every = cJSON_GetObjectItemCaseSensitive(*manifest, "every");
  if (farm_num(*manifest, "volfx_bake", 0) != PROTO_BAKE_VERSION || !cJSON_IsNumber(every) ||
      !cJSON_IsObject(cJSON_GetObjectItemCaseSensitive(*manifest, "scene"))) {
    cJSON_Delete(*manifest);
    *manifest = NULL;
    return farm_say(f, EXIT_FAIL, "%s is not a bake manifest of version %d", path,
                    PROTO_BAKE_VERSION);
  }
  return 0;
}

/*
 * Fetches the main scene's document, sets 'f->frame' from it and, with a 'manifest', checks
 * that the scene is the bake's. Returns 0 or EXIT_FAIL after saying why.
 */
static int check_scene(farm_t *f, const cJSON *manifest, const char *bake_dir) {
  cJSON *doc = NULL;
  if (farm_call(f, "scene.get", farm_main_params(), &doc, NULL) != 0) {
    return farm_say(f, EXIT_FAIL, "%s", f->why);
  }
  f->frame = doc_frame(doc);
  int same =
      manifest == NULL || proto_bake_same(doc, cJSON_GetObjectItemCaseSensitive(manifest, "scene"));
  cJSON_Delete(doc);
  return same ? 0 : farm_say(f, EXIT_FAIL, "bake %s holds another scene", bake_dir);
}

/*
 * Starts the private volfxd on 'data' with the scene: a preset or scene file, or (with
 * 'snapshot') the snapshot 'file' loaded into the default scene; then checks it against the
 * bake's 'manifest', when there is one. Returns 0 or EXIT_FAIL after saying why.
 */
static int open_scene(farm_t *f, const char *data, const char *scene, int snapshot,
                      const char *file, const cJSON *manifest, const char *bake_dir) {
  int rc = farm_server_start(f, data, snapshot ? "" : scene);
  if (rc == 0 && snapshot && load_snapshot(f, file) != 0) {
    rc = farm_say(f, EXIT_FAIL, "cannot load %s: %s", scene, f->why);
  }
  return rc != 0 ? rc : check_scene(f, manifest, bake_dir);
}

/*
 * The data directory and the scene's place in it. With 'bake_dir', its parent; a 'snapshot'
 * must then lie inside it ('*file' receives its name relative to it). Else a snapshot's own
 * directory. 'data' receives the directory, '' when the caller should make one. Returns 0,
 * EXIT_USAGE or EXIT_FAIL after saying why.
 */
static int locate(farm_t *f, const char *bake_dir, const char *snapshot, char *data, size_t cap,
                  char *file, size_t fcap) {
  char real[FARM_PATH_CAP];
  data[0] = file[0] = '\0';
  if (bake_dir != NULL) {
    if (realpath(bake_dir, real) == NULL) {
      return farm_say(f, EXIT_FAIL, "cannot use bake directory %s: %s", bake_dir, strerror(errno));
    }
    const char *base = farm_split_path(real, data, cap);
    if (base[0] == '\0' || strlen(base) > NAME_MAX) {
      return usage(f, "the bake directory %s cannot be the root", bake_dir);
    }
    snprintf(f->bake_base, sizeof(f->bake_base), "%s", base);
  }
  if (snapshot == NULL) {
    return 0;
  }
  char snap[FARM_PATH_CAP];
  if (realpath(snapshot, snap) == NULL) {
    return farm_say(f, EXIT_FAIL, "cannot use snapshot %s: %s", snapshot, strerror(errno));
  }
  if (bake_dir == NULL) {
    snprintf(file, fcap, "%s", farm_split_path(snap, data, cap));
    return 0;
  }
  size_t n = strlen(data);
  const char *rel = snap + n + (strcmp(data, "/") != 0);
  if (strncmp(snap, data, n) != 0 || (strcmp(data, "/") != 0 && snap[n] != '/')) {
    fprintf(stderr,
            "volfx %s: snapshot %s lies outside %s, the parent directory of the bake %s: the "
            "server reads both from there (see volfx --help)\n",
            f->cmd, snapshot, data, bake_dir);
    return EXIT_USAGE;
  }
  snprintf(file, fcap, "%s", rel);
  return 0;
}

/* ---------------------------------------------------------------------------------------- */
/* volfx batch */

typedef struct batch {
  uint64_t first, last, step;
  const char *pattern; /* -o: file names with #### for the frame. */
  uint64_t raw_bytes;  /* The size of a raw frame; 0 for PNG. */
  cJSON *render;       /* The params of every render. */
  uint64_t antialias;  /* --antialias, or 0 to keep the scene's. */
  int overwrite;       /* --overwrite: render frames whose files are whole too. */
  mode_t mode;         /* Permissions of new frame files. */
  uint64_t written, skipped;
} batch_t;

/* Turns the option table into 'b'. Returns 0 or EXIT_USAGE after saying why. */
static int batch_options(farm_t *f, batch_t *b, const char *val[A_COUNT]) {
  uint64_t w = PROTO_DEFAULT_FRAME_SIDE, h = PROTO_DEFAULT_FRAME_SIDE, png_level = 0, aa = 0;
  if (val[A_FIRST] == NULL || val[A_LAST] == NULL || val[A_OUT] == NULL || !val[A_OUT][0]) {
    return usage(f, "needs -s FIRST, -e LAST and -o PATTERN%s", NULL);
  }
  static const int frames[] = {A_FIRST, A_LAST, A_STEP};
  uint64_t *dst[] = {&b->first, &b->last, &b->step};
  b->step = 1;
  for (int k = 0; k < 3; k++) {
    if (val[frames[k]] != NULL && !farm_parse_u64(val[frames[k]], k == 2, FRAME_MAX, dst[k])) {
      return usage(f, "bad number '%s': frames are whole numbers from 0 to 2^53-1, -j from 1",
                   val[frames[k]]);
    }
  }
  if (b->last < b->first) {
    return usage(f, "LAST (-e) is before FIRST (-s)%s", NULL);
  }
  b->pattern = val[A_OUT];
  if (strchr(b->pattern, '#') == NULL && b->first != b->last) {
    return usage(f, "-o '%s' has no # for the frame number, and there are several frames",
                 b->pattern);
  }
  if ((val[A_WIDTH] != NULL && !farm_parse_u64(val[A_WIDTH], 1, 1u << 20, &w)) ||
      (val[A_HEIGHT] != NULL && !farm_parse_u64(val[A_HEIGHT], 1, 1u << 20, &h))) {
    return usage(f, "-W and -H need whole numbers of pixels%s", NULL);
  }
  if (val[A_ANTIALIAS] != NULL && !farm_parse_u64(val[A_ANTIALIAS], 1, 64, &aa)) {
    return usage(f, "bad --antialias '%s' (samples per pixel along each axis)", val[A_ANTIALIAS]);
  }
  b->antialias = aa;
  const char *aov = val[A_AOV] != NULL ? val[A_AOV] : "beauty";
  /* Without --format, a beauty frame takes the format its file name's extension names. */
  const char *format = val[A_FORMAT], *named = farm_format_of_name(b->pattern);
  if (format == NULL) {
    format = strcmp(aov, "beauty") != 0 ? "f32" : named != NULL ? named : "png";
  }
  if (named != NULL && strcmp(named, format) != 0) {
    fprintf(
        stderr,
        "volfx %s: -o '%s' names %s files, but the frames are %s (--format) (see volfx --help)\n",
        f->cmd, b->pattern, named, format);
    return EXIT_USAGE;
  }
  static const struct {
    const char *name;
    unsigned bytes; /* Per pixel; 0 for an encoded format. */
  } formats[] = {{"png", 0}, {"rgba8", 4}, {"rgbaf32", 16}, {"f32", 4}, {"jpeg", 0}, {"webp", 0}};
  size_t k = 0, nformats = sizeof formats / sizeof formats[0];
  while (k < nformats && strcmp(format, formats[k].name) != 0) {
    k++;
  }
  if (k == nformats) {
    return usage(f, "bad --format '%s' (png, rgba8, rgbaf32, f32, jpeg or webp)", format);
  }
  b->raw_bytes = formats[k].bytes * w * h;
  b->render = farm_main_params();
  cJSON_AddNumberToObject(b->render, "width", (double)w);
  cJSON_AddNumberToObject(b->render, "height", (double)h);
  cJSON_AddStringToObject(b->render, "format", format);
  cJSON_AddStringToObject(b->render, "aov", aov);
  if (val[A_LAYERS] != NULL) {
    cJSON *layers = cJSON_AddArrayToObject(b->render, "layers");
    for (const char *s = val[A_LAYERS]; *s != '\0';) {
      size_t n = strcspn(s, ",");
      char *word = n > 0 ? strndup(s, n) : NULL;
      if (word != NULL) {
        cJSON_AddItemToArray(layers, cJSON_CreateString(word));
      }
      free(word);
      s += n + (s[n] == ',');
    }
  }
  if (val[A_CAMERA] != NULL) {
    cJSON *camera = cJSON_Parse(val[A_CAMERA]);
    if (!cJSON_IsObject(camera)) {
      cJSON_Delete(camera);
      return usage(f, "--camera needs a JSON object, not '%s'", val[A_CAMERA]);
    }
    cJSON_AddItemToObject(b->render, "camera", camera);
  }
  if (val[A_PNG_LEVEL] != NULL) {
    int minus = strcmp(val[A_PNG_LEVEL], "-1") == 0;
    if (!minus && !farm_parse_u64(val[A_PNG_LEVEL], 0, 9, &png_level)) {
      return usage(f, "bad --png-level '%s' (-1 to 9)", val[A_PNG_LEVEL]);
    }
    cJSON_AddNumberToObject(b->render, "png_level", minus ? -1 : (double)png_level);
  }
  if (val[A_QUALITY] != NULL) {
    uint64_t quality = 0;
    if (!farm_parse_u64(val[A_QUALITY], 1, 100, &quality)) {
      return usage(f, "bad --quality '%s' (1 to 100, for jpeg and webp)", val[A_QUALITY]);
    }
    cJSON_AddNumberToObject(b->render, "quality", (double)quality);
  }
  b->overwrite = val[A_OVERWRITE] != NULL;
  return 0;
}

/* Sets render.antialias when --antialias was given (again after each snapshot load). */
static int apply_antialias(farm_t *f, const batch_t *b) {
  if (b->antialias == 0) {
    return 0;
  }
  cJSON *p = farm_main_params();
  cJSON_AddStringToObject(p, "path", "render.antialias");
  cJSON_AddNumberToObject(p, "value", (double)b->antialias);
  cJSON *r = NULL;
  int rc = farm_call(f, "scene.set", p, &r, NULL);
  cJSON_Delete(r);
  return rc == 0 ? 0 : farm_say(f, EXIT_FAIL, "%s", f->why);
}

/*
 * Brings the main scene to 'frame': from the bake's latest snapshot at or before it when that
 * is nearer than the scene's own frame (or the scene is past it), then by sim.step. Returns 0
 * or EXIT_FAIL after saying why.
 */
static int reach_frame(farm_t *f, const batch_t *b, uint64_t frame) {
  long k = snapshot_before(f, frame);
  if (k >= 0 && (f->snaps[k] > f->frame || f->frame > frame)) {
    char file[FARM_PATH_CAP];
    snapshot_file(f, f->snaps[k], file, sizeof(file));
    if (load_snapshot(f, file) != 0) {
      return farm_say(f, EXIT_FAIL, "cannot start from the bake's %s: %s", file, f->why);
    }
    if (f->verbose) {
      farm_say(f, 0, "starting from %s", file);
    }
    int rc = apply_antialias(f, b);
    if (rc != 0) {
      return rc;
    }
  }
  if (f->frame > frame) {
    return farm_say(f, EXIT_FAIL, "the scene starts at frame %" PRIu64 ", after this one",
                    f->frame);
  }
  while (f->frame < frame) {
    uint64_t n = frame - f->frame < STEPS_MAX ? frame - f->frame : STEPS_MAX;
    cJSON *p = farm_main_params();
    cJSON_AddNumberToObject(p, "steps", (double)n);
    cJSON *r = NULL;
    if (farm_call(f, "sim.step", p, &r, NULL) != 0) {
      return farm_say(f, EXIT_FAIL, "%s", f->why);
    }
    double now = farm_num(r, "frame", -1);
    cJSON_Delete(r);
    if (now <= (double)f->frame) {
      return farm_say(f, EXIT_FAIL, "sim.step: the scene stays at frame %" PRIu64, f->frame);
    }
    f->frame = (uint64_t)now;
  }
  return 0;
}

/* Renders 'frame' into 'path'. Returns 0 or EXIT_FAIL after saying why. */
static int render_frame(farm_t *f, batch_t *b, uint64_t frame, const char *path) {
  int rc = reach_frame(f, b, frame);
  if (rc != 0) {
    return rc;
  }
  volfx_attachment_t att;
  cJSON *r = NULL;
  if (farm_call(f, "render", cJSON_Duplicate(b->render, 1), &r, &att) != 0) {
    return farm_say(f, EXIT_FAIL, "%s", f->why);
  }
  cJSON_Delete(r);
  char why[FARM_PATH_CAP + 128];
  if (!farm_bytes_whole(att.data, att.len, b->raw_bytes)) {
    rc = farm_say(f, EXIT_FAIL, "render: %zu bytes of %s that are not a whole frame", att.len,
                  att.format);
  } else if (farm_write_atomic(path, att.data, att.len, b->mode, why, sizeof(why)) != 0) {
    rc = farm_say(f, EXIT_FAIL, "%s", why);
  } else {
    b->written++;
    if (f->verbose) {
      farm_say(f, 0, "wrote %s (%zu bytes)", path, att.len);
    }
  }
  volfx_attachment_free(&att);
  return rc;
}

/* Renders every frame of the range that is missing or, with --overwrite, every frame. */
static int batch_frames(farm_t *f, batch_t *b) {
  char path[FARM_PATH_CAP];
  for (uint64_t frame = b->first; frame <= b->last; frame += b->step) {
    snprintf(f->where, sizeof(f->where), "frame %" PRIu64 ": ", frame);
    if (farm_stop_signal != 0) {
      return farm_say(f, EXIT_FAIL, "interrupted by %s", farm_signal_name(farm_stop_signal));
    }
    farm_expand_pattern(b->pattern, frame, path, sizeof(path));
    if (!b->overwrite && farm_file_whole(path, b->raw_bytes)) {
      b->skipped++;
      if (f->verbose) {
        farm_say(f, 0, "skipped, %s is complete", path);
      }
      continue;
    }
    int rc = render_frame(f, b, frame, path);
    if (rc != 0) {
      return rc;
    }
  }
  f->where[0] = '\0';
  return 0;
}

/* Starts the server for the batch and renders. Returns an exit status. */
static int batch_run(farm_t *f, batch_t *b, const char *scene, const char *bake_dir) {
  char path[FARM_PATH_CAP], dir[FARM_PATH_CAP], bad[FARM_PATH_CAP];
  uint64_t todo = 0;
  int found = 0;
  for (uint64_t frame = b->first; frame <= b->last && !found; frame += b->step) {
    if (farm_expand_pattern(b->pattern, frame, path, sizeof(path)) != 0) {
      return usage(f, "-o '%s' makes too long a path", b->pattern);
    }
    found = b->overwrite || !farm_file_whole(path, b->raw_bytes);
    todo = frame;
  }
  if (!found) {
    uint64_t n = (b->last - b->first) / b->step + 1;
    printf("volfx batch: nothing left to do: all %" PRIu64 " frames are complete\n", n);
    b->skipped = n;
    return 0;
  }
  int snapshot = farm_is_snapshot(scene);
  char data[FARM_PATH_CAP], file[FARM_PATH_CAP];
  int rc = locate(f, bake_dir, snapshot ? scene : NULL, data, sizeof(data), file, sizeof(file));
  if (rc != 0) {
    return rc;
  }
  cJSON *manifest = NULL;
  if (bake_dir != NULL && (rc = read_manifest(f, bake_dir, 0, &manifest)) != 0) {
    return rc;
  }
  if (bake_dir != NULL && list_snapshots(f, bake_dir) != 0) {
    cJSON_Delete(manifest);
    return farm_say(f, EXIT_FAIL, "cannot list %s: %s", bake_dir, strerror(errno));
  }
  snprintf(f->where, sizeof(f->where), "frame %" PRIu64 ": ", todo);
  farm_expand_pattern(b->pattern, todo, path, sizeof(path));
  farm_split_path(path, dir, sizeof(dir));
  if (farm_make_dirs(dir, bad, sizeof(bad)) != 0) {
    cJSON_Delete(manifest);
    return farm_say(f, EXIT_FAIL, "cannot write %s: %s: %s", path, bad, strerror(errno));
  }
  if (data[0] == '\0') {
    const char *tmp = getenv("TMPDIR");
    snprintf(f->tmp_data, sizeof(f->tmp_data), "%s/volfx-batch-XXXXXX",
             tmp != NULL && tmp[0] != '\0' ? tmp : "/tmp");
    if (mkdtemp(f->tmp_data) == NULL) {
      f->tmp_data[0] = '\0';
      cJSON_Delete(manifest);
      return farm_say(f, EXIT_FAIL, "cannot make a data directory: %s", strerror(errno));
    }
    snprintf(data, sizeof(data), "%s", f->tmp_data);
  }
  rc = open_scene(f, data, scene, snapshot, file, manifest, bake_dir);
  cJSON_Delete(manifest);
  if (rc == 0) {
    rc = apply_antialias(f, b);
  }
  return rc != 0 ? rc : batch_frames(f, b);
}

int cli_batch(int argc, char **argv) {
  farm_t f = {.cmd = "batch"};
  batch_t b = {0};
  const char *val[A_COUNT] = {0};
  const char *scene = NULL;
  int rc = parse_args(&f, argc, argv, BATCH_OPTS, val, &scene);
  if (rc == 0) {
    rc = batch_options(&f, &b, val);
  }
  if (rc != 0) {
    cJSON_Delete(b.render);
    return rc;
  }
  f.presets = val[A_PRESETS];
  f.device = val[A_DEVICE];
  f.verbose = val[A_VERBOSE] != NULL;
  mode_t mask = umask(0);
  umask(mask);
  b.mode = 0666 & ~mask;
  farm_catch_signals();
  rc = batch_run(&f, &b, scene, val[A_BAKE]);
  cJSON_Delete(b.render);
  if (rc != EXIT_USAGE) {
    printf("volfx batch: %" PRIu64 " frames written, %" PRIu64 " skipped (%" PRIu64 "..%" PRIu64
           ")\n",
           b.written, b.skipped, b.first, b.last);
  }
  return farm_finish(&f, rc);
}

/* ---------------------------------------------------------------------------------------- */
/* volfx bake */

/* Loads the latest snapshot of the bake at or before 'last' that is ahead of the scene, trying
 * older ones when one does not load. Returns the frame loaded, or -1 when none was. */
static int64_t resume_bake(farm_t *f, const char *dir, uint64_t last) {
  for (long k = snapshot_before(f, last); k >= 0; k--) {
    if (f->snaps[k] <= f->frame && f->frame <= last) {
      return -1; /* The scene is there already. */
    }
    char file[FARM_PATH_CAP];
    snapshot_file(f, f->snaps[k], file, sizeof(file));
    if (load_snapshot(f, file) == 0) {
      if (f->verbose) {
        farm_say(f, 0, "resuming from %s/%s", dir, strchr(file, '/') + 1);
      }
      return (int64_t)f->frame;
    }
    farm_say(f, 0, "%s/%s does not load (%s); trying an older one", dir, strchr(file, '/') + 1,
             f->why);
  }
  return -1;
}

/* Runs sim.bake to 'last' and waits for its job to end. Returns an exit status. */
static int bake_job(farm_t *f, const char *dir, uint64_t last, uint64_t every, double *written) {
  cJSON *p = farm_main_params();
  cJSON_AddStringToObject(p, "dir", f->bake_base);
  cJSON_AddNumberToObject(p, "last", (double)last);
  cJSON_AddNumberToObject(p, "every", (double)every);
  cJSON *r = NULL;
  if (farm_call(f, "sim.bake", p, &r, NULL) != 0) {
    return farm_say(f, EXIT_FAIL, "%s", f->why);
  }
  double id = farm_num(r, "id", -1);
  cJSON_Delete(r);
  for (;;) {
    if (farm_stop_signal != 0) {
      return farm_say(f, EXIT_FAIL, "interrupted by %s", farm_signal_name(farm_stop_signal));
    }
    cJSON *msg = NULL;
    int rc = volfx_next_notification(f->conn, "job.progress", 500, &msg, NULL);
    if (rc == VOLFX_E_TIMEOUT || rc == VOLFX_E_INTR) {
      continue;
    }
    if (rc != 0) {
      return farm_say(f, EXIT_FAIL, "sim.bake: %s", volfx_strerror(rc));
    }
    const cJSON *jp = cJSON_GetObjectItemCaseSensitive(msg, "params");
    const char *state = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(jp, "state"));
    const char *file = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(jp, "last"));
    const char *why = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(jp, "error"));
    int ours = farm_num(jp, "id", -2) == id;
    *written = ours ? farm_num(jp, "done", *written) : *written;
    if (ours && f->verbose && file != NULL && file[0] != '\0') {
      const char *slash = strrchr(file, '/');
      farm_say(f, 0, "wrote %s/%s (%.0f of %.0f)", dir, slash != NULL ? slash + 1 : file, *written,
               farm_num(jp, "total", 0));
    }
    int ended = ours && (state == NULL || strcmp(state, "running") != 0);
    if (ended) {
      rc = state != NULL && strcmp(state, "done") == 0
               ? 0
               : farm_say(f, EXIT_FAIL, "sim.bake %s%s%s", state != NULL ? state : "ended",
                          why != NULL ? ": " : "", why != NULL ? why : "");
    }
    cJSON_Delete(msg);
    if (ended) {
      return rc;
    }
  }
}

/* Starts the server for the bake, resumes and bakes. Returns an exit status. */
static int bake_run(farm_t *f, const char *scene, const char *dir, uint64_t last, uint64_t every,
                    double *written, uint64_t *from) {
  char bad[FARM_PATH_CAP], data[FARM_PATH_CAP], file[FARM_PATH_CAP];
  struct stat st;
  int existed = stat(dir, &st) == 0;
  if (farm_make_dirs(dir, bad, sizeof(bad)) != 0) {
    return farm_say(f, EXIT_FAIL, "cannot create directory %s: %s", bad, strerror(errno));
  }
  int snapshot = farm_is_snapshot(scene);
  int rc = locate(f, dir, snapshot ? scene : NULL, data, sizeof(data), file, sizeof(file));
  if (rc == EXIT_USAGE && !existed) {
    rmdir(dir); /* A command-line mistake leaves nothing behind. */
  }
  cJSON *manifest = NULL;
  if (rc != 0 || (rc = read_manifest(f, dir, 1, &manifest)) != 0) {
    return rc;
  }
  double had = farm_num(manifest, "every", (double)every);
  if (had != (double)every) {
    cJSON_Delete(manifest);
    return farm_say(f, EXIT_FAIL, "bake %s was made every %.0f frames, not %" PRIu64 " (-k)", dir,
                    had, every);
  }
  if (list_snapshots(f, dir) != 0) {
    cJSON_Delete(manifest);
    return farm_say(f, EXIT_FAIL, "cannot list %s: %s", dir, strerror(errno));
  }
  rc = open_scene(f, data, scene, snapshot, file, manifest, dir);
  cJSON_Delete(manifest);
  if (rc != 0) {
    return rc;
  }
  int64_t resumed = resume_bake(f, dir, last);
  *from = f->frame;
  if (f->frame > last) {
    return farm_say(f, EXIT_FAIL, "the scene is at frame %" PRIu64 ", after LAST %" PRIu64,
                    f->frame, last);
  }
  if (resumed >= 0 && (uint64_t)resumed == last) {
    printf("volfx bake: nothing left to do: %s holds frame %" PRIu64 "\n", dir, last);
    return 0;
  }
  return bake_job(f, dir, last, every, written);
}

int cli_bake(int argc, char **argv) {
  farm_t f = {.cmd = "bake"};
  const char *val[A_COUNT] = {0};
  const char *scene = NULL;
  uint64_t last = 0, every = PROTO_DEFAULT_BAKE_EVERY, from = 0;
  int rc = parse_args(&f, argc, argv, BAKE_OPTS, val, &scene);
  if (rc != 0) {
    return rc;
  }
  if (val[A_LAST] == NULL || val[A_OUT] == NULL || !val[A_OUT][0]) {
    return usage(&f, "needs -e LAST and -o DIR%s", NULL);
  }
  if (!farm_parse_u64(val[A_LAST], 0, FRAME_MAX, &last)) {
    return usage(&f, "bad frame number '%s' (a whole number from 0 to 2^53-1)", val[A_LAST]);
  }
  if (val[A_EVERY] != NULL && !farm_parse_u64(val[A_EVERY], 1, FRAME_MAX, &every)) {
    return usage(&f, "bad -k '%s' (frames between snapshots, from 1)", val[A_EVERY]);
  }
  f.presets = val[A_PRESETS];
  f.device = val[A_DEVICE];
  f.verbose = val[A_VERBOSE] != NULL;
  farm_catch_signals();
  double written = 0;
  rc = bake_run(&f, scene, val[A_OUT], last, every, &written, &from);
  if (rc != EXIT_USAGE) {
    printf("volfx bake: %.0f snapshots written to %s (frames %" PRIu64 "..%" PRIu64
           ", every %" PRIu64 ")\n",
           written, val[A_OUT], from, last, every);
  }
  return farm_finish(&f, rc);
}
