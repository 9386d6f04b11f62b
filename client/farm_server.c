/*
 * The private volfxd of the render-farm commands (farm.h): started with a random token in its
 * environment on a loopback port of the kernel's choosing, found through its "volfxd listening
 * on HOST:PORT" line, and always stopped: server.shutdown, then SIGTERM, then SIGKILL when it
 * lingers. SIGINT and SIGTERM to the CLI are forwarded to it at once, so a long render or bake
 * ends too; it runs in a process group of its own, so a Ctrl-C at the terminal reaches the CLI
 * only, and it gets SIGTERM when the CLI dies, even of SIGKILL.
 */
#include <errno.h>
#include <fcntl.h>
#include <poll.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "farm.h"
#include "proto.h"

#define START_TIMEOUT_MS 300000 /* Wait for the listening line (kernels may compile). */
#define STOP_GRACE_MS 5000      /* Wait for an exit after server.shutdown or SIGTERM. */

volatile sig_atomic_t farm_stop_signal;
static volatile sig_atomic_t child_pid; /* The private volfxd while it may be signalled. */

/* Prints "volfx CMD: [frame N: ]MESSAGE" to stderr and returns 'status'. */
int farm_say(const farm_t *f, int status, const char *fmt, ...) {
  va_list ap;
  fprintf(stderr, "volfx %s: %s", f->cmd, f->where);
  va_start(ap, fmt);
  vfprintf(stderr, fmt, ap);
  va_end(ap);
  fputc('\n', stderr);
  return status;
}

/* Formats a message into 'buf', cut to 'cap' bytes when longer. */
void farm_text(char *buf, size_t cap, const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(buf, cap, fmt, ap);
  va_end(ap);
}

/* "SIGINT" or "SIGTERM": the signals that stop a run. */
const char *farm_signal_name(int sig) {
  return sig == SIGINT ? "SIGINT" : "SIGTERM";
}

static void on_stop(int sig) {
  farm_stop_signal = sig;
  if (child_pid > 0) {
    kill((pid_t)child_pid, SIGTERM);
  }
}

void farm_catch_signals(void) {
  struct sigaction sa;
  memset(&sa, 0, sizeof(sa));
  sa.sa_handler = on_stop;
  sigemptyset(&sa.sa_mask);
  sa.sa_flags = SA_RESTART;
  sigaction(SIGINT, &sa, NULL);
  sigaction(SIGTERM, &sa, NULL);
}

/* A params object naming the main scene, the only one the private server uses. */
cJSON *farm_main_params(void) {
  cJSON *p = cJSON_CreateObject();
  cJSON_AddStringToObject(p, "scene", PROTO_DEFAULT_SCENE);
  return p;
}

/*
 * One call to the private server. On failure 'f->why' receives "METHOD: MESSAGE (path P)",
 * with the kind of a JSON-RPC error before a message that does not name it. 'params' is taken.
 * Returns 0 or the call's code.
 */
int farm_call(farm_t *f, const char *method, cJSON *params, cJSON **result,
              volfx_attachment_t *att) {
  volfx_error_t e;
  int rc = volfx_call(f->conn, method, params, result, att, &e);
  if (rc == 0) {
    return 0;
  }
  const char *kind = proto_err_message(rc);
  int named = rc > -32000 || strncmp(e.message, kind, strlen(kind)) == 0;
  snprintf(f->why, sizeof(f->why), "%s: %s%s%s%s%s%s", method, named ? "" : kind, named ? "" : ": ",
           e.message[0] != '\0' ? e.message : volfx_strerror(rc),
           e.path[0] != '\0' ? " (path " : "", e.path, e.path[0] != '\0' ? ")" : "");
  if (farm_stop_signal != 0) {
    snprintf(f->why, sizeof(f->why), "interrupted by %s", farm_signal_name(farm_stop_signal));
  }
  return rc;
}

/* The number member 'name' of 'o', or 'dflt'. */
double farm_num(const cJSON *o, const char *name, double dflt) {
  const cJSON *v = cJSON_GetObjectItemCaseSensitive(o, name);
  return cJSON_IsNumber(v) ? v->valuedouble : dflt;
}

/* The path of volfxd: $VOLFX_VOLFXD, or "volfxd" beside this executable. */
static void find_volfxd(char *out, size_t cap) {
  const char *env = getenv("VOLFX_VOLFXD");
  if (env != NULL && env[0] != '\0') {
    snprintf(out, cap, "%s", env);
    return;
  }
  char self[FARM_PATH_CAP], dir[FARM_PATH_CAP];
  ssize_t n = readlink("/proc/self/exe", self, sizeof(self) - 1);
  self[n > 0 ? n : 0] = '\0';
  farm_split_path(self, dir, sizeof(dir));
  if (snprintf(out, cap, "%s/volfxd", n > 0 ? dir : ".") >= (int)cap) {
    snprintf(out, cap, "volfxd");
  }
}

