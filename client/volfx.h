/*
 * libvolfx: a small blocking client for volfxd. It opens one connection (TCP or a Unix
 * socket), sends JSON-RPC 2.0 requests one at a time and waits for each response, reading the
 * raw attachment bytes that follow a response line. Notifications ("frames", "job.progress")
 * that arrive while a response is awaited are kept in a bounded queue and handed out later by
 * volfx_next_notification() and volfx_next_frame(). The wire contract is docs/protocol.md.
 *
 * A connection is not thread-safe: use it from one thread at a time. Functions return 0 on
 * success, a JSON-RPC error code (-32700 ... -32000) when the server answered with an error, or
 * one of the small negative VOLFX_E_* transport codes below.
 */
#ifndef VOLFX_H
#define VOLFX_H

#include <stddef.h>
#include <stdint.h>

#include <cjson/cJSON.h>

#define VOLFX_DEFAULT_HOST "127.0.0.1"
#define VOLFX_DEFAULT_PORT 7878

/* Transport and usage errors. JSON-RPC codes are all below -32000, so these never collide. */
#define VOLFX_ERRNO_MAP(XX)                                                                        \
  XX(INVAL, -1, "invalid argument")                                                                \
  XX(NOMEM, -2, "out of memory")                                                                   \
  XX(CONNECT, -3, "cannot connect")                                                                \
  XX(IO, -4, "i/o error")                                                                          \
  XX(CLOSED, -5, "connection closed by the server")                                                \
  XX(TIMEOUT, -6, "timed out")                                                                     \
  XX(PROTOCOL, -7, "malformed message from the server")                                            \
  XX(INTR, -8, "interrupted")

typedef enum {
#define XX(name, code, msg) VOLFX_E_##name = code,
  VOLFX_ERRNO_MAP(XX)
#undef XX
} volfx_errno_t;

/* An open connection; created by volfx_connect_tcp()/volfx_connect_unix(). */
typedef struct volfx_conn volfx_conn_t;

/*
 * Binary data that came with a result or a notification. 'data' is NULL and 'len' 0 when
 * there was none. The caller owns 'data' and releases it with volfx_attachment_free().
 */
typedef struct volfx_attachment {
  unsigned char *data; /* The bytes, malloc'd; NULL when empty. */
  size_t len;          /* Number of bytes in 'data'. */
  char format[16];     /* "png", "rgba8", "rgbaf32", "f32", "u8"; "" when absent. */
  int width;           /* attachment.width, or 0 when absent. */
  int height;          /* attachment.height, or 0 when absent. */
} volfx_attachment_t;

/*
 * The error a call ended with. For a server error 'code' is the JSON-RPC code, 'message' the
 * server's message and 'path' its data.path ("" when absent); for a transport error 'code' is
 * a VOLFX_E_* value and 'message' describes it. Truncated to fit, always NUL-terminated.
 */
typedef struct volfx_error {
  int code;
  char message[512];
  char path[256];
} volfx_error_t;

/*
 * Connects to 'host' (NULL means VOLFX_DEFAULT_HOST; names are resolved) on 'port' (0 means
 * VOLFX_DEFAULT_PORT). 'timeout_ms' bounds the connect and becomes the connection's I/O
 * timeout (volfx_set_timeout); 0 or less means no timeout. On success '*out' is a new
 * connection owned by the caller, to be released with volfx_close(). Returns 0 or a VOLFX_E_*
 * code; 'err' (may be NULL) receives a description.
 */
int volfx_connect_tcp(volfx_conn_t **out, const char *host, int port, int timeout_ms,
                      volfx_error_t *err);

/* Like volfx_connect_tcp() for the Unix socket at 'path'. */
int volfx_connect_unix(volfx_conn_t **out, const char *path, int timeout_ms, volfx_error_t *err);

/*
 * Sets the time one volfx_call() may take in all, sending and receiving; 0 or less waits
 * forever. A call that times out leaves the connection unusable, since a late response would
 * be taken for the next one: close it.
 */
void volfx_set_timeout(volfx_conn_t *conn, int timeout_ms);

