/*
 * game_loop: the smallest game client of volfxd. It connects (to --port, or to a private
 * volfxd it starts with volfx_server_start when no port is given), subscribes to frames,
 * moves the camera around the scene every few frames with frames.update, draws nothing, and
 * prints the frames it got per second at the end. ctest runs it for a second or two.
 *
 *   game_loop [--port P] [--host H] [--token T] [--volfxd PATH] [--seconds S] [--every N]
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "volfx.h"

typedef struct options {
  const char *host;
  const char *token;
  const char *volfxd;
  int port;
  double seconds; /* How long the loop runs. */
  int every;      /* Frames between camera moves. */
} options_t;

static double now_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

static int usage(const char *why) {
  fprintf(stderr,
          "game_loop: %s\nusage: game_loop [--port P] [--host H] [--token T] [--volfxd PATH] "
          "[--seconds S] [--every N]\n",
          why);
  return 2;
}

static int options_parse(options_t *o, int argc, char **argv) {
  for (int i = 1; i < argc; i++) {
    const char *a = argv[i];
    if (i + 1 >= argc) {
      return usage("an option without its value, or an unknown argument");
    }
    const char *v = argv[++i];
    if (strcmp(a, "--port") == 0) {
      o->port = atoi(v);
    } else if (strcmp(a, "--host") == 0) {
      o->host = v;
    } else if (strcmp(a, "--token") == 0) {
      o->token = v;
    } else if (strcmp(a, "--volfxd") == 0) {
      o->volfxd = v;
    } else if (strcmp(a, "--seconds") == 0) {
      o->seconds = atof(v);
    } else if (strcmp(a, "--every") == 0) {
      o->every = atoi(v);
    } else {
      return usage("unknown option");
    }
  }
  if (o->seconds <= 0 || o->every < 1 || o->port < 0) {
    return usage("--seconds must be positive, --every at least 1, --port not negative");
  }
  return 0;
}

/* The view the game asks for: a small frame, and the camera at 'angle' around the scene. */
static cJSON *view_new(double angle, int with_size) {
  cJSON *view = cJSON_CreateObject();
  cJSON *camera = cJSON_AddObjectToObject(view, "camera");
  const double eye[3] = {7.5 * sin(angle), 2.2, 7.5 * cos(angle)};
  cJSON_AddItemToObject(camera, "eye", cJSON_CreateDoubleArray(eye, 3));
  if (with_size) {
    cJSON_AddNumberToObject(view, "width", 160);
    cJSON_AddNumberToObject(view, "height", 90);
    cJSON_AddNumberToObject(view, "fps", 60);
  }
  return view;
}

/* The loop itself: frames for 'o->seconds', a camera move every 'o->every' frames. */
static int game_run(volfx_conn_t *conn, const options_t *o) {
  volfx_error_t err = {0};
  int64_t id = 0;
  /* The effects move while the game runs; a paused, unchanged scene sends no new frames. */
  int rc = volfx_sim_play(conn, NULL, 60, &err);
  if (rc == 0)
    rc = volfx_subscribe(conn, view_new(0, 1), &id, &err);
  if (rc != 0) {
    fprintf(stderr, "game_loop: starting: %s\n", err.message);
    return 1;
  }
  long frames = 0, moves = 0;
  size_t bytes = 0;
  double start = now_s();
  while (now_s() - start < o->seconds) {
    cJSON *params = NULL;
    volfx_attachment_t att = {0};
    rc = volfx_next_frame(conn, 100, &params, &att);
    if (rc == VOLFX_E_TIMEOUT) {
      continue;
    }
    if (rc != 0) {
      fprintf(stderr, "game_loop: waiting for a frame: %s\n", volfx_strerror(rc));
      return 1;
    }
    frames++;
    bytes += att.len; /* A game would draw att.data here. */
    cJSON_Delete(params);
    volfx_attachment_free(&att);
    if (frames % o->every == 0) {
      moves++;
      /* The new view applies from the next frame, on the same subscription, with no gap. */
      rc = volfx_frames_update(conn, id, view_new(0.1 * (double)moves, 0), &err);
      if (rc != 0) {
        fprintf(stderr, "game_loop: moving the camera: %s\n", err.message);
        return 1;
      }
    }
  }
  double elapsed = now_s() - start;
  cJSON *done = NULL;
  volfx_unsubscribe(conn, id, &done, NULL);
  cJSON_Delete(done);
  printf("game_loop: %ld frames in %.2f s: %.1f fps, %zu bytes, %ld camera moves, %llu "
         "frames replaced while the game was away\n",
         frames, elapsed, frames / elapsed, bytes, moves,
         (unsigned long long)volfx_frames_replaced(conn));
  return frames > 0 ? 0 : 1;
}

int main(int argc, char **argv) {
  options_t o = {.host = NULL, .seconds = 2, .every = 5};
  if (options_parse(&o, argc, argv) != 0) {
    return 2;
  }
  volfx_error_t err = {0};
  volfx_server_t *srv = NULL;
  volfx_conn_t *conn = NULL;
  int rc;
  if (o.port == 0) {
    volfx_server_opts_t so = {.volfxd = o.volfxd};
    rc = volfx_server_start(&srv, &so, &err);
    if (rc == 0) {
      rc = volfx_server_connect(srv, &conn, 30000, &err);
    }
  } else {
    rc = volfx_connect_tcp(&conn, o.host, o.port, 30000, &err);
    if (rc == 0 && o.token != NULL) {
      rc = volfx_auth(conn, o.token, &err);
    }
  }
  int status = 1;
  if (rc != 0) {
    fprintf(stderr, "game_loop: cannot reach volfxd: %s\n", err.message);
  } else {
    status = game_run(conn, &o);
  }
  volfx_close(conn);
  volfx_server_stop(srv, 0, NULL, NULL);
  return status;
}