/* Writes 32 random hex digits and a NUL into 'out'. Returns 0 or -1 with errno set. */
static int make_token(char out[33]) {
  unsigned char raw[16];
  int fd = open("/dev/urandom", O_RDONLY | O_CLOEXEC);
  ssize_t n = fd >= 0 ? read(fd, raw, sizeof(raw)) : -1;
  if (fd >= 0) {
    close(fd);
  }
  if (n != (ssize_t)sizeof(raw)) {
    return -1;
  }
  for (size_t i = 0; i < sizeof(raw); i++) {
    snprintf(out + 2 * i, 3, "%02x", raw[i]);
  }
  return 0;
}

static int64_t now_ms(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (int64_t)ts.tv_sec * 1000 + ts.tv_nsec / 1000000;
}

/* Reaps the private server if it has exited; returns 1 when none is left. */
static int reap(farm_t *f, int *status) {
  sigset_t block, old;
  sigemptyset(&block);
  sigaddset(&block, SIGINT);
  sigaddset(&block, SIGTERM);
  sigprocmask(SIG_BLOCK, &block, &old); /* The handler must never signal a reaped pid. */
  pid_t r = f->pid > 0 ? waitpid(f->pid, status, WNOHANG) : -1;
  if (f->pid <= 0 || r == f->pid || (r < 0 && errno == ECHILD)) {
    child_pid = 0;
    f->pid = 0;
  }
  sigprocmask(SIG_SETMASK, &old, NULL);
  return f->pid == 0;
}

/* Waits up to 'ms' for the private server to exit. Returns 1 when it has. */
static int wait_exit(farm_t *f, int ms, int *status) {
  int64_t deadline = now_ms() + ms;
  while (!reap(f, status)) {
    if (now_ms() >= deadline) {
      return 0;
    }
    struct timespec pause = {0, 10 * 1000000};
    nanosleep(&pause, NULL);
  }
  return 1;
}

/*
 * Reads volfxd's stdout from 'fd' until the line "volfxd listening on HOST:PORT". Returns 0
 * with the port in '*port', or EXIT_FAIL after saying why (the server exited, or stayed silent
 * too long, or a signal came).
 */
static int read_listen_line(farm_t *f, int fd, int *port) {
  static const char mark[] = "volfxd listening on ";
  char buf[4096];
  size_t len = 0;
  int64_t deadline = now_ms() + START_TIMEOUT_MS;
  for (;;) {
    char *nl;
    while ((nl = memchr(buf, '\n', len)) != NULL) {
      *nl = '\0';
      const char *colon = strrchr(buf, ':');
      uint64_t p;
      if (strncmp(buf, mark, sizeof(mark) - 1) == 0 && colon != NULL &&
          farm_parse_u64(colon + 1, 1, 65535, &p)) {
        *port = (int)p;
        return 0;
      }
      len -= (size_t)(nl + 1 - buf);
      memmove(buf, nl + 1, len);
    }
    if (len == sizeof(buf)) {
      len = 0; /* A line too long to be ours. */
    }
    if (farm_stop_signal != 0) {
      return farm_say(f, EXIT_FAIL, "interrupted by %s while volfxd was starting",
                      farm_signal_name(farm_stop_signal));
    }
    int64_t left = deadline - now_ms();
    if (left <= 0) {
      return farm_say(f, EXIT_FAIL, "volfxd did not start listening within %d s",
                      START_TIMEOUT_MS / 1000);
    }
    struct pollfd pfd = {.fd = fd, .events = POLLIN};
    if (poll(&pfd, 1, left > 1000 ? 1000 : (int)left) <= 0) {
      continue;
    }
    ssize_t r = read(fd, buf + len, sizeof(buf) - len);
    if (r < 0 && errno == EINTR) {
      continue;
    }
    if (r <= 0) {
      int st = 0;
      if (!wait_exit(f, STOP_GRACE_MS, &st)) {
        return farm_say(f, EXIT_FAIL, "volfxd closed its output without listening");
      }
      if (WIFSIGNALED(st)) {
        return farm_say(f, EXIT_FAIL, "volfxd died of %s before listening",
                        strsignal(WTERMSIG(st)));
      }
      return farm_say(f, EXIT_FAIL, "volfxd exited with status %d before listening (see above)",
                      WEXITSTATUS(st));
    }
    len += (size_t)r;
  }
}

/*
 * Starts the private volfxd with data directory 'data_dir' and main scene 'scene' ("" for the
 * plain default scene), connects and authenticates. Returns 0, or EXIT_FAIL after saying why;
 * farm_server_stop() cleans up either way.
 */
