/*
 * The render method: one frame, made into a render job by render_job.c, rendered on the render
 * worker and answered with its bytes; the loop thread only validates, queues and answers.
 */
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "dispatch.h"
#include "render_job.h"

typedef struct render_call {
  job_t job;
  call_t *call;
  cJSON *t; /* The client's 't', echoed. */
  int base64;
} render_call_t;

static void on_render_done(job_t *j) {
  render_call_t *rc = j->ctx;
  call_t *call = rc->call;
  server_t *s = call->srv;
  /* A connection that waited for its share of the render queue goes on (the rest of a batch
   * may be waiting for this; a single line's answer resumes it when written anyway). */
  conn_render_done(call->conn);
  render_job_stats(s, j);
  if (j->code != 0) {
    call_error(call, j->code, j->code == PROTO_E_INVALID_PARAMS ? "format" : NULL, "%s: %s",
               proto_err_message(j->code), j->err);
    free(j->out.bytes);
  } else if (call->conn->closing) {
    /* The client went away mid-frame: nothing to send. */
    free(j->out.bytes);
    call_result(call, cJSON_CreateObject());
  } else {
    cJSON *r = cJSON_CreateObject();
    const char *fmt = proto_format_name(j->params.format);
    cJSON_AddNumberToObject(r, "width", j->params.width);
    cJSON_AddNumberToObject(r, "height", j->params.height);
    cJSON_AddStringToObject(r, "format", fmt);
    cJSON_AddStringToObject(r, "aov", render_aov_names[j->params.aov]);
    cJSON_AddNumberToObject(r, "frame", (double)j->frame);
    cJSON_AddNumberToObject(r, "time", j->time);
    render_job_sync(r, j);
    cJSON_AddItemToObject(r, "work_ms", render_job_times(j));
    cJSON_AddNumberToObject(r, "antialias", j->out.antialias);
    if (rc->t) {
      cJSON_AddItemToObject(r, "t", rc->t);
      rc->t = NULL;
    }
    call_result_bytes(call, r, j->out.bytes, j->out.nbytes, fmt, j->params.width, j->params.height,
                      rc->base64);
  }
  cJSON_Delete(rc->t);
  free(rc);
}

static void render_m(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  render_call_t *rc = calloc(1, sizeof *rc);
  if (!rc) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  char path[128], msg[512];
  int code = render_job_from_params(call->srv, e, call->params, NULL, &rc->job, path, sizeof path,
                                    msg, sizeof msg);
  if (code) {
    free(rc);
    call_error(call, code, path, "%s", msg);
    return;
  }
  rc->call = call;
  rc->base64 = strcmp(cJSON_GetObjectItem(call->params, "encoding")->valuestring, "base64") == 0;
  const cJSON *t = cJSON_GetObjectItem(call->params, "t");
  rc->t = t ? cJSON_Duplicate(t, 1) : NULL;
  rc->job.done = on_render_done;
  rc->job.ctx = rc;
  size_t bound = render_answer_bound(&rc->job, rc->base64);
  server_t *s = call->srv;
  if (output_total(s) > 0 && !output_total_fits(s, bound)) {
    /* The frame would pass the server's output budget: refused rather than held. */
    render_job_release(&rc->job);
    cJSON_Delete(rc->t);
    free(rc);
    call_error(call, PROTO_E_LIMIT, NULL,
               "limit exceeded: the server's unsent output (%zu bytes) and this frame (up to "
               "%zu) would pass limits.output_total_bytes (%zu); retry once clients have read",
               output_total(s), bound, s->cfg.budget.output_total_bytes);
    return;
  }
  if (worker_submit(call->srv->worker, &rc->job) != 0) {
    render_job_release(&rc->job);
    cJSON_Delete(rc->t);
    free(rc);
    call_error(call, PROTO_E_BUSY, NULL, "busy: the render queue is full (%d jobs); retry later",
               call->srv->cfg.render_queue);
    return;
  }
  conn_promise(call, bound);
  conn_render_queued(call->conn);
}

static const sch_field_t render_params[] = {
    RENDER_PARAMS_COMMON,
    {.name = "t",
     .type = SCH_ANY,
     .desc = "Any value, echoed in the result to measure latency.",
     .flags = SCH_NO_DEFAULT},
    {0}};

static const int render_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_BUSY,   PROTO_E_LIMIT,
                                    PROTO_E_NOT_FOUND,    PROTO_E_DEVICE, 0};

const method_t method_render = {
    .name = "render",
    .summary = "Renders one frame, returned as an attachment with per-pass timings.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = render_params},
    .result = "{width, height, format, aov, frame, time, version, render_start, encode_end, "
              "work_ms {pass: ms, queue, total}, "
              "antialias, t, attachment {bytes, format, width, height}}",
    .errors = render_errors,
    .handler = render_m};