/*
 * Sends one request and waits for its response.
 * - 'method': the method name, e.g. "scene.get".
 * - 'params': an object or array, or NULL for none. It is taken: freed by this call whatever
 *   it returns.
 * - 'result' (may be NULL): on success '*result' is the "result" member, owned by the caller
 *   (cJSON_Delete). When the result carried an attachment whose bytes came inline as base64,
 *   the "data" member is removed from it after decoding into 'att'. Set to NULL on failure.
 * - 'att' (may be NULL): receives the attachment, owned by the caller; emptied first. With
 *   'att' NULL any attachment is read off the socket and dropped.
 * - 'err' (may be NULL): filled in when the return value is not 0.
 * Notifications that arrive before the response are queued for volfx_next_notification().
 * Returns 0, the server's JSON-RPC error code, or a VOLFX_E_* transport code.
 */
int volfx_call(volfx_conn_t *conn, const char *method, cJSON *params, cJSON **result,
               volfx_attachment_t *att, volfx_error_t *err);

/* Sends "auth" with 'token'. Returns 0, -32001 for a wrong token, or another code as volfx_call. */
int volfx_auth(volfx_conn_t *conn, const char *token, volfx_error_t *err);

/*
 * Calls "frames.subscribe" with 'params' (taken, may be NULL for all defaults) and stores the
 * subscription id in '*id'. Frames then arrive through volfx_next_frame(). Returns as
 * volfx_call.
 */
int volfx_subscribe(volfx_conn_t *conn, cJSON *params, int64_t *id, volfx_error_t *err);

/*
 * Calls "frames.unsubscribe" for 'id'. '*result' (when 'result' is not NULL) receives
 * {"id", "sent", "dropped"}, owned by the caller. Frames of that subscription still queued
 * are discarded. Returns as volfx_call.
 */
int volfx_unsubscribe(volfx_conn_t *conn, int64_t id, cJSON **result, volfx_error_t *err);

/*
 * Waits up to 'timeout_ms' (negative: forever, 0: only what is already buffered) for the next
 * notification whose method is 'method' (NULL: any method); notifications of other methods
 * stay queued. '*msg' receives the whole notification object ({"jsonrpc", "method",
 * "params"}), owned by the caller; 'att' (may be NULL) its attachment. Returns 0,
 * VOLFX_E_TIMEOUT, VOLFX_E_INTR when a signal interrupted the wait, or a transport code.
 */
int volfx_next_notification(volfx_conn_t *conn, const char *method, int timeout_ms, cJSON **msg,
                            volfx_attachment_t *att);

/*
 * volfx_next_notification() for "frames": '*params' receives the notification's params
 * ({"id", "frame", "time", "work_ms", "dropped", ...}), owned by the caller, and 'att' the
 * frame. Returns as volfx_next_notification().
 */
int volfx_next_frame(volfx_conn_t *conn, int timeout_ms, cJSON **params, volfx_attachment_t *att);

/* Notifications dropped from the full local queue so far (the oldest go first). */
uint64_t volfx_queue_dropped(const volfx_conn_t *conn);

/*
 * Frames replaced in the local queue so far. The queue keeps the server's latest-wins: it holds
 * at most one unread frame per subscription, and a newer frame of the same subscription
 * replaces it (moving to the back of the queue), however long a call kept the caller away.
 */
uint64_t volfx_frames_replaced(const volfx_conn_t *conn);

/* Closes the socket and frees 'conn' with everything queued. NULL is allowed. */
void volfx_close(volfx_conn_t *conn);

/* Frees the bytes of 'att' and empties it. NULL is allowed. */
void volfx_attachment_free(volfx_attachment_t *att);

/* The description of a VOLFX_E_* or JSON-RPC code; "unknown error" otherwise. */
const char *volfx_strerror(int code);

/*
 * Every method volfxd has, by name (libvolfx_methods.c). volfx_call() calls any of them with
 * a cJSON params object; the typed wrappers below cover the ones a game loop uses. A param
 * left out (NULL, or absent from 'params') is not sent, so the server's method table gives it
 * its default (docs/protocol.md's method reference).
 */
