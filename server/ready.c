/* --port-file and --ready-fd: see ready.h. */
#include "ready.h"

#include <errno.h>
#include <fcntl.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "log.h"

static struct {
  char path[1024]; /* The port file; "" when none. */
  char temp[1040]; /* Its temporary file while it is not yet published; "" otherwise. */
  int temp_fd;     /* Open on 'temp' until published; -1 otherwise. */
  int published;   /* 'path' holds this server's port and is removed at the end. */
  int ready_fd;    /* The descriptor to tell; -1 when none or already told. */
} ready = {.temp_fd = -1, .ready_fd = -1};

int ready_prepare(const char *port_file, int ready_fd) {
  if (ready_fd >= 0) {
    int fl = fcntl(ready_fd, F_GETFL);
    if (fl < 0 || (fl & O_ACCMODE) == O_RDONLY) {
      LOG(LOG_ERROR, "server", "--ready-fd %d: %s", ready_fd,
          fl < 0 ? "no such open file descriptor" : "the descriptor is open only for reading");
      return -1;
    }
    /* Whatever volfxd starts must not hold the parent's pipe open. */
    fcntl(ready_fd, F_SETFD, FD_CLOEXEC);
    ready.ready_fd = ready_fd;
  }
  if (!port_file || !port_file[0])
    return 0;
  struct stat st;
  if (stat(port_file, &st) == 0 && S_ISDIR(st.st_mode)) {
    LOG(LOG_ERROR, "server", "cannot write the port file %s: it is a directory", port_file);
    return -1;
  }
  snprintf(ready.path, sizeof ready.path, "%s", port_file);
  snprintf(ready.temp, sizeof ready.temp, "%s.XXXXXX", port_file);
  ready.temp_fd = mkstemp(ready.temp);
  if (ready.temp_fd < 0) {
    LOG(LOG_ERROR, "server", "cannot write the port file %s: %s", port_file, strerror(errno));
    ready.temp[0] = ready.path[0] = '\0';
    return -1;
  }
  fchmod(ready.temp_fd, 0644);
  return 0;
}

/* Writes all of 'text' to 'fd'; 0 or -1 with errno set. */
static int write_all(int fd, const char *text) {
  size_t n = strlen(text), done = 0;
  while (done < n) {
    ssize_t w = write(fd, text + done, n - done);
    if (w < 0 && errno == EINTR)
      continue;
    if (w < 0)
      return -1;
    done += (size_t)w;
  }
  return 0;
}

int ready_publish(const char *host, int port, const char *unix_path) {
  char where[1100];
  if (host)
    snprintf(where, sizeof where, "%d\n%s\n", port, host);
  else
    snprintf(where, sizeof where, "0\nunix:%s\n", unix_path);
  int rc = 0;
  if (ready.temp_fd >= 0) {
    int fd = ready.temp_fd;
    ready.temp_fd = -1;
    int ok = write_all(fd, where) == 0 && fsync(fd) == 0;
    int cause = errno;
    if (close(fd) != 0 && ok)
      ok = 0, cause = errno;
    if (ok && rename(ready.temp, ready.path) != 0)
      ok = 0, cause = errno;
    if (!ok) {
      LOG(LOG_ERROR, "server", "cannot write the port file %s: %s", ready.path, strerror(cause));
      rc = -1;
    } else {
      ready.temp[0] = '\0';
      ready.published = 1;
    }
  }
  if (ready.ready_fd >= 0 && rc == 0) {
    char line[1120];
    if (host)
      snprintf(line, sizeof line, "ready %d %s\n", port, host);
    else
      snprintf(line, sizeof line, "ready 0 unix:%s\n", unix_path);
    if (write_all(ready.ready_fd, line) != 0)
      LOG(LOG_WARN, "server", "--ready-fd %d: %s", ready.ready_fd, strerror(errno));
    close(ready.ready_fd);
    ready.ready_fd = -1;
  }
  return rc;
}

void ready_finish(void) {
  if (ready.temp_fd >= 0) {
    close(ready.temp_fd);
    ready.temp_fd = -1;
  }
  if (ready.temp[0]) {
    unlink(ready.temp);
    ready.temp[0] = '\0';
  }
  if (ready.published) {
    unlink(ready.path);
    ready.published = 0;
  }
  if (ready.ready_fd >= 0) {
    close(ready.ready_fd);
    ready.ready_fd = -1;
  }
}
