/*
 * Background jobs (render.sequence, job.list, job.cancel): frame sequences rendered into files
 * under the data directory, owned by the server rather than by a connection.
 */
#ifndef VOLFX_JOBS_H
#define VOLFX_JOBS_H

#include "server.h"

/* render.sequence jobs running at once (server.info limits.jobs_running). */
#define JOBS_MAX_RUNNING 8

/* Jobs running now. */
int jobs_running(const server_t *s);
/* Adds the jobs' connection hooks to 's' (at start-up): a job whose connection closes runs
 * on, without progress notifications. */
void jobs_register(server_t *s);
/* The server is stopping: every running job fails and none starts more work. Call before the
 * worker stops, so that the jobs it cancels find theirs ended. */
void jobs_server_stopping(server_t *s);

#endif