#define VOLFX_METHOD_MAP(XX)                                                                       \
  XX(SERVER_INFO, "server.info")                                                                   \
  XX(RPC_DISCOVER, "rpc.discover")                                                                 \
  XX(AUTH, "auth")                                                                                 \
  XX(SCENE_LIST, "scene.list")                                                                     \
  XX(SCENE_PRESETS, "scene.presets")                                                               \
  XX(SCENE_CREATE, "scene.create")                                                                 \
  XX(SCENE_DELETE, "scene.delete")                                                                 \
  XX(SCENE_GET, "scene.get")                                                                       \
  XX(SCENE_SET, "scene.set")                                                                       \
  XX(SCENE_SAVE, "scene.save")                                                                     \
  XX(SCENE_LOAD, "scene.load")                                                                     \
  XX(SIM_STEP, "sim.step")                                                                         \
  XX(SIM_PLAY, "sim.play")                                                                         \
  XX(SIM_PAUSE, "sim.pause")                                                                       \
  XX(RENDER, "render")                                                                             \
  XX(FRAMES_SUBSCRIBE, "frames.subscribe")                                                         \
  XX(FRAMES_UPDATE, "frames.update")                                                               \
  XX(FRAMES_UNSUBSCRIBE, "frames.unsubscribe")                                                     \
  XX(RENDER_SEQUENCE, "render.sequence")                                                           \
  XX(SIM_BAKE, "sim.bake")                                                                         \
  XX(JOB_LIST, "job.list")                                                                         \
  XX(JOB_CANCEL, "job.cancel")                                                                     \
  XX(FLUID_SET_PARTICLES, "fluid.set_particles")                                                   \
  XX(FLUID_GET_PARTICLES, "fluid.get_particles")                                                   \
  XX(CLOUD_GET_CELLS, "cloud.get_cells")                                                           \
  XX(CLOUD_SET_CELLS, "cloud.set_cells")                                                           \
  XX(STATS, "stats")                                                                               \
  XX(SERVER_SHUTDOWN, "server.shutdown")

typedef enum {
#define XX(id, name) VOLFX_M_##id,
  VOLFX_METHOD_MAP(XX)
#undef XX
      VOLFX_M_COUNT
} volfx_method_t;

/* The name of method 'm' ("scene.get"), or NULL for a value out of range. */
const char *volfx_method_name(volfx_method_t m);

/* volfx_call() of method 'm'; returns VOLFX_E_INVAL for a value out of range. */
int volfx_call_method(volfx_conn_t *conn, volfx_method_t m, cJSON *params, cJSON **result,
                      volfx_attachment_t *att, volfx_error_t *err);

/*
 * Typed wrappers; each returns as volfx_call(). 'scene' NULL means the server's default scene;
 * a cJSON argument is taken (freed whatever the call returns); '*result', when 'result' is not
 * NULL, receives the result, owned by the caller.
 */
/* server.info. */
int volfx_info(volfx_conn_t *conn, cJSON **result, volfx_error_t *err);
int volfx_scene_create(volfx_conn_t *conn, const char *name, const char *preset,
                       volfx_error_t *err);
int volfx_scene_delete(volfx_conn_t *conn, const char *name, volfx_error_t *err);
/* scene.get of dotted 'path' (NULL: the whole document). */
int volfx_scene_get(volfx_conn_t *conn, const char *scene, const char *path, cJSON **result,
                    volfx_error_t *err);
/* scene.set of one 'value' at dotted 'path'; '*version' (may be NULL) gets the new version. */
int volfx_scene_set(volfx_conn_t *conn, const char *scene, const char *path, cJSON *value,
                    int64_t *version, volfx_error_t *err);
/* scene.set of an RFC 7386 merge 'patch', applied atomically. */
int volfx_scene_patch(volfx_conn_t *conn, const char *scene, cJSON *patch, int64_t *version,
                      volfx_error_t *err);
