/*
 * Command line and config file parsing for volfxd. The config file is a JSON object whose
 * members have the long option names ("listen", "data", "token", "idle_timeout", ...) plus a
 * "limits" object; the command line overrides it.
 */
#include "config.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <errno.h>
#include <stddef.h>
#include <getopt.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "files.h"
#include "log.h"

static const char usage[] =
    "Usage: volfxd [options]\n"
    "  --listen HOST:PORT   TCP address (default 127.0.0.1:7878; port 0 picks one; 'none' "
    "disables)\n"
    "  --unix PATH          also listen on a Unix socket\n"
    "  --http HOST:PORT     also serve the browser viewer and WebSocket JSON-RPC there\n"
    "  --http-origin LIST   further Origins allowed to open a WebSocket (comma-separated,\n"
    "                       e.g. https://tools.example.com; '*' allows any)\n"
    "  --web DIR            the viewer's files (default: the source tree's client/web/)\n"
    "  --data DIR           data directory for snapshots, sequences and meshes\n"
    "  --token TOKEN        require 'auth' first (default: $VOLFX_TOKEN)\n"
    "  --insecure           allow a non-loopback address without a token\n"
    "  --device cpu|gpu|N   OpenCL device (default: the CPU device)\n"
    "  --kernels DIR        load OpenCL sources from DIR instead of the embedded copies\n"
    "  --scene FILE|PRESET  the 'main' scene at start (default: the demo preset)\n"
    "  --presets DIR        where preset scenes live (default: the source tree's scenes/)\n"
    "  --config FILE        JSON config file (members named like these options)\n"
    "  --idle-timeout S     close connections idle this long (default 300; 0 never)\n"
    "  --max-connections N  connection limit (default 256)\n"
    "  --port-file PATH     once listening, write 'PORT' and 'HOST' lines to PATH (atomically)\n"
    "  --ready-fd N         once listening, write 'ready PORT HOST' to descriptor N, close it\n"
    "  --log-level L        debug, info, warn, error or quiet (default info)\n"
    "  --precompile         compile and warm every kernel into the kernel cache ($POCL_CACHE_DIR,\n"
    "                       else ~/.cache/volfx/pocl), then exit: for machine images\n"
    "  --version, --help\n";

static int copy_str(char *dst, size_t cap, const char *src, const char *what) {
  if (strlen(src) >= cap) {
    fprintf(stderr, "volfxd: %s is too long (at most %zu bytes)\n", what, cap - 1);
    return CONFIG_ERROR;
  }
  strcpy(dst, src);
  return CONFIG_OK;
}

/* Parses "HOST:PORT" (or "none", which leaves 'host' empty) of option 'what' into 'host' (of
 * 'cap' bytes) and '*port'. */
static int parse_host_port(const char *s, char *host, size_t cap, int *port, const char *what) {
  if (strcmp(s, "none") == 0) {
    host[0] = '\0';
    return CONFIG_OK;
  }
  const char *colon = strrchr(s, ':');
  if (!colon || colon == s) {
    fprintf(stderr, "volfxd: %s wants HOST:PORT, got '%s'\n", what, s);
    return CONFIG_ERROR;
  }
  char *end;
  errno = 0;
  long p = strtol(colon + 1, &end, 10);
  if (errno || *end || end == colon + 1 || p < 0 || p > 65535) {
    fprintf(stderr, "volfxd: %s port must be 0-65535, got '%s'\n", what, colon + 1);
    return CONFIG_ERROR;
  }
  size_t n = (size_t)(colon - s);
  /* Accept "[::1]:7878" as well as "::1:7878". */
  if (s[0] == '[' && colon[-1] == ']') {
    s++;
    n -= 2;
  }
  if (n >= cap) {
    fprintf(stderr, "volfxd: %s host is too long\n", what);
    return CONFIG_ERROR;
  }
  memcpy(host, s, n);
  host[n] = '\0';
  *port = (int)p;
  return CONFIG_OK;
}

static int parse_number(const char *s, double lo, double hi, const char *what, double *out) {
  char *end;
  errno = 0;
  double v = strtod(s, &end);
  if (errno || *end || end == s || !(v >= lo && v <= hi)) {
    fprintf(stderr, "volfxd: %s must be a number in [%g, %g], got '%s'\n", what, lo, hi, s);
    return CONFIG_ERROR;
  }
  *out = v;
  return CONFIG_OK;
}

