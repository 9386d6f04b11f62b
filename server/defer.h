/*
 * Requests that wait for files. A scene change that names a mesh or volume file the cache
 * lacks (scene_files.h) is not answered from a file read on the loop thread: the file is read
 * on libuv's thread pool while the connection is held (its later requests wait, so they see
 * the change), and then the request runs again from the start, finding the file cached, or
 * the fault that refused it (which the request then answers in its own words). The files read
 * stay referenced by the call until it is answered, so a change naming several new files reads
 * each once.
 *
 *   scene_file_t want;
 *   defer_arm(call, &want);
 *   int rc = scene_patch(e->scene, patch, &err);
 *   if (defer_check(call, rc, &err, &want))
 *     return;  (the call is in hand: it is answered later)
 */
#ifndef VOLFX_DEFER_H
#define VOLFX_DEFER_H

#include "scene_files.h"
#include "server.h"

/* Arms the deferral of file reads for the scene change 'call' is about to make. */
void defer_arm(call_t *call, scene_file_t *want);
/* Disarms it; when the change ('rc', 'err') failed for want of a file, queues the read and
 * returns 1: the call is then answered (or run again) later. Otherwise returns 0. */
int defer_check(call_t *call, int rc, const scene_error_t *err, const scene_file_t *want);
/* Drops the files read for 'call' (when it is answered). */
void defer_release(call_t *call);

#endif
