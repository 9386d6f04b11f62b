/* Whole-file reading for configuration, presets and snapshots. */
#ifndef VOLFX_FILES_H
#define VOLFX_FILES_H

#include <stddef.h>

/*
 * Reads the file at 'path' into a NUL-terminated buffer the caller frees. Returns NULL with
 * errno set when it cannot be read or is larger than 'max' bytes (EFBIG). '*len' (may be NULL)
 * receives the size.
 */
char *files_read(const char *path, size_t max, size_t *len);

#endif
