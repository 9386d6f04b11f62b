/*
 * Files of the render-farm commands (farm.h): frame names from #### patterns, frames written
 * whole or not at all, the test of a frame file being complete, and small helpers.
 */
#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <ftw.h>
#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <sys/stat.h>
#include <unistd.h>

#include "farm.h"

static const unsigned char png_signature[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
static const unsigned char png_iend[12] = {0, 0, 0, 0, 'I', 'E', 'N', 'D', 0xae, 0x42, 0x60, 0x82};

/* Parses all of 's' as a whole number from 'min' to 'max'. Returns 1 on success. */
int farm_parse_u64(const char *s, uint64_t min, uint64_t max, uint64_t *out) {
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

/* 1 when 'path' is a snapshot: a file whose first line is a JSON object with "volfx_snapshot". */
int farm_is_snapshot(const char *path) {
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
/* The encoded format a file name's extension names (.png, .jpg or .jpeg, .webp, in any case),
 * or NULL. */
const char *farm_format_of_name(const char *name) {
  static const struct {
    const char *ext, *format;
  } exts[] = {{".png", "png"}, {".jpg", "jpeg"}, {".jpeg", "jpeg"}, {".webp", "webp"}};
  const char *dot = strrchr(name, '.');
  if (dot == NULL || strchr(dot, '/') != NULL) {
    return NULL;
  }
  for (size_t i = 0; i < sizeof exts / sizeof exts[0]; i++) {
    if (strcasecmp(dot, exts[i].ext) == 0) {
      return exts[i].format;
    }
  }
  return NULL;
}

char *farm_read_text(const char *path) {
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
const char *farm_split_path(const char *path, char *dir, size_t cap) {
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
int farm_make_dirs(const char *path, char *bad, size_t cap) {
  char buf[FARM_PATH_CAP];
  if (path[0] == '\0' || snprintf(buf, sizeof(buf), "%s", path) >= (int)sizeof(buf)) {
    snprintf(bad, cap, "%s", path);
    errno = path[0] == '\0' ? ENOENT : ENAMETOOLONG;
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
int farm_write_atomic(const char *path, const void *data, size_t n, mode_t mode, char *why,
                      size_t cap) {
  char dir[FARM_PATH_CAP], tmp[FARM_PATH_CAP], bad[FARM_PATH_CAP];
  const char *base = farm_split_path(path, dir, sizeof(dir));
  if (farm_make_dirs(dir, bad, sizeof(bad)) != 0) {
    farm_text(why, cap, "cannot write %s: %s: %s", path, bad, strerror(errno));
    return -1;
  }
  remove_stale_parts(dir, base);
  if (snprintf(tmp, sizeof(tmp), "%s/.%s.part.XXXXXX", dir, base) >= (int)sizeof(tmp)) {
    farm_text(why, cap, "cannot write %s: %s", path, strerror(ENAMETOOLONG));
    return -1;
  }
  int fd = mkostemp(tmp, O_CLOEXEC);
  if (fd < 0) {
    farm_text(why, cap, "cannot write %s: %s", path, strerror(errno));
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
    farm_text(why, cap, "cannot write %s: %s", path, strerror(err));
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
 * 1 when a file of 'size' bytes that starts with 'head' (12 bytes) and ends with 'tail' (the
 * last 12) is a whole encoded frame: a PNG from its signature to its IEND chunk, a JPEG from its
 * start to its end marker, or a WebP whose RIFF size is the file's.
 */
static int encoded_whole(const unsigned char *head, const unsigned char *tail, size_t size) {
  if (size < 12 + 12)
    return 0;
  if (memcmp(head, png_signature, sizeof(png_signature)) == 0)
    return memcmp(tail, png_iend, sizeof(png_iend)) == 0;
  if (head[0] == 0xff && head[1] == 0xd8 && head[2] == 0xff)
    return tail[10] == 0xff && tail[11] == 0xd9;
  if (memcmp(head, "RIFF", 4) == 0 && memcmp(head + 8, "WEBP", 4) == 0) {
    uint64_t riff = (uint64_t)head[4] | (uint64_t)head[5] << 8 | (uint64_t)head[6] << 16 |
                    (uint64_t)head[7] << 24;
    return riff + 8 == size;
  }
  return 0;
}

/*
 * 1 when 'n' bytes at 'data' are a whole frame: exactly 'raw_bytes' of a raw format, or (with
 * 'raw_bytes' 0) a whole PNG, JPEG or WebP.
 */
int farm_bytes_whole(const unsigned char *data, size_t n, uint64_t raw_bytes) {
  if (raw_bytes > 0) {
    return n == raw_bytes;
  }
  return n >= 24 && encoded_whole(data, data + n - 12, n);
}

/* farm_bytes_whole() for the file at 'path'; 0 when there is none. */
int farm_file_whole(const char *path, uint64_t raw_bytes) {
  int fd = open(path, O_RDONLY | O_CLOEXEC);
  struct stat st;
  if (fd < 0) {
    return 0;
  }
  int whole = 0;
  if (fstat(fd, &st) == 0 && S_ISREG(st.st_mode)) {
    size_t size = (size_t)st.st_size;
    unsigned char head[12], tail[12];
    if (raw_bytes > 0) {
      whole = (uint64_t)st.st_size == raw_bytes;
    } else if (size >= sizeof(head) + sizeof(tail) &&
               pread(fd, head, sizeof(head), 0) == (ssize_t)sizeof(head) &&
               pread(fd, tail, sizeof(tail), st.st_size - 12) == (ssize_t)sizeof(tail)) {
      whole = encoded_whole(head, tail, size);
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
int farm_expand_pattern(const char *pattern, uint64_t frame, char *out, size_t cap) {
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

static int remove_entry(const char *path, const struct stat *st, int kind, struct FTW *ftw) {
  (void)st;
  (void)kind;
  (void)ftw;
  remove(path);
  return 0;
}

void farm_remove_tree(const char *path) {
  nftw(path, remove_entry, 16, FTW_DEPTH | FTW_PHYS);
}
