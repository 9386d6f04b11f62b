/*
 * The files a scene names, and their cache (scene_files.h). Lookups run on the loop thread;
 * scene_file_load runs on any thread. The lock guards only the cache's list: files are read
 * and parsed outside it, so a long read holds up no lookup of another file.
 */
#include "scene_files.h"

#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "datapath.h"
#include "proto.h"

static char *g_data_dir; /* Owned copy of the directory files are resolved under, or NULL. */

/* One cached file: a mesh, or a grid of given dims and format. */
typedef struct file_entry {
  char *path; /* Resolved (real) path. */
  dev_t dev;
  ino_t ino;
  off_t size;
  struct timespec mtime;
  int grid;
  uint32_t dims[3];
  int u8;
  mesh_t *mesh;
  density_grid_t *data;
  /* A read that failed, kept while the request that read it pins it (scene_pin_t.fault) and
   * until the next prune after that: the request runs again and answers with this error in
   * its own words, however long its retry takes to come (scene.load reads its snapshot again
   * first). */
  int failed;
  scene_error_t fault;
  int pins;     /* Guarded by g_lock. */
  int unlinked; /* Out of the list (its file changed) but still pinned: freed by the last pin. */
  struct file_entry *next;
} file_entry_t;

static pthread_mutex_t g_lock = PTHREAD_MUTEX_INITIALIZER;
static file_entry_t *g_files; /* Guarded by g_lock. */
static scene_file_t *g_want;  /* Armed deferral (loop thread only), or NULL. */

static int fail(scene_error_t *err, int code, const char *path, const char *fmt, ...) {
  if (!err)
    return -1;
  err->code = code;
  snprintf(err->path, sizeof err->path, "%s", path);
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(err->message, sizeof err->message, fmt, ap);
  va_end(ap);
  return -1;
}

void scene_set_data_dir(const char *dir) {
  free(g_data_dir);
  g_data_dir = dir ? strdup(dir) : NULL;
}

void scene_files_defer(scene_file_t *want) {
  g_want = want;
}

static void entry_free(file_entry_t *e) {
  mesh_unref(e->mesh);
  density_grid_unref(e->data);
  free(e->path);
  free(e);
}

static int entry_refs(const file_entry_t *e) {
  if (e->failed)
    return e->pins > 0 ? 2 : 0;
  return e->grid ? atomic_load(&e->data->refs) : atomic_load(&e->mesh->refs);
}

/* A file whose only reference is the cache's cannot gain another except through the cache,
 * and the lock is held, so reading the count is enough. */
void scene_files_prune(void) {
  pthread_mutex_lock(&g_lock);
  for (file_entry_t **pp = &g_files; *pp;) {
    file_entry_t *e = *pp;
    if (entry_refs(e) <= 1) {
      *pp = e->next;
      entry_free(e);
    } else {
      pp = &e->next;
    }
  }
  pthread_mutex_unlock(&g_lock);
}

static int same_key(const file_entry_t *e, const scene_file_t *f) {
  return e->grid == f->grid && strcmp(e->path, f->real) == 0 &&
         (!f->grid || (memcmp(e->dims, f->dims, sizeof e->dims) == 0 && e->u8 == f->u8));
}

static int same_stat(const file_entry_t *e, const struct stat *st) {
  return e->dev == st->st_dev && e->ino == st->st_ino && e->size == st->st_size &&
         e->mtime.tv_sec == st->st_mtim.tv_sec && e->mtime.tv_nsec == st->st_mtim.tv_nsec;
}

/* Takes a reference to the cached contents of 'f' into 'pin': 1 when cached, 0 when not, -1
 * with 'err' set when the read of this very file failed just before, for the field 'f' names.
 * An entry for the same file whose stat changed is dropped: snapshots keep the old contents,
 * new ones read the new file. */
static int lookup(const scene_file_t *f, scene_pin_t *pin, scene_error_t *err) {
  int hit = 0;
  pthread_mutex_lock(&g_lock);
  for (file_entry_t **pp = &g_files; *pp; pp = &(*pp)->next) {
    file_entry_t *e = *pp;
    if (!same_key(e, f))
      continue;
    if (same_stat(e, &f->st) && e->failed) {
      if (strcmp(e->fault.path, f->path) == 0 && err) {
        *err = e->fault;
        hit = -1;
      }
    } else if (same_stat(e, &f->st)) {
      pin->mesh = e->mesh ? mesh_ref(e->mesh) : NULL;
      pin->grid = e->data ? density_grid_ref(e->data) : NULL;
      hit = 1;
    } else {
      *pp = e->next;
      if (e->failed && e->pins > 0)
        e->unlinked = 1;
      else
        entry_free(e);
    }
    break;
  }
  pthread_mutex_unlock(&g_lock);
  return hit;
}

