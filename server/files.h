/* Whole-file reading for configuration, presets and snapshots, and durable whole-file writes. */
#ifndef VOLFX_FILES_H
#define VOLFX_FILES_H

#include <stddef.h>

/*
 * Reads the file at 'path' into a NUL-terminated buffer the caller frees. Returns NULL with
 * errno set when it cannot be read or is larger than 'max' bytes (EFBIG). '*len' (may be NULL)
 * receives the size.
 */
char *files_read(const char *path, size_t max, size_t *len);

/*
 * Writes 'n' bytes at 'data' to 'path' atomically and durably: into a temporary file beside
 * it, fsync, rename over 'path', fsync of the directory. A reader sees the old file or the
 * whole new one, never a part. Returns 0, or errno with '*step' naming what failed ("create",
 * "write", "rename"); the temporary file is removed on failure. Blocks: call it off the loop.
 */
int files_write_atomic(const char *path, const void *data, size_t n, const char **step);

#endif
