/*
 * libvolfx's private volfxd for test suites (volfx_server_* in volfx.h): a temporary directory
 * holding the data directory and the log, a fork that puts volfxd in its own process group with
 * PR_SET_PDEATHSIG before exec, a pipe passed as --ready-fd whose one line gives the port, and
 * a stop that sends SIGTERM, waits, and kills the group if it must.
 */
#include "volfx.h"

#include <errno.h>
#include <fcntl.h>
#include <ftw.h>
#include <limits.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#define MAX_ARGS 64

struct volfx_server {
  pid_t pid;
  int port;
  int stop_timeout_ms;
  char host[64];
  char token[256];
  char root[PATH_MAX];     /* The temporary directory: data/ and volfxd.log. */
  char data_dir[PATH_MAX]; /* root/data */
  char log_path[PATH_MAX]; /* root/volfxd.log */
};

static int fail(volfx_error_t *err, int code, const char *fmt, const char *arg) {
  if (err != NULL) {
    err->code = code;
    snprintf(err->message, sizeof err->message, fmt, arg);
    err->path[0] = '\0';
  }
  return code;
}

static int64_t clock_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (int64_t)ts.tv_sec * 1000 + ts.tv_nsec / 1000000;
}

/* 'out' receives 32 random hex digits. */
static void random_token(char out[33]) {
  unsigned char b[16] = {0};
  int fd = open("/dev/urandom", O_RDONLY | O_CLOEXEC);
  if (fd < 0 || read(fd, b, sizeof b) != (ssize_t)sizeof b) {
    /* No /dev/urandom: the token guards only a loopback test server. */
    srand((unsigned)(clock_ms() ^ getpid()));
    for (size_t i = 0; i < sizeof b; i++)
      b[i] = (unsigned char)rand();
  }
  if (fd >= 0)
    close(fd);
  for (size_t i = 0; i < sizeof b; i++)
    snprintf(out + 2 * i, 3, "%02x", b[i]);
}

static int remove_one(const char *path, const struct stat *st, int flag, struct FTW *ftw) {
  (void)st, (void)flag, (void)ftw;
  remove(path);
  return 0;
}

static void remove_tree(const char *root) {
  if (root[0])
    nftw(root, remove_one, 16, FTW_DEPTH | FTW_PHYS);
}

/* The log's last error line (else its last line), for an error message. */
static void log_last_line(const volfx_server_t *srv, char *out, size_t cap) {
  out[0] = '\0';
  FILE *f = fopen(srv->log_path, "rb");
  if (!f)
    return;
  char line[1024];
  int had_error = 0;
  while (fgets(line, sizeof line, f)) {
    int is_error = strstr(line, "error") != NULL;
    if (line[0] == '\n' || (had_error && !is_error))
      continue;
    had_error |= is_error;
    size_t n = strcspn(line, "\n");
    n = n < cap ? n : cap - 1;
    memcpy(out, line, n);
    out[n] = '\0';
  }
  fclose(f);
}

/* In the child: its own process group, death with the parent, the log as stdout and stderr,
 * the ready pipe kept open across exec, then volfxd. Never returns. */
static void child_exec(const char *exe, char **argv, int log_fd, int ready_fd, pid_t parent) {
  setpgid(0, 0);
  prctl(PR_SET_PDEATHSIG, SIGKILL);
  if (getppid() != parent)
    _exit(127);
  int devnull = open("/dev/null", O_RDONLY);
  if (devnull >= 0)
    dup2(devnull, 0);
  dup2(log_fd, 1);
  dup2(log_fd, 2);
  fcntl(ready_fd, F_SETFD, 0);
  execvp(exe, argv);
  dprintf(2, "volfx_server_start: cannot run %s: %s\n", exe, strerror(errno));
  _exit(127);
}

/* Waits up to 'timeout_ms' for the child's line on 'fd'; fills 'line'. Returns 0, VOLFX_E_CLOSED
 * on end-of-file first, or VOLFX_E_TIMEOUT. */
