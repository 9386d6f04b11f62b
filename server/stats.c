/* Counters for the 'stats' method: per-pass times, frame rate and process memory. */
#include "stats.h"

#include <stdio.h>
#include <string.h>
#include <unistd.h>

void stats_init(stats_t *st, uint64_t now) {
  memset(st, 0, sizeof *st);
  st->started_ns = now;
}

void stats_pass(stats_t *st, const char *name, double ms) {
  int i;
  for (i = 0; i < st->npasses; i++)
    if (strcmp(st->passes[i].name, name) == 0)
      break;
  if (i == st->npasses) {
    if (st->npasses == STATS_MAX_PASSES)
      return;
    st->passes[st->npasses++].name = name;
  }
  st->passes[i].last_ms = ms;
  st->passes[i].sum_ms += ms;
  st->passes[i].count++;
}

void stats_frame(stats_t *st, uint64_t now) {
  st->frame_ns[st->frames % STATS_FPS_WINDOW] = now;
  st->frames++;
}

double stats_fps(const stats_t *st, uint64_t now) {
  const uint64_t window = 2000000000ull;
  uint64_t n = st->frames < STATS_FPS_WINDOW ? st->frames : STATS_FPS_WINDOW;
  uint64_t count = 0, oldest = now;
  for (uint64_t i = 0; i < n; i++) {
    uint64_t t = st->frame_ns[i];
    if (now - t <= window) {
      count++;
      if (t < oldest)
        oldest = t;
    }
  }
  if (count < 2)
    return (double)count / 2.0;
  /* When the ring is full of recent frames, the rate is measured over the ring's span. */
  double span = count == STATS_FPS_WINDOW ? (double)(now - oldest) / 1e9 : 2.0;
  return span > 0 ? (double)count / span : 0;
}

cJSON *stats_passes_json(const stats_t *st) {
  cJSON *o = cJSON_CreateObject();
  for (int i = 0; i < st->npasses; i++) {
    cJSON *p = cJSON_AddObjectToObject(o, st->passes[i].name);
    cJSON_AddNumberToObject(p, "last_ms", st->passes[i].last_ms);
    cJSON_AddNumberToObject(p, "mean_ms", st->passes[i].sum_ms / (double)st->passes[i].count);
    cJSON_AddNumberToObject(p, "count", (double)st->passes[i].count);
  }
  return o;
}

uint64_t stats_rss_bytes(void) {
  FILE *f = fopen("/proc/self/statm", "r");
  if (!f)
    return 0;
  unsigned long size, resident;
  int n = fscanf(f, "%lu %lu", &size, &resident);
  fclose(f);
  return n == 2 ? (uint64_t)resident * (uint64_t)sysconf(_SC_PAGESIZE) : 0;
}