enum {
  OPT_LISTEN = 256,
  OPT_UNIX,
  OPT_DATA,
  OPT_TOKEN,
  OPT_INSECURE,
  OPT_DEVICE,
  OPT_KERNELS,
  OPT_SCENE,
  OPT_PRESETS,
  OPT_CONFIG,
  OPT_IDLE,
  OPT_MAXCONN,
  OPT_LOGLEVEL,
  OPT_PORT_FILE,
  OPT_READY_FD,
  OPT_PRECOMPILE,
  OPT_VERSION,
  OPT_HELP,
  OPT_HTTP,
  OPT_HTTP_ORIGIN,
  OPT_WEB
};

static const struct option long_options[] = {
    {"listen", required_argument, 0, OPT_LISTEN},
    {"unix", required_argument, 0, OPT_UNIX},
    {"data", required_argument, 0, OPT_DATA},
    {"token", required_argument, 0, OPT_TOKEN},
    {"insecure", no_argument, 0, OPT_INSECURE},
    {"device", required_argument, 0, OPT_DEVICE},
    {"kernels", required_argument, 0, OPT_KERNELS},
    {"scene", required_argument, 0, OPT_SCENE},
    {"presets", required_argument, 0, OPT_PRESETS},
    {"config", required_argument, 0, OPT_CONFIG},
    {"idle-timeout", required_argument, 0, OPT_IDLE},
    {"max-connections", required_argument, 0, OPT_MAXCONN},
    {"log-level", required_argument, 0, OPT_LOGLEVEL},
    {"port-file", required_argument, 0, OPT_PORT_FILE},
    {"ready-fd", required_argument, 0, OPT_READY_FD},
    {"precompile", no_argument, 0, OPT_PRECOMPILE},
    {"version", no_argument, 0, OPT_VERSION},
    {"help", no_argument, 0, OPT_HELP},
    {"http", required_argument, 0, OPT_HTTP},
    {"http-origin", required_argument, 0, OPT_HTTP_ORIGIN},
    {"web", required_argument, 0, OPT_WEB},
    {0, 0, 0, 0},
};

/* Applies one option, from the command line or the config file. */
static int apply_option(config_t *c, int opt, const char *arg) {
  double v;
  switch (opt) {
  case OPT_LISTEN:
    return parse_host_port(arg, c->listen_host, sizeof c->listen_host, &c->listen_port, "--listen");
  case OPT_HTTP:
    return parse_host_port(arg, c->http_host, sizeof c->http_host, &c->http_port, "--http");
  case OPT_HTTP_ORIGIN:
    return copy_str(c->http_origins, sizeof c->http_origins, arg, "--http-origin");
  case OPT_WEB:
    return copy_str(c->web_dir, sizeof c->web_dir, arg, "--web");
  case OPT_UNIX:
    return copy_str(c->unix_path, sizeof c->unix_path, arg, "--unix");
  case OPT_DATA:
    return copy_str(c->data_dir, sizeof c->data_dir, arg, "--data");
  case OPT_TOKEN:
    return copy_str(c->token, sizeof c->token, arg, "--token");
  case OPT_INSECURE:
    c->insecure = 1;
    return CONFIG_OK;
  case OPT_PRECOMPILE:
    c->precompile = 1;
    return CONFIG_OK;
  case OPT_DEVICE:
    return copy_str(c->device, sizeof c->device, arg, "--device");
  case OPT_KERNELS:
    return copy_str(c->kernels_dir, sizeof c->kernels_dir, arg, "--kernels");
  case OPT_SCENE:
    return copy_str(c->scene, sizeof c->scene, arg, "--scene");
  case OPT_PRESETS:
    return copy_str(c->presets_dir, sizeof c->presets_dir, arg, "--presets");
  case OPT_PORT_FILE:
    return copy_str(c->port_file, sizeof c->port_file, arg, "--port-file");
  case OPT_READY_FD:
    if (parse_number(arg, 0, 1 << 20, "--ready-fd", &v))
      return CONFIG_ERROR;
    if (v != (int)v) {
      fprintf(stderr, "volfxd: --ready-fd wants a descriptor number, got '%s'\n", arg);
      return CONFIG_ERROR;
    }
    c->ready_fd = (int)v;
    return CONFIG_OK;
  case OPT_IDLE:
    if (parse_number(arg, 0, 86400 * 365, "--idle-timeout", &v))
      return CONFIG_ERROR;
    c->idle_timeout_s = v;
    return CONFIG_OK;
  case OPT_MAXCONN:
    if (parse_number(arg, 1, 65536, "--max-connections", &v))
      return CONFIG_ERROR;
    c->limits.connections = (uint32_t)v;
    return CONFIG_OK;
  case OPT_LOGLEVEL:
    c->log_level = log_level_parse(arg);
    if (c->log_level < 0) {
      fprintf(stderr, "volfxd: --log-level must be debug, info, warn, error or quiet\n");
      return CONFIG_ERROR;
    }
    return CONFIG_OK;
  }
  return CONFIG_ERROR;
}

