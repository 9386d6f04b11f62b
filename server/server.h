/*
 * The server's shared state and the types that cross module boundaries on the loop thread:
 * connections, the ordered reply queue of each connection, calls in progress, and the
 * registry of scenes. Everything here is touched only by the libuv loop thread; the render
 * worker sees only jobs (worker.h).
 */
#ifndef VOLFX_SERVER_H
#define VOLFX_SERVER_H

#include <stdint.h>
#include <uv.h>

#include "config.h"
#include "proto.h"
#include "scene.h"
#include "stats.h"

typedef struct server server_t;
typedef struct conn conn_t;
typedef struct reply reply_t;
typedef struct call call_t;
typedef struct sub sub_t;
typedef struct worker worker_t;
typedef struct method method_t;
typedef struct fluid_host fluid_host_t;
typedef struct seq_job seq_job_t;
typedef struct conn_transport conn_transport_t;

/* One response (or nothing, for a notification) inside a reply. */
typedef struct reply_part {
  cJSON *response; /* NULL for a notification, or when 'line' holds the response. */
  char *line;      /* The response already printed, with its newline, owned; or NULL. */
  size_t line_len;
  unsigned char *att; /* Attachment bytes, owned; NULL when none. */
  size_t att_len;
  int done;
} reply_part_t;

/*
 * What one request line is answered with: one response, or the array answering a batch.
 * Replies are queued per connection in arrival order and written only from the head, so
 * requests are answered in order even when their work finishes out of order.
 */
struct reply {
  reply_t *next;
  int batch;       /* 1: the parts are written as one JSON array. */
  int nparts;      /* Requests in the line. */
  int pending;     /* Parts not done yet. */
  size_t promised; /* Bytes its parts' work will write (conn_promise), counted in the conn's. */
  reply_part_t parts[];
};

/*
 * What a feature does with the connections it hangs state off (subscriptions, jobs): each such
 * feature adds one table at start-up (conn_hooks_add), and the transport (net.c) runs every
 * table's hooks without naming a feature. A NULL hook is nothing to do.
 */
typedef struct conn_hooks {
  const char *name;            /* The feature, for the log. */
  void (*on_close)(conn_t *c); /* The connection is closing: let go of it (nothing more is
                                  written to it). */
  void (*on_drain)(conn_t *c); /* Its socket's write queue is empty: write what waits. */
  void (*on_stop)(conn_t *c);  /* The server is stopping: end what hangs off the connection,
                                  telling the client; it closes once that is written. */
} conn_hooks_t;

/* Hook tables a server holds at most. */
#define CONN_HOOKS_MAX 8

/*
 * How a connection's bytes move: a libuv stream (TCP, Unix socket; net.c) or a WebSocket
 * (ws_conn.c). The connection's requests, replies and limits are the same over either.
 */
struct conn_transport {
  /* Sends 'line' ('len' bytes, ended by '\n') and then the 'n' attachments 'atts' ('lens'
   * bytes; NULL entries are skipped); takes every buffer (free()), also on failure. Returns 0
   * and calls conn_written once all is sent or dropped, or -1 without calling it. */
  int (*write)(conn_t *c, char *line, size_t len, unsigned char **atts, const size_t *lens, int n);
  void (*read_stop)(conn_t *c);
  void (*read_start)(conn_t *c);
  /* Bytes handed to the transport and not yet sent. */
  size_t (*queued)(const conn_t *c);
  /* Closes the transport; it calls conn_unref once when it is done with the connection. */
  void (*close)(conn_t *c);
};

