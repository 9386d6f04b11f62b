/* The data directory and the files opened beneath it (see datapath.h). */
#include "datapath.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <pthread.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/random.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>
#ifdef SYS_openat2
#include <linux/openat2.h>
#endif

#include "proto.h"

/* Set by datapath_init before any request runs; read by every thread after. */
static int g_root = -1;
static char g_root_path[PATH_MAX];
static int g_openat2; /* 1: the kernel resolves beneath a directory (openat2). */

/* Most directory entries datapath_init's sweep visits, so that a huge tree cannot hold up the
 * start for long; directories written to later are swept then (datapath_sweep_beside). */
#define SWEEP_START_ENTRIES 200000
#define SWEEP_START_DEPTH 16

#ifdef SYS_openat2
static long openat2_beneath(int dirfd, const char *name, int flags, mode_t mode) {
  struct open_how how = {.flags = (uint64_t)(flags | O_CLOEXEC),
                         .mode = flags & (O_CREAT | O_TMPFILE) ? mode : 0,
                         .resolve = RESOLVE_BENEATH | RESOLVE_NO_MAGICLINKS};
  return syscall(SYS_openat2, dirfd, name, &how, sizeof how);
}
#endif

/* datapath_sweep, visiting at most '*budget' entries in all. */
static int sweep(int dirfd, int depth, long *budget) {
  int fd = openat(dirfd, ".", O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  DIR *d = fd >= 0 ? fdopendir(fd) : NULL;
  if (!d) {
    if (fd >= 0)
      close(fd);
    return 0;
  }
  time_t now = time(NULL);
  int removed = 0;
  struct dirent *de;
  while (*budget > 0 && (de = readdir(d))) {
    --*budget;
    const char *name = de->d_name;
    if (datapath_is_temp(name)) {
      struct stat st;
      if (fstatat(fd, name, &st, AT_SYMLINK_NOFOLLOW) == 0 && !S_ISDIR(st.st_mode) &&
          st.st_mtime + DATAPATH_TEMP_STALE_S <= now && unlinkat(fd, name, 0) == 0)
        removed++;
    } else if (depth > 0 && name[0] != '.' && (de->d_type == DT_DIR || de->d_type == DT_UNKNOWN)) {
      int sub = openat(fd, name, O_RDONLY | O_DIRECTORY | O_NOFOLLOW | O_CLOEXEC);
      if (sub >= 0) {
        removed += sweep(sub, depth - 1, budget);
        close(sub);
      }
    }
  }
  closedir(d);
  return removed;
}

int datapath_init(const char *dir) {
  if (g_root >= 0)
    close(g_root);
  g_root = -1;
  g_root_path[0] = '\0';
  if (!dir || !dir[0])
    return 0;
  if (strlen(dir) >= sizeof g_root_path)
    return ENAMETOOLONG;
  int fd = open(dir, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0)
    return errno;
  g_openat2 = 0;
#ifdef SYS_openat2
  /* A kernel before 5.6 answers ENOSYS, and some seccomp filters EPERM. VOLFX_NO_OPENAT2 tries
   * the other way on a kernel that has it. */
  const char *off = getenv("VOLFX_NO_OPENAT2");
  if (!off || !off[0] || strcmp(off, "0") == 0) {
    long probe = openat2_beneath(fd, ".", O_PATH | O_DIRECTORY, 0);
    if (probe >= 0) {
      close((int)probe);
      g_openat2 = 1;
    }
  }
#endif
  g_root = fd;
  snprintf(g_root_path, sizeof g_root_path, "%s", dir);
  /* Strip trailing slashes so that datapath_relative matches "DIR/name". */
  for (size_t n = strlen(g_root_path); n > 1 && g_root_path[n - 1] == '/'; n--)
    g_root_path[n - 1] = '\0';
  long budget = SWEEP_START_ENTRIES;
  sweep(g_root, SWEEP_START_DEPTH, &budget);
  return 0;
}

int datapath_root(void) {
  return g_root;
}

/* Letters, digits, '_', '-', '.', '/'; no empty, "." or ".." component; not absolute; no
 * component starting with '.' (so no hidden or temporary files of ours). */
int datapath_name_ok(const char *name) {
  size_t n = strlen(name);
  if (n == 0 || n > 255 || name[0] == '/' || name[n - 1] == '/')
    return 0;
  const char *p = name;
  while (*p) {
    if (*p == '.' || *p == '/')
      return 0; /* A component starting with '.', or an empty component. */
    while (*p && *p != '/') {
      char c = *p++;
      if (!((c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
            c == '_' || c == '-' || c == '.'))
        return 0;
    }
    if (*p == '/')
      p++;
  }
  return 1;
}

int datapath_check(const char *name, char *why, size_t whylen) {
  if (g_root < 0) {
    snprintf(why, whylen, "files are unavailable: the server was started without --data");
    return PROTO_E_INVALID_PARAMS;
  }
  if (!datapath_name_ok(name)) {
    snprintf(why, whylen,
             "\"%.64s\" must be a relative path inside the data directory of at most 255 bytes: "
             "letters, digits, '_', '-', '.', '/', no component starting with '.'",
             name);
    return PROTO_E_INVALID_PARAMS;
  }
  return 0;
}

const char *datapath_relative(const char *path) {
  if (path[0] != '/')
    return path;
  size_t n = strlen(g_root_path);
  if (n == 0 || strncmp(path, g_root_path, n) != 0 || path[n] != '/' || !path[n + 1])
    return NULL;
  return path + n + 1;
}

/* Without openat2: opens each directory of 'name' with O_NOFOLLOW, then the last component
 * with 'flags' | O_NOFOLLOW. A ".." component is refused, so the walk never leaves the tree. */
static int walk(const char *name, int flags, mode_t mode) {
  char buf[PATH_MAX];
  if (snprintf(buf, sizeof buf, "%s", name) >= (int)sizeof buf) {
    errno = ENAMETOOLONG;
    return -1;
  }
  int cur = g_root, fd = -1;
  char *save, *comp = strtok_r(buf, "/", &save);
  if (!comp)
    comp = ".";
  for (;;) {
    char *next = strtok_r(NULL, "/", &save);
    if (strcmp(comp, "..") == 0) {
      errno = EXDEV;
      break;
    }
    int sub;
    if (next)
      sub = openat(cur, comp, O_PATH | O_DIRECTORY | O_NOFOLLOW | O_CLOEXEC);
    else
      sub = fd = openat(cur, comp, flags | O_NOFOLLOW | O_CLOEXEC, mode);
    if (sub < 0) {
      struct stat st;
      /* A link where a directory should be is refused as a link, not as a file. */
      if (errno == ENOTDIR && fstatat(cur, comp, &st, AT_SYMLINK_NOFOLLOW) == 0 &&
          S_ISLNK(st.st_mode))
        errno = ELOOP;
      break;
    }
    if (!next)
      break;
    if (cur != g_root)
      close(cur);
    cur = sub;
    comp = next;
  }
  int e = errno;
  if (cur != g_root)
    close(cur);
  errno = e;
  return fd;
}

int datapath_open(const char *name, int flags, mode_t mode) {
  if (g_root < 0) {
    errno = ENOENT;
    return -1;
  }
#ifdef SYS_openat2
  if (g_openat2) {
    for (int tries = 0;; tries++) {
      long fd = openat2_beneath(g_root, name, flags, mode);
      /* EAGAIN: a rename raced the resolution of a ".." that a link held; try again. */
      if (fd >= 0 || (errno != EAGAIN && errno != EINTR) || tries >= 16)
        return (int)fd;
    }
  }
#endif
  return walk(name, flags, mode);
}

int datapath_open_dir(const char *name, const char **base) {
  char dir[PATH_MAX];
  const char *slash = strrchr(name, '/');
  *base = slash ? slash + 1 : name;
  if (!**base || strcmp(*base, ".") == 0 || strcmp(*base, "..") == 0) {
    errno = EISDIR;
    return -1;
  }
  if (!slash)
    snprintf(dir, sizeof dir, ".");
  else if ((size_t)(slash - name) >= sizeof dir) {
    errno = ENAMETOOLONG;
    return -1;
  } else
    snprintf(dir, sizeof dir, "%.*s", (int)(slash - name), name);
  return datapath_open(dir, O_RDONLY | O_DIRECTORY, 0);
}

int datapath_fd_regular(int fd, size_t max, struct stat *st) {
  if (fstat(fd, st) != 0)
    return -1;
  if (!S_ISREG(st->st_mode)) {
    errno = S_ISDIR(st->st_mode) ? EISDIR : S_ISLNK(st->st_mode) ? ELOOP : ENODEV;
    return -1;
  }
  if ((uint64_t)st->st_size > (uint64_t)max) {
    errno = EFBIG;
    return -1;
  }
  int fl = fcntl(fd, F_GETFL);
  if (fl < 0 || fcntl(fd, F_SETFL, fl & ~O_NONBLOCK) != 0)
    return -1;
  return 0;
}

int datapath_open_regular(const char *name, size_t max, struct stat *st) {
  int fd = datapath_open(name, O_RDONLY | O_NONBLOCK | O_NOCTTY, 0);
  if (fd >= 0 && datapath_fd_regular(fd, max, st) != 0) {
    int e = errno;
    close(fd);
    errno = e;
    return -1;
  }
  return fd;
}

char *datapath_fd_read(int fd, size_t size, size_t *len) {
  char *buf = malloc(size + 1);
  if (!buf) {
    errno = ENOMEM;
    return NULL;
  }
  size_t got = 0;
  while (got < size) {
    ssize_t r = read(fd, buf + got, size - got);
    if (r < 0 && errno == EINTR)
      continue;
    if (r < 0) {
      int e = errno;
      free(buf);
      errno = e;
      return NULL;
    }
    if (r == 0)
      break; /* Cut short while read: the caller's checks see the bytes there are. */
    got += (size_t)r;
  }
  buf[got] = '\0';
  if (len)
    *len = got;
  return buf;
}

char *datapath_read(const char *name, size_t max, size_t *len) {
  struct stat st;
  int fd = datapath_open_regular(name, max, &st);
  if (fd < 0)
    return NULL;
  char *text = datapath_fd_read(fd, (size_t)st.st_size, len);
  int e = errno;
  close(fd);
  errno = e;
  return text;
}

int datapath_mkdirs(const char *name) {
  char part[PATH_MAX];
  size_t n = strlen(name);
  if (n == 0 || n >= sizeof part)
    return n ? ENAMETOOLONG : EINVAL;
  for (size_t i = 1; i <= n; i++) {
    if (name[i] != '/' && name[i] != '\0')
      continue;
    snprintf(part, sizeof part, "%.*s", (int)i, name);
    int fd = datapath_open(part, O_PATH | O_DIRECTORY, 0);
    if (fd < 0 && errno == ENOENT) {
      const char *base;
      int dir = datapath_open_dir(part, &base);
      if (dir < 0)
        return errno;
      int rc = mkdirat(dir, base, 0755) == 0 || errno == EEXIST ? 0 : errno;
      close(dir);
      if (rc)
        return rc;
      fd = datapath_open(part, O_PATH | O_DIRECTORY, 0);
    }
    if (fd < 0)
      return errno;
    close(fd);
  }
  return 0;
}

int datapath_error(int err, const char *name, int writing, size_t max, char *why, size_t whylen) {
  int code = PROTO_E_INVALID_PARAMS;
  switch (err) {
  case ENOENT:
    code = PROTO_E_NOT_FOUND;
    if (writing)
      snprintf(why, whylen, "the directory of \"%.64s\" does not exist", name);
    else
      snprintf(why, whylen, "\"%.64s\" not found", name);
    break;
  case ENOTDIR:
    snprintf(why, whylen, "\"%.64s\": a component before the last is not a directory", name);
    break;
  case EISDIR:
    snprintf(why, whylen, "\"%.64s\" is a directory", name);
    break;
  case ENODEV:
  case ENXIO:
    snprintf(why, whylen, "\"%.64s\" is not a regular file", name);
    break;
  case EXDEV:
  case ELOOP:
    snprintf(why, whylen,
             "\"%.64s\" is or passes through a link that is not followed (one leading outside "
             "the data directory, absolute, or any where the kernel lacks openat2)",
             name);
    break;
  case ENAMETOOLONG:
    snprintf(why, whylen, "\"%.64s\" is too long", name);
    break;
  case EFBIG:
    snprintf(why, whylen, "\"%.64s\" is larger than %zu MiB", name, max >> 20);
    break;
  case EACCES:
  case EPERM:
  case EROFS:
    snprintf(why, whylen, "\"%.64s\" cannot be %s: %s", name, writing ? "written" : "read",
             strerror(err));
    break;
  case ENOSPC:
  case EDQUOT:
    code = PROTO_E_LIMIT;
    snprintf(why, whylen, "no room to write \"%.64s\": %s", name, strerror(err));
    break;
  default:
    code = PROTO_E_INTERNAL;
    snprintf(why, whylen, "cannot %s \"%.64s\": %s", writing ? "write" : "read", name,
             strerror(err));
  }
  return code;
}

void datapath_temp_name(char *out) {
  static _Atomic uint64_t counter;
  uint64_t r;
  if (getrandom(&r, sizeof r, GRND_NONBLOCK) != (ssize_t)sizeof r) {
    /* No entropy yet: a name still unique to this process, mixed so it is hard to guess. */
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    r = (uint64_t)ts.tv_nsec ^ ((uint64_t)ts.tv_sec << 30) ^ ((uint64_t)getpid() << 40) ^
        ++counter * 0x9e3779b97f4a7c15ull;
    r ^= r >> 31;
    r *= 0xbf58476d1ce4e5b9ull;
    r ^= r >> 29;
  }
  snprintf(out, DATAPATH_TEMP_SIZE, "%s%016llx", DATAPATH_TEMP_PREFIX, (unsigned long long)r);
}

int datapath_is_temp(const char *name) {
  size_t n = sizeof DATAPATH_TEMP_PREFIX - 1;
  if (strncmp(name, DATAPATH_TEMP_PREFIX, n) != 0)
    return 0;
  for (size_t i = 0; i < 16; i++) {
    char c = name[n + i];
    if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f')))
      return 0;
  }
  return name[n + 16] == '\0';
}

int datapath_sweep(int dirfd, int depth) {
  long budget = LONG_MAX;
  return sweep(dirfd, depth, &budget);
}

/* The directories swept lately, so that a job writing thousands of files into one directory
 * reads it once a minute rather than once a file. */
#define SWEPT_SLOTS 64
static struct {
  dev_t dev;
  ino_t ino;
  time_t at;
} g_swept[SWEPT_SLOTS];
static pthread_mutex_t g_swept_lock = PTHREAD_MUTEX_INITIALIZER;

void datapath_sweep_beside(int dirfd) {
  struct stat st;
  if (fstat(dirfd, &st) != 0)
    return;
  time_t now = time(NULL);
  pthread_mutex_lock(&g_swept_lock);
  int slot = 0;
  for (int i = 0; i < SWEPT_SLOTS; i++) {
    if (g_swept[i].at && g_swept[i].dev == st.st_dev && g_swept[i].ino == st.st_ino) {
      slot = i;
      break;
    }
    if (g_swept[i].at < g_swept[slot].at)
      slot = i; /* Otherwise the oldest slot is reused. */
  }
  int due = !(g_swept[slot].dev == st.st_dev && g_swept[slot].ino == st.st_ino &&
              g_swept[slot].at && now - g_swept[slot].at < 60);
  if (due) {
    g_swept[slot].dev = st.st_dev;
    g_swept[slot].ino = st.st_ino;
    g_swept[slot].at = now;
  }
  pthread_mutex_unlock(&g_swept_lock);
  if (due)
    datapath_sweep(dirfd, 0);
}

static int inside(const char *root, const char *path) {
  size_t n = strlen(root);
  return strncmp(path, root, n) == 0 && (path[n] == '/' || path[n] == '\0');
}

int datapath_resolve(const char *data_dir, const char *name, int must_exist, char *out,
                     size_t outlen, char *why, size_t whylen, int *notfound) {
  char root[PATH_MAX], joined[PATH_MAX], real[PATH_MAX];
  if (notfound)
    *notfound = 0;
  if (!data_dir || !data_dir[0]) {
    snprintf(why, whylen, "files are unavailable: the server was started without --data");
    return -1;
  }
  if (!datapath_name_ok(name)) {
    snprintf(why, whylen,
             "\"%.64s\" must be a relative path inside the data directory: letters, digits, "
             "'_', '-', '.', '/', no component starting with '.'",
             name);
    return -1;
  }
  if (!realpath(data_dir, root)) {
    snprintf(why, whylen, "the data directory is missing");
    return -1;
  }
  if (snprintf(joined, sizeof joined, "%s/%s", root, name) >= (int)sizeof joined) {
    snprintf(why, whylen, "\"%.64s\" is too long", name);
    return -1;
  }
  if (must_exist) {
    if (!realpath(joined, real)) {
      if (notfound)
        *notfound = errno == ENOENT;
      snprintf(why, whylen, "\"%.64s\" not found", name);
      return -1;
    }
  } else {
    /* The directory must exist and be inside; the file itself may be new. */
    char dir[PATH_MAX];
    snprintf(dir, sizeof dir, "%s", joined);
    char *slash = strrchr(dir, '/');
    *slash = '\0';
    char realdir[PATH_MAX];
    if (!realpath(dir, realdir)) {
      if (notfound)
        *notfound = errno == ENOENT;
      snprintf(why, whylen, "the directory of \"%.64s\" does not exist", name);
      return -1;
    }
    if (snprintf(real, sizeof real, "%s/%s", realdir, slash + 1) >= (int)sizeof real) {
      snprintf(why, whylen, "\"%.64s\" is too long", name);
      return -1;
    }
    struct stat st;
    if (lstat(real, &st) == 0 && !S_ISREG(st.st_mode)) {
      snprintf(why, whylen, "\"%.64s\" exists and is not a regular file", name);
      return -1;
    }
  }
  if (!inside(root, real)) {
    snprintf(why, whylen, "\"%.64s\" leads outside the data directory", name);
    return -1;
  }
  if (snprintf(out, outlen, "%s", real) >= (int)outlen) {
    snprintf(why, whylen, "\"%.64s\" is too long", name);
    return -1;
  }
  return 0;
}
