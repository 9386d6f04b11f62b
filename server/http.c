/*
 * The --http listener: one libwebsockets context on the server's libuv loop (a foreign loop,
 * so no thread or loop of its own), whose single vhost serves the viewer's static files from
 * cfg.web_dir through a libwebsockets file mount (its MIME table, its URL cleaning) and takes
 * WebSocket upgrades for ws_conn.c after checking their Origin. The stop waits for the
 * WebSockets to drain as the TCP connections do, then destroys the context; libwebsockets
 * closes its handles on the loop, which then ends.
 */
#include "http.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>

#include "log.h"

struct http_server {
  struct lws_context *ctx;
  struct lws_vhost *vhost;
  struct lws_http_mount mount;
  void *loops[1];
  uv_timer_t finish; /* Destroys the context outside libwebsockets' own callbacks. */
  int port;
  unsigned nws; /* WebSockets open. */
  int stopping;
};

static const struct lws_protocols http_protocols[] = {
    {0}, /* ws_conn_protocol, copied in at the start (it is defined in another unit). */
    {0},
};

/* libwebsockets' log lines go to volfxd's log: its errors as warnings, nothing else. */
static void http_log(int level, const char *line) {
  size_t n = strlen(line);
  while (n && (line[n - 1] == '\n' || line[n - 1] == '\r'))
    n--;
  LOG(level == LLL_ERR ? LOG_WARN : LOG_DEBUG, "http", "libwebsockets: %.*s", (int)n, line);
}

int http_listen(server_t *s) {
  const config_t *cfg = &s->cfg;
  if (!cfg->http_host[0])
    return 0;
  struct http_server *h = calloc(1, sizeof *h);
  static struct lws_protocols protocols[2];
  if (!h)
    return -1;
  memcpy(protocols, http_protocols, sizeof protocols);
  protocols[0] = ws_conn_protocol;
  s->http = h;
  lws_set_log_level(LLL_ERR | LLL_WARN, http_log);

  h->mount.mountpoint = "/";
  h->mount.mountpoint_len = 1;
  h->mount.origin = cfg->web_dir;
  h->mount.def = "index.html";
  h->mount.origin_protocol = LWSMPRO_FILE;
  h->mount.cache_max_age = 0;
  h->loops[0] = s->loop;

  struct lws_context_creation_info info;
  memset(&info, 0, sizeof info);
  info.options = LWS_SERVER_OPTION_LIBUV | LWS_SERVER_OPTION_UV_NO_SIGSEGV_SIGFPE_SPIN |
                 LWS_SERVER_OPTION_EXPLICIT_VHOSTS |
                 LWS_SERVER_OPTION_HTTP_HEADERS_SECURITY_BEST_PRACTICES_ENFORCE;
  info.foreign_loops = h->loops;
  info.user = s;
  /* Plain HTTP connections (file requests) are bounded by libwebsockets' table of sockets: as
   * many as limits.connections, plus its listener and its own few. WebSockets on top are
   * counted against limits.connections with the TCP ones (conn_open). */
  info.fd_limit_per_thread = cfg->limits.connections + 8;
  h->ctx = lws_create_context(&info);
  if (!h->ctx) {
    LOG(LOG_ERROR, "http", "cannot start libwebsockets with the libuv event loop");
    return -1;
  }
  /* "localhost" binds the loopback address; a wildcard binds every interface. */
  const char *iface = cfg->http_host;
  if (strcmp(iface, "localhost") == 0)
    iface = "127.0.0.1";
  else if (strcmp(iface, "0.0.0.0") == 0 || strcmp(iface, "::") == 0)
    iface = NULL;
  info.port = cfg->http_port ? cfg->http_port : CONTEXT_PORT_NO_LISTEN_SERVER;
  info.iface = iface;
  info.protocols = protocols;
  info.mounts = &h->mount;
  info.vhost_name = "volfx";
  info.timeout_secs = 30;
  if (cfg->http_port == 0)
    info.port = 0; /* The kernel picks one; http_port reads it back. */
  h->vhost = lws_create_vhost(h->ctx, &info);
  if (!h->vhost) {
    LOG(LOG_ERROR, "http", "cannot serve http on %s:%d", cfg->http_host, cfg->http_port);
    return -1;
  }
  h->port = lws_get_vhost_listen_port(h->vhost);
  uv_timer_init(s->loop, &h->finish);
  h->finish.data = s;
  LOG(LOG_INFO, "http", "serving %s", cfg->web_dir);
  printf("volfxd http on %s:%d\n", cfg->http_host, h->port);
  fflush(stdout);
  return 0;
}