#define LIMIT(name, lo, hi, member, kind)                                                          \
  { name, lo, hi, offsetof(config_t, member), kind }

const config_limit_t config_limits[] = {
    LIMIT("line_bytes", 1024, 1 << 30, limits.line_bytes, 'z'),
    LIMIT("frame_side", 1, 16384, limits.frame_side, 'u'),
    LIMIT("particles", 1, 1 << 26, limits.particles, 'u'),
    LIMIT("cloud_side", 1, 1024, limits.cloud_side, 'u'),
    LIMIT("connections", 1, 65536, limits.connections, 'u'),
    LIMIT("output_bytes", 1 << 20, 1e12, limits.output_bytes, 'z'),
    LIMIT("output_total_bytes", 1 << 20, 1e13, budget.output_total_bytes, 'z'),
    LIMIT("render_queue", 1, 65536, render_queue, 'i'),
    LIMIT("idle_timeout_s", 0, 86400 * 365, idle_timeout_s, 'd'),
    LIMIT("auth_timeout_s", 0.1, 3600, budget.auth_timeout_s, 'd'),
    LIMIT("unauthenticated", 1, 65536, budget.unauthenticated, 'u'),
    LIMIT("auth_failures", 1, 1000, budget.auth_failures, 'u'),
    LIMIT("scenes", 1, 4096, budget.scenes, 'u'),
    LIMIT("scene_bytes", 1 << 20, 1e13, budget.scene_bytes, 'z'),
    LIMIT("keyframes", 1, 1 << 20, budget.keyframes, 'u'),
    LIMIT("automaton_steps", 1, 1e9, budget.automaton_steps, 'u'),
    LIMIT("job_frames", 1, 4294967295.0, budget.job_frames, 'u'),
    LIMIT("job_bytes", 1 << 20, 1e15, budget.job_bytes, 'z'),
    LIMIT("data_reserve_bytes", 0, 1e15, budget.data_reserve_bytes, 'z'),
    {0},
};

double config_limit_value(const config_t *c, const config_limit_t *l) {
  const char *at = (const char *)c + l->offset;
  switch (l->kind) {
  case 'z':
    return (double)*(const size_t *)at;
  case 'u':
    return *(const uint32_t *)at;
  case 'i':
    return *(const int *)at;
  default:
    return *(const double *)at;
  }
}

static void limit_set(config_t *c, const config_limit_t *l, double v) {
  char *at = (char *)c + l->offset;
  switch (l->kind) {
  case 'z':
    *(size_t *)at = (size_t)v;
    break;
  case 'u':
    *(uint32_t *)at = (uint32_t)v;
    break;
  case 'i':
    *(int *)at = (int)v;
    break;
  default:
    *(double *)at = v;
  }
}

/* Reads the "limits" object of the config file. */
static int apply_limits(config_t *c, const cJSON *lim) {
  const cJSON *it;
  cJSON_ArrayForEach(it, lim) {
    const config_limit_t *l = config_limits;
    while (l->name && strcmp(it->string, l->name) != 0)
      l++;
    if (!l->name || !cJSON_IsNumber(it) ||
        !(it->valuedouble >= l->lo && it->valuedouble <= l->hi)) {
      fprintf(stderr, "volfxd: config: limits.%s is unknown or out of range\n", it->string);
      return CONFIG_ERROR;
    }
    limit_set(c, l, it->valuedouble);
  }
  return CONFIG_OK;
}

static int load_file(config_t *c, const char *path) {
  char *text = files_read(path, 1u << 20, NULL);
  if (!text) {
    fprintf(stderr, "volfxd: cannot read config %s: %s\n", path, strerror(errno));
    return CONFIG_ERROR;
  }
  cJSON *doc = cJSON_Parse(text);
  free(text);
  if (!cJSON_IsObject(doc)) {
    fprintf(stderr, "volfxd: config %s is not a JSON object\n", path);
    cJSON_Delete(doc);
    return CONFIG_ERROR;
  }
  int rc = CONFIG_OK;
  const cJSON *it;
  cJSON_ArrayForEach(it, doc) {
    if (strcmp(it->string, "limits") == 0) {
      rc = cJSON_IsObject(it) ? apply_limits(c, it) : CONFIG_ERROR;
    } else {
      const struct option *o = long_options;
      while (o->name && strcmp(o->name, it->string) != 0)
        o++;
      if (!o->name || o->val == OPT_CONFIG || o->val == OPT_HELP || o->val == OPT_VERSION) {
        fprintf(stderr, "volfxd: config %s: unknown member '%s'\n", path, it->string);
        rc = CONFIG_ERROR;
      } else if (o->has_arg == no_argument) {
        if (cJSON_IsTrue(it))
          rc = apply_option(c, o->val, NULL);
      } else if (cJSON_IsString(it)) {
        rc = apply_option(c, o->val, it->valuestring);
      } else if (cJSON_IsNumber(it)) {
        char num[64];
        snprintf(num, sizeof num, "%.17g", it->valuedouble);
        rc = apply_option(c, o->val, num);
      } else {
        fprintf(stderr, "volfxd: config %s: '%s' must be a string or number\n", path, it->string);
        rc = CONFIG_ERROR;
      }
    }
    if (rc)
      break;
  }
  cJSON_Delete(doc);
  return rc;
}

