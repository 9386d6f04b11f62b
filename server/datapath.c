/* Confinement of request file names to the data directory (see datapath.h). */
#include "datapath.h"

#include <errno.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

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
