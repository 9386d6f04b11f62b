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

int files_write_atomic(const char *path, const void *data, size_t n, const char **step) {
  char tmp[PATH_MAX + 32];
  snprintf(tmp, sizeof tmp, "%s.tmp%ld", path, (long)getpid());
  int fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) {
    *step = "create";
    return errno;
  }
  const char *p = data;
  int err = 0;
  while (n > 0 && !err) {
    ssize_t w = write(fd, p, n);
    if (w < 0 && errno == EINTR)
      continue;
    if (w <= 0)
      err = w < 0 ? errno : EIO;
    else {
      p += w;
      n -= (size_t)w;
    }
  }
  if (!err && fsync(fd) != 0)
    err = errno;
  close(fd);
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