static int read_ready(int fd, int timeout_ms, char *line, size_t cap) {
  size_t n = 0;
  int64_t deadline = clock_ms() + timeout_ms;
  while (n == 0 || line[n - 1] != '\n') {
    int64_t left = deadline - clock_ms();
    if (left <= 0)
      return VOLFX_E_TIMEOUT;
    struct pollfd p = {.fd = fd, .events = POLLIN};
    int r = poll(&p, 1, (int)(left > 1000 ? 1000 : left));
    if (r < 0 && errno != EINTR)
      return VOLFX_E_IO;
    if (r <= 0)
      continue;
    ssize_t got = read(fd, line + n, cap - 1 - n);
    if (got < 0 && errno == EINTR)
      continue;
    if (got <= 0)
      return VOLFX_E_CLOSED;
    n += (size_t)got;
    line[n] = '\0';
    if (n == cap - 1)
      break;
  }
  return 0;
}

/* Waits up to 'timeout_ms' for 'pid' to end; 1 with '*status' set, 0 when still running. */
static int wait_exit(pid_t pid, int timeout_ms, int *status) {
  int64_t deadline = clock_ms() + timeout_ms;
  for (;;) {
    pid_t r = waitpid(pid, status, WNOHANG);
    if (r == pid || (r < 0 && errno != EINTR))
      return 1;
    if (clock_ms() >= deadline)
      return 0;
    struct timespec ts = {0, 10 * 1000 * 1000};
    nanosleep(&ts, NULL);
  }
}

static void kill_now(volfx_server_t *srv) {
  if (kill(-srv->pid, SIGKILL) != 0)
    kill(srv->pid, SIGKILL);
  int status;
  waitpid(srv->pid, &status, 0);
}

