/*
 * Counters behind the 'stats' method: requests, errors, frames, per-pass render times and the
 * recent frame rate. Updated and read on the loop thread only.
 */
#ifndef VOLFX_STATS_H
#define VOLFX_STATS_H

#include <stdint.h>

#include <cjson/cJSON.h>

#define STATS_MAX_PASSES 16
#define STATS_FPS_WINDOW 64

typedef struct stats {
  uint64_t started_ns;
  uint64_t requests, errors, frames;
  uint64_t frames_shared; /* Subscription frames given from a render made for another one. */
  uint64_t connections_total;
  struct {
    const char *name;
    double last_ms, sum_ms;
    uint64_t count;
  } passes[STATS_MAX_PASSES];
  int npasses;
  uint64_t frame_ns[STATS_FPS_WINDOW]; /* Completion times of the latest frames (a ring). */
} stats_t;

void stats_init(stats_t *st, uint64_t now);
void stats_pass(stats_t *st, const char *name, double ms);
void stats_frame(stats_t *st, uint64_t now);
/* Frames per second over the frames of the last two seconds. */
double stats_fps(const stats_t *st, uint64_t now);
/* The "passes" object of the stats result. */
cJSON *stats_passes_json(const stats_t *st);
/* Resident set size of this process in bytes, or 0 when unknown. */
uint64_t stats_rss_bytes(void);

#endif
