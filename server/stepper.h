/*
 * Simulation stepping in slices (stepper.c): a run of steps whose cloud or fluid work would
 * hold the render worker for long (sim.step, the catch-up of sim.pause, render.sequence and
 * sim.bake moving to their next frame) is taken a slice at a time, each slice a job or two on
 * the worker sized to about STEPPER_SLICE_NS, the next slice queued only when the last is done,
 * behind whatever else waits. Other scenes' renders run in between, and the stepping can be
 * stopped between slices. Every function here runs on the loop thread.
 */
#ifndef VOLFX_STEPPER_H
#define VOLFX_STEPPER_H

#include "server.h"

/* Worker time one slice of simulation work is sized for. */
#define STEPPER_SLICE_NS 50e6
/* Loop time the clock's advance (the waves' animations) may take at once. */
#define STEPPER_ADVANCE_NS 5e6
/* Most simulation steps in one slice or one advance of the clock, however cheap. */
#define STEPPER_MAX_STEPS 100000u

/* What a simulation job reports when done (cloud_submit_step, fluid_submit_step): 0 or a
 * PROTO_E_* code with a message. */
typedef struct sim_wait sim_wait_t;
struct sim_wait {
  void (*done)(sim_wait_t *w, int code, const char *err);
};

typedef struct stepper stepper_t;

/* How a stepping ended, handed to its callback. */
typedef struct stepper_end {
  int code;             /* 0, or the PROTO_E_* code of a failure (a job failed, the scene was
                           deleted, the server is shutting down). */
  char err[512];        /* The failure, when 'code' is set. */
  const char *cut;      /* With code 0: NULL when every step was taken, else why the steps
                           left were not ("sim.pause", "cancelled", ...). */
  scene_entry_t *scene; /* The scene, or NULL when it was deleted. */
} stepper_end_t;

/* Called once when the stepping ends; the stepper is freed when it returns. */
typedef void (*stepper_cb)(void *ctx, const stepper_end_t *end);

/* The simulation steps of 'e' one slice takes: as many as fit in STEPPER_SLICE_NS of worker
 * time at the cost the scene's last jobs measured, 1 while that is unknown, at most
 * STEPPER_MAX_STEPS. */
uint64_t stepper_slice_steps(const scene_entry_t *e);

/*
 * Advances the clock of 'e' by 'steps' steps of 'dt' and brings its cloud and fluid along,
 * slice by slice; the steps they owed the clock before (sim.play ticks that found a job
 * running) are taken too. The clock moves with each slice, so it is where the simulations
 * will be once the slice's jobs are done, and a stepping stopped part-way leaves them
 * consistent. It stops after the slice in flight when the scene is deleted, its cells or
 * particles are replaced, stepper_stop_scene is called (sim.pause) or stepper_cancel. 'cb'
 * (may be NULL) gets 'ctx' and how it ended. Returns 1 when it ended before returning (cb
 * called), 0 when cb will be called later (and '*out', when not NULL, is the stepper until
 * then), or -1 when the worker's queue has no room for a slice (nothing done, cb not called).
 */
int stepper_start(server_t *srv, scene_entry_t *e, uint64_t steps, double dt, stepper_cb cb,
                  void *ctx, stepper_t **out);

/* Stops 'st' after its slice in flight; its callback follows with cut "cancelled". */
void stepper_cancel(stepper_t *st);

/* Stops every stepping of 'e' started before, each after its slice in flight (sim.pause). */
void stepper_stop_scene(scene_entry_t *e);

#endif
