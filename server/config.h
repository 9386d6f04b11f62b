/*
 * volfxd's configuration: defaults, then the config file (--config, JSON), then the command
 * line, then VOLFX_TOKEN when no token was given. Everything here is read-only once the
 * server starts.
 */
#ifndef VOLFX_CONFIG_H
#define VOLFX_CONFIG_H

#include "proto.h"

typedef struct config {
  char listen_host[256]; /* Empty when TCP is disabled ("--listen none"). */
  int listen_port;       /* 0 picks a free port. */
  char unix_path[256];   /* Empty: no Unix socket. */
  char data_dir[1024];   /* Empty: no data directory (file methods refused). */
  char token[256];       /* Empty: no authentication. */
  int insecure;          /* Allow a non-loopback listener without a token. */
  int precompile;        /* Compile and warm every kernel into the cache, then exit. */
  char device[64];       /* "cpu", "gpu", an index, or empty for the default. */
  char kernels_dir[1024];
  char scene[1024]; /* Preset name or file for the "main" scene; empty for defaults. */
  char presets_dir[1024];
  int log_level;
  double idle_timeout_s; /* 0 disables the idle timeout. */
  int render_queue;      /* Most render jobs waiting; more get -32002. */
  proto_limits_t limits;
} config_t;

enum { CONFIG_OK = 0, CONFIG_EXIT_OK = 1, CONFIG_ERROR = -1 };

/*
 * Fills 'c' from defaults, the config file and 'argv'. Returns CONFIG_OK, CONFIG_EXIT_OK after
 * printing --help or --version, or CONFIG_ERROR after printing what was wrong to stderr.
 */
int config_load(config_t *c, int argc, char **argv);

/* 1 when 'host' is a loopback address or "localhost". */
int config_host_is_loopback(const char *host);

#endif
