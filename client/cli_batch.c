/*
 * volfx batch and volfx bake: render-farm commands that need no running server. Each starts a
 * private volfxd (loopback, port 0, a random token passed in its environment, log level warn),
 * reads its port from the "volfxd listening on HOST:PORT" line, drives it over one connection
 * and always stops it: server.shutdown, then SIGTERM and SIGKILL when it lingers, also after an
 * error and when the CLI gets SIGINT or SIGTERM (forwarded at once, so that a long render or
 * bake ends too). The server dies with the CLI even when the CLI is killed outright.
 *
 * `batch` renders frames FIRST..LAST to files named by a #### pattern. Each frame goes to a
 * temporary file beside its target, is fsynced and renamed into place, so a file under its
 * final name is always whole; frames whose files are whole already are skipped, and no server
 * starts when none is missing. `bake` simulates a shot once with the server's sim.bake job,
 * which saves a snapshot every K frames into a bake directory; `batch --bake DIR` then starts
 * from the snapshot nearest before the frames it needs instead of simulating from the start.
 */
#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <ftw.h>
#include <inttypes.h>
#include <limits.h>
#include <poll.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/prctl.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "cli_batch.h"
#include "proto.h"
#include "volfx.h"

#define EXIT_FAIL 1                   /* A frame, the bake or the server failed. */
#define EXIT_USAGE 2                  /* The command line was wrong; nothing was started. */
#define FRAME_MAX 9007199254740991ULL /* 2^53 - 1, the largest sim.frame. */
#define STEPS_MAX 100000              /* The most steps one sim.step takes. */
#define START_TIMEOUT_MS 300000       /* Wait for the listening line (kernels may compile). */
#define STOP_GRACE_MS 5000            /* Wait for an exit after server.shutdown or SIGTERM. */
#define PATH_CAP (PATH_MAX + 64)      /* Room for a path and a suffix or prefix. */

static const unsigned char png_signature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
static const unsigned char png_iend[12] = {0, 0, 0, 0, 'I', 'E', 'N', 'D', 0xae, 0x42, 0x60, 0x82};

static volatile sig_atomic_t stop_signal; /* SIGINT or SIGTERM, once received. */
static volatile sig_atomic_t child_pid;   /* The private volfxd while it may be signalled. */

/* The state of one batch or bake run. */
typedef struct farm {
  const char *cmd;         /* "batch" or "bake": named in every message. */
  char where[48];          /* "frame N: " while working toward frame N, else "". */
  char why[1024];          /* What the last failed call said. */
  const char *presets;     /* --presets DIR for volfxd, or NULL. */
  const char *device;      /* --device D for volfxd, or NULL. */
  int verbose;             /* -v: a line per frame or snapshot. */
  pid_t pid;               /* The private volfxd; 0 when none runs. */
  volfx_conn_t *conn;      /* The connection to it, or NULL. */
  char tmp_data[PATH_CAP]; /* A data directory of our own, removed at the end, or "". */
  uint64_t *snaps;         /* Frames of the bake directory's snapshots, ascending. */
  size_t nsnaps;
  char bake_base[NAME_MAX + 1]; /* The bake directory's name inside the data directory. */
  uint64_t frame;               /* The private scene's current frame. */
} farm_t;

/* Options of both commands, parsed into one table of values (flags get ""). */
enum {
  A_FIRST,
  A_LAST,
  A_STEP,
  A_OUT,
  A_BAKE,
  A_EVERY,
  A_WIDTH,
  A_HEIGHT,
  A_FORMAT,
  A_AOV,
  A_LAYERS,
  A_CAMERA,
  A_PNG_LEVEL,
  A_ANTIALIAS,
  A_PRESETS,
  A_DEVICE,
  A_OVERWRITE,
  A_VERBOSE,
  A_COUNT
};

static const struct {
  const char *name, *alias;
  int flag; /* 1: takes no value. */
} options[A_COUNT] = {
    [A_FIRST] = {"--start", "-s", 0},         [A_LAST] = {"--end", "-e", 0},
    [A_STEP] = {"--jump", "-j", 0},           [A_OUT] = {"--output", "-o", 0},
    [A_BAKE] = {"--bake", NULL, 0},           [A_EVERY] = {"--every", "-k", 0},
    [A_WIDTH] = {"--width", "-W", 0},         [A_HEIGHT] = {"--height", "-H", 0},
    [A_FORMAT] = {"--format", "-f", 0},       [A_AOV] = {"--aov", NULL, 0},
    [A_LAYERS] = {"--layers", NULL, 0},       [A_CAMERA] = {"--camera", NULL, 0},
    [A_PNG_LEVEL] = {"--png-level", NULL, 0}, [A_ANTIALIAS] = {"--antialias", NULL, 0},
    [A_PRESETS] = {"--presets", NULL, 0},     [A_DEVICE] = {"--device", NULL, 0},
    [A_OVERWRITE] = {"--overwrite", NULL, 1}, [A_VERBOSE] = {"--verbose", "-v", 1},
};

#define BIT(a) (1u << (a))
#define BATCH_OPTS                                                                                 \
  (BIT(A_FIRST) | BIT(A_LAST) | BIT(A_STEP) | BIT(A_OUT) | BIT(A_BAKE) | BIT(A_WIDTH) |            \
   BIT(A_HEIGHT) | BIT(A_FORMAT) | BIT(A_AOV) | BIT(A_LAYERS) | BIT(A_CAMERA) | BIT(A_PNG_LEVEL) | \
   BIT(A_ANTIALIAS) | BIT(A_PRESETS) | BIT(A_DEVICE) | BIT(A_OVERWRITE) | BIT(A_VERBOSE))
#define BAKE_OPTS                                                                                  \
  (BIT(A_LAST) | BIT(A_EVERY) | BIT(A_OUT) | BIT(A_PRESETS) | BIT(A_DEVICE) | BIT(A_VERBOSE))

/* Prints "volfx CMD: [frame N: ]MESSAGE" to stderr and returns 'status'. */
__attribute__((format(printf, 3, 4))) static int say(const farm_t *f, int status, const char *fmt,
                                                     ...) {
  va_list ap;
  fprintf(stderr, "volfx %s: %s", f->cmd, f->where);
  va_start(ap, fmt);
  vfprintf(stderr, fmt, ap);
  va_end(ap);
  fputc('\n', stderr);
  return status;
}

/* Formats a message into 'buf', cut to 'cap' bytes when longer. */
__attribute__((format(printf, 3, 4))) static void text(char *buf, size_t cap, const char *fmt,
                                                       ...) {
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(buf, cap, fmt, ap);
  va_end(ap);
}

