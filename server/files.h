/*
 * Whole-file reading for configuration, presets and snapshots, and durable whole-file writes
 * into the data directory. Writes, and reads of files in the data directory, open beneath its
 * descriptor (datapath.h); the operator's own files (--config, --scene) are read by path.
 */
#ifndef VOLFX_FILES_H
#define VOLFX_FILES_H

#include <stddef.h>
#include <sys/types.h>

#include "datapath.h"

/*
 * Reads the regular file at 'path' (opened without blocking, so a FIFO is refused at once) into
 * a NUL-terminated buffer the caller frees. An absolute path inside the data directory is
 * opened beneath it (datapath_relative); any other path as it is. Returns NULL with errno set
 * when it cannot be read, is not a regular file (EISDIR, ENODEV) or is larger than 'max' bytes
 * (EFBIG). '*len' (may be NULL) receives the size.
 */
char *files_read(const char *path, size_t max, size_t *len);

/* The same for the file 'name' (one component, not a link) in directory 'dirfd'. */
char *files_read_at(int dirfd, const char *name, size_t max, size_t *len);

/* Writes all 'n' bytes at 'data' to 'fd'. Returns 0 or errno. */
int files_write_all(int fd, const void *data, size_t n);

/* A write in progress to a temporary file beside its target. */
typedef struct files_atomic {
  int dir;                      /* The target's directory. */
  int fd;                       /* The temporary file. */
  char tmp[DATAPATH_TEMP_SIZE]; /* Its name in 'dir'. */
  char base[256];               /* The target's name in 'dir'. */
} files_atomic_t;

/*
 * Starts an atomic write of 'name' in the data directory (relative to it, or an absolute path
 * inside it as datapath_resolve gives): opens its directory beneath the data directory, refuses
 * a target that exists and is not a regular file (EISDIR, ELOOP for a link, ENODEV), removes
 * stale temporary files there (datapath_sweep_beside) and creates a temporary file of a random
 * name exclusively (so nothing planted is opened), with permissions 'mode'. Returns 0, or an
 * errno with '*step' naming what failed ("open", "create"), nothing left behind.
 */
int files_atomic_begin(files_atomic_t *a, const char *name, mode_t mode, const char **step);

/* Ends a write begun by files_atomic_begin: fsync, close, rename over the target, fsync of the
 * directory. Returns 0, or an errno with '*step' ("write", "rename"); the temporary file is
 * removed on failure. */
int files_atomic_commit(files_atomic_t *a, const char **step);

/* Drops a write begun by files_atomic_begin: closes and removes the temporary file. */
void files_atomic_abort(files_atomic_t *a);

/*
 * Writes 'n' bytes at 'data' to 'name' in the data directory (as files_atomic_begin takes it)
 * atomically and durably: a reader sees the old file or the whole new one, never a part.
 * Returns 0, or errno with '*step' naming what failed ("open", "create", "write", "rename").
 * Blocks: call it off the loop.
 */
int files_write_atomic(const char *name, const void *data, size_t n, const char **step);

#endif
