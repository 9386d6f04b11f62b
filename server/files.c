/* Whole-file reading and atomic writes (see files.h). */
#include "files.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

/* Reads the regular file open at 'fd' (O_NONBLOCK) and closes it. */
static char *read_fd(int fd, size_t max, size_t *len) {
  if (fd < 0)
    return NULL;
  struct stat st;
  char *text = NULL;
  if (datapath_fd_regular(fd, max, &st) == 0)
    text = datapath_fd_read(fd, (size_t)st.st_size, len);
  int e = errno;
  close(fd);
  errno = e;
  return text;
}

char *files_read(const char *path, size_t max, size_t *len) {
  if (path[0] == '/' && datapath_root() >= 0) {
    const char *name = datapath_relative(path);
    if (name)
      return datapath_read(name, max, len);
  }
  return read_fd(open(path, O_RDONLY | O_NONBLOCK | O_NOCTTY | O_CLOEXEC), max, len);
}

char *files_read_at(int dirfd, const char *name, size_t max, size_t *len) {
  if (strchr(name, '/')) {
    errno = ENOENT;
    return NULL;
  }
  return read_fd(openat(dirfd, name, O_RDONLY | O_NONBLOCK | O_NOCTTY | O_NOFOLLOW | O_CLOEXEC),
                 max, len);
}

int files_write_all(int fd, const void *data, size_t n) {
  const char *p = data;
  while (n > 0) {
    ssize_t w = write(fd, p, n);
    if (w < 0 && errno == EINTR)
      continue;
    if (w <= 0)
      return w < 0 ? errno : EIO;
    p += w;
    n -= (size_t)w;
  }
  return 0;
}

int files_atomic_begin(files_atomic_t *a, const char *name, mode_t mode, const char **step) {
  a->dir = a->fd = -1;
  *step = "open";
  const char *rel = datapath_relative(name), *base;
  if (!rel)
    return EXDEV;
  a->dir = datapath_open_dir(rel, &base);
  if (a->dir < 0)
    return errno;
  int err = 0;
  struct stat st;
  if (snprintf(a->base, sizeof a->base, "%s", base) >= (int)sizeof a->base)
    err = ENAMETOOLONG;
  else if (fstatat(a->dir, base, &st, AT_SYMLINK_NOFOLLOW) == 0 && !S_ISREG(st.st_mode))
    err = S_ISDIR(st.st_mode) ? EISDIR : S_ISLNK(st.st_mode) ? ELOOP : ENODEV;
  if (err) {
    close(a->dir);
    a->dir = -1;
    return err;
  }
  datapath_sweep_beside(a->dir);
  *step = "create";
  for (int tries = 0; tries < 16; tries++) {
    datapath_temp_name(a->tmp);
    /* Created exclusively: an existing file or link of that name is never opened. */
    a->fd = openat(a->dir, a->tmp, O_CREAT | O_EXCL | O_WRONLY | O_NOFOLLOW | O_CLOEXEC, mode);
    if (a->fd >= 0 || errno != EEXIST)
      break;
  }
  if (a->fd < 0 || fchmod(a->fd, mode) != 0) {
    err = errno;
    if (a->fd >= 0) {
      close(a->fd);
      unlinkat(a->dir, a->tmp, 0);
    }
    close(a->dir);
    a->dir = a->fd = -1;
    return err;
  }
  return 0;
}

void files_atomic_abort(files_atomic_t *a) {
  if (a->fd >= 0) {
    close(a->fd);
    unlinkat(a->dir, a->tmp, 0);
  }
  if (a->dir >= 0)
    close(a->dir);
  a->dir = a->fd = -1;
}

int files_atomic_commit(files_atomic_t *a, const char **step) {
  int err = fsync(a->fd) != 0 ? errno : 0;
  if (close(a->fd) != 0 && !err)
    err = errno;
  a->fd = -1;
  if (!err && renameat(a->dir, a->tmp, a->dir, a->base) != 0) {
    err = errno;
    *step = "rename";
  } else if (err) {
    *step = "write";
  }
  if (err) {
    unlinkat(a->dir, a->tmp, 0);
  } else {
    /* The rename is durable once the directory is synced. */
    fsync(a->dir);
  }
  close(a->dir);
  a->dir = -1;
  return err;
}

int files_write_atomic(const char *name, const void *data, size_t n, const char **step) {
  files_atomic_t a;
  int err = files_atomic_begin(&a, name, 0644, step);
  if (err)
    return err;
  err = files_write_all(a.fd, data, n);
  if (err) {
    *step = "write";
    files_atomic_abort(&a);
    return err;
  }
  return files_atomic_commit(&a, step);
}
