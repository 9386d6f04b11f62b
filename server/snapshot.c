/*
 * scene.save and scene.load: snapshots of a scene in the data directory. A snapshot is one
 * JSON header line, {"volfx_snapshot": 1, "name", "scene": {...}, "sections": [...], "crc32"},
 * followed by the binary sections it lists, each {"name", "bytes", ...} and exactly 'bytes'
 * long, in order: simulation state that is not in the document (the cloud's cells and density,
 * the fluid's particles). "crc32" is a CRC-32 of what a load takes from the file: the header's
 * values (not their spelling) without "name", "crc32" and scene.sim.playing, then every byte
 * after the header line. Files are written atomically (temporary file, fsync, rename, fsync of
 * the directory), opened beneath the data directory (datapath.h), and all file I/O runs on
 * libuv's thread pool, never on the loop thread.
 */
#include <errno.h>
#include <math.h>
#include <limits.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include "datapath.h"
#include "defer.h"
#include "dispatch.h"
#include "files.h"
#include "reserve.h"
#include "snapshot.h"

#define SNAPSHOT_VERSION 1
#define SNAPSHOT_MAX_BYTES (256u << 20)

/* What a snapshot written holds: the header line and references to the state after it. */
struct snapshot_out {
  char *text; /* The header line. */
  size_t len;
  cloud_cells_t *cells; /* NULL: no cloud section. */
  density_grid_t *density;
  particles_t *particles; /* NULL: a fluid section of no particles. */
};

typedef struct snap_work {
  uv_work_t req;
  call_t *call;
  char file[256]; /* The client's name for it, under the data directory. */
  char scene[64];
  int err; /* errno of the failed step, or 0. */
  const char *step;
  snapshot_out_t *out;     /* save: what is written. */
  size_t written;          /* save: the file's size. */
  char data_dir[PATH_MAX]; /* save: for the free-space reserve. */
  uint64_t reserve;        /* save: limits.data_reserve_bytes. */
  char short_of[300];      /* save: why the reserve refused it; "" when it did not. */
  /* load: the bytes read and the sections found in them. */
  char *text;
  size_t len;
  cloud_cells_t *cells;
  density_grid_t *density;
  particles_t *particles; /* NULL: no fluid section. */
  char bad[160];          /* Why the sections are refused, "" when they are fine. */
} snap_work_t;

/* ---- The cloud section: hum, act and cld as packed little-endian 64-bit words (rows of
 * ceil(nx / 64) words, x fastest, then y, then z), then the density as little-endian f32. ---- */

static size_t cloud_section_bytes(const cloud_cells_t *c) {
  return 3 * 8 * (size_t)c->words * c->n[1] * c->n[2] + 4 * cloud_cells_count(c);
}

static void put_le(unsigned char *p, uint64_t v, int n) {
  for (int i = 0; i < n; i++)
    p[i] = (unsigned char)(v >> (8 * i));
}

static uint64_t get_le(const unsigned char *p, int n) {
  uint64_t v = 0;
  for (int i = 0; i < n; i++)
    v |= (uint64_t)p[i] << (8 * i);
  return v;
}

/* Thread pool: the section's bytes, or NULL on OOM. */
static unsigned char *cloud_section(const cloud_cells_t *c, const density_grid_t *d) {
  size_t nw = (size_t)c->words * c->n[1] * c->n[2], n = cloud_cells_count(c);
  unsigned char *buf = malloc(cloud_section_bytes(c)), *p = buf;
  if (!buf)
    return NULL;
  const uint64_t *planes[3] = {c->hum, c->act, c->cld};
  for (int k = 0; k < 3; k++)
    for (size_t i = 0; i < nw; i++, p += 8)
      put_le(p, planes[k][i], 8);
  for (size_t i = 0; i < n; i++, p += 4) {
    uint32_t u;
    memcpy(&u, &d->data[i], 4);
    put_le(p, u, 4);
  }
  return buf;
}

/*
 * Thread pool: the cloud section described by 'sec' from 'bytes' ('len' of them), checked:
 * dims within the largest grid, the byte count, bits beyond nx clear, densities finite and not
 * negative. Fills w->cells and w->density, or w->bad.
 */
