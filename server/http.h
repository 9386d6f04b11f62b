/*
 * The browser viewer's listener (--http): libwebsockets serves the files of the viewer
 * (client/web/) over HTTP and JSON-RPC over WebSocket, on the server's own libuv loop. A
 * WebSocket is a connection (conn_t) like a TCP one, with its own transport (ws_conn.c).
 */
#ifndef VOLFX_HTTP_H
#define VOLFX_HTTP_H

#include <libwebsockets.h>

#include "server.h"

/* Starts the listener when the configuration names one (cfg.http_host); 0, or -1 (logged). */
int http_listen(server_t *s);
/* Stops taking WebSockets; the listener closes once the last one has closed. */
void http_stop(server_t *s);
/* Whether a WebSocket upgrade with 'origin' ("scheme://host[:port]") and 'host' (the Host
 * header; either may be NULL) may open: no Origin (not a browser), the server's own address,
 * or one of --http-origin. */
int http_origin_allowed(const server_t *s, const char *origin, const char *host);

/* ws_conn.c: the WebSocket protocol, JSON-RPC in text messages. */
extern const struct lws_protocols ws_conn_protocol;
/* A WebSocket opened, or closed: once the last one has closed during a stop, the listener
 * closes. */
void http_ws_opened(server_t *s);
void http_ws_closed(server_t *s);

#endif
