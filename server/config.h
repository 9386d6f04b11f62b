/*
 * volfxd's configuration: defaults, then the config file (--config, JSON), then the command
 * line, then VOLFX_TOKEN when no token was given. Everything here is read-only once the
 * server starts.
 */
#ifndef VOLFX_CONFIG_H
#define VOLFX_CONFIG_H

#include "proto.h"

/* Server-wide budgets and per-client bounds beyond the protocol's own limits. */
typedef struct budget {
  size_t output_total_bytes; /* Unsent output and frames in the making, all connections. */
  double auth_timeout_s;     /* An unauthenticated connection is closed after this long. */
  uint32_t unauthenticated;  /* Most connections that have not authenticated (with a token). */
  uint32_t auth_failures;    /* Wrong tokens before the connection is closed. */
  uint32_t scenes;           /* Most scenes. */
  size_t scene_bytes;        /* The simulation state of all scenes together, estimated. */
  uint32_t keyframes;        /* Animation keys in one scene's document. */
  uint32_t automaton_steps;  /* Most cloud automaton steps one sim.step may ask for. */
  uint32_t job_frames;       /* Most files one render.sequence or sim.bake job writes. */
  size_t job_bytes;          /* Most bytes one job writes. */
  size_t data_reserve_bytes; /* Free space writes under --data leave on its file system. */
} budget_t;

typedef struct config {
  char listen_host[256]; /* Empty when TCP is disabled ("--listen none"). */
  int listen_port;       /* 0 picks a free port. */
  char unix_path[256];   /* Empty: no Unix socket. */
  char http_host[256];   /* Empty: no HTTP/WebSocket listener (--http). */
  int http_port;
  char http_origins[1024]; /* Further Origins a WebSocket may come from, comma-separated. */
  char web_dir[1024];      /* The viewer's static files. */
  char data_dir[1024];     /* Empty: no data directory (file methods refused). */
  char token[256];         /* Empty: no authentication. */
  int insecure;            /* Allow a non-loopback listener without a token. */
  int precompile;          /* Compile and warm every kernel into the cache, then exit. */
  char device[64];         /* "cpu", "gpu", an index, or empty for the default. */
  char kernels_dir[1024];
  char scene[1024]; /* Preset name or file for the "main" scene; empty for defaults. */
  char presets_dir[1024];
  int log_level;
  double idle_timeout_s; /* 0 disables the idle timeout. */
  int render_queue;      /* Most render jobs waiting; more get -32002. */
  char port_file[1024];  /* Written with the bound port once listening; empty: none. */
  int ready_fd;          /* Told "ready PORT HOST" once listening, then closed; -1: none. */
  proto_limits_t limits;
  budget_t budget;
} config_t;

/* One configurable limit: its name in "limits" (config file and server.info), its range, and
 * where it lives in config_t. */
typedef struct config_limit {
  const char *name;
  double lo, hi;
  size_t offset; /* Of the value in config_t. */
  char kind;     /* 'z' size_t, 'u' uint32_t, 'i' int, 'd' double. */
} config_limit_t;

/* Every limit, in the order server.info lists them; ends with a NULL name. */
extern const config_limit_t config_limits[];

/* The value of limit 'l' in 'c'. */
double config_limit_value(const config_t *c, const config_limit_t *l);

enum { CONFIG_OK = 0, CONFIG_EXIT_OK = 1, CONFIG_ERROR = -1 };

/*
 * Fills 'c' from defaults, the config file and 'argv'. Returns CONFIG_OK, CONFIG_EXIT_OK after
 * printing --help or --version, or CONFIG_ERROR after printing what was wrong to stderr.
 */
int config_load(config_t *c, int argc, char **argv);

/* 1 when 'host' is a loopback address or "localhost". */
int config_host_is_loopback(const char *host);

#endif
