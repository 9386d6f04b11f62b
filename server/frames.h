/*
 * Frame subscriptions: a timer per subscription renders frames at its rate and pushes them
 * as 'frames' notifications. Latest frame wins: while the connection's socket is still busy
 * with earlier output, at most one finished frame waits per subscription, and a newer one
 * replaces it; every frame that is due or rendered but never delivered is counted as dropped.
 */
#ifndef VOLFX_FRAMES_H
#define VOLFX_FRAMES_H

#include <math.h>

#include "server.h"
#include "render_job.h"
#include "worker.h"

#define FRAMES_MAX_PER_CONN 16

/* Adds the subscriptions' connection hooks to 's' (at start-up): a closing connection's
 * subscriptions end, a drained one gets the frames waiting, and a server stopping ends each
 * with a 'frames.ended' notification, reason "shutdown". */
void frames_register(server_t *s);
/* The scene was deleted: ends its subscriptions with a 'frames.ended' notification. */
void frames_scene_deleted(server_t *s, const char *scene);

/* A call of a METHOD_SCENE_TAG method succeeded: its 'tag' param, if any, becomes its scene's
 * newest tag, echoed by the frames that show the scene from now on, and the scene's
 * subscriptions that last ticked an interval ago or more tick at once. */
void frames_scene_changed(call_t *call);

#endif