/* Caches what 'pin' holds as the contents of 'f', unless another thread cached the same file
 * meanwhile: then 'pin' is switched to that copy. Out of memory leaves it uncached. */
static void insert(const scene_file_t *f, scene_pin_t *pin, const scene_error_t *fault) {
  pthread_mutex_lock(&g_lock);
  for (file_entry_t *e = g_files; e; e = e->next)
    if (same_key(e, f) && same_stat(e, &f->st) && !e->failed && !fault) {
      scene_pin_release(pin);
      pin->mesh = e->mesh ? mesh_ref(e->mesh) : NULL;
      pin->grid = e->data ? density_grid_ref(e->data) : NULL;
      pthread_mutex_unlock(&g_lock);
      return;
    }
  file_entry_t *e = calloc(1, sizeof *e);
  if (e && (e->path = strdup(f->real))) {
    e->dev = f->st.st_dev;
    e->ino = f->st.st_ino;
    e->size = f->st.st_size;
    e->mtime = f->st.st_mtim;
    e->grid = f->grid;
    memcpy(e->dims, f->dims, sizeof e->dims);
    e->u8 = f->u8;
    e->mesh = pin->mesh ? mesh_ref(pin->mesh) : NULL;
    e->data = pin->grid ? density_grid_ref(pin->grid) : NULL;
    if (fault) {
      e->failed = 1;
      e->fault = *fault;
      e->pins = 1;
      pin->fault = e;
    }
    e->next = g_files;
    g_files = e;
  } else {
    free(e);
  }
  pthread_mutex_unlock(&g_lock);
}

void scene_pin_release(scene_pin_t *pin) {
  mesh_unref(pin->mesh);
  density_grid_unref(pin->grid);
  pin->mesh = NULL;
  pin->grid = NULL;
  if (pin->fault) {
    file_entry_t *e = pin->fault;
    pthread_mutex_lock(&g_lock);
    if (--e->pins == 0 && e->unlinked)
      entry_free(e);
    pthread_mutex_unlock(&g_lock);
    pin->fault = NULL;
  }
}

/* Replaces the absolute 'real' path in a loader message by the client's 'file', so errors do
 * not reveal where the data directory lives. */
static void scrub_message(char *msg, size_t len, const char *real, const char *file) {
  char *at = strstr(msg, real);
  if (!at)
    return;
  char tail[256];
  snprintf(tail, sizeof tail, "%s", at + strlen(real));
  snprintf(at, len - (size_t)(at - msg), "%s%s", file, tail);
}

/* The densities of grid file 'f': u8 (byte / 255) or f32 (little-endian, finite and
 * non-negative). NULL with 'err' set on failure. */
static density_grid_t *grid_read(const scene_file_t *f, scene_error_t *err) {
  const char *p = f->path;
  size_t n = (size_t)f->dims[0] * f->dims[1] * f->dims[2], want = n * (f->u8 ? 1 : 4);
  if ((uint64_t)f->st.st_size != want) {
    fail(err, PROTO_E_INVALID_PARAMS, p,
         "%s: \"%.64s\" holds %lld bytes, but dims %ux%ux%u of %s need %zu", p, f->file,
         (long long)f->st.st_size, f->dims[0], f->dims[1], f->dims[2], f->u8 ? "u8" : "f32", want);
    return NULL;
  }
  density_grid_t *g = density_grid_new(f->dims);
  unsigned char *raw = malloc(want ? want : 1);
  if (!g || !raw) {
    density_grid_unref(g);
    free(raw);
    fail(err, PROTO_E_INTERNAL, p, "%s: out of memory for a %zu-voxel grid", p, n);
    return NULL;
  }
  FILE *fp = fopen(f->real, "rb");
  size_t got = fp ? fread(raw, 1, want, fp) : 0;
  if (fp)
    fclose(fp);
  if (got != want) {
    density_grid_unref(g);
    free(raw);
    fail(err, PROTO_E_INVALID_PARAMS, p, "%s: cannot read \"%.64s\"", p, f->file);
    return NULL;
  }
  for (size_t i = 0; i < n; i++) {
    float v;
    if (f->u8) {
      v = raw[i] / 255.0f;
    } else {
      uint32_t b = (uint32_t)raw[4 * i] | (uint32_t)raw[4 * i + 1] << 8 |
                   (uint32_t)raw[4 * i + 2] << 16 | (uint32_t)raw[4 * i + 3] << 24;
      memcpy(&v, &b, sizeof v);
      if (!isfinite(v) || v < 0) {
        size_t x = i % f->dims[0], y = i / f->dims[0] % f->dims[1];
        size_t z = i / f->dims[0] / f->dims[1];
        density_grid_unref(g);
        free(raw);
        fail(err, PROTO_E_INVALID_PARAMS, p,
             "%s: \"%.64s\" has density %g at voxel (%zu, %zu, %zu); densities must be finite "
             "and non-negative",
             p, f->file, (double)v, x, y, z);
        return NULL;
      }
    }
    g->data[i] = v;
  }
  free(raw);
  return g;
}

