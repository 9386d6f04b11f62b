/*
 * volfxd: reads the configuration, brings up the OpenCL renderer (warming every kernel), the
 * render worker and the 'main' scene, listens, prints "volfxd listening on HOST:PORT" once
 * connections are accepted (and tells a service manager, the --port-file and the --ready-fd
 * that it is ready), and runs the libuv loop
 * until SIGINT, SIGTERM or server.shutdown. SIGHUP re-reads the log level from the config file
 * and the command line; it never stops the server.
 */
#include <errno.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "log.h"
#include "ready.h"
#include "reclaim.h"
#include "scene_files.h"
#include "seeding.h"
#include "service.h"
#include "sim_fluid.h"
#include "server.h"
#include "worker.h"

static void on_signal(uv_signal_t *h, int signum) {
  server_t *s = h->data;
  LOG(LOG_INFO, "server", "signal %d (%s): stopping", signum, strsignal(signum));
  service_stopping();
  server_request_stop(s);
}

/* main's side of the service manager: SIGHUP's handle and the command line it reads the
 * configuration from again, the watch that reports a stop, and the STATUS= line. */
static struct {
  uv_signal_t signal;
  uv_check_t stop_watch; /* Tells the service manager once a stop has begun, however begun. */
  int argc;
  char **argv;
  char status[640]; /* STATUS= once serving, sent again after a reload. */
} reload;

/*
 * SIGHUP: reads the config file and the command line again, as at start, and applies the one
 * setting that can change while running, the log level; the rest (addresses, directories,
 * limits, token) needs a restart. A file that no longer parses keeps the current level. stderr
 * needs no reopening: it is a stream (the journal's, or whatever the caller redirected it to).
 */
static void on_sighup(uv_signal_t *h, int signum) {
  server_t *s = h->data;
  (void)signum;
  if (s->stopping) {
    LOG(LOG_INFO, "server", "SIGHUP while stopping: ignored");
    return;
  }
  service_reloading();
  config_t *c = malloc(sizeof *c);
  log_level_t before = log_threshold;
  if (c && config_load(c, reload.argc, reload.argv) == CONFIG_OK) {
    log_set_threshold((log_level_t)c->log_level);
    /* Written at any threshold but quiet, so that a reload always leaves a trace. */
    if (log_threshold != LOG_QUIET)
      log_write(LOG_INFO, "server", "SIGHUP: configuration read again; log level %s (was %s)",
                log_level_name(log_threshold), log_level_name(before));
  } else {
    LOG(LOG_ERROR, "server", "SIGHUP: cannot read the configuration again; log level stays %s",
        log_level_name(before));
  }
  free(c);
  service_ready(reload.status);
}

static void on_stop_watch(uv_check_t *h) {
  server_t *s = h->data;
  if (s->stopping) {
    service_stopping();
    uv_check_stop(h);
  }
}

static void close_any(uv_handle_t *h, void *arg) {
  (void)arg;
  if (!uv_is_closing(h))
    uv_close(h, NULL);
}

/* Prints the address clients should use, with the port the kernel picked for port 0, and tells
 * the service manager, the port file and the ready descriptor that volfxd is ready. Returns 0,
 * or -1 when the port file could not be written. */
static int announce(server_t *s) {
  char where[320];
  int rc;
  if (s->has_tcp) {
    struct sockaddr_storage addr;
    int len = sizeof addr;
    char host[64] = "?";
    int port = 0;
    uv_tcp_getsockname(&s->tcp, (struct sockaddr *)&addr, &len);
    if (addr.ss_family == AF_INET6) {
      uv_ip6_name((struct sockaddr_in6 *)&addr, host, sizeof host);
      port = ntohs(((struct sockaddr_in6 *)&addr)->sin6_port);
    } else {
      uv_ip4_name((struct sockaddr_in *)&addr, host, sizeof host);
      port = ntohs(((struct sockaddr_in *)&addr)->sin_port);
    }
    snprintf(where, sizeof where, "%s:%d", host, port);
    rc = ready_publish(host, port, NULL);
  } else {
    snprintf(where, sizeof where, "unix:%s", s->cfg.unix_path);
    rc = ready_publish(NULL, 0, s->cfg.unix_path);
  }
  if (rc != 0)
    return -1;
  printf("volfxd listening on %s\n", where);
  fflush(stdout);
  snprintf(reload.status, sizeof reload.status, "serving on %s (%s)", where, s->device);
  service_ready(reload.status);
  return 0;
}