/* Reports a command-line mistake about 'arg' and returns EXIT_USAGE. */
static int usage(const farm_t *f, const char *fmt, const char *arg) {
  fprintf(stderr, "volfx %s: ", f->cmd);
  fprintf(stderr, fmt, arg != NULL ? arg : "");
  fputs(" (see volfx --help)\n", stderr);
  return EXIT_USAGE;
}

/* "SIGINT" or "SIGTERM": the signals that stop a run. */
static const char *signal_name(int sig) {
  return sig == SIGINT ? "SIGINT" : "SIGTERM";
}

static void on_stop(int sig) {
  stop_signal = sig;
  if (child_pid > 0) {
    kill((pid_t)child_pid, SIGTERM);
  }
}

static void catch_stop_signals(void) {
  struct sigaction sa;
  memset(&sa, 0, sizeof(sa));
  sa.sa_handler = on_stop;
  sigemptyset(&sa.sa_mask);
  sa.sa_flags = SA_RESTART;
  sigaction(SIGINT, &sa, NULL);
  sigaction(SIGTERM, &sa, NULL);
}

/* Parses all of 's' as a whole number from 'min' to 'max'. Returns 1 on success. */
static int parse_u64(const char *s, uint64_t min, uint64_t max, uint64_t *out) {
  if (s[0] < '0' || s[0] > '9') {
    return 0;
  }
  char *end;
  errno = 0;
  unsigned long long v = strtoull(s, &end, 10);
  if (*end != '\0' || errno != 0 || v < min || v > max) {
    return 0;
  }
  *out = v;
  return 1;
}

/*
 * Reads the command's words into 'val' (indexed by A_*; NULL when absent, "" for a flag given)
 * and its one positional word into '*scene'. Only the options in 'accepted' are known.
 * "--name=VALUE" works for long names. Returns 0 or EXIT_USAGE after saying why.
 */
static int parse_args(const farm_t *f, int argc, char **argv, unsigned accepted,
                      const char *val[A_COUNT], const char **scene) {
  for (int i = 1; i < argc; i++) {
    const char *a = argv[i];
    int k = 0;
    const char *inline_val = NULL;
    for (; k < A_COUNT; k++) {
      size_t n = strlen(options[k].name);
      if (!(accepted & BIT(k))) {
        continue;
      }
      if (strcmp(a, options[k].name) == 0 ||
          (options[k].alias != NULL && strcmp(a, options[k].alias) == 0)) {
        break;
      }
      if (!options[k].flag && strncmp(a, options[k].name, n) == 0 && a[n] == '=') {
        inline_val = a + n + 1;
        break;
      }
    }
    if (k < A_COUNT && options[k].flag) {
      val[k] = "";
    } else if (k < A_COUNT && inline_val != NULL) {
      val[k] = inline_val;
    } else if (k < A_COUNT) {
      if (i + 1 >= argc) {
        return usage(f, "%s needs a value", a);
      }
      val[k] = argv[++i];
    } else if (a[0] == '-' && a[1] != '\0') {
      return usage(f, "unknown option '%s'", a);
    } else if (*scene == NULL) {
      *scene = a;
    } else {
      return usage(f, "unexpected '%s': give one PRESET, SCENE.json or SNAPSHOT", a);
    }
  }
  if (*scene == NULL) {
    return usage(f, "needs a PRESET, SCENE.json or SNAPSHOT%s", NULL);
  }
  return 0;
}

/* 1 when 'path' is a snapshot: a file whose first line is a JSON object with "volfx_snapshot". */
static int is_snapshot(const char *path) {
  FILE *fp = fopen(path, "rb");
  if (fp == NULL) {
    return 0;
  }
  struct stat st;
  char *line = NULL;
  size_t cap = 0;
  ssize_t n = fstat(fileno(fp), &st) == 0 && S_ISREG(st.st_mode) ? getline(&line, &cap, fp) : -1;
  fclose(fp);
  cJSON *head = n > 0 ? cJSON_ParseWithLength(line, (size_t)n) : NULL;
  int yes = cJSON_IsObject(head) && cJSON_HasObjectItem(head, "volfx_snapshot");
  cJSON_Delete(head);
  free(line);
  return yes;
}

/* Reads a whole small file into a NUL-terminated string, or NULL with errno set. */
static char *read_text(const char *path) {
  FILE *fp = fopen(path, "rb");
  if (fp == NULL) {
    return NULL;
  }
  char *text = NULL;
  size_t cap = 0, len = 0;
  for (;;) {
    if (len + 4096 + 1 > cap) {
      cap = (cap + 4096) * 2;
      char *bigger = realloc(text, cap);
      if (bigger == NULL) {
        free(text);
        fclose(fp);
        errno = ENOMEM;
        return NULL;
      }
      text = bigger;
    }
    size_t r = fread(text + len, 1, cap - len - 1, fp);
    len += r;
    if (r == 0) {
      break;
    }
  }
  int bad = ferror(fp);
  fclose(fp);
  if (bad) {
    free(text);
    errno = EIO;
    return NULL;
  }
  text[len] = '\0';
  return text;
}

/*
 * Splits 'path' into the directory part (copied to 'dir', "." when there is none) and the
 * name after the last slash (returned, pointing into 'path').
 */
static const char *split_path(const char *path, char *dir, size_t cap) {
  const char *slash = strrchr(path, '/');
  if (slash == NULL) {
    snprintf(dir, cap, ".");
    return path;
  }
  size_t n = slash == path ? 1 : (size_t)(slash - path);
  snprintf(dir, cap, "%.*s", (int)n, path);
  return slash + 1;
}

/*
 * Creates directory 'path' and its missing parents (mkdir -p). On failure returns -1 with
 * errno set and 'bad' holding the directory that could not be made.
 */
static int make_dirs(const char *path, char *bad, size_t cap) {
  char buf[PATH_CAP];
  if (snprintf(buf, sizeof(buf), "%s", path) >= (int)sizeof(buf)) {
    snprintf(bad, cap, "%s", path);
    errno = ENAMETOOLONG;
    return -1;
  }
  for (char *p = buf + 1;; p++) {
    if (*p != '/' && *p != '\0') {
      continue;
    }
    char saved = *p;
    *p = '\0';
    struct stat st;
    int bad_dir = mkdir(buf, 0777) != 0 && errno != EEXIST;
    if (!bad_dir && stat(buf, &st) != 0) {
      bad_dir = 1;
    } else if (!bad_dir && !S_ISDIR(st.st_mode)) {
      bad_dir = 1;
      errno = ENOTDIR;
    }
    if (bad_dir) {
      snprintf(bad, cap, "%s", buf);
      return -1;
    }
    if (saved == '\0') {
      return 0;
    }
    *p = saved;
  }
}

