/*
 * The cloud's stepping (step_cloud.c): automaton steps and density passes run as jobs on the
 * render worker, in order with the renders, and the steps the cloud owes the clock. The
 * methods (methods_cloud.c, methods_scene.c), the clock (play.c, stepper.c) and the jobs call
 * these. Every function here runs on the loop thread.
 */
#ifndef VOLFX_STEP_CLOUD_H
#define VOLFX_STEP_CLOUD_H

#include "server.h"
#include "stepper.h"

/* Whether a step of 'e' must step its cloud: cloud.enabled. */
int cloud_wants_step(const scene_entry_t *e);
/* Whether a cloud job of 'e' is queued or running. */
int cloud_busy(const scene_entry_t *e);
/*
 * Submits a job taking up to 'max' (at most STEPPER_MAX_STEPS) of the simulation steps the
 * cloud of 'e' owes the clock (cloud_owe_steps), oldest first, each cloud.steps_per_frame
 * automaton steps and a density blended in (smoothing); the result replaces the scene's cells
 * and density when done, and 'w' (may be NULL) is told then. A job with 'w' is a slice of
 * stepping already admitted (stepper.c) and is queued past the queue's limit. Returns the
 * steps taken (0: none owed, nothing submitted), or -1 when the worker refused the job (they
 * stay owed).
 */
int64_t cloud_submit_step(server_t *srv, scene_entry_t *e, uint64_t max, sim_wait_t *w);
/*
 * Records that the clock took 'steps' steps the cloud has not: the next cloud_submit_step
 * takes them, so the cells reach the clock's frame whatever the timing. Forgotten when the
 * cells are replaced.
 */
void cloud_owe_steps(scene_entry_t *e, uint64_t steps);
/* The steps the cloud of 'e' owes the clock. */
uint64_t cloud_owed(const scene_entry_t *e);
/*
 * Submits a job computing the density of the cells of 'e' anew, unsmoothed (after a change of
 * cloud.metaball_radius), after the cloud jobs queued; 'call' is answered then with the
 * scene's version at submission. Returns 0, or -1 as cloud_submit_step.
 */
int cloud_submit_density(server_t *srv, scene_entry_t *e, call_t *call);
/*
 * Makes 'cells' (taken in every case) the cells of the cloud of 'e' and queues a job computing
 * their density anew, unsmoothed, ahead of no earlier cloud job; 'call' is answered when it is
 * done with {field, cells}, 'field' (a static string) naming the field that was set. Returns
 * 0, PROTO_E_BUSY when the worker's queue is full or PROTO_E_INTERNAL when out of memory (the
 * scene unchanged in both).
 */
int cloud_submit_cells(server_t *srv, scene_entry_t *e, cloud_cells_t *cells, const char *field,
                       call_t *call);

#endif
