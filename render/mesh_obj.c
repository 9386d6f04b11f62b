/*
 * Wavefront OBJ loading for mesh objects, and the reference count that lets scene snapshots
 * share a loaded mesh. Only geometry is read: 'v' records and 'f' records in any of the
 * forms i, i/t, i//n and i/t/n, with negative indices counting back from the latest vertex.
 * Polygons are fanned into triangles; every other record (vt, vn, o, g, s, usemtl, ...) is
 * skipped.
 */
#include <errno.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>
#include <sys/stat.h>

#include "render_scene.h"

#define OBJ_MAX_TRIS (4u << 20) /* Most triangles in one mesh. */

mesh_t *mesh_ref(mesh_t *m) {
  if (m)
    atomic_fetch_add_explicit(&m->refs, 1, memory_order_relaxed);
  return m;
}

void mesh_unref(mesh_t *m) {
  /* The release/acquire pair makes every use by other holders happen before the free. */
  if (m && atomic_fetch_sub_explicit(&m->refs, 1, memory_order_acq_rel) == 1) {
    free(m->tri);
    free(m);
  }
}

/* A growing array of floats. */
typedef struct fvec {
  float *p;
  size_t len, cap;
} fvec_t;

static int fvec_reserve(fvec_t *v, size_t more) {
  if (v->len + more <= v->cap)
    return 0;
  size_t cap = v->cap ? v->cap : 1024;
  while (cap < v->len + more)
    cap *= 2;
  float *p = realloc(v->p, cap * sizeof(float));
  if (p == NULL)
    return -1;
  v->p = p, v->cap = cap;
  return 0;
}

typedef struct parser {
  const char *path;
  int line;
  char *err;
  size_t errlen;
} parser_t;

static void fail(parser_t *ps, const char *fmt, ...) {
  if (ps->err == NULL || ps->errlen == 0)
    return;
  int n = snprintf(ps->err, ps->errlen, "%s:%d: ", ps->path, ps->line);
  if (n < 0 || (size_t)n >= ps->errlen)
    return;
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(ps->err + n, ps->errlen - (size_t)n, fmt, ap);
  va_end(ap);
}

/* Reads the whole file into a NUL-terminated buffer, refusing files over MESH_OBJ_MAX_BYTES. */
static char *read_file(const char *path, size_t *len, char *err, size_t errlen) {
  FILE *f = fopen(path, "rb");
  if (f == NULL) {
    snprintf(err, errlen, "%s: %s", path, strerror(errno));
    return NULL;
  }
  struct stat st;
  if (fstat(fileno(f), &st) != 0 || !S_ISREG(st.st_mode)) {
    snprintf(err, errlen, "%s: not a regular file", path);
    fclose(f);
    return NULL;
  }
  if ((unsigned long long)st.st_size > MESH_OBJ_MAX_BYTES) {
    snprintf(err, errlen, "%s: file is %lld bytes, over the limit of %u", path,
             (long long)st.st_size, MESH_OBJ_MAX_BYTES);
    fclose(f);
    return NULL;
  }
  char *text = malloc((size_t)st.st_size + 1);
  size_t n = text ? fread(text, 1, (size_t)st.st_size, f) : 0;
  if (text == NULL || ferror(f)) {
    snprintf(err, errlen, "%s: %s", path, text ? "read error" : "out of memory");
    free(text);
    fclose(f);
    return NULL;
  }
  fclose(f);
  text[n] = '\0';
  *len = n;
  return text;
}

static int is_space(char c) {
  return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f';
}

/* Parses the rest of a 'v' record: three finite coordinates; a fourth (w) is ignored. */
static int parse_vertex(parser_t *ps, char *p, fvec_t *verts) {
  float xyz[3];
  for (int i = 0; i < 3; i++) {
    char *next;
    xyz[i] = strtof(p, &next);
    if (next == p || !isfinite(xyz[i])) {
      fail(ps, "vertex needs three finite coordinates");
      return -1;
    }
    p = next;
  }
  if (fvec_reserve(verts, 3) != 0) {
    fail(ps, "out of memory");
    return -1;
  }
  memcpy(verts->p + verts->len, xyz, sizeof xyz);
  verts->len += 3;
  return 0;
}