/*
 * --precompile: the renderer has built its program and warmed every render kernel; one fluid
 * step warms the simulation's kernels too, and closing the renderer saves the program binary
 * beside PoCL's cache. A later start with the same cache directory loads it in milliseconds
 * instead of compiling for seconds: a machine image or a farm runs this once.
 */
static int precompile(renderer_t *r, uint64_t t0) {
  char err[512] = "";
  fluid_params_t p;
  fluid_params_default(&p);
  p.max_particles = 1024;
  fluid_sim_t *sim = fluid_sim_create(renderer_device(r), &p, err, sizeof err);
  float pos[3 * 8];
  for (int i = 0; i < 8; i++)
    pos[3 * i] = 0.1f * (float)i, pos[3 * i + 1] = 0.5f, pos[3 * i + 2] = 0;
  int ok = sim && fluid_sim_set_particles(sim, pos, NULL, 8, err, sizeof err) == 0 &&
           fluid_sim_step(sim, 1.0 / 60, err, sizeof err) == 0;
  fluid_sim_destroy(sim);
  char device[256];
  snprintf(device, sizeof device, "%s", renderer_device_name(r));
  renderer_destroy(r);
  if (!ok) {
    LOG(LOG_ERROR, "opencl", "precompiling the fluid's kernels failed: %s", err);
    return 1;
  }
  const char *dir = getenv("POCL_CACHE_DIR");
  printf("volfxd: kernels for %s compiled into %s in %.0f ms\n", device, dir ? dir : "PoCL's cache",
         (double)(now_ns() - t0) / 1e6);
  return 0;
}