static void cloud_unsection(snap_work_t *w, const cJSON *sec, const unsigned char *bytes,
                            size_t len) {
  const cJSON *dims = cJSON_GetObjectItem(sec, "dims");
  const cJSON *step = cJSON_GetObjectItem(sec, "step");
  uint32_t n[3];
  for (int i = 0; i < 3; i++) {
    const cJSON *v = cJSON_GetArrayItem(dims, i);
    if (!cJSON_IsArray(dims) || cJSON_GetArraySize(dims) != 3 || !cJSON_IsNumber(v) ||
        v->valuedouble < 1 || v->valuedouble > CLOUD_MAX_SIDE ||
        v->valuedouble != (uint32_t)v->valuedouble) {
      snprintf(w->bad, sizeof w->bad, "the cloud section's dims are not 3 sides in 1..%d",
               CLOUD_MAX_SIDE);
      return;
    }
    n[i] = (uint32_t)v->valuedouble;
  }
  if (!cJSON_IsNumber(step) || step->valuedouble < 0 || step->valuedouble > 9007199254740992.0) {
    snprintf(w->bad, sizeof w->bad, "the cloud section's step is not a count");
    return;
  }
  /* The byte count first, so that a short file cannot make us allocate a large grid. */
  size_t cells = (size_t)n[0] * n[1] * n[2];
  size_t want = 3 * 8 * (size_t)((n[0] + 63) / 64) * n[1] * n[2] + 4 * cells;
  if (len != want) {
    snprintf(w->bad, sizeof w->bad, "the cloud section has %zu bytes, not %zu", len, want);
    return;
  }
  w->cells = cloud_cells_new(n);
  w->density = density_grid_new(n);
  if (!w->cells || !w->density) {
    snprintf(w->bad, sizeof w->bad, "out of memory for the cloud");
    return;
  }
  w->cells->step = (uint64_t)step->valuedouble;
  size_t W = w->cells->words, rows = (size_t)n[1] * n[2], count = cloud_cells_count(w->cells);
  uint64_t last = n[0] % 64 ? ((uint64_t)1 << (n[0] % 64)) - 1 : ~(uint64_t)0;
  uint64_t *planes[3] = {w->cells->hum, w->cells->act, w->cells->cld};
  const unsigned char *p = bytes;
  for (int k = 0; k < 3; k++)
    for (size_t r = 0; r < rows; r++)
      for (size_t i = 0; i < W; i++, p += 8) {
        uint64_t v = get_le(p, 8);
        if (i == W - 1 && (v & ~last)) {
          snprintf(w->bad, sizeof w->bad, "the cloud section has cells beyond the grid");
          return;
        }
        planes[k][r * W + i] = v;
      }
  for (size_t i = 0; i < count; i++, p += 4) {
    uint32_t u = (uint32_t)get_le(p, 4);
    float x;
    memcpy(&x, &u, 4);
    if (!isfinite(x) || x < 0) {
      snprintf(w->bad, sizeof w->bad, "the cloud section has a density that is %g", x);
      return;
    }
    w->density->data[i] = x;
  }
}

/* ---- The fluid section: 'count' positions, then as many velocities, each x, y, z as
 * little-endian f32 (as fluid.set_particles takes them). ---- */

static size_t fluid_section_bytes(const particles_t *p) {
  return p ? 24 * (size_t)p->count : 0;
}

/* Thread pool: the section's bytes (one byte when there are no particles), or NULL on OOM. */
static unsigned char *fluid_section(const particles_t *p) {
  size_t n = p ? 3 * (size_t)p->count : 0;
  unsigned char *buf = malloc(fluid_section_bytes(p) + 1), *q = buf;
  if (!buf)
    return NULL;
  for (int k = 0; k < 2; k++)
    for (size_t i = 0; i < n; i++, q += 4) {
      uint32_t u;
      memcpy(&u, k ? &p->vel[i] : &p->pos[i], 4);
      put_le(q, u, 4);
    }
  return buf;
}

/* Thread pool: the fluid section described by 'sec', checked: a count the bytes match, every
 * value finite (the bounds are the document's, checked by the commit). Fills w->particles, or
 * w->bad. */
