/*
 * The scene's clock while it plays (sim.play, sim.pause, scene.set of sim.playing): the play
 * timer takes the steps wall time owes, moves the clock and owes them to the fluid and the
 * cloud, whose step jobs (step_fluid.c, step_cloud.c) take them one slice at a time; stopping
 * hands what they still owe to a stepping (stepper.c).
 */
#include <math.h>

#include "play.h"
#include "step_cloud.h"
#include "step_fluid.h"

/* Owes 'n' clock steps to the simulations of 'e' and, for each with no job running, submits
 * one slice of what it owes (the next tick takes more). */
static void play_steps(scene_entry_t *e, uint64_t n) {
  uint64_t slice = stepper_slice_steps(e);
  if (fluid_wants_step(e)) {
    fluid_owe_steps(e, n);
    if (!fluid_busy(e))
      fluid_submit_step(e->srv, e, slice, scene_dt(e->scene), NULL);
  }
  if (cloud_wants_step(e)) {
    cloud_owe_steps(e, n);
    if (!cloud_busy(e))
      cloud_submit_step(e->srv, e, slice, NULL);
  }
}

/* The play timer: takes the steps that wall time owes since play started. */
static void on_play(uv_timer_t *t) {
  scene_entry_t *e = t->data;
  double elapsed = (double)(now_ns() - e->play_start_ns) / 1e9;
  uint64_t due = (uint64_t)floor(elapsed * e->rate);
  if (due > e->play_steps) {
    uint64_t n = due - e->play_steps;
    /* After a long stall, do not try to catch up more than a second's worth. */
    if (n > (uint64_t)ceil(e->rate))
      n = (uint64_t)ceil(e->rate);
    scene_advance(e->scene, n, scene_dt(e->scene));
    e->play_steps = due;
    /* One job at a time per scene and simulation: while one runs, these steps are owed, and
     * the next job takes them first, so the state at a frame does not depend on the timing. */
    play_steps(e, n);
  }
}

static void set_playing(scene_entry_t *e, int playing) {
  cJSON *patch = cJSON_CreateObject();
  cJSON *sim = cJSON_AddObjectToObject(patch, "sim");
  cJSON_AddBoolToObject(sim, "playing", playing);
  scene_error_t err;
  scene_patch(e->scene, patch, &err);
  cJSON_Delete(patch);
}

void play_start(scene_entry_t *e, double rate) {
  e->rate = rate;
  e->play_start_ns = now_ns();
  e->play_steps = 0;
  /* Tick at the step rate up to 200 Hz; faster rates take several steps per tick. */
  double hz = e->rate < 200 ? e->rate : 200;
  uint64_t ms = (uint64_t)(1000.0 / hz);
  uv_timer_start(&e->play, on_play, ms ? ms : 1, ms ? ms : 1);
  set_playing(e, 1);
}

int play_stop(scene_entry_t *e, stepper_cb cb, void *ctx) {
  uv_timer_stop(&e->play);
  e->rate = 0;
  set_playing(e, 0);
  stepper_stop_scene(e);
  return stepper_start(e->srv, e, 0, scene_dt(e->scene), cb, ctx, NULL);
}
