/*
 * Snapshots written outside scene.save (snapshot.c): a scene's document and simulation state
 * taken on the loop thread as references to its immutable parts, then encoded and written
 * atomically on the thread pool, in scene.save's format. sim.bake writes its snapshots so.
 */
#ifndef VOLFX_SNAPSHOT_H
#define VOLFX_SNAPSHOT_H

#include <stddef.h>

#include "scene.h"

typedef struct snapshot_out snapshot_out_t;

/* Loop thread: takes the scene's state as it is now. NULL when out of memory. */
snapshot_out_t *snapshot_out_new(const scene_t *s);

/* Any thread: writes the snapshot to 'path' atomically. Returns 0 with the file's size in
 * '*bytes', or an errno value with the failed step ("create", "write", ...) in '*step'. */
int snapshot_out_write(snapshot_out_t *o, const char *path, size_t *bytes, const char **step);

/* Any thread: drops the references and frees 'o'; NULL is fine. */
void snapshot_out_free(snapshot_out_t *o);

#endif