/* sim.step of 'steps' steps (0: the server's default); '*result' gets {time, frame}. */
int volfx_sim_step(volfx_conn_t *conn, const char *scene, int steps, cJSON **result,
                   volfx_error_t *err);
/* sim.play at 'rate' steps per second (0 or less: the server's default). */
int volfx_sim_play(volfx_conn_t *conn, const char *scene, double rate, volfx_error_t *err);
int volfx_sim_pause(volfx_conn_t *conn, const char *scene, volfx_error_t *err);
/* render with 'params' (NULL: all defaults); the frame lands in 'att'. */
int volfx_render(volfx_conn_t *conn, cJSON *params, cJSON **result, volfx_attachment_t *att,
                 volfx_error_t *err);
/*
 * frames.update: changes subscription 'id''s view live (camera, width, height, fps, format,
 * quality, layers in 'view', taken). A server without it answers -32601 (method not found).
 */
int volfx_frames_update(volfx_conn_t *conn, int64_t id, cJSON *view, volfx_error_t *err);
int volfx_stats(volfx_conn_t *conn, cJSON **result, volfx_error_t *err);

/*
 * A private volfxd for a C or C++ test suite (libvolfx_server.c). volfx_server_start() runs
 * volfxd on 127.0.0.1 port 0 with a temporary --data directory and a token, its stdout and
 * stderr in a log file, and waits on --ready-fd until it listens. volfxd runs in its own
 * process group and dies with the process that started it (PR_SET_PDEATHSIG), so a test that
 * crashes leaves no server behind. volfx_server_stop() stops it with SIGTERM (SIGKILL after
 * the stop timeout), removes its files and frees the handle.
 */
typedef struct volfx_server volfx_server_t;

typedef struct volfx_server_opts {
  const char *volfxd;      /* The executable; NULL: $VOLFX_VOLFXD, else "volfxd" on PATH. */
  const char *const *args; /* More volfxd options, NULL-terminated; NULL for none. */
  const char *token;       /* NULL: a random one. */
  int start_timeout_ms;    /* How long to wait for readiness; 0 or less: 120000. */
  int stop_timeout_ms;     /* How long SIGTERM may take before SIGKILL; 0 or less: 30000. */
} volfx_server_opts_t;

/*
 * Starts volfxd as 'opts' (NULL: all defaults) says and waits until it listens. On success
 * '*out' is the running server, owned by the caller until volfx_server_stop(). Returns 0,
 * VOLFX_E_INVAL for bad options, VOLFX_E_IO when it cannot be started, VOLFX_E_CLOSED when it
 * exited before it was ready, VOLFX_E_PROTOCOL for a ready line it cannot read, or
 * VOLFX_E_TIMEOUT; 'err' then says why, quoting the log's last error line.
 */
int volfx_server_start(volfx_server_t **out, const volfx_server_opts_t *opts, volfx_error_t *err);

/* Where it listens, its token, data directory, log file and process id; valid until stop. */
int volfx_server_port(const volfx_server_t *srv);
const char *volfx_server_host(const volfx_server_t *srv);
const char *volfx_server_token(const volfx_server_t *srv);
const char *volfx_server_data_dir(const volfx_server_t *srv);
const char *volfx_server_log_path(const volfx_server_t *srv);
int volfx_server_pid(const volfx_server_t *srv);

/* Connects to 'srv' and authenticates with its token; returns as volfx_connect_tcp(). */
int volfx_server_connect(volfx_server_t *srv, volfx_conn_t **out, int timeout_ms,
                         volfx_error_t *err);

/*
 * Stops 'srv' (NULL is allowed), removes its temporary files unless 'keep_files', and frees
 * it. '*exit_status' (may be NULL) receives volfxd's exit status, or 128 + the signal that
 * ended it. Returns 0 when volfxd exited with status 0, VOLFX_E_TIMEOUT when it had to be
 * killed, VOLFX_E_IO when it ended otherwise ('err' says how).
 */
int volfx_server_stop(volfx_server_t *srv, int keep_files, int *exit_status, volfx_error_t *err);

#endif
