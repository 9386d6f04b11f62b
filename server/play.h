/*
 * The scene's free-running clock (play.c): sim.play's timer and its stop. Every function here
 * runs on the loop thread.
 */
#ifndef VOLFX_PLAY_H
#define VOLFX_PLAY_H

#include "server.h"
#include "stepper.h"

/* Plays 'e' at 'rate' simulation steps per second of wall time, from now; sets sim.playing. */
void play_start(scene_entry_t *e, double rate);

/*
 * Stops playing, and any stepping of the scene begun before (each sim.step's after its slice
 * in flight, answered with the clock it reached); clears sim.playing. The steps the fluid and
 * the cloud still owe the clock are then taken, in slices; 'cb' (may be NULL) gets 'ctx' when
 * they are. Returns as stepper_start.
 */
int play_stop(scene_entry_t *e, stepper_cb cb, void *ctx);

#endif