/* Removes the temporary files a killed run left beside 'base' in 'dir'. */
static void remove_stale_parts(const char *dir, const char *base) {
  char prefix[NAME_MAX + 16];
  int n = snprintf(prefix, sizeof(prefix), ".%s.part.", base);
  DIR *d = opendir(dir);
  if (d == NULL || n < 0 || (size_t)n >= sizeof(prefix)) {
    if (d != NULL) {
      closedir(d);
    }
    return;
  }
  struct dirent *e;
  while ((e = readdir(d)) != NULL) {
    if (strncmp(e->d_name, prefix, (size_t)n) == 0 && strlen(e->d_name) == (size_t)n + 6) {
      unlinkat(dirfd(d), e->d_name, 0);
    }
  }
  closedir(d);
}

/*
 * Writes 'n' bytes to 'path' so that no reader ever sees part of them under that name: into a
 * new temporary file beside it, fsynced, renamed over 'path', and the directory fsynced. The
 * directory is created first when missing. Returns 0, or -1 with 'why' saying what failed.
 */
static int write_atomic(const char *path, const void *data, size_t n, mode_t mode, char *why,
                        size_t cap) {
  char dir[PATH_CAP], tmp[PATH_CAP], bad[PATH_CAP];
  const char *base = split_path(path, dir, sizeof(dir));
  if (make_dirs(dir, bad, sizeof(bad)) != 0) {
    text(why, cap, "cannot write %s: %s: %s", path, bad, strerror(errno));
    return -1;
  }
  remove_stale_parts(dir, base);
  if (snprintf(tmp, sizeof(tmp), "%s/.%s.part.XXXXXX", dir, base) >= (int)sizeof(tmp)) {
    text(why, cap, "cannot write %s: %s", path, strerror(ENAMETOOLONG));
    return -1;
  }
  int fd = mkostemp(tmp, O_CLOEXEC);
  if (fd < 0) {
    text(why, cap, "cannot write %s: %s", path, strerror(errno));
    return -1;
  }
  const char *p = data;
  size_t left = n;
  int err = fchmod(fd, mode) == 0 ? 0 : errno;
  while (err == 0 && left > 0) {
    ssize_t w = write(fd, p, left);
    if (w < 0 && errno == EINTR) {
      continue;
    }
    if (w <= 0) {
      err = w < 0 ? errno : EIO;
      break;
    }
    p += w;
    left -= (size_t)w;
  }
  if (err == 0 && fsync(fd) != 0) {
    err = errno;
  }
  if (close(fd) != 0 && err == 0) {
    err = errno;
  }
  if (err == 0 && rename(tmp, path) != 0) {
    err = errno;
  }
  if (err != 0) {
    unlink(tmp);
    text(why, cap, "cannot write %s: %s", path, strerror(err));
    return -1;
  }
  int dfd = open(dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dfd >= 0) {
    fsync(dfd);
    close(dfd);
  }
  return 0;
}

/*
 * 1 when 'n' bytes at 'data' are a whole frame: exactly 'raw_bytes' of a raw format, or (with
 * 'raw_bytes' 0) a PNG from its signature to its IEND chunk.
 */
static int bytes_whole(const unsigned char *data, size_t n, uint64_t raw_bytes) {
  if (raw_bytes > 0) {
    return n == raw_bytes;
  }
  return n >= sizeof(png_signature) + sizeof(png_iend) &&
         memcmp(data, png_signature, sizeof(png_signature)) == 0 &&
         memcmp(data + n - sizeof(png_iend), png_iend, sizeof(png_iend)) == 0;
}

/* bytes_whole() for the file at 'path'; 0 when there is none. */
static int file_whole(const char *path, uint64_t raw_bytes) {
  int fd = open(path, O_RDONLY | O_CLOEXEC);
  struct stat st;
  if (fd < 0) {
    return 0;
  }
  int whole = 0;
  if (fstat(fd, &st) == 0 && S_ISREG(st.st_mode)) {
    size_t size = (size_t)st.st_size;
    unsigned char head[8], tail[12];
    if (raw_bytes > 0) {
      whole = (uint64_t)st.st_size == raw_bytes;
    } else if (size >= sizeof(head) + sizeof(tail) &&
               pread(fd, head, sizeof(head), 0) == (ssize_t)sizeof(head) &&
               pread(fd, tail, sizeof(tail), st.st_size - 12) == (ssize_t)sizeof(tail)) {
      whole = memcmp(head, png_signature, sizeof(head)) == 0 &&
              memcmp(tail, png_iend, sizeof(tail)) == 0;
    }
  }
  close(fd);
  return whole;
}

/*
 * Expands 'pattern' for 'frame' into 'out': each run of '#' becomes the frame number padded
 * with zeros to the run's length (longer when the number needs more digits). Returns 0, or -1
 * when 'out' is too small.
 */
static int expand_pattern(const char *pattern, uint64_t frame, char *out, size_t cap) {
  size_t o = 0;
  for (const char *s = pattern; *s != '\0';) {
    if (*s == '#') {
      size_t run = strspn(s, "#");
      int w = snprintf(out + o, cap - o, "%0*" PRIu64, (int)(run > 64 ? 64 : run), frame);
      if (w < 0 || (size_t)w >= cap - o) {
        return -1;
      }
      o += (size_t)w;
      s += run;
    } else {
      if (o + 1 >= cap) {
        return -1;
      }
      out[o++] = *s++;
    }
  }
  out[o] = '\0';
  return 0;
}

/* Removes every file under 'path' and then 'path' itself. */
static int remove_entry(const char *path, const struct stat *st, int kind, struct FTW *ftw) {
  (void)st;
  (void)kind;
  (void)ftw;
  remove(path);
  return 0;
}

/* ---------------------------------------------------------------------------------------- */
/* The private server */

/* A params object naming the main scene, the only one the private server uses. */
static cJSON *main_params(void) {
  cJSON *p = cJSON_CreateObject();
  cJSON_AddStringToObject(p, "scene", "main");
  return p;
}

/*
 * One call to the private server. On failure 'f->why' receives "METHOD: MESSAGE (path P)",
 * with the kind of a JSON-RPC error before a message that does not name it. 'params' is taken.
 * Returns 0 or the call's code.
 */