/*
 * Parses the 'f' record at 'p' and appends its triangles (v0, v[i], v[i+1]) to 'tris'. Texture
 * and normal indices are skipped; vertex indices are 1-based or negative (relative).
 */
static int parse_face(parser_t *ps, char *p, const fvec_t *verts, fvec_t *tris) {
  long nverts = (long)(verts->len / 3);
  long first = 0, prev = 0;
  int count = 0;
  for (;;) {
    while (is_space(*p))
      p++;
    if (*p == '\0' || *p == '\n' || *p == '#')
      break;
    char *next;
    errno = 0;
    long idx = strtol(p, &next, 10);
    if (next == p || errno == ERANGE) {
      fail(ps, "bad face vertex \"%.20s\"", p);
      return -1;
    }
    long v = idx > 0 ? idx - 1 : nverts + idx;
    if (idx == 0 || v < 0 || v >= nverts) {
      fail(ps, "vertex index %ld out of range (%ld vertices so far)", idx, nverts);
      return -1;
    }
    /* Skip "/t", "//n" or "/t/n". */
    p = next;
    while (*p == '/' || *p == '-' || *p == '+' || (*p >= '0' && *p <= '9'))
      p++;
    if (*p != '\0' && *p != '\n' && *p != '#' && !is_space(*p)) {
      fail(ps, "bad face vertex near \"%.20s\"", p);
      return -1;
    }
    if (count == 0) {
      first = v;
    } else if (count >= 2) {
      if (tris->len / 9 >= OBJ_MAX_TRIS) {
        fail(ps, "mesh has more than %u triangles", OBJ_MAX_TRIS);
        return -1;
      }
      if (fvec_reserve(tris, 9) != 0) {
        fail(ps, "out of memory");
        return -1;
      }
      float *t = tris->p + tris->len;
      memcpy(t, verts->p + 3 * first, 3 * sizeof(float));
      memcpy(t + 3, verts->p + 3 * prev, 3 * sizeof(float));
      memcpy(t + 6, verts->p + 3 * v, 3 * sizeof(float));
      tris->len += 9;
    }
    prev = v;
    count++;
  }
  if (count < 3) {
    fail(ps, "face needs at least three vertices, has %d", count);
    return -1;
  }
  return 0;
}

mesh_t *mesh_load_obj(const char *path, char *err, size_t errlen) {
  char dummy[1];
  if (err == NULL || errlen == 0)
    err = dummy, errlen = sizeof dummy;
  size_t len;
  char *text = read_file(path, &len, err, errlen);
  if (text == NULL)
    return NULL;
  mesh_t *m = mesh_parse_obj(text, len, path, err, errlen);
  free(text);
  return m;
}

mesh_t *mesh_parse_obj(char *text, size_t len, const char *name, char *err, size_t errlen) {
  char dummy[1];
  if (err == NULL || errlen == 0)
    err = dummy, errlen = sizeof dummy;
  parser_t ps = {.path = name, .line = 0, .err = err, .errlen = errlen};
  fvec_t verts = {0}, tris = {0};
  int rc = 0;
  char *p = text;
  while (rc == 0 && p < text + len) {
    ps.line++;
    char *eol = memchr(p, '\n', (size_t)(text + len - p));
    if (eol)
      *eol = '\0';
    if (memchr(p, '\0', (size_t)((eol ? eol : text + len) - p)) != NULL) {
      fail(&ps, "NUL byte in text");
      rc = -1;
      break;
    }
    char *s = p;
    while (is_space(*s))
      s++;
    if (s[0] == 'v' && is_space(s[1]))
      rc = parse_vertex(&ps, s + 1, &verts);
    else if (s[0] == 'f' && is_space(s[1]))
      rc = parse_face(&ps, s + 1, &verts, &tris);
    p = eol ? eol + 1 : text + len;
  }
  free(verts.p);
  if (rc == 0 && tris.len == 0) {
    snprintf(err, errlen, "%s: no faces", name);
    rc = -1;
  }
  mesh_t *m = rc == 0 ? malloc(sizeof *m) : NULL;
  if (m == NULL) {
    if (rc == 0)
      snprintf(err, errlen, "%s: out of memory", name);
    free(tris.p);
    return NULL;
  }
  atomic_init(&m->refs, 1);
  m->ntri = (uint32_t)(tris.len / 9);
  m->tri = tris.p;
  return m;
}