static void fluid_unsection(snap_work_t *w, const cJSON *sec, const unsigned char *bytes,
                            size_t len) {
  const cJSON *count = cJSON_GetObjectItem(sec, "count");
  if (!cJSON_IsNumber(count) || count->valuedouble < 0 || count->valuedouble > UINT32_MAX ||
      count->valuedouble != (uint32_t)count->valuedouble) {
    snprintf(w->bad, sizeof w->bad, "the fluid section's count is not a number of particles");
    return;
  }
  uint32_t n = (uint32_t)count->valuedouble;
  if (len != 24 * (size_t)n) {
    snprintf(w->bad, sizeof w->bad, "the fluid section has %zu bytes, not %zu for %u particles",
             len, 24 * (size_t)n, n);
    return;
  }
  w->particles = particles_new(n);
  if (!w->particles) {
    snprintf(w->bad, sizeof w->bad, "out of memory for %u particles", n);
    return;
  }
  for (size_t i = 0; i < 6 * (size_t)n; i++) {
    uint32_t u = (uint32_t)get_le(bytes + 4 * i, 4);
    float x;
    memcpy(&x, &u, 4);
    if (!isfinite(x)) {
      snprintf(w->bad, sizeof w->bad,
               "the fluid section's particle %zu has a %s that is not finite",
               i % (3 * (size_t)n) / 3, i < 3 * (size_t)n ? "position" : "velocity");
      return;
    }
    (i < 3 * (size_t)n ? w->particles->pos : w->particles->vel)[i % (3 * (size_t)n)] = x;
  }
}

/* ---- The checksum ---- */

/* Where a value lies in the header, for the members the checksum leaves out. */
enum { AT_HEADER, AT_SCENE, AT_SIM, AT_OTHER };

static uLong crc_bytes(uLong crc, const void *p, size_t n) {
  const unsigned char *b = p;
  while (n > 0) { /* zlib takes at most UINT_MAX bytes at once. */
    uInt k = n > UINT_MAX ? UINT_MAX : (uInt)n;
    crc = crc32(crc, b, k);
    b += k;
    n -= k;
  }
  return crc;
}

static uLong crc_string(uLong crc, const char *s) {
  unsigned char len[4];
  size_t n = strlen(s);
  put_le(len, n, 4);
  return crc_bytes(crc_bytes(crc, len, 4), s, n);
}

/*
 * Feeds the JSON value 'v' into 'crc' as its type, member names and order, numbers' bits and
 * strings' bytes: the same for any spelling of the same value (spaces, escapes, exponents), so
 * that writer and reader agree without printing it the same way. 'at' is where 'v' lies:
 * "name" and "crc32" of the header and the scene's sim.playing are left out, being no part of
 * what a load takes from the file.
 */
static uLong crc_json(uLong crc, const cJSON *v, int at) {
  unsigned char tag = (unsigned char)(v->type & 0xff);
  crc = crc_bytes(crc, &tag, 1);
  if (cJSON_IsNumber(v)) {
    double d = v->valuedouble == 0 ? 0 : v->valuedouble; /* -0 and 0 alike. */
    uint64_t bits;
    unsigned char le[8];
    memcpy(&bits, &d, 8);
    put_le(le, bits, 8);
    crc = crc_bytes(crc, le, 8);
  } else if (cJSON_IsString(v)) {
    crc = crc_string(crc, v->valuestring);
  } else if (cJSON_IsArray(v) || cJSON_IsObject(v)) {
    const cJSON *c;
    cJSON_ArrayForEach(c, v) {
      const char *k = cJSON_IsObject(v) ? c->string : NULL;
      if (k && ((at == AT_HEADER && (strcmp(k, "name") == 0 || strcmp(k, "crc32") == 0)) ||
                (at == AT_SIM && strcmp(k, "playing") == 0)))
        continue;
      if (k)
        crc = crc_string(crc, k);
      int next = !k                                           ? AT_OTHER
                 : at == AT_HEADER && strcmp(k, "scene") == 0 ? AT_SCENE
                 : at == AT_SCENE && strcmp(k, "sim") == 0    ? AT_SIM
                                                              : AT_OTHER;
      crc = crc_json(crc, c, next);
    }
    tag = 0xff; /* The end of the container, so that nesting counts. */
    crc = crc_bytes(crc, &tag, 1);
  }
  return crc;
}