static int call(farm_t *f, const char *method, cJSON *params, cJSON **result,
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
  if (stop_signal != 0) {
    snprintf(f->why, sizeof(f->why), "interrupted by %s", signal_name(stop_signal));
  }
  return rc;
}

/* The number member 'name' of 'o', or 'dflt'. */
static double num_member(const cJSON *o, const char *name, double dflt) {
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
  char self[PATH_CAP], dir[PATH_CAP];
  ssize_t n = readlink("/proc/self/exe", self, sizeof(self) - 1);
  self[n > 0 ? n : 0] = '\0';
  split_path(self, dir, sizeof(dir));
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
          parse_u64(colon + 1, 1, 65535, &p)) {
        *port = (int)p;
        return 0;
      }
      len -= (size_t)(nl + 1 - buf);
      memmove(buf, nl + 1, len);
    }
    if (len == sizeof(buf)) {
      len = 0; /* A line too long to be ours. */
    }
    if (stop_signal != 0) {
      return say(f, EXIT_FAIL, "interrupted by %s while volfxd was starting",
                 signal_name(stop_signal));
    }
    int64_t left = deadline - now_ms();
    if (left <= 0) {
      return say(f, EXIT_FAIL, "volfxd did not start listening within %d s",
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
        return say(f, EXIT_FAIL, "volfxd closed its output without listening");
      }
      if (WIFSIGNALED(st)) {
        return say(f, EXIT_FAIL, "volfxd died of %s before listening", strsignal(WTERMSIG(st)));
      }
      return say(f, EXIT_FAIL, "volfxd exited with status %d before listening (see above)",
                 WEXITSTATUS(st));
    }
    len += (size_t)r;
  }
}

/*
 * Starts the private volfxd with data directory 'data_dir' and main scene 'scene' ("" for the
 * plain default scene), connects and authenticates. Returns 0, or EXIT_FAIL after saying why;
 * server_stop() cleans up either way.
 */
static int server_start(farm_t *f, const char *data_dir, const char *scene) {
  char exe[PATH_CAP], token[33];
  find_volfxd(exe, sizeof(exe));
  if (access(exe, X_OK) != 0) {
    return say(f, EXIT_FAIL, "cannot run %s: %s (set VOLFX_VOLFXD to the volfxd to use)", exe,
               strerror(errno));
  }
  if (make_token(token) != 0) {
    return say(f, EXIT_FAIL, "cannot read /dev/urandom: %s", strerror(errno));
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
    return say(f, EXIT_FAIL, "cannot make a pipe: %s", strerror(errno));
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
    return say(f, EXIT_FAIL, "cannot start volfxd: %s", strerror(errno));
  }
  f->pid = pid;
  child_pid = pid;
  if (stop_signal != 0) {
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
    return say(f, EXIT_FAIL, "cannot talk to volfxd on port %d: %s", port, e.message);
  }
  return 0;
}

/* Stops the private server (server.shutdown, then SIGTERM, then SIGKILL) and removes the data
 * directory of our own. */
static void server_stop(farm_t *f) {
  if (f->conn != NULL && stop_signal == 0) {
    volfx_set_timeout(f->conn, STOP_GRACE_MS);
    volfx_call(f->conn, "server.shutdown", NULL, NULL, NULL, NULL);
  }
  volfx_close(f->conn);
  f->conn = NULL;
  int st = 0;
  if (f->pid > 0 && !wait_exit(f, STOP_GRACE_MS, &st)) {
    kill(f->pid, SIGTERM);
    if (!wait_exit(f, STOP_GRACE_MS, &st)) {
      f->where[0] = '\0';
      say(f, 0, "volfxd did not stop; killed");
      kill(f->pid, SIGKILL);
      wait_exit(f, INT_MAX, &st);
    }
  }
  if (f->tmp_data[0] != '\0') {
    nftw(f->tmp_data, remove_entry, 16, FTW_DEPTH | FTW_PHYS);
    f->tmp_data[0] = '\0';
  }
}

/* Ends a run: stops the server, frees what is left and, after SIGINT or SIGTERM, dies of it. */
static int finish(farm_t *f, int status) {
  server_stop(f);
  free(f->snaps);
  fflush(stdout);
  if (stop_signal != 0) {
    signal(stop_signal, SIG_DFL);
    raise(stop_signal);
  }
  return status;
}

/* ---------------------------------------------------------------------------------------- */
/* Scenes, snapshots and bakes */

/* The scene's current frame from its document. */
static uint64_t doc_frame(const cJSON *doc) {
  double v = num_member(cJSON_GetObjectItemCaseSensitive(doc, "sim"), "frame", 0);
  return v > 0 ? (uint64_t)v : 0;
}

/* Loads snapshot 'file' (relative to the data directory) into the main scene and sets
 * 'f->frame' to its frame. Returns 0 or the call's code with 'f->why' set. */
static int load_snapshot(farm_t *f, const char *file) {
  cJSON *p = main_params();
  cJSON_AddStringToObject(p, "file", file);
  cJSON *r = NULL;
  int rc = call(f, "scene.load", p, &r, NULL);
  if (rc == 0) {
    double v = num_member(r, "frame", 0);
    f->frame = v > 0 ? (uint64_t)v : 0;
  }
  cJSON_Delete(r);
  return rc;
}

static int cmp_u64(const void *a, const void *b) {
  uint64_t x = *(const uint64_t *)a, y = *(const uint64_t *)b;
  return x < y ? -1 : x > y;
}

/*
 * Lists the snapshots of bake directory 'dir' into 'f->snaps' (frames, ascending). Names that
 * are not exactly PROTO_BAKE_FILE of a frame are ignored. Returns 0 or -1 with errno set.
 */
static int list_snapshots(farm_t *f, const char *dir) {
  DIR *d = opendir(dir);
  if (d == NULL) {
    return -1;
  }
  size_t cap = 0;
  struct dirent *e;
  while ((e = readdir(d)) != NULL) {
    uint64_t frame;
    char digits[32], again[64];
    const char *name = e->d_name;
    size_t n = strlen(name);
    if (n < 12 || n - 11 >= sizeof(digits) || strncmp(name, "frame_", 6) != 0) {
      continue;
    }
    snprintf(digits, sizeof(digits), "%.*s", (int)(n - 11), name + 6);
    if (!parse_u64(digits, 0, FRAME_MAX, &frame)) {
      continue;
    }
    snprintf(again, sizeof(again), PROTO_BAKE_FILE, (unsigned long long)frame);
    if (strcmp(again, name) != 0) {
      continue;
    }
    if (f->nsnaps == cap) {
      cap = cap != 0 ? cap * 2 : 64;
      uint64_t *bigger = realloc(f->snaps, cap * sizeof(*bigger));
      if (bigger == NULL) {
        closedir(d);
        errno = ENOMEM;
        return -1;
      }
      f->snaps = bigger;
    }
    f->snaps[f->nsnaps++] = frame;
  }
  closedir(d);
  qsort(f->snaps, f->nsnaps, sizeof(*f->snaps), cmp_u64);
  return 0;
}