struct conn {
  union {
    uv_tcp_t tcp;
    uv_pipe_t pipe;
  } h;
  uv_stream_t *stream; /* NULL for a WebSocket. */
  const conn_transport_t *transport;
  void *transport_ctx; /* The transport's own state (a WebSocket's). */
  uv_timer_t idle;
  uv_timer_t stall; /* Runs while output is unsent; closes when nothing is read for long. */
  uv_timer_t delay; /* Holds back the answer to a wrong token (conn_auth_failed). */
  server_t *srv;
  conn_t *prev, *next;
  uint64_t id;
  proto_reader_t reader;
  reply_t *head, *tail; /* Replies not yet written. */
  /* The back-pressure counters, changed only by output.c's functions: */
  size_t out_bytes; /* Bytes handed to libuv and not yet written to the socket. */
  size_t promised;  /* Bytes of answers queued (render jobs) and not yet handed to libuv. */
  int renders;      /* Its render requests queued or running on the worker. */
  int out_paused;   /* Reading stopped because the connection was full (conn_full). */
  int refs;         /* Open handles + calls in flight + subscriptions. */
  int closing;      /* No further reads; writes are dropped. */
  int draining;     /* Close once every reply is written (shutdown, oversize line). */
  int authed;
  int unauth_counted;      /* Counted in server_t.nunauth (a token server, not yet authed). */
  uint32_t auth_failures;  /* Wrong tokens so far. */
  call_t *delayed;         /* The auth call 'delay' will answer, or NULL. */
  size_t stall_mark;       /* The socket's write queue when output last moved. */
  uint64_t stall_since_ns; /* When output last moved. */
  sub_t *subs;
  uint64_t requests;
  /* Holds (conn_hold) of calls whose effect later requests must see first, such as a
   * scene.set waiting for a file: while any is held, no further request is dispatched and the
   * socket is not read. A batch stopped part-way waits in 'batch' from 'batch_next'. */
  int held;
  cJSON *batch;
  const cJSON *batch_next;
  reply_t *batch_reply;
  int batch_part;
};

/* A request being served. Handlers finish it exactly once with call_result* or call_error. */
struct call {
  server_t *srv;
  conn_t *conn;
  reply_t *reply;
  int part;
  cJSON *id;     /* A copy of the request's id; NULL for a notification. */
  cJSON *params; /* Validated params with defaults filled; owned. */
  const method_t *method;
  uint64_t t_start_ns;
  struct call_files *files; /* Files read for this call while it waited (defer.c), or NULL. */
  int holding;              /* call_hold: the connection waits for this call's answer. */
};

/* A scene held by the server, with its free-running simulation timer (play.c). */
typedef struct scene_entry {
  struct scene_entry *next;
  server_t *srv;
  scene_t *scene;
  uv_timer_t play; /* Runs while playing. */
  double rate;     /* Steps per second while playing. */
  uint64_t play_start_ns;
  uint64_t play_steps; /* Steps taken since play_start_ns. */
  int closing;
  struct fluid_host *fluid; /* The fluid's simulation state (step_fluid.c); NULL for none. */
  uint64_t cloud_owed;      /* Steps the clock took that no cloud job has (step_cloud.c). */
  uint64_t cloud_owed_gen;  /* The scene's cloud_gen 'cloud_owed' belongs to. */
  cJSON *tag;       /* The newest 'tag' of a call that changed the scene (frames.c), or NULL. */
  uint64_t tag_seq; /* Its number in the order of every tag given (0: none yet). */
} scene_entry_t;

struct server {
  uv_loop_t *loop;
  config_t cfg;
  uv_tcp_t tcp;
  uv_pipe_t pipe;
  int has_tcp, has_pipe;
  struct http_server *http; /* The --http listener (http.c), or NULL. */
  int pipe_bound;           /* The Unix socket file is ours (bound by this process). */
  uv_signal_t sigint, sigterm;
  uv_idle_t stopper;     /* Runs the shutdown once the current callbacks are done. */
  uv_timer_t stop_timer; /* Closes connections that never drain during a shutdown. */
  conn_t *conns;
  unsigned nconns;
  uint64_t next_conn_id;
  scene_entry_t *scenes;
  worker_t *worker;
  char platform[256], device[256];
  uint64_t next_sub_id;
  seq_job_t *jobs; /* Background jobs, running and recently ended, newest first (jobs.h). */
  uint64_t next_job_id;
  unsigned nsubs;
  unsigned nunauth;    /* Connections that have not authenticated yet (token servers). */
  size_t output_total; /* Unsent output, answers promised and subscription frames, all
                          connections (budget.output_total_bytes); output.c's alone. */
  const conn_hooks_t *conn_hooks[CONN_HOOKS_MAX]; /* Run by net.c (conn_hooks_add). */
  unsigned nconn_hooks;
  stats_t stats;
  int stopping;
};

