/*
 * The server side of the cloud (methods_cloud.c): automaton steps and density passes run as
 * jobs on the render worker, in order with the renders. Every function here runs on the loop
 * thread.
 */
#ifndef VOLFX_CLOUD_H
#define VOLFX_CLOUD_H

#include "server.h"

/* Whether a step of 'e' must step its cloud: cloud.enabled. */
int cloud_wants_step(const scene_entry_t *e);
/* Whether a cloud job of 'e' is queued or running. */
int cloud_busy(const scene_entry_t *e);
/*
 * Submits a job taking 'steps' simulation steps of the cloud of 'e' (each cloud.steps_per_frame
 * automaton steps), then its density, smoothed; the result replaces the scene's cells and
 * density when done, and 'call' (NULL for none) is answered then with the scene's clock.
 * Returns 0, or -1 when the worker's queue is full (nothing submitted).
 */
int cloud_submit_step(server_t *srv, scene_entry_t *e, unsigned steps, call_t *call);
/*
 * Records that the clock took 'steps' steps the cloud did not (a sim.play tick that found a
 * cloud job running): the next cloud_submit_step takes them first, so the cells reach the
 * clock's frame whatever the timing. Forgotten when the cells are replaced.
 */
void cloud_owe_steps(scene_entry_t *e, unsigned steps);
/*
 * Submits a job computing the density of the cells of 'e' anew, unsmoothed (after a change of
 * cloud.metaball_radius), after the cloud jobs queued; 'call' is answered then with the
 * scene's version at submission. Returns 0, or -1 as cloud_submit_step.
 */
int cloud_submit_density(server_t *srv, scene_entry_t *e, call_t *call);

#endif
