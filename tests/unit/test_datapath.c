/*
 * The data directory's files (server/datapath.c, server/files.c): names, opening beneath the
 * directory with openat2 and with the O_NOFOLLOW walk (links inside, links out, a file used as
 * a directory, FIFOs, sizes), directories made, atomic writes, temporary files' names and the
 * sweep of stale ones, and the protocol codes of each error.
 */
#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include "check.h"
#include "datapath.h"
#include "files.h"
#include "proto.h"

static char root[PATH_MAX], outside[PATH_MAX];

static void put(const char *rel, const char *text) {
  char p[PATH_MAX * 2];
  snprintf(p, sizeof p, "%s/%s", root, rel);
  FILE *f = fopen(p, "wb");
  CHECK(f != NULL, "cannot write %s", p);
  if (f) {
    fputs(text, f);
    fclose(f);
  }
}

static void age(const char *rel, long seconds) {
  char p[PATH_MAX * 2];
  snprintf(p, sizeof p, "%s/%s", root, rel);
  struct timespec t[2] = {{time(NULL) - seconds, 0}, {time(NULL) - seconds, 0}};
  CHECK(utimensat(AT_FDCWD, p, t, AT_SYMLINK_NOFOLLOW) == 0, "utimensat %s", p);
}

static int exists(const char *rel) {
  char p[PATH_MAX * 2];
  struct stat st;
  snprintf(p, sizeof p, "%s/%s", root, rel);
  return lstat(p, &st) == 0;
}

/* Reads 'name' beneath the data directory: 0 with 'want' as its text, or the errno. */
static int read_err(const char *name, const char *want) {
  size_t len;
  errno = 0;
  char *text = datapath_read(name, 1 << 20, &len);
  if (!text)
    return errno ? errno : -1;
  int same = want && strcmp(text, want) == 0;
  free(text);
  return same ? 0 : -2;
}

static void names(void) {
  const char *good[] = {"a", "a.snap", "dir/sub/x.json", "x-y_z.1", NULL};
  const char *bad[] = {"",
                       "/etc/passwd",
                       "../x",
                       "a/../b",
                       ".hidden",
                       "a/.b",
                       "a//b",
                       "a/",
                       "bad name",
                       "a\\b",
                       ".volfx-tmp-0123456789abcdef",
                       NULL};
  for (int i = 0; good[i]; i++)
    CHECK(datapath_name_ok(good[i]), "\"%s\" is a good name", good[i]);
  for (int i = 0; bad[i]; i++)
    CHECK(!datapath_name_ok(bad[i]), "\"%s\" is refused", bad[i]);
  char longest[300];
  memset(longest, 'n', 255);
  longest[255] = '\0';
  CHECK(datapath_name_ok(longest), "255 bytes are fine");
  longest[255] = 'n';
  longest[256] = '\0';
  CHECK(!datapath_name_ok(longest), "256 bytes are not");
}