/* The index of the latest snapshot at or before 'frame', or -1. */
static long snapshot_before(const farm_t *f, uint64_t frame) {
  long k = -1;
  for (size_t i = 0; i < f->nsnaps && f->snaps[i] <= frame; i++) {
    k = (long)i;
  }
  return k;
}

/* The bake snapshot of 'frame' as the server names it: "BASE/frame_NNNNNN.snap". */
static void snapshot_file(const farm_t *f, uint64_t frame, char *out, size_t cap) {
  char name[64];
  snprintf(name, sizeof(name), PROTO_BAKE_FILE, (unsigned long long)frame);
  snprintf(out, cap, "%s/%s", f->bake_base, name);
}

/*
 * Reads 'dir'/bake.json into '*manifest' (owned by the caller; left NULL when there is none
 * and that is 'optional'). Returns 0 or EXIT_FAIL after saying why.
 */
static int read_manifest(const farm_t *f, const char *dir, int optional, cJSON **manifest) {
  char path[PATH_CAP];
  snprintf(path, sizeof(path), "%s/%s", dir, PROTO_BAKE_MANIFEST);
  char *text = read_text(path);
  *manifest = NULL;
  if (text == NULL && errno == ENOENT && optional) {
    return 0;
  }
  if (text == NULL) {
    return say(f, EXIT_FAIL, "cannot read %s: %s", path, strerror(errno));
  }
  *manifest = cJSON_Parse(text);
  free(text);
  const cJSON *every = cJSON_GetObjectItemCaseSensitive(*manifest, "every");
  if (num_member(*manifest, "volfx_bake", 0) != PROTO_BAKE_VERSION || !cJSON_IsNumber(every) ||
      !cJSON_IsObject(cJSON_GetObjectItemCaseSensitive(*manifest, "scene"))) {
    cJSON_Delete(*manifest);
    *manifest = NULL;
    return say(f, EXIT_FAIL, "%s is not a bake manifest of version %d", path, PROTO_BAKE_VERSION);
  }
  return 0;
}

/*
 * Fetches the main scene's document, sets 'f->frame' from it and, with a 'manifest', checks
 * that the scene is the bake's. Returns 0 or EXIT_FAIL after saying why.
 */
static int check_scene(farm_t *f, const cJSON *manifest, const char *bake_dir) {
  cJSON *doc = NULL;
  if (call(f, "scene.get", main_params(), &doc, NULL) != 0) {
    return say(f, EXIT_FAIL, "%s", f->why);
  }
  f->frame = doc_frame(doc);
  int same =
      manifest == NULL || proto_bake_same(doc, cJSON_GetObjectItemCaseSensitive(manifest, "scene"));
  cJSON_Delete(doc);
  return same ? 0 : say(f, EXIT_FAIL, "bake %s holds another scene", bake_dir);
}

/*
 * The data directory and the scene's place in it. With 'bake_dir', its parent; a 'snapshot'
 * must then lie inside it ('*file' receives its name relative to it). Else a snapshot's own
 * directory. 'data' receives the directory, '' when the caller should make one. Returns 0,
 * EXIT_USAGE or EXIT_FAIL after saying why.
 */
static int locate(farm_t *f, const char *bake_dir, const char *snapshot, char *data, size_t cap,
                  char *file, size_t fcap) {
  char real[PATH_CAP];
  data[0] = file[0] = '\0';
  if (bake_dir != NULL) {
    if (realpath(bake_dir, real) == NULL) {
      return say(f, EXIT_FAIL, "cannot use bake directory %s: %s", bake_dir, strerror(errno));
    }
    const char *base = split_path(real, data, cap);
    if (base[0] == '\0' || strlen(base) > NAME_MAX) {
      return usage(f, "the bake directory %s cannot be the root", bake_dir);
    }
    snprintf(f->bake_base, sizeof(f->bake_base), "%s", base);
  }
  if (snapshot == NULL) {
    return 0;
  }
  char snap[PATH_CAP];
  if (realpath(snapshot, snap) == NULL) {
    return say(f, EXIT_FAIL, "cannot use snapshot %s: %s", snapshot, strerror(errno));
  }
  if (bake_dir == NULL) {
    snprintf(file, fcap, "%s", split_path(snap, data, cap));
    return 0;
  }
  size_t n = strlen(data);
  const char *rel = snap + n + (strcmp(data, "/") != 0);
  if (strncmp(snap, data, n) != 0 || (strcmp(data, "/") != 0 && snap[n] != '/')) {
    fprintf(stderr,
            "volfx %s: snapshot %s lies outside %s, the parent directory of the bake %s: the "
            "server reads both from there (see volfx --help)\n",
            f->cmd, snapshot, data, bake_dir);
    return EXIT_USAGE;
  }
  snprintf(file, fcap, "%s", rel);
  return 0;
}

/* ---------------------------------------------------------------------------------------- */
/* volfx batch */

typedef struct batch {
  uint64_t first, last, step;
  const char *pattern; /* -o: file names with #### for the frame. */
  uint64_t raw_bytes;  /* The size of a raw frame; 0 for PNG. */
  cJSON *render;       /* The params of every render. */
  uint64_t antialias;  /* --antialias, or 0 to keep the scene's. */
  int overwrite;       /* --overwrite: render frames whose files are whole too. */
  mode_t mode;         /* Permissions of new frame files. */
  uint64_t written, skipped;
} batch_t;