/* The members a snapshot header may have. */
static int header_member_ok(const char *k) {
  static const char *const known[] = {"volfx_snapshot", "name", "scene", "sections", "crc32"};
  for (size_t i = 0; i < sizeof known / sizeof *known; i++)
    if (strcmp(k, known[i]) == 0)
      return 1;
  return 0;
}

/*
 * Thread pool: checks the header 'head' of the snapshot whose bytes after the header line are
 * 'rest' ('n' of them): only known members, and a "crc32" that matches, if there is one (older
 * snapshots have none). Returns 0, or -1 with the reason in 'bad'.
 */
static int header_verify(const cJSON *head, const unsigned char *rest, size_t n, char *bad,
                         size_t badlen) {
  const cJSON *m;
  cJSON_ArrayForEach(m, head) {
    if (!header_member_ok(m->string)) {
      snprintf(bad, badlen, "the header has an unknown member \"%.32s\"", m->string);
      return -1;
    }
  }
  const cJSON *sum = cJSON_GetObjectItemCaseSensitive(head, "crc32");
  if (!sum)
    return 0;
  if (!cJSON_IsNumber(sum) || sum->valuedouble < 0 || sum->valuedouble > 4294967295.0 ||
      sum->valuedouble != floor(sum->valuedouble)) {
    snprintf(bad, badlen, "the header's crc32 is not a 32-bit checksum");
    return -1;
  }
  uLong crc = crc_bytes(crc_json(crc32(0, NULL, 0), head, AT_HEADER), rest, n);
  if ((double)crc != sum->valuedouble) {
    snprintf(bad, badlen, "the file is damaged: its checksum is %lu, the header's crc32 says %.0f",
             crc, sum->valuedouble);
    return -1;
  }
  return 0;
}

int snapshot_out_write(snapshot_out_t *o, const char *path, size_t *bytes, const char **step) {
  unsigned char *sec = o->cells ? cloud_section(o->cells, o->density) : NULL;
  unsigned char *fsec = fluid_section(o->particles);
  size_t sec_n = o->cells ? cloud_section_bytes(o->cells) : 0;
  size_t fsec_n = fluid_section_bytes(o->particles);
  /* The checksum is of the header as a reader parses it, so it is parsed here too. */
  cJSON *head = proto_parse(o->text, o->len, NULL, 0);
  char *line = NULL;
  size_t line_len = 0;
  if ((o->cells && !sec) || !fsec || !head || !(line = malloc(o->len + 32))) {
    free(sec);
    free(fsec);
    free(line);
    cJSON_Delete(head);
    *step = "encode";
    return ENOMEM;
  }
  uLong crc = crc_json(crc32(0, NULL, 0), head, AT_HEADER);
  cJSON_Delete(head);
  crc = crc_bytes(crc_bytes(crc, sec, sec_n), fsec, fsec_n);
  /* The header printed ends in "}\n": the checksum goes in as its last member. */
  line_len =
      (size_t)snprintf(line, o->len + 32, "%.*s,\"crc32\":%lu}\n", (int)(o->len - 2), o->text, crc);

  files_atomic_t a;
  int err = files_atomic_begin(&a, path, 0600, step);
  if (!err) {
    err = files_write_all(a.fd, line, line_len);
    if (!err && sec)
      err = files_write_all(a.fd, sec, sec_n);
    if (!err)
      err = files_write_all(a.fd, fsec, fsec_n);
    if (err) {
      *step = "write";
      files_atomic_abort(&a);
    } else {
      err = files_atomic_commit(&a, step);
    }
  }
  free(sec);
  free(fsec);
  free(line);
  if (!err)
    *bytes = line_len + sec_n + fsec_n;
  return err;
}

void snapshot_out_free(snapshot_out_t *o) {
  if (!o)
    return;
  free(o->text);
  cloud_cells_unref(o->cells);
  density_grid_unref(o->density);
  particles_unref(o->particles);
  free(o);
}

