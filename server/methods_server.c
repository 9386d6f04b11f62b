/*
 * Methods about the server itself: server.info, rpc.discover, auth, stats and
 * server.shutdown.
 */
#include <string.h>

#include "dispatch.h"
#include "jobs.h"
#include "reclaim.h"
#include "frames.h"
#include "scene.h"
#include "worker.h"

static cJSON *limits_json(const server_t *s) {
  cJSON *l = cJSON_CreateObject();
  for (const config_limit_t *k = config_limits; k->name; k++)
    cJSON_AddNumberToObject(l, k->name, config_limit_value(&s->cfg, k));
  cJSON_AddNumberToObject(l, "subscriptions_per_connection", FRAMES_MAX_PER_CONN);
  cJSON_AddNumberToObject(l, "jobs_running", JOBS_MAX_RUNNING);
  return l;
}

static void server_info(call_t *call) {
  server_t *s = call->srv;
  cJSON *r = cJSON_CreateObject();
  cJSON_AddStringToObject(r, "name", "volfxd");
  cJSON_AddStringToObject(r, "version", VOLFX_VERSION);
  cJSON_AddStringToObject(r, "protocol", PROTO_VERSION);
  cJSON *cl = cJSON_AddObjectToObject(r, "opencl");
  cJSON_AddStringToObject(cl, "platform", s->platform);
  cJSON_AddStringToObject(cl, "device", s->device);
  cJSON_AddItemToObject(r, "limits", limits_json(s));
  cJSON *names = cJSON_AddArrayToObject(r, "scenes");
  for (scene_entry_t *e = s->scenes; e; e = e->next)
    cJSON_AddItemToArray(names, cJSON_CreateString(e->scene->name));
  cJSON_AddBoolToObject(r, "auth_required", s->cfg.token[0] != '\0');
  call_result(call, r);
}

static void rpc_discover(call_t *call) {
  call_result(call, discover_document(call->srv));
}

/* Compares in time independent of where the strings first differ. */
static int token_equal(const char *a, const char *b) {
  size_t la = strlen(a), lb = strlen(b);
  unsigned diff = (unsigned)(la ^ lb);
  for (size_t i = 0; i < la; i++)
    diff |= (unsigned)(unsigned char)a[i] ^ (unsigned char)b[i % (lb ? lb : 1)];
  return diff == 0;
}

static void auth(call_t *call) {
  const char *token = cJSON_GetStringValue(cJSON_GetObjectItem(call->params, "token"));
  const char *want = call->srv->cfg.token;
  if (want[0] && !token_equal(token, want)) {
    conn_auth_failed(call); /* Answered after a delay; enough of them close the connection. */
    return;
  }
  /* The idle timeout counts from here: before, the connection had budget.auth_timeout_s. */
  conn_authenticated(call->conn);
  cJSON *r = cJSON_CreateObject();
  cJSON_AddBoolToObject(r, "authenticated", 1);
  call_result(call, r);
}

static void stats(call_t *call) {
  server_t *s = call->srv;
  uint64_t now = now_ns();
  cJSON *r = cJSON_CreateObject();
  cJSON_AddNumberToObject(r, "uptime_s", (double)(now - s->stats.started_ns) / 1e9);
  cJSON_AddNumberToObject(r, "connections", s->nconns);
  cJSON_AddNumberToObject(r, "connections_total", (double)s->stats.connections_total);
  cJSON_AddNumberToObject(r, "requests", (double)s->stats.requests);
  cJSON_AddNumberToObject(r, "errors", (double)s->stats.errors);
  cJSON_AddNumberToObject(r, "frames_rendered", (double)s->stats.frames);
  cJSON_AddNumberToObject(r, "frames_shared", (double)s->stats.frames_shared);
  cJSON_AddNumberToObject(r, "fps", stats_fps(&s->stats, now));
  cJSON_AddNumberToObject(r, "render_queue", worker_queue_depth(s->worker));
  cJSON_AddNumberToObject(r, "subscriptions", s->nsubs);
  cJSON_AddNumberToObject(r, "jobs", jobs_running(s));
  cJSON_AddItemToObject(r, "passes", stats_passes_json(&s->stats));
  cJSON *mem = cJSON_AddObjectToObject(r, "memory");
  cJSON_AddNumberToObject(mem, "rss_bytes", (double)stats_rss_bytes());
  cJSON_AddNumberToObject(mem, "output_queued_bytes", (double)output_queued_bytes(s));
  cJSON_AddNumberToObject(mem, "output_total_bytes", (double)output_total(s));
  cJSON_AddNumberToObject(mem, "scene_bytes", (double)scene_sim_bytes_total());
  cJSON_AddNumberToObject(r, "unauthenticated", s->nunauth);
  cJSON_AddNumberToObject(mem, "kept_bytes", (double)reclaim_kept_bytes());
  call_result(call, r);
}

static void shutdown_server(call_t *call) {
  cJSON *r = cJSON_CreateObject();
  cJSON_AddBoolToObject(r, "shutting_down", 1);
  server_t *s = call->srv;
  call_result(call, r);
  server_request_stop(s);
}

static const sch_field_t no_params[] = {{0}};
static const sch_field_t auth_params[] = {{.name = "token",
                                           .type = SCH_STRING,
                                           .desc = "The server's token.",
                                           .max = 255,
                                           .flags = SCH_REQUIRED},
                                          {0}};

static const int auth_errors[] = {PROTO_E_UNAUTHORIZED, 0};
static const int common_errors[] = {PROTO_E_UNAUTHORIZED, 0};

const method_t method_server_info = {
    .name = "server.info",
    .summary = "Version, protocol version, OpenCL platform and device, limits and scenes.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = no_params},
    .result = "{name, version, protocol, opencl {platform, device}, limits, scenes, "
              "auth_required}",
    .errors = common_errors,
    .handler = server_info};

const method_t method_rpc_discover = {
    .name = "rpc.discover",
    .summary = "The OpenRPC document of every method, with the scene schema.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = no_params},
    .result = "An OpenRPC 1.2.6 document.",
    .errors = common_errors,
    .handler = rpc_discover};

const method_t method_auth = {
    .name = "auth",
    .summary = "Authenticates the connection; required first when the server has a token.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = auth_params},
    .result = "{authenticated: true}",
    .errors = auth_errors,
    .handler = auth,
    .flags = METHOD_NO_AUTH};

const method_t method_stats = {
    .name = "stats",
    .summary = "Per-pass render times, frame rate, queue depths, connections and memory.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = no_params},
    .result = "{uptime_s, connections, requests, errors, frames_rendered, frames_shared, fps, "
              "render_queue, "
              "subscriptions, passes, memory {rss_bytes, output_queued_bytes, kept_bytes}}",
    .errors = common_errors,
    .handler = stats};

const method_t method_server_shutdown = {
    .name = "server.shutdown",
    .summary = "Stops the server gracefully after answering; needs the token when one is set.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = no_params},
    .result = "{shutting_down: true}",
    .errors = common_errors,
    .handler = shutdown_server};