/* The opens, in the mode datapath_init chose ('openat2' 1 when the kernel resolves beneath). */
static void opens(int openat2) {
  const char *mode = openat2 ? "openat2" : "walk";
  CHECK(read_err("a/b/f.txt", "inside") == 0, "%s: a plain file", mode);
  int e = read_err("link_out/x.txt", NULL);
  CHECK(e == EXDEV || e == ELOOP, "%s: an absolute link out is refused (%d)", mode, e);
  e = read_err("rel_out/x.txt", NULL);
  CHECK(e == EXDEV || e == ELOOP, "%s: a relative link out is refused (%d)", mode, e);
  e = read_err("link_file", NULL);
  CHECK(e == EXDEV || e == ELOOP, "%s: a link to a file outside is refused (%d)", mode, e);
  e = read_err("link_in/b/f.txt", "inside");
  CHECK(openat2 ? e == 0 : e == ELOOP, "%s: a link inside (%d)", mode, e);
  CHECK(read_err("file.txt/x", NULL) == ENOTDIR, "%s: a file used as a directory", mode);
  CHECK(read_err("a", NULL) == EISDIR, "%s: a directory", mode);
  CHECK(read_err("fifo", NULL) == ENODEV, "%s: a FIFO, at once", mode);
  CHECK(read_err("missing", NULL) == ENOENT, "%s: a missing file", mode);
  e = datapath_open("../outside/x.txt", O_RDONLY, 0) < 0 ? errno : 0;
  CHECK(e == EXDEV, "%s: '..' out is refused (%d)", mode, e);
  struct stat st;
  errno = 0;
  CHECK(datapath_open_regular("a/b/f.txt", 3, &st) < 0 && errno == EFBIG, "%s: over 'max'", mode);

  /* Directories made beneath, and not through a file. */
  char dir[64];
  snprintf(dir, sizeof dir, "made-%s/x/y", mode);
  CHECK(datapath_mkdirs(dir) == 0, "%s: mkdirs", mode);
  int fd = datapath_open(dir, O_PATH | O_DIRECTORY, 0);
  CHECK(fd >= 0, "%s: the directories exist", mode);
  if (fd >= 0)
    close(fd);
  CHECK(datapath_mkdirs(dir) == 0, "%s: mkdirs again", mode);
  CHECK(datapath_mkdirs("file.txt/x") == ENOTDIR, "%s: mkdirs through a file", mode);
  e = datapath_mkdirs("link_out/new");
  CHECK(e == EXDEV || e == ELOOP, "%s: mkdirs through a link out (%d)", mode, e);

  /* Atomic writes. */
  const char *step = NULL;
  char name[64], abs[PATH_MAX * 2];
  snprintf(name, sizeof name, "a/w-%s.txt", mode);
  CHECK(files_write_atomic(name, "new", 3, &step) == 0, "%s: a write", mode);
  CHECK(read_err(name, "new") == 0, "%s: what was written", mode);
  snprintf(abs, sizeof abs, "%s/%s", root, name);
  CHECK(files_write_atomic(abs, "abs", 3, &step) == 0, "%s: a write by absolute path", mode);
  char *text = files_read(abs, 100, NULL);
  CHECK(text && strcmp(text, "abs") == 0, "%s: files_read of a path inside", mode);
  free(text);
  snprintf(abs, sizeof abs, "%s/x.txt", outside);
  CHECK(files_write_atomic(abs, "no", 2, &step) == EXDEV, "%s: an absolute path outside", mode);
  CHECK(files_write_atomic("a", "no", 2, &step) == EISDIR, "%s: over a directory", mode);
  CHECK(files_write_atomic("link_file", "no", 2, &step) == ELOOP, "%s: over a link", mode);
  e = files_write_atomic("link_out/x.txt", "no", 2, &step);
  CHECK(e == EXDEV || e == ELOOP, "%s: through a link out (%d)", mode, e);
  CHECK(files_write_atomic("nodir/x.txt", "no", 2, &step) == ENOENT, "%s: a missing directory",
        mode);
  CHECK(files_write_atomic("file.txt/x.txt", "no", 2, &step) == ENOTDIR, "%s: under a plain file",
        mode);
  text = files_read(abs, 100, NULL);
  CHECK(text && strcmp(text, "outside") == 0, "%s: nothing was written outside", mode);
  free(text);
}

static void temps(void) {
  char a[DATAPATH_TEMP_SIZE], b[DATAPATH_TEMP_SIZE];
  datapath_temp_name(a);
  datapath_temp_name(b);
  CHECK(datapath_is_temp(a) && datapath_is_temp(b) && strcmp(a, b) != 0, "%s %s", a, b);
  CHECK(strlen(a) == DATAPATH_TEMP_SIZE - 1, "its length");
  CHECK(!datapath_name_ok(a), "no request can name one");
  CHECK(!datapath_is_temp(".volfx-tmp-0123") && !datapath_is_temp(".volfx-tmp-0123456789ABCDEF") &&
            !datapath_is_temp(".volfx-tmp-0123456789abcdefg") && !datapath_is_temp("x.tmp"),
        "other names");

  char dir[PATH_MAX * 2];
  snprintf(dir, sizeof dir, "%s/s", root);
  mkdir(dir, 0755);
  put("s/.volfx-tmp-00000000000000aa", "old");
  age("s/.volfx-tmp-00000000000000aa", 3600);
  put("s/.volfx-tmp-00000000000000bb", "fresh");
  put("s/.volfx-tmp-zz", "other");
  age("s/.volfx-tmp-zz", 3600);
  int fd = datapath_open("s", O_RDONLY | O_DIRECTORY, 0);
  CHECK(fd >= 0, "open s");
  datapath_sweep_beside(fd);
  CHECK(!exists("s/.volfx-tmp-00000000000000aa"), "a stale one is removed");
  CHECK(exists("s/.volfx-tmp-00000000000000bb") && exists("s/.volfx-tmp-zz"), "others stay");
  /* Once a minute at most for one directory. */
  put("s/.volfx-tmp-00000000000000cc", "old");
  age("s/.volfx-tmp-00000000000000cc", 3600);
  datapath_sweep_beside(fd);
  CHECK(exists("s/.volfx-tmp-00000000000000cc"), "not swept twice within a minute");
  CHECK(datapath_sweep(fd, 0) == 1 && !exists("s/.volfx-tmp-00000000000000cc"),
        "datapath_sweep itself always sweeps");
  if (fd >= 0)
    close(fd);
}

