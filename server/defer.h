/*
 * Requests that wait for files or seedings. A scene change that names a mesh or volume file
 * the cache lacks (scene_files.h), or that needs a cloud's cells or the fluid's initial
 * particles seeded (seeding.h), is not answered from work done on the loop thread: the file is
 * read, or the seeding made, on libuv's thread pool while the connection is held (its later
 * requests wait, so they see the change), and then the request runs again from the start,
 * finding the file or the seeding cached, or the fault that refused the file (which the
 * request then answers in its own words). What was made stays referenced by the call until it is
 * answered, so a change naming several new files reads each once.
 *
 *   defer_want_t want;
 *   defer_arm(call, &want);
 *   int rc = scene_patch(e->scene, patch, &err);
 *   if (defer_check(call, rc, &err, &want))
 *     return;  (the call is in hand: it is answered later)
 */
#ifndef VOLFX_DEFER_H
#define VOLFX_DEFER_H

#include "seeding.h"
#include "scene_files.h"
#include "server.h"

/* What a deferred change waits for, filled by the lookup that deferred it. */
typedef struct defer_want {
  scene_file_t file; /* A file to read (SCENE_DEFERRED). */
  seed_want_t seed;  /* A seeding to make (SCENE_DEFERRED_SEED). */
} defer_want_t;

/* Arms the deferral of file reads and seedings for the scene change 'call' is about to make. */
void defer_arm(call_t *call, defer_want_t *want);
/* Disarms it; when the change ('rc', 'err') failed for want of a file or of cells, queues the
 * work and returns 1: the call is then answered (or run again) later. Otherwise returns 0. */
int defer_check(call_t *call, int rc, const scene_error_t *err, defer_want_t *want);
/* Drops the files and cells made for 'call' (when it is answered). */
void defer_release(call_t *call);

#endif