/* Starts the process of 'srv' and waits for its ready line. */
static int spawn(volfx_server_t *srv, const volfx_server_opts_t *o, volfx_error_t *err) {
  const char *exe = o->volfxd ? o->volfxd : getenv("VOLFX_VOLFXD");
  if (!exe || !exe[0])
    exe = "volfxd";
  int pipefd[2];
  if (pipe2(pipefd, O_CLOEXEC) != 0)
    return fail(err, VOLFX_E_IO, "cannot make the ready pipe: %s", strerror(errno));
  int log_fd = open(srv->log_path, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (log_fd < 0) {
    close(pipefd[0]), close(pipefd[1]);
    return fail(err, VOLFX_E_IO, "cannot create the log file: %s", strerror(errno));
  }
  char fd_text[16];
  snprintf(fd_text, sizeof fd_text, "%d", pipefd[1]);
  char *argv[MAX_ARGS + 12];
  int n = 0;
  argv[n++] = (char *)exe;
  const char *fixed[] = {"--listen", "127.0.0.1:0", "--data",     srv->data_dir,
                         "--token",  srv->token,    "--ready-fd", fd_text};
  for (size_t i = 0; i < sizeof fixed / sizeof fixed[0]; i++)
    argv[n++] = (char *)fixed[i];
  for (int i = 0; o->args && o->args[i]; i++)
    argv[n++] = (char *)o->args[i];
  argv[n] = NULL;

  pid_t parent = getpid();
  srv->pid = fork();
  if (srv->pid == 0)
    child_exec(exe, argv, log_fd, pipefd[1], parent);
  int fork_errno = errno;
  close(log_fd);
  close(pipefd[1]);
  if (srv->pid < 0) {
    close(pipefd[0]);
    return fail(err, VOLFX_E_IO, "cannot fork: %s", strerror(fork_errno));
  }
  char line[256];
  int timeout = o->start_timeout_ms > 0 ? o->start_timeout_ms : 120000;
  int rc = read_ready(pipefd[0], timeout, line, sizeof line);
  close(pipefd[0]);
  char last[400];
  if (rc != 0) {
    kill_now(srv);
    log_last_line(srv, last, sizeof last);
    return fail(err, rc,
                rc == VOLFX_E_TIMEOUT ? "volfxd was not ready in time; its log says: %s"
                                      : "volfxd exited before it was ready; its log says: %s",
                last);
  }
  if (sscanf(line, "ready %d %63s", &srv->port, srv->host) != 2 || srv->port <= 0) {
    kill_now(srv);
    line[strcspn(line, "\n")] = '\0';
    return fail(err, VOLFX_E_PROTOCOL, "volfxd's ready line is not 'ready PORT HOST': %s", line);
  }
  return 0;
}

int volfx_server_start(volfx_server_t **out, const volfx_server_opts_t *opts, volfx_error_t *err) {
  static const volfx_server_opts_t defaults = {0};
  const volfx_server_opts_t *o = opts ? opts : &defaults;
  if (out == NULL)
    return fail(err, VOLFX_E_INVAL, "%s", "volfx_server_start: 'out' is NULL");
  *out = NULL;
  int nargs = 0;
  while (o->args && o->args[nargs])
    nargs++;
  if (nargs > MAX_ARGS)
    return fail(err, VOLFX_E_INVAL, "volfx_server_start: more than %s extra arguments", "64");
  if (o->token && (!o->token[0] || strlen(o->token) >= 256))
    return fail(err, VOLFX_E_INVAL, "%s", "volfx_server_start: the token must be 1-255 bytes");
  volfx_server_t *srv = calloc(1, sizeof *srv);
  if (!srv)
    return fail(err, VOLFX_E_NOMEM, "%s", "out of memory");
  srv->stop_timeout_ms = o->stop_timeout_ms > 0 ? o->stop_timeout_ms : 30000;
  if (o->token)
    snprintf(srv->token, sizeof srv->token, "%s", o->token);
  else
    random_token(srv->token);
  const char *tmp = getenv("TMPDIR");
  snprintf(srv->root, sizeof srv->root, "%s/volfx-test-XXXXXX", tmp && tmp[0] ? tmp : "/tmp");
  if (!mkdtemp(srv->root)) {
    int e = errno;
    free(srv);
    return fail(err, VOLFX_E_IO, "cannot make a temporary directory: %s", strerror(e));
  }
  snprintf(srv->data_dir, sizeof srv->data_dir, "%.*s/data", PATH_MAX - 16, srv->root);
  snprintf(srv->log_path, sizeof srv->log_path, "%.*s/volfxd.log", PATH_MAX - 16, srv->root);
  int rc = mkdir(srv->data_dir, 0700) == 0
               ? spawn(srv, o, err)
               : fail(err, VOLFX_E_IO, "cannot make the data directory: %s", strerror(errno));
  if (rc != 0) {
    remove_tree(srv->root);
    free(srv);
    return rc;
  }
  *out = srv;
  return 0;
}

int volfx_server_port(const volfx_server_t *srv) {
  return srv->port;
}
const char *volfx_server_host(const volfx_server_t *srv) {
  return srv->host;
}
const char *volfx_server_token(const volfx_server_t *srv) {
  return srv->token;
}
const char *volfx_server_data_dir(const volfx_server_t *srv) {
  return srv->data_dir;
}
const char *volfx_server_log_path(const volfx_server_t *srv) {
  return srv->log_path;
}
int volfx_server_pid(const volfx_server_t *srv) {
  return (int)srv->pid;
}

int volfx_server_connect(volfx_server_t *srv, volfx_conn_t **out, int timeout_ms,
                         volfx_error_t *err) {
  int rc = volfx_connect_tcp(out, srv->host, srv->port, timeout_ms, err);
  if (rc == 0 && (rc = volfx_auth(*out, srv->token, err)) != 0) {
    volfx_close(*out);
    *out = NULL;
  }
  return rc;
}

int volfx_server_stop(volfx_server_t *srv, int keep_files, int *exit_status, volfx_error_t *err) {
  if (srv == NULL)
    return 0;
  int status = 0, rc = 0;
  kill(srv->pid, SIGTERM);
  if (!wait_exit(srv->pid, srv->stop_timeout_ms, &status)) {
    kill_now(srv);
    status = 128 + SIGKILL;
    rc = fail(err, VOLFX_E_TIMEOUT, "%s", "volfxd did not stop after SIGTERM; killed");
  } else if (WIFSIGNALED(status)) {
    int sig = WTERMSIG(status);
    status = 128 + sig;
    rc = fail(err, VOLFX_E_IO, "volfxd was killed by signal %s", strsignal(sig));
  } else {
    status = WEXITSTATUS(status);
    char text[16];
    snprintf(text, sizeof text, "%d", status);
    if (status != 0)
      rc = fail(err, VOLFX_E_IO, "volfxd exited with status %s", text);
  }
  if (exit_status)
    *exit_status = status;
  if (!keep_files)
    remove_tree(srv->root);
  free(srv);
  return rc;
}
