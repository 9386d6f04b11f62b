/* Whole-file reading and atomic writes (see files.h). */
#include "files.h"

#include <errno.h>
#include <fcntl.h>
#include <libgen.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

char *files_read(const char *path, size_t max, size_t *len) {
  FILE *f = fopen(path, "rb");
  if (!f)
    return NULL;
  struct stat st;
  if (fstat(fileno(f), &st) != 0 || !S_ISREG(st.st_mode) || (size_t)st.st_size > max) {
    int e = S_ISREG(st.st_mode) ? EFBIG : EISDIR;
    fclose(f);
    errno = e;
    return NULL;
  }
  size_t n = (size_t)st.st_size;
  char *buf = malloc(n + 1);
  if (!buf || fread(buf, 1, n, f) != n) {
    int e = buf ? EIO : ENOMEM;
    free(buf);
    fclose(f);
    errno = e;
    return NULL;
  }
  fclose(f);
  buf[n] = '\0';
  if (len)
    *len = n;
  return buf;
}

int files_temp_beside(const char *path, char *tmp, size_t len, mode_t mode) {
  if ((size_t)snprintf(tmp, len, "%s.tmpXXXXXX", path) >= len) {
    errno = ENAMETOOLONG;
    return -1;
  }
  /* mkostemp opens with O_CREAT | O_EXCL under a random name: a link is not followed. */
  int fd = mkostemp(tmp, O_CLOEXEC);
  if (fd >= 0 && fchmod(fd, mode) != 0) {
    int e = errno;
    close(fd);
    unlink(tmp);
    errno = e;
    return -1;
  }
  return fd;
}

int files_finish_atomic(int fd, const char *tmp, const char *path, const char **step) {
  int err = fsync(fd) != 0 ? errno : 0;
  if (close(fd) != 0 && !err)
    err = errno;
  if (err) {
    *step = "write";
    unlink(tmp);
    return err;
  }
  if (rename(tmp, path) != 0) {
    err = errno;
    *step = "rename";
    unlink(tmp);
    return err;
  }
  /* The rename is durable once the directory is synced. */
  char dir[PATH_MAX];
  snprintf(dir, sizeof dir, "%s", path);
  int dfd = open(dirname(dir), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dfd >= 0) {
    fsync(dfd);
    close(dfd);
  }
  return 0;
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

int files_write_atomic(const char *path, const void *data, size_t n, const char **step) {
  char tmp[PATH_MAX + 32];
  int fd = files_temp_beside(path, tmp, sizeof tmp, 0644);
  if (fd < 0) {
    *step = "create";
    return errno;
  }
  int err = files_write_all(fd, data, n);
  if (err) {
    *step = "write";
    close(fd);
    unlink(tmp);
    return err;
  }
  return files_finish_atomic(fd, tmp, path, step);
}
