/*
 * libvolfx's private volfxd for C test suites (volfx_server_* in client/volfx.h): started on a
 * free port with a token and a temporary data directory, ready through --ready-fd, served over
 * volfx_server_connect, stopped cleanly with its files removed; a start that fails names the
 * cause from the log; a crash is reported at the stop; and a test process that dies takes its
 * volfxd with it. VOLFXD_PATH is the volfxd built beside this test.
 */
#include <errno.h>
#include <ftw.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "check.h"
#include "volfx.h"

static int exists(const char *path) {
  struct stat st;
  return stat(path, &st) == 0;
}

/* 1 while 'pid' runs (a zombie counts as ended). */
static int running(pid_t pid) {
  char path[64], state = 0;
  snprintf(path, sizeof path, "/proc/%d/stat", (int)pid);
  FILE *f = fopen(path, "r");
  if (!f)
    return 0;
  int ok = fscanf(f, "%*d (%*[^)]) %c", &state) == 1;
  fclose(f);
  return ok && state != 'Z';
}

static int wait_gone(pid_t pid, int ms) {
  for (int i = 0; i < ms / 10 && running(pid); i++) {
    struct timespec ts = {0, 10 * 1000 * 1000};
    nanosleep(&ts, NULL);
  }
  return !running(pid);
}

static void start_serve_stop(void) {
  volfx_server_opts_t o = {.volfxd = VOLFXD_PATH};
  volfx_server_t *srv = NULL;
  volfx_error_t err = {0};
  int rc = volfx_server_start(&srv, &o, &err);
  CHECK(rc == 0, "start: %d %s", rc, err.message);
  if (rc != 0)
    return;
  CHECK(volfx_server_port(srv) > 0 && volfx_server_port(srv) != VOLFX_DEFAULT_PORT, "port %d",
        volfx_server_port(srv));
  CHECK(strcmp(volfx_server_host(srv), "127.0.0.1") == 0, "host %s", volfx_server_host(srv));
  CHECK(strlen(volfx_server_token(srv)) == 32, "a random token: %s", volfx_server_token(srv));
  CHECK(exists(volfx_server_data_dir(srv)), "data directory %s", volfx_server_data_dir(srv));

  volfx_conn_t *c = NULL;
  rc = volfx_server_connect(srv, &c, 30000, &err);
  CHECK(rc == 0, "connect: %s", err.message);
  cJSON *info = NULL;
  if (c)
    rc = volfx_call(c, "server.info", NULL, &info, NULL, &err);
  const cJSON *name = cJSON_GetObjectItemCaseSensitive(info, "name");
  CHECK(rc == 0 && cJSON_IsString(name) && strcmp(name->valuestring, "volfxd") == 0,
        "server.info: %d %s", rc, err.message);
  cJSON_Delete(info);
  volfx_close(c);

  volfx_conn_t *anon = NULL;
  rc = volfx_connect_tcp(&anon, volfx_server_host(srv), volfx_server_port(srv), 30000, &err);
  if (rc == 0)
    rc = volfx_call(anon, "server.info", NULL, NULL, NULL, &err);
  CHECK(rc == -32001, "a connection without the token is refused: %d", rc);
  volfx_close(anon);

  char root[4096];
  snprintf(root, sizeof root, "%s", volfx_server_data_dir(srv));
  *strrchr(root, '/') = '\0';
  pid_t pid = volfx_server_pid(srv);
  int status = -1;
  rc = volfx_server_stop(srv, 0, &status, &err);
  CHECK(rc == 0 && status == 0, "a clean stop: %d, status %d: %s", rc, status, err.message);
  CHECK(!running(pid), "volfxd %d has ended", (int)pid);
  CHECK(!exists(root), "its temporary files are removed: %s", root);
}

static void failures_are_named(void) {
  const char *args[] = {"--scene", "no-such-preset", NULL};
  volfx_server_opts_t o = {.volfxd = VOLFXD_PATH, .args = args};
  volfx_server_t *srv = NULL;
  volfx_error_t err = {0};
  int rc = volfx_server_start(&srv, &o, &err);
  CHECK(rc == VOLFX_E_CLOSED && srv == NULL, "a start that fails: %d", rc);
  CHECK(strstr(err.message, "no-such-preset") != NULL, "the error quotes the log: %s", err.message);
  o = (volfx_server_opts_t){.volfxd = "/nonexistent/volfxd"};
  rc = volfx_server_start(&srv, &o, &err);
  CHECK(rc == VOLFX_E_CLOSED && strstr(err.message, "/nonexistent/volfxd"),
        "a missing executable: %d %s", rc, err.message);
  o = (volfx_server_opts_t){.volfxd = VOLFXD_PATH, .token = ""};
  CHECK(volfx_server_start(&srv, &o, &err) == VOLFX_E_INVAL, "an empty token is refused");
  CHECK(volfx_server_start(NULL, &o, &err) == VOLFX_E_INVAL, "a NULL 'out' is refused");
  CHECK(volfx_server_stop(NULL, 0, NULL, NULL) == 0, "stopping NULL does nothing");

  /* A crash shows at the stop. */
  o = (volfx_server_opts_t){.volfxd = VOLFXD_PATH};
  rc = volfx_server_start(&srv, &o, &err);
  CHECK(rc == 0, "start: %s", err.message);
  if (rc == 0) {
    kill(volfx_server_pid(srv), SIGKILL);
    int status = 0;
    rc = volfx_server_stop(srv, 0, &status, &err);
    CHECK(rc == VOLFX_E_IO && status == 128 + SIGKILL && strstr(err.message, "signal"),
          "a crash is reported: %d, status %d, %s", rc, status, err.message);
  }
}

/* A test process that dies without stopping its server (abort, SIGKILL) takes it along. */
static void no_server_outlives_its_test(void) {
  int fds[2];
  CHECK(pipe(fds) == 0, "pipe");
  pid_t test = fork();
  if (test == 0) {
    close(fds[0]);
    volfx_server_opts_t o = {.volfxd = VOLFXD_PATH};
    volfx_server_t *srv = NULL;
    int pid = volfx_server_start(&srv, &o, NULL) == 0 ? volfx_server_pid(srv) : -1;
    if (write(fds[1], &pid, sizeof pid) != (ssize_t)sizeof pid)
      _exit(1);
    raise(SIGKILL);
  }
  close(fds[1]);
  int pid = -1;
  CHECK(read(fds[0], &pid, sizeof pid) == (ssize_t)sizeof pid && pid > 0, "the test's server");
  close(fds[0]);
  waitpid(test, NULL, 0);
  if (pid > 0)
    CHECK(wait_gone(pid, 30000), "volfxd %d outlived the test process that started it", pid);
}

static int remove_one(const char *path, const struct stat *st, int flag, struct FTW *ftw) {
  (void)st, (void)flag, (void)ftw;
  return remove(path);
}

int main(void) {
  /* One fresh kernel cache for the servers of this test. */
  char cache[] = "/tmp/volfx-pocl-XXXXXX";
  int own_cache = !getenv("POCL_CACHE_DIR") && mkdtemp(cache);
  if (own_cache)
    setenv("POCL_CACHE_DIR", cache, 1);
  start_serve_stop();
  failures_are_named();
  no_server_outlives_its_test();
  if (own_cache)
    nftw(cache, remove_one, 16, FTW_DEPTH | FTW_PHYS);
  printf("test_volfx_server: %d checks, %d failed\n", checks, failures);
  return failures != 0;
}
