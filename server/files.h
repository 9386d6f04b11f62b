/* Whole-file reading for configuration, presets and snapshots, and durable whole-file writes. */
#ifndef VOLFX_FILES_H
#define VOLFX_FILES_H

#include <stddef.h>
#include <sys/types.h>

/*
 * Reads the file at 'path' into a NUL-terminated buffer the caller frees. Returns NULL with
 * errno set when it cannot be read or is larger than 'max' bytes (EFBIG). '*len' (may be NULL)
 * receives the size.
 */
char *files_read(const char *path, size_t max, size_t *len);

/*
 * Creates a temporary file beside 'path' for writing, under a name no other writer can have
 * and that nothing can have planted (created exclusively: an existing file or link of that
 * name is never opened), with permissions 'mode'. Returns its descriptor with its name in
 * 'tmp' ('len' bytes), or -1 with errno set.
 */
int files_temp_beside(const char *path, char *tmp, size_t len, mode_t mode);

/* Writes all 'n' bytes at 'data' to 'fd'. Returns 0 or errno. */
int files_write_all(int fd, const void *data, size_t n);

/*
 * Ends a write into temporary file 'fd' named 'tmp': fsync, close, rename over 'path', fsync of
 * the directory. Returns 0, or errno with '*step' naming what failed ("write", "rename"); the
 * temporary file is removed on failure.
 */
int files_finish_atomic(int fd, const char *tmp, const char *path, const char **step);

/*
 * Writes 'n' bytes at 'data' to 'path' atomically and durably: into a temporary file beside
 * it, fsync, rename over 'path', fsync of the directory. A reader sees the old file or the
 * whole new one, never a part. Returns 0, or errno with '*step' naming what failed ("create",
 * "write", "rename"); the temporary file is removed on failure. Blocks: call it off the loop.
 */
int files_write_atomic(const char *path, const void *data, size_t n, const char **step);

#endif
