/*
 * The server side of the particle fluid (methods_fluid.c): per-scene simulations stepped on
 * the render worker. Every function here runs on the loop thread.
 */
#ifndef VOLFX_FLUID_H
#define VOLFX_FLUID_H

#include "server.h"

/* Whether a step of 'e' must step its fluid: fluid.enabled and particles to move. */
int fluid_wants_step(const scene_entry_t *e);
/* Whether a fluid step of 'e' is queued or running. */
int fluid_busy(const scene_entry_t *e);
/*
 * Submits a job stepping the fluid of 'e' by 'steps' steps of 'dt' from its current particles;
 * the result replaces them when done, and 'call' (sim.step; NULL for none) is answered then
 * with the scene's clock. The steps owed (fluid_owe_steps) are taken first; 0 steps with none
 * owed submits nothing. Returns 0, or -1 when the worker's queue is full (nothing submitted;
 * the steps are then owed).
 */
int fluid_submit_step(server_t *srv, scene_entry_t *e, unsigned steps, double dt, call_t *call);

/*
 * Records that the clock took 'steps' steps the fluid did not (a sim.play tick that found a
 * step job running): the next fluid_submit_step takes them first, so the particles reach the
 * clock's frame whatever the timing. Forgotten when the particles are replaced.
 */
void fluid_owe_steps(scene_entry_t *e, unsigned steps);
/* Detaches the fluid of a scene being removed and has the worker free its simulation. */
void fluid_scene_removed(server_t *srv, scene_entry_t *e);

#endif