int main(int argc, char **argv) {
  static server_t srv;
  server_t *s = &srv;
  int journal = log_init();
  int rc = config_load(&s->cfg, argc, argv);
  if (rc != CONFIG_OK) {
    /* config_load said why on stderr without a priority; this line is what `journalctl -p err`
     * shows. */
    if (rc == CONFIG_ERROR && journal)
      LOG(LOG_ERROR, "config", "invalid configuration: not starting");
    return rc == CONFIG_EXIT_OK ? 0 : 2;
  }
  log_set_threshold((log_level_t)s->cfg.log_level);
  reload.argc = argc;
  reload.argv = argv;
  signal(SIGPIPE, SIG_IGN);
  /* A SIGHUP while the kernels compile must not end the start; the handler comes later. */
  signal(SIGHUP, SIG_IGN);

  if (s->cfg.data_dir[0]) {
    if (mkdir(s->cfg.data_dir, 0700) != 0 && errno != EEXIST) {
      LOG(LOG_ERROR, "server", "cannot create data directory %s: %s", s->cfg.data_dir,
          strerror(errno));
      return 1;
    }
    char *real = realpath(s->cfg.data_dir, NULL);
    if (real) {
      snprintf(s->cfg.data_dir, sizeof s->cfg.data_dir, "%s", real);
      free(real);
    }
  }
  /* The port file's place and the ready descriptor are checked before the slow start. */
  if (!s->cfg.precompile && ready_prepare(s->cfg.port_file, s->cfg.ready_fd) != 0) {
    ready_finish();
    return 1;
  }
  scene_set_data_dir(s->cfg.data_dir[0] ? s->cfg.data_dir : NULL);
  scene_set_volume_limit(s->cfg.limits.cloud_side);
  scene_set_cloud_side(s->cfg.limits.cloud_side);

  service_status("starting: OpenCL device and kernels");
  uint64_t t0 = now_ns();
  renderer_opts_t ropts = {.device = s->cfg.device[0] ? s->cfg.device : NULL,
                           .kernels_dir = s->cfg.kernels_dir[0] ? s->cfg.kernels_dir : NULL};
  renderer_t *renderer = NULL;
  char err[8192];
  if (renderer_create(&ropts, &renderer, err, sizeof err) != 0) {
    LOG(LOG_ERROR, "opencl", "%s", err);
    ready_finish();
    return 1;
  }
  if (s->cfg.precompile)
    return precompile(renderer, t0);
  snprintf(s->platform, sizeof s->platform, "%s", renderer_platform_name(renderer));
  snprintf(s->device, sizeof s->device, "%s", renderer_device_name(renderer));
  LOG(LOG_INFO, "opencl", "%s / %s ready in %.0f ms", s->platform, s->device,
      (double)(now_ns() - t0) / 1e6);

  s->loop = uv_default_loop();
  if (reclaim_start() != 0)
    LOG(LOG_WARN, "server", "no reclaimer thread: big blocks are freed where they are dropped");
  stats_init(&s->stats, now_ns());
  s->worker = worker_start(s->loop, renderer, s->cfg.render_queue);
  if (!s->worker) {
    renderer_destroy(renderer);
    reclaim_stop();
    ready_finish();
    return 1;
  }

  /* Signals first: every path out of here, even a failed start, goes through the stop, which
   * closes them. */
  uv_signal_init(s->loop, &s->sigint);
  uv_signal_init(s->loop, &s->sigterm);
  s->sigint.data = s->sigterm.data = s;
  uv_signal_start(&s->sigint, on_signal, SIGINT);
  uv_signal_start(&s->sigterm, on_signal, SIGTERM);
  /* SIGHUP and the stop watch do not keep the loop alive; they are closed with whatever is left
   * once it ends. */
  uv_signal_init(s->loop, &reload.signal);
  reload.signal.data = s;
  uv_signal_start(&reload.signal, on_sighup, SIGHUP);
  uv_unref((uv_handle_t *)&reload.signal);
  uv_check_init(s->loop, &reload.stop_watch);
  reload.stop_watch.data = s;
  uv_check_start(&reload.stop_watch, on_stop_watch);
  uv_unref((uv_handle_t *)&reload.stop_watch);

  scene_error_t serr = {0};
  if (!server_add_scene(s, PROTO_DEFAULT_SCENE, s->cfg.scene[0] ? s->cfg.scene : NULL, &serr)) {
    LOG(LOG_ERROR, "scene", "cannot load the main scene: %s%s%s", serr.message,
        serr.path[0] ? " at " : "", serr.path);
    server_request_stop(s);
    uv_run(s->loop, UV_RUN_DEFAULT);
    uv_walk(s->loop, close_any, NULL);
    uv_run(s->loop, UV_RUN_DEFAULT);
    uv_loop_close(s->loop);
    reclaim_stop();
    ready_finish();
    return 1;
  }

  int exit_code = 0;
  server_features_register(s);
  if (net_listen(s) != 0 || announce(s) != 0) {
    exit_code = 1;
    server_request_stop(s);
  }
  uv_run(s->loop, UV_RUN_DEFAULT);
  service_stopping();
  /* Whatever is left (an unreferenced timer, SIGHUP's handler) is closed so the loop can be
   * freed. A SIGHUP from here on is ignored rather than fatal. */
  uv_walk(s->loop, close_any, NULL);
  uv_run(s->loop, UV_RUN_DEFAULT);
  signal(SIGHUP, SIG_IGN);
  uv_loop_close(s->loop);
  /* Every call is answered now, so nothing pins the caches: a seeding or a failed read that
   * finished after the scenes were removed is dropped here. */
  seeding_prune();
  scene_files_prune();
  reclaim_stop();
  ready_finish();
  LOG(LOG_INFO, "server", "stopped");
  return exit_code;
}