static void errors(void) {
  char why[256];
  struct {
    int err, writing, code;
  } cases[] = {{ENOENT, 0, PROTO_E_NOT_FOUND},
               {ENOENT, 1, PROTO_E_NOT_FOUND},
               {ENOTDIR, 0, PROTO_E_INVALID_PARAMS},
               {EISDIR, 1, PROTO_E_INVALID_PARAMS},
               {ENODEV, 0, PROTO_E_INVALID_PARAMS},
               {ELOOP, 0, PROTO_E_INVALID_PARAMS},
               {EXDEV, 1, PROTO_E_INVALID_PARAMS},
               {EFBIG, 0, PROTO_E_INVALID_PARAMS},
               {ENAMETOOLONG, 1, PROTO_E_INVALID_PARAMS},
               {EACCES, 0, PROTO_E_INVALID_PARAMS},
               {ENOSPC, 1, PROTO_E_LIMIT},
               {EIO, 0, PROTO_E_INTERNAL}};
  for (size_t i = 0; i < sizeof cases / sizeof *cases; i++) {
    int code =
        datapath_error(cases[i].err, "x.snap", cases[i].writing, 256u << 20, why, sizeof why);
    CHECK(code == cases[i].code, "errno %d: code %d, want %d", cases[i].err, code, cases[i].code);
    CHECK(strstr(why, "x.snap") && !strstr(why, root), "errno %d: %s", cases[i].err, why);
  }
  datapath_error(EFBIG, "x.snap", 0, 256u << 20, why, sizeof why);
  CHECK(strstr(why, "256 MiB") != NULL, "%s", why);
}

int main(void) {
  char base[] = "/tmp/volfx-datapath-XXXXXX";
  CHECK(mkdtemp(base) != NULL, "mkdtemp");
  snprintf(root, sizeof root, "%s/data", base);
  snprintf(outside, sizeof outside, "%s/outside", base);
  mkdir(root, 0755);
  mkdir(outside, 0755);
  char p[PATH_MAX * 2], q[PATH_MAX * 2];
  snprintf(p, sizeof p, "%s/a", root);
  mkdir(p, 0755);
  snprintf(p, sizeof p, "%s/a/b", root);
  mkdir(p, 0755);
  put("a/b/f.txt", "inside");
  put("file.txt", "plain");
  snprintf(q, sizeof q, "%s/x.txt", outside);
  FILE *f = fopen(q, "w");
  if (f) {
    fputs("outside", f);
    fclose(f);
  }
  snprintf(p, sizeof p, "%s/link_out", root);
  CHECK(symlink(outside, p) == 0, "symlink");
  snprintf(p, sizeof p, "%s/rel_out", root);
  CHECK(symlink("../outside", p) == 0, "symlink");
  snprintf(p, sizeof p, "%s/link_file", root);
  CHECK(symlink(q, p) == 0, "symlink");
  snprintf(p, sizeof p, "%s/link_in", root);
  CHECK(symlink("a", p) == 0, "symlink");
  snprintf(p, sizeof p, "%s/fifo", root);
  CHECK(mkfifo(p, 0644) == 0, "mkfifo");

  names();
  /* With openat2 where the kernel has it, then with the walk. */
  CHECK(datapath_init(root) == 0, "datapath_init");
  int fd = datapath_open(".", O_PATH | O_DIRECTORY, 0);
  CHECK(fd >= 0, "the root opens");
  if (fd >= 0)
    close(fd);
  setenv("VOLFX_NO_OPENAT2", "1", 1);
  CHECK(datapath_init(root) == 0, "datapath_init without openat2");
  opens(0);
  unsetenv("VOLFX_NO_OPENAT2");
  CHECK(datapath_init(root) == 0, "datapath_init");
  /* Whether this kernel resolves beneath: an inside link opens only then. */
  int has = datapath_open("link_in/b/f.txt", O_RDONLY, 0);
  if (has >= 0)
    close(has);
  opens(has >= 0);
  temps();
  errors();
  CHECK(datapath_init(NULL) == 0 && datapath_root() < 0, "no data directory");
  CHECK(datapath_read("a/b/f.txt", 100, NULL) == NULL && errno == ENOENT, "nothing opens");

  char cmd[PATH_MAX * 2 + 16];
  snprintf(cmd, sizeof cmd, "rm -rf '%s'", base);
  if (system(cmd) != 0)
    fprintf(stderr, "could not remove %s\n", base);
  printf("test_datapath: %d checks, %d failed\n", checks, failures);
  return failures ? 1 : 0;
}