int scene_file_load(const scene_file_t *f, scene_pin_t *pin, scene_error_t *err) {
  scene_error_t local;
  if (!err)
    err = &local;
  pin->mesh = NULL;
  pin->grid = NULL;
  pin->fault = NULL;
  int ok;
  if (f->grid) {
    ok = (pin->grid = grid_read(f, err)) != NULL;
  } else {
    char why[256] = "";
    ok = (pin->mesh = mesh_load_obj(f->real, why, sizeof why)) != NULL;
    if (!ok) {
      scrub_message(why, sizeof why, f->real, f->file);
      fail(err, PROTO_E_INVALID_PARAMS, f->path, "%s: %s", f->path,
           why[0] ? why : "cannot load the mesh");
    }
  }
  insert(f, pin, ok ? NULL : err);
  return ok ? 0 : -1;
}

/* Resolves the client's 'file' for field 'path' into 'f' (a regular file under the data
 * directory). */
static int resolve(const char *file, const char *path, scene_file_t *f, scene_error_t *err) {
  char why[256];
  snprintf(f->file, sizeof f->file, "%s", file);
  snprintf(f->path, sizeof f->path, "%s", path);
  if (datapath_resolve(g_data_dir, file, 1, f->real, sizeof f->real, why, sizeof why, NULL) != 0)
    return fail(err, PROTO_E_INVALID_PARAMS, path, "%s: %s", path, why);
  if (stat(f->real, &f->st) != 0 || !S_ISREG(f->st.st_mode))
    return fail(err, PROTO_E_INVALID_PARAMS, path, "%s: \"%.64s\" is not a regular file", path,
                file);
  return 0;
}

/* The contents of 'f' into 'pin': cached, read now, or (deferral armed) recorded. */
static int get(scene_file_t *f, scene_pin_t *pin, scene_error_t *err) {
  int cached = lookup(f, pin, err);
  if (cached)
    return cached > 0 ? 0 : -1;
  if (g_want) {
    *g_want = *f;
    return fail(err, SCENE_DEFERRED, f->path, "%s: \"%.64s\" is being read", f->path, f->file);
  }
  return scene_file_load(f, pin, err);
}

mesh_t *scene_mesh_get(const char *file, const char *path, scene_error_t *err) {
  scene_file_t f = {.grid = 0};
  scene_pin_t pin = {0};
  if (resolve(file, path, &f, err) != 0 || get(&f, &pin, err) != 0) {
    scene_pin_release(&pin); /* A fault read on the spot stays cached only until a prune. */
    return NULL;
  }
  return pin.mesh;
}

density_grid_t *scene_grid_get(const char *file, int index, const uint32_t dims[3], int u8,
                               scene_error_t *err) {
  char p[64];
  snprintf(p, sizeof p, "volumes.%d.file", index);
  scene_file_t f = {.grid = 1, .dims = {dims[0], dims[1], dims[2]}, .u8 = u8};
  scene_pin_t pin = {0};
  if (resolve(file, p, &f, err) != 0 || get(&f, &pin, err) != 0) {
    scene_pin_release(&pin);
    return NULL;
  }
  return pin.grid;
}
