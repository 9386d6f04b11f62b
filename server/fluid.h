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
 * with the scene's clock. Returns 0, or -1 when the worker's queue is full (nothing submitted).
 */
int fluid_submit_step(server_t *srv, scene_entry_t *e, unsigned steps, double dt, call_t *call);
/* Detaches the fluid of a scene being removed and has the worker free its simulation. */
void fluid_scene_removed(server_t *srv, scene_entry_t *e);

#endif