static void on_finish_closed(uv_handle_t *handle) {
  free(((server_t *)handle->data)->http);
}

static void on_finish(uv_timer_t *t) {
  server_t *s = t->data;
  struct http_server *h = s->http;
  if (h->ctx)
    lws_context_destroy(h->ctx);
  h->ctx = NULL;
  uv_close((uv_handle_t *)&h->finish, on_finish_closed);
}

void http_stop(server_t *s) {
  struct http_server *h = s->http;
  if (!h || h->stopping)
    return;
  h->stopping = 1;
  if (!h->vhost) { /* The start failed part-way. */
    if (h->ctx)
      lws_context_destroy(h->ctx);
    free(h);
    s->http = NULL;
    return;
  }
  if (h->nws == 0)
    uv_timer_start(&h->finish, on_finish, 0, 0);
}

void http_ws_opened(server_t *s) {
  s->http->nws++;
}

void http_ws_closed(server_t *s) {
  struct http_server *h = s->http;
  if (--h->nws == 0 && h->stopping)
    uv_timer_start(&h->finish, on_finish, 0, 0);
}

/* Splits "name", "name:port" or "[v6]:port" ('n' bytes) into 'name' (brackets removed) and
 * '*port' (80 when absent). Returns 0, or -1 when the name does not fit. */
static int split_host_port(const char *hp, size_t n, char *name, size_t cap, int *port) {
  const char *colon = memrchr(hp, ':', n);
  const char *bracket = memrchr(hp, ']', n);
  *port = 80;
  if (colon && (!bracket || colon > bracket) && (hp[0] == '[' || memchr(hp, ':', n) == colon)) {
    *port = atoi(colon + 1);
    n = (size_t)(colon - hp);
  }
  if (n >= 2 && hp[0] == '[' && hp[n - 1] == ']') {
    hp++;
    n -= 2;
  }
  if (n >= cap)
    return -1;
  memcpy(name, hp, n);
  name[n] = '\0';
  return 0;
}

/* Whether 'name' is an IP address written out (not a name that DNS could point anywhere). */
static int host_is_literal(const char *name) {
  if (strchr(name, ':'))
    return 1; /* IPv6. */
  for (const char *c = name; *c; c++)
    if (!(*c == '.' || (*c >= '0' && *c <= '9')))
      return 0;
  return 1;
}

/* Whether 'origin' is on the operator's --http-origin list. */
static int origin_listed(const char *list, const char *origin) {
  while (*list) {
    size_t n = strcspn(list, ",");
    const char *item = list;
    size_t len = n;
    while (len && *item == ' ')
      item++, len--;
    while (len && item[len - 1] == ' ')
      len--;
    if ((len == 1 && item[0] == '*') || (len == strlen(origin) && strncmp(item, origin, len) == 0))
      return 1;
    list += n + (list[n] == ',');
  }
  return 0;
}

int http_origin_allowed(const server_t *s, const char *origin, const char *host) {
  if (!origin || !origin[0])
    return 1; /* Not a browser: a browser always sends its page's Origin. */
  const config_t *cfg = &s->cfg;
  if (origin_listed(cfg->http_origins, origin))
    return 1;
  /* Else the server's own address, as a page it served has it. */
  char name[300];
  int port;
  if (strncmp(origin, "http://", 7) != 0 ||
      split_host_port(origin + 7, strlen(origin + 7), name, sizeof name, &port) != 0 ||
      port != (s->http ? s->http->port : cfg->http_port))
    return 0;
  const char *own = cfg->http_host;
  if (strcmp(own, "0.0.0.0") == 0 || strcmp(own, "::") == 0)
    /* Every interface: the page's Host, when that is an address rather than a name (a name
     * could be any site's, pointed here by its DNS). */
    return host && host_is_literal(name) && strcasecmp(origin + 7, host) == 0;
  return strcasecmp(name, own) == 0 ||
         (config_host_is_loopback(own) && config_host_is_loopback(name));
}
