/*
 * Back-pressure accounting: the one owner of the counters that decide whether a connection may
 * run a further request. Per connection: its unsent output (handed to libuv, not yet on the
 * socket), the bytes its answers still in the making will write (promised), and its renders in
 * the shared queue. Over all connections: the output total (unsent output, answers promised and
 * subscription frames in the making or waiting) counted against budget.output_total_bytes.
 *
 * The output limit (limits.output_bytes) is backpressure, not a cut-off: while a connection's
 * unsent output and its promised answers pass it, conn_full holds, and the transport (net.c)
 * reads no further request from it, so a client that pipelines is slowed to the pace it reads
 * at, and one answer larger than the limit (a 4096² float frame) still goes out whole. Once the
 * server's output budget is spent, a connection that has output pending runs no further request
 * until the total is back under it, so the clients that wait for nothing go on. Before
 * authentication (on a server with a token) a connection may hold little: its answers are
 * errors and the auth result.
 *
 * The transport, the dispatcher, the handlers and the subscriptions change these counters only
 * through the functions here (server.h, "output.c").
 */
#include "server.h"

/* The most output an unauthenticated connection may have unsent (its answers are errors). */
#define UNAUTH_OUTPUT_BYTES 65536

void output_total_add(server_t *s, long long delta) {
  size_t budget = s->cfg.budget.output_total_bytes;
  int was_over = s->output_total > budget;
  s->output_total += (size_t)delta;
  if (!was_over || s->output_total > budget)
    return;
  /* Back under the budget: connections paused by it may go on. */
  for (conn_t *c = s->conns, *next; c; c = next) {
    next = c->next;
    if (c->out_paused && !c->closing)
      conn_resume(c);
  }
}

int output_total_fits(const server_t *s, size_t bytes) {
  return s->output_total + bytes <= s->cfg.budget.output_total_bytes;
}

size_t output_total(const server_t *s) {
  return s->output_total;
}

size_t output_queued_bytes(const server_t *s) {
  size_t queued = 0;
  for (const conn_t *c = s->conns; c; c = c->next)
    queued += c->out_bytes;
  return queued;
}

int conn_full(const conn_t *c) {
  const server_t *s = c->srv;
  size_t own = c->out_bytes + c->promised;
  size_t limit = c->authed ? s->cfg.limits.output_bytes : UNAUTH_OUTPUT_BYTES;
  return own > limit || c->renders >= CONN_RENDERS_MAX ||
         (own > 0 && s->output_total > s->cfg.budget.output_total_bytes);
}

void conn_output_queued(conn_t *c, size_t bytes) {
  c->out_bytes += bytes;
  output_total_add(c->srv, (long long)bytes);
}

void conn_output_written(conn_t *c, size_t bytes) {
  c->out_bytes -= bytes;
}

void conn_promise(call_t *call, size_t bytes) {
  call->reply->promised += bytes;
  call->conn->promised += bytes;
  output_total_add(call->srv, (long long)bytes);
}

void conn_promise_settle(conn_t *c, reply_t *r) {
  c->promised -= r->promised;
  output_total_add(c->srv, -(long long)r->promised);
  r->promised = 0;
}

void conn_render_queued(conn_t *c) {
  c->renders++;
}

void conn_render_done(conn_t *c) {
  c->renders--;
  /* A connection that waited for its share of the render queue goes on. */
  conn_resume(c);
}
