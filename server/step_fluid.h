/*
 * The fluid's stepping (step_fluid.c): per-scene particle simulations stepped on the render
 * worker, and the steps each owes the clock. The methods (methods_fluid.c), the clock
 * (play.c, stepper.c) and the server's life cycle call these. Every function here runs on the
 * loop thread.
 */
#ifndef VOLFX_STEP_FLUID_H
#define VOLFX_STEP_FLUID_H

#include "server.h"
#include "sim_fluid.h"
#include "stepper.h"

/* Whether a step of 'e' must step its fluid: fluid.enabled and particles to move. */
int fluid_wants_step(const scene_entry_t *e);
/* Whether a fluid step of 'e' is queued or running. */
int fluid_busy(const scene_entry_t *e);
/*
 * Submits a job taking up to 'max' (at most STEPPER_MAX_STEPS) of the steps of 'dt' the fluid
 * of 'e' owes the clock (fluid_owe_steps), oldest first; the result replaces the particles
 * when done, and 'w' (may be NULL) is told then. A job with 'w' is a slice of stepping already
 * admitted (stepper.c) and is queued past the queue's limit. Returns the steps taken (0: none
 * owed, nothing submitted), or -1 when the worker refused the job (they stay owed).
 */
int64_t fluid_submit_step(server_t *srv, scene_entry_t *e, uint64_t max, double dt, sim_wait_t *w);

/*
 * Records that the clock took 'steps' steps the fluid has not: the next fluid_submit_step
 * takes them, so the particles reach the clock's frame whatever the timing. Forgotten when
 * the particles are replaced.
 */
void fluid_owe_steps(scene_entry_t *e, uint64_t steps);
/* The steps the fluid of 'e' owes the clock. */
uint64_t fluid_owed(const scene_entry_t *e);
/* The simulation parameters of a scene's validated document 'doc', emitters included. */
void fluid_params_of(const cJSON *doc, fluid_params_t *p);
/* Detaches the fluid of a scene being removed and has the worker free its simulation. */
void fluid_scene_removed(server_t *srv, scene_entry_t *e);

#endif