/* Turns the option table into 'b'. Returns 0 or EXIT_USAGE after saying why. */
static int batch_options(farm_t *f, batch_t *b, const char *val[A_COUNT]) {
  uint64_t w = 512, h = 512, png_level = 0, aa = 0;
  if (val[A_FIRST] == NULL || val[A_LAST] == NULL || val[A_OUT] == NULL) {
    return usage(f, "needs -s FIRST, -e LAST and -o PATTERN%s", NULL);
  }
  static const int frames[] = {A_FIRST, A_LAST, A_STEP};
  uint64_t *dst[] = {&b->first, &b->last, &b->step};
  b->step = 1;
  for (int k = 0; k < 3; k++) {
    if (val[frames[k]] != NULL && !parse_u64(val[frames[k]], k == 2, FRAME_MAX, dst[k])) {
      return usage(f, "bad number '%s': frames are whole numbers from 0 to 2^53-1, -j from 1",
                   val[frames[k]]);
    }
  }
  if (b->last < b->first) {
    return usage(f, "LAST (-e) is before FIRST (-s)%s", NULL);
  }
  b->pattern = val[A_OUT];
  if (strchr(b->pattern, '#') == NULL && b->first != b->last) {
    return usage(f, "-o '%s' has no # for the frame number, and there are several frames",
                 b->pattern);
  }
  if ((val[A_WIDTH] != NULL && !parse_u64(val[A_WIDTH], 1, 1u << 20, &w)) ||
      (val[A_HEIGHT] != NULL && !parse_u64(val[A_HEIGHT], 1, 1u << 20, &h))) {
    return usage(f, "-W and -H need whole numbers of pixels%s", NULL);
  }
  if (val[A_ANTIALIAS] != NULL && !parse_u64(val[A_ANTIALIAS], 1, 64, &aa)) {
    return usage(f, "bad --antialias '%s' (samples per pixel along each axis)", val[A_ANTIALIAS]);
  }
  b->antialias = aa;
  const char *aov = val[A_AOV] != NULL ? val[A_AOV] : "beauty";
  const char *format = val[A_FORMAT];
  if (format == NULL) {
    format = strcmp(aov, "beauty") == 0 ? "png" : "f32";
  }
  static const struct {
    const char *name;
    unsigned bytes; /* Per pixel; 0 for PNG. */
  } formats[] = {{"png", 0}, {"rgba8", 4}, {"rgbaf32", 16}, {"f32", 4}};
  size_t k = 0;
  while (k < 4 && strcmp(format, formats[k].name) != 0) {
    k++;
  }
  if (k == 4) {
    return usage(f, "bad --format '%s' (png, rgba8, rgbaf32 or f32)", format);
  }
  b->raw_bytes = formats[k].bytes * w * h;
  b->render = main_params();
  cJSON_AddNumberToObject(b->render, "width", (double)w);
  cJSON_AddNumberToObject(b->render, "height", (double)h);
  cJSON_AddStringToObject(b->render, "format", format);
  cJSON_AddStringToObject(b->render, "aov", aov);
  if (val[A_LAYERS] != NULL) {
    cJSON *layers = cJSON_AddArrayToObject(b->render, "layers");
    for (const char *s = val[A_LAYERS]; *s != '\0';) {
      size_t n = strcspn(s, ",");
      char word[64];
      if (n > 0 && n < sizeof(word)) {
        snprintf(word, sizeof(word), "%.*s", (int)n, s);
        cJSON_AddItemToArray(layers, cJSON_CreateString(word));
      }
      s += n + (s[n] == ',');
    }
  }
  if (val[A_CAMERA] != NULL) {
    cJSON *camera = cJSON_Parse(val[A_CAMERA]);
    if (!cJSON_IsObject(camera)) {
      cJSON_Delete(camera);
      return usage(f, "--camera needs a JSON object, not '%s'", val[A_CAMERA]);
    }
    cJSON_AddItemToObject(b->render, "camera", camera);
  }
  if (val[A_PNG_LEVEL] != NULL) {
    int minus = strcmp(val[A_PNG_LEVEL], "-1") == 0;
    if (!minus && !parse_u64(val[A_PNG_LEVEL], 0, 9, &png_level)) {
      return usage(f, "bad --png-level '%s' (-1 to 9)", val[A_PNG_LEVEL]);
    }
    cJSON_AddNumberToObject(b->render, "png_level", minus ? -1 : (double)png_level);
  }
  b->overwrite = val[A_OVERWRITE] != NULL;
  return 0;
}

/* Sets render.antialias when --antialias was given (again after each snapshot load). */
static int apply_antialias(farm_t *f, const batch_t *b) {
  if (b->antialias == 0) {
    return 0;
  }
  cJSON *p = main_params();
  cJSON_AddStringToObject(p, "path", "render.antialias");
  cJSON_AddNumberToObject(p, "value", (double)b->antialias);
  cJSON *r = NULL;
  int rc = call(f, "scene.set", p, &r, NULL);
  cJSON_Delete(r);
  return rc == 0 ? 0 : say(f, EXIT_FAIL, "%s", f->why);
}

/*
 * Brings the main scene to 'frame': from the bake's latest snapshot at or before it when that
 * is nearer than the scene's own frame (or the scene is past it), then by sim.step. Returns 0
 * or EXIT_FAIL after saying why.
 */
static int reach_frame(farm_t *f, const batch_t *b, uint64_t frame) {
  long k = snapshot_before(f, frame);
  if (k >= 0 && (f->snaps[k] > f->frame || f->frame > frame)) {
    char file[PATH_CAP];
    snapshot_file(f, f->snaps[k], file, sizeof(file));
    if (load_snapshot(f, file) != 0) {
      return say(f, EXIT_FAIL, "cannot start from the bake's %s: %s", file, f->why);
    }
    if (f->verbose) {
      say(f, 0, "starting from %s", file);
    }
    int rc = apply_antialias(f, b);
    if (rc != 0) {
      return rc;
    }
  }
  if (f->frame > frame) {
    return say(f, EXIT_FAIL, "the scene starts at frame %" PRIu64 ", after this one", f->frame);
  }
  while (f->frame < frame) {
    uint64_t n = frame - f->frame < STEPS_MAX ? frame - f->frame : STEPS_MAX;
    cJSON *p = main_params();
    cJSON_AddNumberToObject(p, "steps", (double)n);
    cJSON *r = NULL;
    if (call(f, "sim.step", p, &r, NULL) != 0) {
      return say(f, EXIT_FAIL, "%s", f->why);
    }
    double now = num_member(r, "frame", -1);
    cJSON_Delete(r);
    if (now <= (double)f->frame) {
      return say(f, EXIT_FAIL, "sim.step: the scene stays at frame %" PRIu64, f->frame);
    }
    f->frame = (uint64_t)now;
  }
  return 0;
}