snapshot_out_t *snapshot_out_new(const scene_t *s) {
  snapshot_out_t *o = calloc(1, sizeof *o);
  if (!o)
    return NULL;
  cJSON *head = cJSON_CreateObject();
  cJSON_AddNumberToObject(head, "volfx_snapshot", SNAPSHOT_VERSION);
  cJSON_AddStringToObject(head, "name", s->name);
  cJSON_AddItemToObject(head, "scene", cJSON_Duplicate(s->doc, 1));
  cJSON *sections = cJSON_AddArrayToObject(head, "sections");
  if (s->cloud_cells && s->cloud_density) {
    /* The cells and density are immutable: the thread pool reads them through references. */
    o->cells = cloud_cells_ref(s->cloud_cells);
    o->density = density_grid_ref(s->cloud_density);
    cJSON *sec = cJSON_CreateObject();
    cJSON_AddStringToObject(sec, "name", "cloud");
    cJSON_AddNumberToObject(sec, "bytes", (double)cloud_section_bytes(o->cells));
    cJSON *dims = cJSON_AddArrayToObject(sec, "dims");
    for (int i = 0; i < 3; i++)
      cJSON_AddItemToArray(dims, cJSON_CreateNumber(o->cells->n[i]));
    cJSON_AddNumberToObject(sec, "step", (double)o->cells->step);
    cJSON_AddItemToArray(sections, sec);
  }
  /* The particles, also immutable; a section of none says the scene had none. */
  o->particles = particles_ref(s->particles);
  cJSON *fsec = cJSON_CreateObject();
  cJSON_AddStringToObject(fsec, "name", "fluid");
  cJSON_AddNumberToObject(fsec, "bytes", (double)fluid_section_bytes(o->particles));
  cJSON_AddNumberToObject(fsec, "count", o->particles ? o->particles->count : 0);
  cJSON_AddItemToArray(sections, fsec);
  o->text = proto_print_line(head, &o->len);
  cJSON_Delete(head);
  if (!o->text) {
    snapshot_out_free(o);
    return NULL;
  }
  return o;
}

/* Thread pool: writes the snapshot next to its final name, then renames it into place. */
static void save_work(uv_work_t *req) {
  snap_work_t *w = req->data;
  const snapshot_out_t *o = w->out;
  uint64_t bytes =
      o->len + (o->cells ? cloud_section_bytes(o->cells) : 0) + fluid_section_bytes(o->particles);
  if (reserve_check(w->data_dir, bytes, w->reserve, w->short_of, sizeof w->short_of) != 0) {
    w->err = ENOSPC;
    w->step = "reserve";
    return;
  }
  w->err = snapshot_out_write(w->out, w->file, &w->written, &w->step);
}

static void snap_work_free(snap_work_t *w) {
  snapshot_out_free(w->out);
  free(w->text);
  cloud_cells_unref(w->cells);
  density_grid_unref(w->density);
  particles_unref(w->particles);
  free(w);
}

static void save_done(uv_work_t *req, int status) {
  snap_work_t *w = req->data;
  call_t *call = w->call;
  if (status != 0 || w->err) {
    char why[256];
    int code = datapath_error(w->err ? w->err : EIO, w->file, 1, 0, why, sizeof why);
    if (w->short_of[0])
      call_error(call, PROTO_E_LIMIT, "file", "%s: file: %s", proto_err_message(PROTO_E_LIMIT),
                 w->short_of);
    else if (w->step && strcmp(w->step, "encode") == 0)
      call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    else
      call_error(call, code, "file", "%s: file: %s", proto_err_message(code), why);
  } else {
    cJSON *r = cJSON_CreateObject();
    cJSON_AddStringToObject(r, "file", w->file);
    cJSON_AddNumberToObject(r, "bytes", (double)w->written);
    call_result(call, r);
  }
  snap_work_free(w);
}

/* The work of a scene.save or scene.load whose file name passed the loop thread's checks; NULL
 * with the call answered. The file itself is opened on the thread pool. */
static snap_work_t *work_for(call_t *call) {
  const char *file = cJSON_GetStringValue(cJSON_GetObjectItem(call->params, "file"));
  char why[256];
  int code = datapath_check(file, why, sizeof why);
  if (code) {
    call_error(call, code, "file", "%s: file: %s", proto_err_message(code), why);
    return NULL;
  }
  snap_work_t *w = calloc(1, sizeof *w);
  if (!w) {
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return NULL;
  }
  snprintf(w->file, sizeof w->file, "%s", file);
  w->call = call;
  w->req.data = w;
  return w;
}

