/*
 * The files a scene names, and their cache (scene_files.h). Lookups run on the loop thread;
 * scene_file_load runs on any thread. The lock guards only the cache's list: files are read
 * and parsed outside it, so a long read holds up no lookup of another file. Every file is
 * opened beneath the data directory (datapath.h), and its contents are read from the very
 * descriptor whose stat keys them.
 */
#include "scene_files.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <pthread.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "datapath.h"
#include "proto.h"

/* One cached file: a mesh, or a grid of given dims and format. */
typedef struct file_entry {
  char *path; /* The file's name under the data directory. */
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
  proto_error_t fault;
  int pins;     /* Guarded by g_lock. */
  int unlinked; /* Out of the list (its file changed) but still pinned: freed by the last pin. */
  struct file_entry *next;
} file_entry_t;

static pthread_mutex_t g_lock = PTHREAD_MUTEX_INITIALIZER;
static file_entry_t *g_files; /* Guarded by g_lock. */
static scene_file_t *g_want;  /* Armed deferral (loop thread only), or NULL. */

/* The data directory is opened here, once, for every file a request names (snapshots and job
 * output too): scene_set_data_dir is what start-up calls with it. */
void scene_set_data_dir(const char *dir) {
  datapath_init(dir);
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
static int lookup(const scene_file_t *f, scene_pin_t *pin, proto_error_t *err) {
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
static void insert(const scene_file_t *f, scene_pin_t *pin, const proto_error_t *fault) {
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

/* The densities of grid file 'f', open at 'fd' with stat 'st': u8 (byte / 255) or f32
 * (little-endian, finite and non-negative). NULL with 'err' set on failure. */
static density_grid_t *grid_read(const scene_file_t *f, int fd, const struct stat *st,
                                 proto_error_t *err) {
  const char *p = f->path;
  size_t n = (size_t)f->dims[0] * f->dims[1] * f->dims[2], want = n * (f->u8 ? 1 : 4);
  if ((uint64_t)st->st_size != want) {
    proto_error_set(err, PROTO_E_INVALID_PARAMS, p,
                    "%s: \"%.64s\" holds %lld bytes, but dims %ux%ux%u of %s need %zu", p, f->file,
                    (long long)st->st_size, f->dims[0], f->dims[1], f->dims[2],
                    f->u8 ? "u8" : "f32", want);
    return NULL;
  }
  density_grid_t *g = density_grid_new(f->dims);
  size_t got = 0;
  unsigned char *raw = g ? (unsigned char *)datapath_fd_read(fd, want, &got) : NULL;
  if (!g || (!raw && errno == ENOMEM)) {
    density_grid_unref(g);
    free(raw);
    proto_error_set(err, PROTO_E_INTERNAL, p, "%s: out of memory for a %zu-voxel grid", p, n);
    return NULL;
  }
  if (!raw || got != want) {
    density_grid_unref(g);
    free(raw);
    proto_error_set(err, PROTO_E_INVALID_PARAMS, p, "%s: cannot read \"%.64s\"%s", p, f->file,
                    raw ? ": it was cut short while read" : "");
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
        proto_error_set(
            err, PROTO_E_INVALID_PARAMS, p,
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

/* The mesh in the OBJ file 'f', open at 'fd' with stat 'st'. NULL with 'err' set. */
static mesh_t *mesh_read(const scene_file_t *f, int fd, const struct stat *st, proto_error_t *err) {
  if ((uint64_t)st->st_size > MESH_OBJ_MAX_BYTES) {
    proto_error_set(err, PROTO_E_INVALID_PARAMS, f->path,
                    "%s: \"%.64s\" is %lld bytes, over the limit of %u", f->path, f->file,
                    (long long)st->st_size, MESH_OBJ_MAX_BYTES);
    return NULL;
  }
  size_t len;
  char *text = datapath_fd_read(fd, (size_t)st->st_size, &len);
  if (!text) {
    proto_error_set(err, errno == ENOMEM ? PROTO_E_INTERNAL : PROTO_E_INVALID_PARAMS, f->path,
                    "%s: cannot read \"%.64s\": %s", f->path, f->file, strerror(errno));
    return NULL;
  }
  char why[256] = "";
  mesh_t *m = mesh_parse_obj(text, len, f->file, why, sizeof why);
  free(text);
  if (!m)
    proto_error_set(err, PROTO_E_INVALID_PARAMS, f->path, "%s: %s", f->path,
                    why[0] ? why : "cannot load the mesh");
  return m;
}

int scene_file_load(const scene_file_t *f, scene_pin_t *pin, proto_error_t *err) {
  proto_error_t local;
  if (!err)
    err = &local;
  pin->mesh = NULL;
  pin->grid = NULL;
  pin->fault = NULL;
  /* The file read is the one opened now, which may differ from the one the lookup saw: it is
   * cached under the stat of what was read. */
  scene_file_t now = *f;
  int fd = datapath_open_regular(f->real, SIZE_MAX, &now.st);
  int ok = 0;
  if (fd < 0) {
    char why[256];
    int code = datapath_error(errno, f->file, 0, 0, why, sizeof why);
    proto_error_set(err, code == PROTO_E_INTERNAL ? code : PROTO_E_INVALID_PARAMS, f->path,
                    "%s: %s", f->path, why);
    now.st = f->st;
  } else if (f->grid) {
    ok = (pin->grid = grid_read(f, fd, &now.st, err)) != NULL;
  } else {
    ok = (pin->mesh = mesh_read(f, fd, &now.st, err)) != NULL;
  }
  if (fd >= 0)
    close(fd);
  insert(&now, pin, ok ? NULL : err);
  return ok ? 0 : -1;
}

/* Finds the client's 'file' for field 'path' and fills 'f' (a regular file under the data
 * directory). The stat comes from a descriptor opened beneath the data directory with O_PATH,
 * which reads nothing and so cannot block on a FIFO. */
static int resolve(const char *file, const char *path, scene_file_t *f, proto_error_t *err) {
  char why[256];
  snprintf(f->file, sizeof f->file, "%s", file);
  snprintf(f->path, sizeof f->path, "%s", path);
  snprintf(f->real, sizeof f->real, "%s", file);
  if (datapath_check(file, why, sizeof why) != 0)
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, path, "%s: %s", path, why);
  int fd = datapath_open(file, O_PATH, 0);
  int e = fd < 0 || fstat(fd, &f->st) != 0 ? errno : 0;
  if (fd >= 0)
    close(fd);
  if (!e && !S_ISREG(f->st.st_mode))
    e = S_ISDIR(f->st.st_mode) ? EISDIR : S_ISLNK(f->st.st_mode) ? ELOOP : ENODEV;
  if (e) {
    int code = datapath_error(e, file, 0, 0, why, sizeof why);
    return proto_error_set(err, code == PROTO_E_INTERNAL ? code : PROTO_E_INVALID_PARAMS, path,
                           "%s: %s", path, why);
  }
  return 0;
}

/* The contents of 'f' into 'pin': cached, read now, or (deferral armed) recorded. */
static int get(scene_file_t *f, scene_pin_t *pin, proto_error_t *err) {
  int cached = lookup(f, pin, err);
  if (cached)
    return cached > 0 ? 0 : -1;
  if (g_want) {
    *g_want = *f;
    return proto_error_set(err, SCENE_DEFERRED, f->path, "%s: \"%.64s\" is being read", f->path,
                           f->file);
  }
  return scene_file_load(f, pin, err);
}

mesh_t *scene_mesh_get(const char *file, const char *path, proto_error_t *err) {
  scene_file_t f = {.grid = 0};
  scene_pin_t pin = {0};
  if (resolve(file, path, &f, err) != 0 || get(&f, &pin, err) != 0) {
    scene_pin_release(&pin); /* A fault read on the spot stays cached only until a prune. */
    return NULL;
  }
  return pin.mesh;
}

density_grid_t *scene_grid_get(const char *file, int index, const uint32_t dims[3], int u8,
                               proto_error_t *err) {
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