int farm_server_start(farm_t *f, const char *data_dir, const char *scene) {
  char exe[FARM_PATH_CAP], token[33];
  find_volfxd(exe, sizeof(exe));
  if (access(exe, X_OK) != 0) {
    return farm_say(f, EXIT_FAIL, "cannot run %s: %s (set VOLFX_VOLFXD to the volfxd to use)", exe,
                    strerror(errno));
  }
  if (make_token(token) != 0) {
    return farm_say(f, EXIT_FAIL, "cannot read /dev/urandom: %s", strerror(errno));
  }
  const char *args[16] = {exe,       "--listen", "127.0.0.1:0", "--data", data_dir,
                          "--scene", scene,      "--log-level", "warn"};
  int n = 9;
  if (f->presets != NULL) {
    args[n++] = "--presets";
    args[n++] = f->presets;
  }
  if (f->device != NULL) {
    args[n++] = "--device";
    args[n++] = f->device;
  }
  int fds[2];
  if (pipe2(fds, O_CLOEXEC) != 0) {
    return farm_say(f, EXIT_FAIL, "cannot make a pipe: %s", strerror(errno));
  }
  pid_t parent = getpid();
  pid_t pid = fork();
  if (pid == 0) {
    /* Its own process group: a Ctrl-C at the terminal reaches the CLI only, which stops the
     * server in order. And the server gets SIGTERM when the CLI dies, even of SIGKILL. */
    setpgid(0, 0);
    prctl(PR_SET_PDEATHSIG, SIGTERM);
    if (getppid() != parent) {
      _exit(127);
    }
    sigset_t none;
    sigemptyset(&none);
    sigprocmask(SIG_SETMASK, &none, NULL);
    dup2(fds[1], STDOUT_FILENO);
    int null = open("/dev/null", O_RDONLY);
    if (null >= 0) {
      dup2(null, STDIN_FILENO);
    }
    /* The token goes in the environment, where other users cannot read it (unlike argv). */
    setenv("VOLFX_TOKEN", token, 1);
    const char *cpus = getenv("SLURM_CPUS_PER_TASK");
    if (cpus != NULL && cpus[0] != '\0' && getenv("POCL_MAX_PTHREAD_COUNT") == NULL) {
      setenv("POCL_MAX_PTHREAD_COUNT", cpus, 1);
    }
    execv(exe, (char *const *)args);
    fprintf(stderr, "volfx %s: cannot run %s: %s\n", f->cmd, exe, strerror(errno));
    _exit(127);
  }
  close(fds[1]);
  if (pid < 0) {
    close(fds[0]);
    return farm_say(f, EXIT_FAIL, "cannot start volfxd: %s", strerror(errno));
  }
  f->pid = pid;
  child_pid = pid;
  if (farm_stop_signal != 0) {
    kill(pid, SIGTERM); /* The signal came before the handler knew the pid. */
  }
  int port = 0;
  int rc = read_listen_line(f, fds[0], &port);
  close(fds[0]); /* Nothing more is read: volfxd ignores SIGPIPE. */
  if (rc != 0) {
    return rc;
  }
  volfx_error_t e;
  rc = volfx_connect_tcp(&f->conn, "127.0.0.1", port, 10000, &e);
  if (rc == 0) {
    volfx_set_timeout(f->conn, 0); /* A frame or a long simulation may take any time. */
    rc = volfx_auth(f->conn, token, &e);
  }
  if (rc != 0) {
    return farm_say(f, EXIT_FAIL, "cannot talk to volfxd on port %d: %s", port, e.message);
  }
  return 0;
}

/* Stops the private server (server.shutdown, then SIGTERM, then SIGKILL) and removes the data
 * directory of our own. */
void farm_server_stop(farm_t *f) {
  if (f->conn != NULL && farm_stop_signal == 0) {
    volfx_set_timeout(f->conn, STOP_GRACE_MS);
    volfx_call(f->conn, "server.shutdown", NULL, NULL, NULL, NULL);
  }
  volfx_close(f->conn);
  f->conn = NULL;
  int st = 0, ran = f->pid > 0, killed = 0;
  if (ran && !wait_exit(f, STOP_GRACE_MS, &st)) {
    kill(f->pid, SIGTERM);
    if (!wait_exit(f, STOP_GRACE_MS, &st)) {
      f->where[0] = '\0';
      farm_say(f, 0, "volfxd did not stop; killed");
      kill(f->pid, SIGKILL);
      wait_exit(f, INT_MAX, &st);
      killed = 1;
    }
  }
  /* A crash explains a lost connection; its own log may say nothing. */
  if (ran && !killed && WIFSIGNALED(st)) {
    farm_say(f, 0, "volfxd died of signal %d (%s)", WTERMSIG(st), strsignal(WTERMSIG(st)));
  } else if (ran && !killed && WIFEXITED(st) && WEXITSTATUS(st) != 0) {
    farm_say(f, 0, "volfxd exited with status %d", WEXITSTATUS(st));
  }
  if (f->tmp_data[0] != '\0') {
    farm_remove_tree(f->tmp_data);
    f->tmp_data[0] = '\0';
  }
}

/* Ends a run: stops the server, frees what is left and, after SIGINT or SIGTERM, dies of it. */
int farm_finish(farm_t *f, int status) {
  farm_server_stop(f);
  free(f->snaps);
  fflush(stdout);
  if (farm_stop_signal != 0) {
    signal(farm_stop_signal, SIG_DFL);
    raise(farm_stop_signal);
  }
  return status;
}