static void scene_save(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  snap_work_t *w = work_for(call);
  if (!w)
    return;
  w->out = snapshot_out_new(e->scene);
  if (!w->out) {
    snap_work_free(w);
    call_error(call, PROTO_E_INTERNAL, NULL, "internal error: out of memory");
    return;
  }
  snprintf(w->data_dir, sizeof w->data_dir, "%s", call->srv->cfg.data_dir);
  w->reserve = call->srv->cfg.budget.data_reserve_bytes;
  uv_queue_work(call->srv->loop, &w->req, save_work, save_done);
}

/* Thread pool: reads the whole file. */
static void load_work(uv_work_t *req) {
  snap_work_t *w = req->data;
  w->text = datapath_read(w->file, SNAPSHOT_MAX_BYTES, &w->len);
  if (!w->text) {
    w->err = errno;
    w->step = "read";
    return;
  }
  /* The checksum, then the sections after the header line; a bad one is reported by
   * load_done, as is a header that does not parse. */
  char *nl = memchr(w->text, '\n', w->len);
  size_t off = nl ? (size_t)(nl - w->text) + 1 : w->len;
  cJSON *head = proto_parse(w->text, nl ? off - 1 : w->len, NULL, 0);
  if (!head || !cJSON_IsObject(head) ||
      header_verify(head, (const unsigned char *)w->text + off, w->len - off, w->bad,
                    sizeof w->bad) != 0) {
    cJSON_Delete(head);
    return;
  }
  const cJSON *sections = cJSON_GetObjectItem(head, "sections");
  const cJSON *sec;
  cJSON_ArrayForEach(sec, sections) {
    const cJSON *bytes = cJSON_GetObjectItem(sec, "bytes");
    const char *name = cJSON_GetStringValue(cJSON_GetObjectItem(sec, "name"));
    if (!cJSON_IsNumber(bytes) || bytes->valuedouble < 0 || !name ||
        bytes->valuedouble > (double)(w->len - off)) {
      snprintf(w->bad, sizeof w->bad, "a section's size runs past the end of the file");
      break;
    }
    size_t n = (size_t)bytes->valuedouble;
    if (strcmp(name, "cloud") == 0 && !w->cells)
      cloud_unsection(w, sec, (const unsigned char *)w->text + off, n);
    else if (strcmp(name, "fluid") == 0 && !w->particles)
      fluid_unsection(w, sec, (const unsigned char *)w->text + off, n);
    if (w->bad[0])
      break;
    off += n;
  }
  cJSON_Delete(head);
}

/* Whether 'doc' (not yet validated) enables a cloud of the dimensions of 'c'. */
static int cloud_fits(const cJSON *doc, const cloud_cells_t *c) {
  const cJSON *cloud = cJSON_GetObjectItem(doc, "cloud");
  const cJSON *grid = cJSON_GetObjectItem(cloud, "grid");
  if (!cJSON_IsTrue(cJSON_GetObjectItem(cloud, "enabled")) || cJSON_GetArraySize(grid) != 3)
    return 0;
  for (int i = 0; i < 3; i++) {
    const cJSON *v = cJSON_GetArrayItem(grid, i);
    if (!cJSON_IsNumber(v) || v->valuedouble != c->n[i])
      return 0;
  }
  return 1;
}