int config_host_is_loopback(const char *host) {
  /* An address written out, not a name that merely starts like one ("127.0.0.1.example"). */
  struct in_addr v4;
  struct in6_addr v6;
  if (inet_pton(AF_INET, host, &v4) == 1)
    return (ntohl(v4.s_addr) >> 24) == 127;
  if (inet_pton(AF_INET6, host, &v6) == 1)
    return IN6_IS_ADDR_LOOPBACK(&v6);
  return strcmp(host, "localhost") == 0;
}

int config_load(config_t *c, int argc, char **argv) {
  memset(c, 0, sizeof *c);
  strcpy(c->listen_host, PROTO_DEFAULT_HOST);
  c->listen_port = PROTO_DEFAULT_PORT;
  strcpy(c->presets_dir, VOLFX_PRESET_DIR);
  strcpy(c->web_dir, VOLFX_WEB_DIR);
  strcpy(c->scene, "demo");
  c->log_level = LOG_INFO;
  c->idle_timeout_s = 300;
  c->render_queue = 64;
  c->ready_fd = -1;
  proto_limits_default(&c->limits);
  c->budget = (budget_t){.output_total_bytes = (size_t)1 << 30,
                         .auth_timeout_s = 10,
                         .unauthenticated = 16,
                         .auth_failures = 3,
                         .scenes = 64,
                         .scene_bytes = (size_t)4 << 30,
                         .keyframes = 4096,
                         .automaton_steps = 1000000,
                         .job_frames = 1000000,
                         .job_bytes = (size_t)64 << 30,
                         .data_reserve_bytes = (size_t)1 << 30};

  /* The config file is read first so that the command line overrides it. */
  for (int i = 1; i < argc; i++) {
    const char *arg = NULL;
    if (strcmp(argv[i], "--config") == 0 && i + 1 < argc)
      arg = argv[i + 1];
    else if (strncmp(argv[i], "--config=", 9) == 0)
      arg = argv[i] + 9;
    if (arg && load_file(c, arg))
      return CONFIG_ERROR;
  }

  optind = 1;
  opterr = 0;
  int opt;
  while ((opt = getopt_long(argc, argv, "", long_options, NULL)) != -1) {
    switch (opt) {
    case OPT_HELP:
      fputs(usage, stdout);
      return CONFIG_EXIT_OK;
    case OPT_VERSION:
      printf("volfxd %s (protocol %s)\n", VOLFX_VERSION, PROTO_VERSION);
      return CONFIG_EXIT_OK;
    case OPT_CONFIG:
      break;
    case '?':
    case ':':
      fprintf(stderr, "volfxd: bad option '%s' (see --help)\n", argv[optind - 1]);
      return CONFIG_ERROR;
    default:
      if (apply_option(c, opt, optarg))
        return CONFIG_ERROR;
    }
  }
  if (optind < argc) {
    fprintf(stderr, "volfxd: unexpected argument '%s' (see --help)\n", argv[optind]);
    return CONFIG_ERROR;
  }
  const char *env = getenv("VOLFX_TOKEN");
  if (!c->token[0] && env && env[0] && copy_str(c->token, sizeof c->token, env, "VOLFX_TOKEN"))
    return CONFIG_ERROR;

  if (c->listen_host[0] && !config_host_is_loopback(c->listen_host) && !c->token[0] &&
      !c->insecure) {
    fprintf(stderr, "volfxd: refusing to listen on %s without a token; set --token or --insecure\n",
            c->listen_host);
    return CONFIG_ERROR;
  }
  if (c->http_host[0] && !config_host_is_loopback(c->http_host) && !c->token[0] && !c->insecure) {
    fprintf(stderr,
            "volfxd: refusing to serve http on %s without a token; set --token or --insecure\n",
            c->http_host);
    return CONFIG_ERROR;
  }
  if (!c->listen_host[0] && !c->unix_path[0]) {
    fprintf(stderr, "volfxd: nothing to listen on (--listen none without --unix)\n");
    return CONFIG_ERROR;
  }
  return CONFIG_OK;
}