/* Render requests of one connection that may wait in the shared render queue at once; its
 * further requests wait unread, so one client's pipeline leaves room for the others. */
#define CONN_RENDERS_MAX 16

/* net.c */
int net_listen(server_t *s);
/* Adds a feature's hooks, run for every connection from now on (at start-up, before
 * net_listen). Returns 0, or -1 (logged) when CONN_HOOKS_MAX tables are held. */
int conn_hooks_add(server_t *s, const conn_hooks_t *h);
/* A new connection over 'transport' (its state 'ctx'), counted against the connection and
 * authentication limits: refused ones get a -32003 error and close. NULL when out of memory. */
conn_t *conn_open(server_t *s, const conn_transport_t *transport, void *ctx);
/* Bytes a transport received ('n' of them): fed to the request reader and dispatched. */
void conn_received(conn_t *c, const char *data, size_t n);
/* A transport's write of 'total' bytes ended ('status' < 0: failed, UV_ECANCELED: dropped). */
void conn_written(conn_t *c, size_t total, int status);
/* Bytes handed to the transport and not yet sent: 0 when the socket is idle. */
size_t conn_queued(const conn_t *c);
/* Queues 'line' (and 'att', if any) for writing; takes ownership of both (free()). */
void conn_write(conn_t *c, char *line, size_t len, unsigned char *att, size_t att_len);
/* Closes a connection at once, dropping unwritten output. */
void conn_close(conn_t *c);
/* Stops reading and closes the connection once every reply is written. */
void conn_finish(conn_t *c);
/* Runs what the connection waits to run (lines, the rest of a batch) if it is no longer full. */
void conn_resume(conn_t *c);
/* Marks the connection authenticated: the idle timeout counts from now. */
void conn_authenticated(conn_t *c);
/* Answers the auth call 'call' with a wrong-token error after a short delay; closes the
 * connection after budget.auth_failures of them. */
void conn_auth_failed(call_t *call);
/* Writes every reply at the head of the queue that is complete. */
void conn_flush_replies(conn_t *c);
void conn_unref(conn_t *c);
/* Stops dispatching the connection's requests until a matching conn_release. */
void conn_hold(conn_t *c);
/* Ends a hold; the last one resumes the requests that waited, in order. */
void conn_release(conn_t *c);
/* Stops accepting and reading; closes every connection once its replies are written. */
void net_stop(server_t *s);

/* output.c: the back-pressure counters. */
/* Adds 'delta' (negative to take back) to the server's output total; a drop below the budget
 * lets the connections it paused go on. */
void output_total_add(server_t *s, long long delta);
/* Whether 'bytes' more keep the server's output total within budget.output_total_bytes. */
int output_total_fits(const server_t *s, size_t bytes);
/* The server's output total: unsent output, answers promised, subscription frames. */
size_t output_total(const server_t *s);
/* The unsent output of every connection together. */
size_t output_queued_bytes(const server_t *s);
/* Whether the connection may not run a further request now: its output or its renders are
 * at their limits, or the server's output budget is spent and the connection has output
 * pending. */
int conn_full(const conn_t *c);
/* 'bytes' were handed to libuv for the connection: counted in its output and the total. */
void conn_output_queued(conn_t *c, size_t bytes);
/* 'bytes' of the connection's output were written (or dropped): they leave its count; the
 * caller takes them from the total (output_total_add) once it has reacted to the write. */