static void load_done(uv_work_t *req, int status) {
  snap_work_t *w = req->data;
  call_t *call = w->call;
  conn_t *c = call->conn;
  c->refs++; /* Answering the call may drop the last reference of a closed connection. */
  scene_entry_t *e = server_find_scene(call->srv, w->scene);
  char why[256] = "";
  cJSON *head = NULL;
  if (status != 0 || w->err) {
    int code =
        datapath_error(w->err ? w->err : EIO, w->file, 0, SNAPSHOT_MAX_BYTES, why, sizeof why);
    call_error(call, code, "file", "%s: file: %s", proto_err_message(code), why);
  } else if (!e) {
    call_error(call, PROTO_E_NOT_FOUND, "scene", "not found: scene '%s' was deleted", w->scene);
  } else {
    char *nl = memchr(w->text, '\n', w->len);
    head = proto_parse(w->text, nl ? (size_t)(nl - w->text) : w->len, why, sizeof why);
    const cJSON *doc = cJSON_GetObjectItem(head, "scene");
    if (!head || !cJSON_IsNumber(cJSON_GetObjectItem(head, "volfx_snapshot")) ||
        cJSON_GetObjectItem(head, "volfx_snapshot")->valuedouble != SNAPSHOT_VERSION ||
        !cJSON_IsObject(doc)) {
      call_error(call, PROTO_E_INVALID_PARAMS, "file",
                 "invalid params: file: \"%s\" is not a volfx snapshot (version %d)%s%s", w->file,
                 SNAPSHOT_VERSION, why[0] ? ": " : "", why);
    } else if (w->bad[0]) {
      call_error(call, PROTO_E_INVALID_PARAMS, "file", "invalid params: file: \"%s\": %s", w->file,
                 w->bad);
    } else if (w->particles && w->particles->count > call->srv->cfg.limits.particles) {
      call_error(call, PROTO_E_LIMIT, "file",
                 "%s: file: \"%s\" holds %u particles, over limits.particles (%u)",
                 proto_err_message(PROTO_E_LIMIT), w->file, w->particles->count,
                 call->srv->cfg.limits.particles);
    } else if (w->cells && !cloud_fits(doc, w->cells)) {
      call_error(call, PROTO_E_INVALID_PARAMS, "file",
                 "invalid params: file: \"%s\": the cloud section does not match cloud.grid, "
                 "or the cloud is not enabled",
                 w->file);
    } else {
      scene_error_t err = {0};
      defer_want_t want;
      defer_arm(call, &want);
      /* The cells saved take the place of freshly seeded ones (cloud_fits checked their grid). */
      scene_saved_t saved = {w->cells, w->density, w->particles};
      int rc = scene_replace_saved(e->scene, doc, &saved, &err);
      if (defer_check(call, rc, &err, &want)) {
        /* A file the snapshot names is being read: the call runs again after, from the top. */
      } else if (rc != 0) {
        int code = err.code ? err.code : PROTO_E_INVALID_PARAMS;
        call_error(call, code, err.path[0] ? err.path : "file", "%s: snapshot \"%s\": %s",
                   proto_err_message(code), w->file, err.message);
      } else {
        /* Playing is the server's state, not the file's. */
        cJSON *patch = cJSON_CreateObject();
        cJSON_AddBoolToObject(cJSON_AddObjectToObject(patch, "sim"), "playing", e->rate > 0);
        scene_patch(e->scene, patch, &err);
        cJSON_Delete(patch);
        cJSON *r = cJSON_CreateObject();
        cJSON_AddStringToObject(r, "file", w->file);
        cJSON_AddNumberToObject(r, "version", (double)e->scene->version);
        cJSON_AddNumberToObject(r, "frame", scene_frame(e->scene));
        cJSON_AddNumberToObject(r, "time", scene_time(e->scene));
        call_result(call, r);
      }
    }
  }
  cJSON_Delete(head);
  snap_work_free(w);
  conn_release(c);
  conn_unref(c);
}

static void scene_load(call_t *call) {
  scene_entry_t *e = call_scene(call);
  if (!e)
    return;
  snap_work_t *w = work_for(call);
  if (!w)
    return;
  snprintf(w->scene, sizeof w->scene, "%s", e->scene->name);
  /* Later requests of the connection wait for the scene they would see. */
  conn_hold(call->conn);
  uv_queue_work(call->srv->loop, &w->req, load_work, load_done);
}

static const sch_field_t file_params[] = {
    PARAM_SCENE,
    {.name = "file",
     .type = SCH_STRING,
     .desc = "Snapshot file, relative to the data directory (its directory must exist).",
     .max = 255,
     .flags = SCH_REQUIRED},
    {0}};

static const int save_errors[] = {PROTO_E_UNAUTHORIZED, PROTO_E_NOT_FOUND, 0};

const method_t method_scene_save = {
    .name = "scene.save",
    .summary = "Writes a snapshot of the scene (JSON plus binary state) atomically under the "
               "data directory.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = file_params},
    .result = "{file, bytes}",
    .errors = save_errors,
    .handler = scene_save};

const method_t method_scene_load = {
    .name = "scene.load",
    .summary = "Replaces the scene with a snapshot from the data directory; on any error "
               "nothing changes.",
    .params = &(sch_field_t){.type = SCH_OBJECT, .fields = file_params},
    .result = "{file, version, frame, time}",
    .errors = save_errors,
    .handler = scene_load};