/* Renders 'frame' into 'path'. Returns 0 or EXIT_FAIL after saying why. */
static int render_frame(farm_t *f, batch_t *b, uint64_t frame, const char *path) {
  int rc = reach_frame(f, b, frame);
  if (rc != 0) {
    return rc;
  }
  volfx_attachment_t att;
  cJSON *r = NULL;
  if (call(f, "render", cJSON_Duplicate(b->render, 1), &r, &att) != 0) {
    return say(f, EXIT_FAIL, "%s", f->why);
  }
  cJSON_Delete(r);
  char why[PATH_CAP + 128];
  if (!bytes_whole(att.data, att.len, b->raw_bytes)) {
    rc = say(f, EXIT_FAIL, "render: %zu bytes of %s that are not a whole frame", att.len,
             att.format);
  } else if (write_atomic(path, att.data, att.len, b->mode, why, sizeof(why)) != 0) {
    rc = say(f, EXIT_FAIL, "%s", why);
  } else {
    b->written++;
    if (f->verbose) {
      say(f, 0, "wrote %s (%zu bytes)", path, att.len);
    }
  }
  volfx_attachment_free(&att);
  return rc;
}

/* Renders every frame of the range that is missing or, with --overwrite, every frame. */
static int batch_frames(farm_t *f, batch_t *b) {
  char path[PATH_CAP];
  for (uint64_t frame = b->first; frame <= b->last; frame += b->step) {
    snprintf(f->where, sizeof(f->where), "frame %" PRIu64 ": ", frame);
    if (stop_signal != 0) {
      return say(f, EXIT_FAIL, "interrupted by %s", signal_name(stop_signal));
    }
    expand_pattern(b->pattern, frame, path, sizeof(path));
    if (!b->overwrite && file_whole(path, b->raw_bytes)) {
      b->skipped++;
      if (f->verbose) {
        say(f, 0, "skipped, %s is complete", path);
      }
      continue;
    }
    int rc = render_frame(f, b, frame, path);
    if (rc != 0) {
      return rc;
    }
  }
  f->where[0] = '\0';
  return 0;
}

/* Starts the server for the batch and renders. Returns an exit status. */
static int batch_run(farm_t *f, batch_t *b, const char *scene, const char *bake_dir) {
  char path[PATH_CAP], dir[PATH_CAP], bad[PATH_CAP];
  uint64_t todo = 0;
  int found = 0;
  for (uint64_t frame = b->first; frame <= b->last && !found; frame += b->step) {
    if (expand_pattern(b->pattern, frame, path, sizeof(path)) != 0) {
      return usage(f, "-o '%s' makes too long a path", b->pattern);
    }
    found = b->overwrite || !file_whole(path, b->raw_bytes);
    todo = frame;
  }
  if (!found) {
    uint64_t n = (b->last - b->first) / b->step + 1;
    printf("volfx batch: nothing left to do: all %" PRIu64 " frames are complete\n", n);
    b->skipped = n;
    return 0;
  }
  int snapshot = is_snapshot(scene);
  char data[PATH_CAP], file[PATH_CAP];
  int rc = locate(f, bake_dir, snapshot ? scene : NULL, data, sizeof(data), file, sizeof(file));
  if (rc != 0) {
    return rc;
  }
  cJSON *manifest = NULL;
  if (bake_dir != NULL && (rc = read_manifest(f, bake_dir, 0, &manifest)) != 0) {
    return rc;
  }
  if (bake_dir != NULL && list_snapshots(f, bake_dir) != 0) {
    cJSON_Delete(manifest);
    return say(f, EXIT_FAIL, "cannot list %s: %s", bake_dir, strerror(errno));
  }
  snprintf(f->where, sizeof(f->where), "frame %" PRIu64 ": ", todo);
  expand_pattern(b->pattern, todo, path, sizeof(path));
  split_path(path, dir, sizeof(dir));
  if (make_dirs(dir, bad, sizeof(bad)) != 0) {
    cJSON_Delete(manifest);
    return say(f, EXIT_FAIL, "cannot write %s: %s: %s", path, bad, strerror(errno));
  }
  if (data[0] == '\0') {
    const char *tmp = getenv("TMPDIR");
    snprintf(f->tmp_data, sizeof(f->tmp_data), "%s/volfx-batch-XXXXXX",
             tmp != NULL && tmp[0] != '\0' ? tmp : "/tmp");
    if (mkdtemp(f->tmp_data) == NULL) {
      f->tmp_data[0] = '\0';
      cJSON_Delete(manifest);
      return say(f, EXIT_FAIL, "cannot make a data directory: %s", strerror(errno));
    }
    snprintf(data, sizeof(data), "%s", f->tmp_data);
  }
  rc = server_start(f, data, snapshot ? "" : scene);
  if (rc == 0 && snapshot && load_snapshot(f, file) != 0) {
    rc = say(f, EXIT_FAIL, "cannot load %s: %s", scene, f->why);
  }
  if (rc == 0) {
    rc = check_scene(f, manifest, bake_dir);
  }
  cJSON_Delete(manifest);
  if (rc == 0) {
    rc = apply_antialias(f, b);
  }
  return rc != 0 ? rc : batch_frames(f, b);
}

int cli_batch(int argc, char **argv) {
  farm_t f = {.cmd = "batch"};
  batch_t b = {0};
  const char *val[A_COUNT] = {0};
  const char *scene = NULL;
  int rc = parse_args(&f, argc, argv, BATCH_OPTS, val, &scene);
  if (rc == 0) {
    rc = batch_options(&f, &b, val);
  }
  if (rc != 0) {
    cJSON_Delete(b.render);
    return rc;
  }
  f.presets = val[A_PRESETS];
  f.device = val[A_DEVICE];
  f.verbose = val[A_VERBOSE] != NULL;
  mode_t mask = umask(0);
  umask(mask);
  b.mode = 0666 & ~mask;
  catch_stop_signals();
  rc = batch_run(&f, &b, scene, val[A_BAKE]);
  cJSON_Delete(b.render);
  if (rc != EXIT_USAGE) {
    printf("volfx batch: %" PRIu64 " frames written, %" PRIu64 " skipped (%" PRIu64 "..%" PRIu64
           ")\n",
           b.written, b.skipped, b.first, b.last);
  }
  return finish(&f, rc);
}

/* ---------------------------------------------------------------------------------------- */
/* volfx bake */

/* Loads the latest snapshot of the bake at or before 'last' that is ahead of the scene, trying
 * older ones when one does not load. Returns the frame loaded, or -1 when none was. */
