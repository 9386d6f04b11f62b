/*
 * The files a scene document names: OBJ meshes (objects[].file) and raw volume grids
 * (volumes[].file), opened beneath the data directory and cached by name, inode, size and mtime
 * (grids also by dims and format), so that changes which keep a file do not read it
 * again. The cache holds one reference to each file's contents; snapshots hold their own.
 *
 * A lookup that misses reads the file on the spot, unless the caller armed a deferral
 * (scene_files_defer): then the miss is recorded in a scene_file_t and the lookup fails with
 * SCENE_DEFERRED, changing nothing. The caller reads the file elsewhere (scene_file_load, on
 * any thread; server/defer.c runs it on libuv's thread pool) and tries the change again, which
 * then finds the file cached. So a client adding a large mesh does not stall the loop thread
 * that every other client is served from.
 */
#ifndef VOLFX_SCENE_FILES_H
#define VOLFX_SCENE_FILES_H

#include <limits.h>
#include <stdint.h>
#include <sys/stat.h>

#include "proto_error.h"
#include "render_scene.h"

/* proto_error_t.code of a change that needs a file read first (not a protocol code). */
#define SCENE_DEFERRED 1

/* A file a change needs that the cache lacks: enough to read it anywhere, and to name it in
 * errors as the client wrote it. */
typedef struct scene_file {
  int grid;            /* 0 an OBJ mesh, 1 a raw volume grid. */
  char real[PATH_MAX]; /* Its key in the cache: its name under the data directory. */
  struct stat st;      /* Its stat when it was looked up. */
  char file[256];      /* The client's name for it. */
  char path[64];       /* The field naming it ("objects.3.file", "volumes.0.file"). */
  uint32_t dims[3];    /* For a grid: voxels along x, y, z. */
  int u8;              /* For a grid: 1 bytes, 0 little-endian floats. */
} scene_file_t;

/* A loaded file's contents, referenced on behalf of a request until it is answered, so the
 * cache keeps them however its other entries come and go. */
typedef struct scene_pin {
  mesh_t *mesh;
  density_grid_t *grid;
  struct file_entry *fault; /* A failed read, kept cached for the request; else NULL. */
} scene_pin_t;

/* Sets the directory relative to which mesh files are resolved (the data directory). Paths
 * that would leave it are refused. NULL refuses every mesh file. */
void scene_set_data_dir(const char *dir);

/* Until called again with NULL, a lookup that misses fills '*want' and fails with
 * SCENE_DEFERRED instead of reading the file. Loop thread only. */
void scene_files_defer(scene_file_t *want);

/* Reads 'f' into the cache, with a reference in 'pin'. Any thread. Returns 0, or -1 with 'err'
 * naming the field and the fault (wrong size, bad data, unreadable); the fault is then cached,
 * pinned by 'pin' and until the next prune after its release, so a lookup of the same file for
 * the same field fails with it at once. */
int scene_file_load(const scene_file_t *f, scene_pin_t *pin, proto_error_t *err);
void scene_pin_release(scene_pin_t *pin);

/* A counted reference to the mesh of 'file' for the object field 'path', cached or loaded.
 * NULL with 'err' set (err->code SCENE_DEFERRED while a deferral is armed and it is not
 * cached). */
mesh_t *scene_mesh_get(const char *file, const char *path, proto_error_t *err);
/* The same for the grid of volumes['index'].file, 'dims' voxels of u8 or f32. */
density_grid_t *scene_grid_get(const char *file, int index, const uint32_t dims[3], int u8,
                               proto_error_t *err);

/* Drops cached files that no snapshot or pin uses any more. */
void scene_files_prune(void);

#endif