void conn_output_written(conn_t *c, size_t bytes);
/* Counts 'bytes' that the work of 'call' will write towards its connection's output, so that
 * no further request is read while the output written and promised passes the limit. */
void conn_promise(call_t *call, size_t bytes);
/* The reply 'r' of 'c' is written or dropped: what its work promised leaves the counts. */
void conn_promise_settle(conn_t *c, reply_t *r);
/* A render request of 'c' entered the shared render queue. */
void conn_render_queued(conn_t *c);
/* A render request of 'c' left the render queue: the connection goes on if it waited for that. */
void conn_render_done(conn_t *c);

/* dispatch.c */
/* Handles one complete request line from 'c'. */
void dispatch_line(conn_t *c, char *line, size_t len);
/* Dispatches the rest of a batch that a hold stopped part-way, until done or held again. */
void dispatch_resume(conn_t *c);
/* Holds the call's connection (conn_hold) until the call is answered: for a call answered later,
 * from a job, whose effect the connection's next requests must see (a sim.step's steps, the
 * density of cloud.set_cells). Call it only once the answer is sure to come later: a hold ended
 * inside the handler would dispatch the next requests from within it. */
void call_hold(call_t *call);
/* Finishes 'call' with 'result' (taken). */
void call_result(call_t *call, cJSON *result);
/* Finishes 'call' with 'result' (taken) and binary data (taken), as an attachment or, when
 * 'base64' is set, as result.data. Adds result.attachment. */
void call_result_bytes(call_t *call, cJSON *result, unsigned char *bytes, size_t n,
                       const char *format, uint32_t width, uint32_t height, int base64);
/* Answers of this many bytes or more are made and encoded off the loop thread. */
#define CALL_BYTES_OFF_LOOP (256 * 1024)
/* Builds the bytes of a result's attachment: returns them (malloc'd) with their count in '*n',
 * or NULL when out of memory. */
typedef unsigned char *(*call_bytes_fn)(void *ctx, size_t *n);
/* Finishes 'call' as call_result_bytes does, with the bytes make(ctx) returns. When about
 * 'size' bytes or more are expected (CALL_BYTES_OFF_LOOP), make, the base64 encoding and the
 * printing of the response run on libuv's thread pool, and the call is finished afterwards
 * (its reply keeps its place); else all of it runs at once. drop(ctx) (may be NULL) runs on the
 * loop thread when make is done with. */
void call_result_made(call_t *call, cJSON *result, call_bytes_fn make, void (*drop)(void *),
                      void *ctx, size_t size, const char *format, int base64);
/* Finishes 'call' with an error; 'path' may be NULL. The message is printf-formatted. */
void call_error(call_t *call, int code, const char *path, const char *fmt, ...)
    __attribute__((format(printf, 4, 5)));

/* server.c: the scene registry and the life cycle. */
scene_entry_t *server_find_scene(server_t *s, const char *name);
/* Adds a scene; 'preset' as in scene.create. Returns NULL with 'err' set. */
scene_entry_t *server_add_scene(server_t *s, const char *name, const char *preset,
                                scene_error_t *err);
void server_remove_scene(server_t *s, scene_entry_t *e);
/* Loads a preset by name (presets_dir/NAME.json); only the operator's --scene (s->cfg.scene
 * itself) may be a file path. NULL with 'err' set. */
cJSON *server_load_preset(server_t *s, const char *name, scene_error_t *err);
/* Adds the connection hooks of every feature that hangs state off connections (subscriptions,
 * jobs); called once at start-up, before net_listen. */
void server_features_register(server_t *s);
/* Starts the graceful stop from any loop callback. */
void server_request_stop(server_t *s);
/* Monotonic nanoseconds. */
uint64_t now_ns(void);

#endif