static int64_t resume_bake(farm_t *f, const char *dir, uint64_t last) {
  for (long k = snapshot_before(f, last); k >= 0; k--) {
    if (f->snaps[k] <= f->frame && f->frame <= last) {
      return -1; /* The scene is there already. */
    }
    char file[PATH_CAP];
    snapshot_file(f, f->snaps[k], file, sizeof(file));
    if (load_snapshot(f, file) == 0) {
      if (f->verbose) {
        say(f, 0, "resuming from %s/%s", dir, strchr(file, '/') + 1);
      }
      return (int64_t)f->frame;
    }
    say(f, 0, "%s/%s does not load (%s); trying an older one", dir, strchr(file, '/') + 1, f->why);
  }
  return -1;
}

/* Runs sim.bake to 'last' and waits for its job to end. Returns an exit status. */
static int bake_job(farm_t *f, const char *dir, uint64_t last, uint64_t every, double *written) {
  cJSON *p = main_params();
  cJSON_AddStringToObject(p, "dir", f->bake_base);
  cJSON_AddNumberToObject(p, "last", (double)last);
  cJSON_AddNumberToObject(p, "every", (double)every);
  cJSON *r = NULL;
  if (call(f, "sim.bake", p, &r, NULL) != 0) {
    return say(f, EXIT_FAIL, "%s", f->why);
  }
  double id = num_member(r, "id", -1);
  cJSON_Delete(r);
  for (;;) {
    if (stop_signal != 0) {
      return say(f, EXIT_FAIL, "interrupted by %s", signal_name(stop_signal));
    }
    cJSON *msg = NULL;
    int rc = volfx_next_notification(f->conn, "job.progress", 500, &msg, NULL);
    if (rc == VOLFX_E_TIMEOUT || rc == VOLFX_E_INTR) {
      continue;
    }
    if (rc != 0) {
      return say(f, EXIT_FAIL, "sim.bake: %s", volfx_strerror(rc));
    }
    const cJSON *jp = cJSON_GetObjectItemCaseSensitive(msg, "params");
    const char *state = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(jp, "state"));
    const char *file = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(jp, "last"));
    const char *why = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(jp, "error"));
    int ours = num_member(jp, "id", -2) == id;
    *written = ours ? num_member(jp, "done", *written) : *written;
    if (ours && f->verbose && file != NULL && file[0] != '\0') {
      const char *slash = strrchr(file, '/');
      say(f, 0, "wrote %s/%s (%.0f of %.0f)", dir, slash != NULL ? slash + 1 : file, *written,
          num_member(jp, "total", 0));
    }
    int ended = ours && (state == NULL || strcmp(state, "running") != 0);
    if (ended) {
      rc = state != NULL && strcmp(state, "done") == 0
               ? 0
               : say(f, EXIT_FAIL, "sim.bake %s%s%s", state != NULL ? state : "ended",
                     why != NULL ? ": " : "", why != NULL ? why : "");
    }
    cJSON_Delete(msg);
    if (ended) {
      return rc;
    }
  }
}

/* Starts the server for the bake, resumes and bakes. Returns an exit status. */
static int bake_run(farm_t *f, const char *scene, const char *dir, uint64_t last, uint64_t every,
                    double *written, uint64_t *from) {
  char bad[PATH_CAP], data[PATH_CAP], file[PATH_CAP];
  if (make_dirs(dir, bad, sizeof(bad)) != 0) {
    return say(f, EXIT_FAIL, "cannot create directory %s: %s", bad, strerror(errno));
  }
  int snapshot = is_snapshot(scene);
  int rc = locate(f, dir, snapshot ? scene : NULL, data, sizeof(data), file, sizeof(file));
  cJSON *manifest = NULL;
  if (rc != 0 || (rc = read_manifest(f, dir, 1, &manifest)) != 0) {
    return rc;
  }
  double had = num_member(manifest, "every", (double)every);
  if (had != (double)every) {
    cJSON_Delete(manifest);
    return say(f, EXIT_FAIL, "bake %s was made every %.0f frames, not %" PRIu64 " (-k)", dir, had,
               every);
  }
  if (list_snapshots(f, dir) != 0) {
    cJSON_Delete(manifest);
    return say(f, EXIT_FAIL, "cannot list %s: %s", dir, strerror(errno));
  }
  rc = server_start(f, data, snapshot ? "" : scene);
  if (rc == 0 && snapshot && load_snapshot(f, file) != 0) {
    rc = say(f, EXIT_FAIL, "cannot load %s: %s", scene, f->why);
  }
  if (rc == 0) {
    rc = check_scene(f, manifest, dir);
  }
  cJSON_Delete(manifest);
  if (rc != 0) {
    return rc;
  }
  int64_t resumed = resume_bake(f, dir, last);
  *from = f->frame;
  if (f->frame > last) {
    return say(f, EXIT_FAIL, "the scene is at frame %" PRIu64 ", after LAST %" PRIu64, f->frame,
               last);
  }
  if (resumed >= 0 && (uint64_t)resumed == last) {
    printf("volfx bake: nothing left to do: %s holds frame %" PRIu64 "\n", dir, last);
    return 0;
  }
  return bake_job(f, dir, last, every, written);
}

int cli_bake(int argc, char **argv) {
  farm_t f = {.cmd = "bake"};
  const char *val[A_COUNT] = {0};
  const char *scene = NULL;
  uint64_t last = 0, every = 24, from = 0;
  int rc = parse_args(&f, argc, argv, BAKE_OPTS, val, &scene);
  if (rc != 0) {
    return rc;
  }
  if (val[A_LAST] == NULL || val[A_OUT] == NULL) {
    return usage(&f, "needs -e LAST and -o DIR%s", NULL);
  }
  if (!parse_u64(val[A_LAST], 0, FRAME_MAX, &last)) {
    return usage(&f, "bad frame number '%s' (a whole number from 0 to 2^53-1)", val[A_LAST]);
  }
  if (val[A_EVERY] != NULL && !parse_u64(val[A_EVERY], 1, FRAME_MAX, &every)) {
    return usage(&f, "bad -k '%s' (frames between snapshots, from 1)", val[A_EVERY]);
  }
  f.presets = val[A_PRESETS];
  f.device = val[A_DEVICE];
  f.verbose = val[A_VERBOSE] != NULL;
  catch_stop_signals();
  double written = 0;
  rc = bake_run(&f, scene, val[A_OUT], last, every, &written, &from);
  if (rc != EXIT_USAGE) {
    printf("volfx bake: %.0f snapshots written to %s (frames %" PRIu64 "..%" PRIu64
           ", every %" PRIu64 ")\n",
           written, val[A_OUT], from, last, every);
  }
  return finish(&f, rc);
}
