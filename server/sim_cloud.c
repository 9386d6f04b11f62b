/*
 * The cloud automaton and its density (sim_cloud.h). A step reads each word of act with its
 * neighbours: the x neighbours are the word shifted by one or two bits, with the bits carried
 * over from the words beside it; the y and z neighbours are the same word of the rows beside
 * it (a zero row outside the grid). So a step costs about twenty word operations per 64 cells.
 * The random draws of the Dobashi rules hash (seed, step, draw, cell), so the result does not
 * depend on the packing, and rows outside every ellipsoid of the supply are skipped.
 *
 * The density is the sum of a separable truncated Gaussian around every cloud cell, in three
 * 1-D passes that skip empty rows: the x pass adds, for each non-zero byte of a row of cells,
 * the kernel summed over that byte's bits (a table); the y pass, plane by plane, and then the z
 * pass, row by row, sum the input rows within reach into four output rows at a time. The loops
 * run over contiguous floats in 16-wide vectors (this file is built with -O3, see
 * server/CMakeLists.txt, and the hot functions for AVX-512 and AVX2 too), and the planes and
 * rows are shared among up to four threads.
 */
#include "sim_cloud.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "parallel.h"
#include "reclaim.h"

#define GOLDEN 0x9E3779B1u

/* The hot loops are built for each vector width (parallel.h). */
#define CLONES PAR_CLONES

cloud_cells_t *cloud_cells_new(const uint32_t n[3]) {
  for (int i = 0; i < 3; i++)
    if (n[i] < 1 || n[i] > CLOUD_MAX_SIDE)
      return NULL;
  cloud_cells_t *c = calloc(1, sizeof *c);
  if (!c)
    return NULL;
  atomic_init(&c->refs, 1);
  memcpy(c->n, n, sizeof c->n);
  c->words = (n[0] + 63) / 64;
  size_t nw = (size_t)c->words * n[1] * n[2];
  c->hum = calloc(3 * nw, sizeof *c->hum);
  if (!c->hum) {
    free(c);
    return NULL;
  }
  c->act = c->hum + nw;
  c->cld = c->act + nw;
  return c;
}

static size_t plane_words(const cloud_cells_t *c) {
  return (size_t)c->words * c->n[1] * c->n[2];
}

cloud_cells_t *cloud_cells_copy(const cloud_cells_t *c) {
  cloud_cells_t *d = cloud_cells_new(c->n);
  if (!d)
    return NULL;
  memcpy(d->hum, c->hum, 3 * plane_words(c) * sizeof *c->hum);
  d->step = c->step;
  return d;
}

cloud_cells_t *cloud_cells_ref(cloud_cells_t *c) {
  if (c)
    atomic_fetch_add(&c->refs, 1);
  return c;
}

void cloud_cells_unref(cloud_cells_t *c) {
  if (c && atomic_fetch_sub(&c->refs, 1) == 1) {
    reclaim_free(c->hum, 3 * plane_words(c) * sizeof *c->hum);
    free(c);
  }
}

size_t cloud_cells_count(const cloud_cells_t *c) {
  return (size_t)c->n[0] * c->n[1] * c->n[2];
}

uint64_t *cloud_cells_plane(const cloud_cells_t *c, cloud_field_t f) {
  return f == CLOUD_HUM ? c->hum : f == CLOUD_ACT ? c->act : c->cld;
}

int cloud_cell(const cloud_cells_t *c, cloud_field_t f, uint32_t x, uint32_t y, uint32_t z) {
  const uint64_t *row = cloud_cells_plane(c, f) + ((size_t)z * c->n[1] + y) * c->words;
  return (int)(row[x / 64] >> (x % 64) & 1);
}

int cloud_cells_any(const cloud_cells_t *c, cloud_field_t f) {
  const uint64_t *p = cloud_cells_plane(c, f);
  uint64_t any = 0;
  for (size_t i = 0, n = plane_words(c); i < n; i++)
    any |= p[i];
  return any != 0;
}

void cloud_cells_export(const cloud_cells_t *c, cloud_field_t f, uint8_t *out) {
  const uint64_t *p = cloud_cells_plane(c, f);
  uint32_t nx = c->n[0];
  size_t rows = (size_t)c->n[1] * c->n[2];
  for (size_t r = 0; r < rows; r++, out += nx) {
    const uint64_t *row = p + r * c->words;
    for (uint32_t x = 0; x < nx; x++)
      out[x] = (uint8_t)(row[x / 64] >> (x % 64) & 1);
  }
}

void cloud_cells_import(cloud_cells_t *c, cloud_field_t f, const uint8_t *in) {
  uint64_t *p = cloud_cells_plane(c, f);
  uint32_t nx = c->n[0];
  size_t rows = (size_t)c->n[1] * c->n[2];
  memset(p, 0, plane_words(c) * sizeof *p);
  for (size_t r = 0; r < rows; r++, in += nx) {
    uint64_t *row = p + r * c->words;
    for (uint32_t x = 0; x < nx; x++)
      row[x / 64] |= (uint64_t)(in[x] != 0) << (x % 64);
  }
}

/* ---- Random draws ---- */

/* A 32-bit finaliser with full avalanche (every input bit flips each output bit with
 * probability close to 1/2); a bijection. */
static inline uint32_t mix32(uint32_t x) {
  x ^= x >> 16;
  x *= 0x7feb352du;
  x ^= x >> 15;
  x *= 0x846ca68bu;
  x ^= x >> 16;
  return x;
}

/* The part of the hash that does not depend on the cell. */
static uint32_t draw_base(uint64_t seed, uint64_t step, uint32_t which) {
  uint32_t h = mix32((uint32_t)seed ^ 0x6a09e667u);
  h = mix32(h ^ (uint32_t)(seed >> 32));
  h = mix32(h ^ (uint32_t)step);
  h = mix32(h ^ (uint32_t)(step >> 32));
  return mix32(h ^ (which * 0x85ebca6bu + 0x27d4eb2fu));
}

static inline uint32_t cell_hash(uint32_t base, uint32_t cell) {
  return mix32((cell * GOLDEN) ^ base);
}

uint32_t cloud_hash(uint64_t seed, uint64_t step, uint32_t which, uint32_t cell) {
  return cell_hash(draw_base(seed, step, which), cell);
}

uint64_t cloud_threshold(double p) {
  if (!(p > 0))
    return 0;
  if (p >= 1)
    return (uint64_t)1 << 32;
  return (uint64_t)floor(p * 4294967296.0);
}

/* 1 - q² of ellipsoid 'e' at (x, y, z); negative outside. */
static double ellipsoid_inside(const cloud_ellipsoid_t *e, double x, double y, double z) {
  double dx = (x - e->center[0]) / e->radii[0];
  double dy = (y - e->center[1]) / e->radii[1];
  double dz = (z - e->center[2]) / e->radii[2];
  return 1.0 - (dx * dx + dy * dy + dz * dz);
}

double cloud_shape(const cloud_params_t *p, double x, double y, double z) {
  if (p->nellipsoids <= 0)
    return 1.0;
  double best = 0;
  for (int i = 0; i < p->nellipsoids && i < CLOUD_MAX_ELLIPSOIDS; i++) {
    double v = ellipsoid_inside(&p->ellipsoids[i], x, y, z);
    if (v > best)
      best = v;
  }
  return best;
}

/*
 * cloud_shape(p, x, y, z) for x in [0, nx) into s: the same operations on the same values, to
 * the last bit (this file is built without contracting a * b + c into fused multiply-adds),
 * with each ellipsoid's y and z terms computed once for the row and the ellipsoids that miss
 * the row skipped (there dx² + dy² + dz² >= dy² + dz² >= 1, rounding being monotonic).
 */
static void row_shape(const cloud_params_t *p, uint32_t nx, double y, double z, double *s) {
  for (uint32_t x = 0; x < nx; x++)
    s[x] = 0;
  for (int i = 0; i < p->nellipsoids && i < CLOUD_MAX_ELLIPSOIDS; i++) {
    const cloud_ellipsoid_t *e = &p->ellipsoids[i];
    double dy = (y - e->center[1]) / e->radii[1];
    double dz = (z - e->center[2]) / e->radii[2];
    double dyy = dy * dy, dzz = dz * dz;
    if (!(dyy + dzz < 1))
      continue;
    for (uint32_t x = 0; x < nx; x++) {
      double dx = (x - e->center[0]) / e->radii[0];
      double v = 1.0 - (dx * dx + dyy + dzz);
      s[x] = v > s[x] ? v : s[x];
    }
  }
}

/* Whether row (y, z) passes through any ellipsoid (or there are none). */
static int row_in_shape(const cloud_params_t *p, double y, double z) {
  if (p->nellipsoids <= 0)
    return 1;
  for (int i = 0; i < p->nellipsoids && i < CLOUD_MAX_ELLIPSOIDS; i++) {
    const cloud_ellipsoid_t *e = &p->ellipsoids[i];
    double dy = (y - e->center[1]) / e->radii[1];
    double dz = (z - e->center[2]) / e->radii[2];
    if (dy * dy + dz * dz < 1)
      return 1;
  }
  return 0;
}

/*
 * The mask of the cells of word 'w' of row (y, z) that take an event of probability 'prob'
 * (times the shape when 'shaped'), drawing from 'base'.
 */
static inline uint64_t draw_mask(const cloud_cells_t *c, uint32_t base, double prob, uint64_t thr,
                                 const double *shape, uint32_t w, uint32_t y, uint32_t z) {
  uint32_t x0 = w * 64, nx = c->n[0];
  uint32_t nb = nx - x0 < 64 ? nx - x0 : 64;
  uint32_t cell0 = x0 + nx * (y + c->n[1] * z);
  uint64_t m = 0;
  if (!shape) {
    if (thr > UINT32_MAX)
      return nb == 64 ? ~(uint64_t)0 : ((uint64_t)1 << nb) - 1;
    /* Hashes and compares of 64 cells as one vector loop, then the 0/1 bytes packed eight at
     * a time: (v × 0x0102040810204080) >> 56 gathers byte i's low bit into bit i. */
    uint8_t hit[64];
    uint32_t t32 = (uint32_t)thr;
    for (uint32_t b = 0; b < 64; b++)
      hit[b] = cell_hash(base, cell0 + b) < t32;
    for (uint32_t g = 0; g < 8; g++) {
      uint64_t v;
      memcpy(&v, hit + 8 * g, 8);
      m |= ((v * 0x0102040810204080ull) >> 56) << (8 * g);
    }
    return nb == 64 ? m : m & (((uint64_t)1 << nb) - 1);
  }
  for (uint32_t b = 0; b < nb; b++) {
    double s = shape[x0 + b];
    if (s > 0 && (uint64_t)cell_hash(base, cell0 + b) < cloud_threshold(prob * s))
      m |= (uint64_t)1 << b;
  }
  return m;
}

/* The seeding of cloud_cells_seed, built for each vector width (CLONES). */
CLONES static void seed_cells(cloud_cells_t *c, const cloud_params_t *p, double hum, double act) {
  uint32_t bh = draw_base(p->seed, 0, CLOUD_DRAW_INIT_HUM);
  uint32_t ba = draw_base(p->seed, 0, CLOUD_DRAW_INIT_ACT);
  uint64_t th = cloud_threshold(hum), ta = cloud_threshold(act);
  uint32_t nx = c->n[0];
  for (uint32_t z = 0; z < c->n[2]; z++)
    for (uint32_t y = 0; y < c->n[1]; y++) {
      if (!row_in_shape(p, y, z))
        continue;
      size_t r = ((size_t)z * c->n[1] + y) * c->words;
      for (uint32_t w = 0; w < c->words; w++) {
        uint32_t nb = nx - w * 64 < 64 ? nx - w * 64 : 64;
        uint64_t inside = nb == 64 ? ~(uint64_t)0 : ((uint64_t)1 << nb) - 1;
        if (p->nellipsoids > 0) {
          inside = 0;
          for (uint32_t b = 0; b < nb; b++)
            if (cloud_shape(p, w * 64 + b, y, z) > 0)
              inside |= (uint64_t)1 << b;
        }
        if (!inside || !th)
          continue;
        uint64_t h = inside & draw_mask(c, bh, hum, th, NULL, w, y, z);
        c->hum[r + w] = h;
        c->act[r + w] = h && ta ? h & draw_mask(c, ba, act, ta, NULL, w, y, z) : 0;
      }
    }
}

void cloud_cells_seed(cloud_cells_t *c, const cloud_params_t *p, double hum, double act) {
  memset(c->hum, 0, 3 * plane_words(c) * sizeof *c->hum);
  c->step = 0;
  seed_cells(c, p, hum, act);
}

/* ---- The step ---- */

/* The bits of word 'w' of a row that are cells (x < nx). */
static uint64_t valid(uint32_t nx, uint32_t w) {
  uint32_t nb = nx - w * 64;
  return nb >= 64 ? ~(uint64_t)0 : ((uint64_t)1 << nb) - 1;
}

/* Moves row 'row' ('words' words, 'nx' cells) by 's' cells along x: new[x] = old[x - s]. */
static void shift_row(uint64_t *row, uint32_t words, uint32_t nx, long s) {
  if (s == 0)
    return;
  long W = words;
  if (s >= (long)nx || -s >= (long)nx) {
    memset(row, 0, (size_t)words * sizeof *row);
    return;
  }
  if (s > 0) {
    long q = s / 64;
    int r = (int)(s % 64);
    for (long w = W - 1; w >= 0; w--) {
      long src = w - q;
      uint64_t v = src >= 0 ? row[src] << r : 0;
      if (r && src - 1 >= 0)
        v |= row[src - 1] >> (64 - r);
      row[w] = v;
    }
  } else {
    long t = -s, q = t / 64;
    int r = (int)(t % 64);
    for (long w = 0; w < W; w++) {
      long src = w + q;
      uint64_t v = src < W ? row[src] >> r : 0;
      if (r && src + 1 < W)
        v |= row[src + 1] << (64 - r);
      row[w] = v;
    }
  }
  if (nx % 64)
    row[W - 1] &= ((uint64_t)1 << (nx % 64)) - 1;
}

/* The growth rules on every word of planes [z0, z1): out from in. */
static void grow(const cloud_cells_t *in, cloud_cells_t *out, uint32_t z0, uint32_t z1) {
  uint32_t W = in->words, ny = in->n[1], nz = in->n[2];
  uint64_t zero[CLOUD_MAX_SIDE / 64] = {0};
  size_t zs = (size_t)W * ny; /* Words per z plane. */
  for (uint32_t z = z0; z < z1; z++)
    for (uint32_t y = 0; y < ny; y++) {
      size_t r = (size_t)z * zs + (size_t)y * W;
      const uint64_t *a = in->act + r;
      const uint64_t *ym1 = y >= 1 ? a - W : zero, *ym2 = y >= 2 ? a - 2 * W : zero;
      const uint64_t *yp1 = y + 1 < ny ? a + W : zero;
      const uint64_t *zm1 = z >= 1 ? a - zs : zero, *zm2 = z >= 2 ? a - 2 * zs : zero;
      const uint64_t *zp1 = z + 1 < nz ? a + zs : zero;
      const uint64_t *h = in->hum + r, *cl = in->cld + r;
      uint64_t *oh = out->hum + r, *oa = out->act + r, *oc = out->cld + r;
      for (uint32_t w = 0; w < W; w++) {
        uint64_t v = a[w];
        uint64_t prev = w > 0 ? a[w - 1] : 0, next = w + 1 < W ? a[w + 1] : 0;
        uint64_t f = (v << 1 | prev >> 63) | (v << 2 | prev >> 62) | (v >> 1 | next << 63) |
                     ym1[w] | ym2[w] | yp1[w] | zm1[w] | zm2[w] | zp1[w];
        oc[w] = cl[w] | v;
        oh[w] = h[w] & ~v;
        oa[w] = ~v & h[w] & f;
      }
    }
}

/* The Dobashi part of a step on planes [z0, z1): draws on 'out', grown from 'in', then the
 * wind. */
CLONES static void dobashi(const cloud_cells_t *in, cloud_cells_t *out, const cloud_params_t *p,
                           uint32_t z0, uint32_t z1) {
  uint32_t W = in->words, ny = in->n[1], nx = in->n[0];
  uint64_t te = cloud_threshold(p->p_ext), th = cloud_threshold(p->p_hum);
  uint64_t ta = cloud_threshold(p->p_act);
  uint32_t be = draw_base(p->seed, in->step, CLOUD_DRAW_EXT);
  uint32_t bh = draw_base(p->seed, in->step, CLOUD_DRAW_HUM);
  uint32_t ba = draw_base(p->seed, in->step, CLOUD_DRAW_ACT);
  int shaped = p->nellipsoids > 0;
  double srow[CLOUD_MAX_SIDE]; /* The shape along the row, when shaped. */
  long shift = cloud_wind_shift(p, in->step, in->step + 1);
  for (uint32_t z = z0; z < z1; z++)
    for (uint32_t y = 0; y < ny; y++) {
      size_t r = ((size_t)z * ny + y) * W;
      int supply = row_in_shape(p, y, z);
      const double *shape = NULL;
      if (shaped && supply && (th || ta)) {
        row_shape(p, nx, y, z, srow);
        shape = srow;
      }
      for (uint32_t w = 0; w < W; w++) {
        /* Draws that could change nothing are skipped: no cloud to clear, all humid. */
        if (te && out->cld[r + w])
          out->cld[r + w] &= ~draw_mask(in, be, p->p_ext, te, NULL, w, y, z);
        if (supply && th && ~out->hum[r + w] & valid(nx, w))
          out->hum[r + w] |= draw_mask(in, bh, p->p_hum, th, shape, w, y, z);
        if (supply && ta)
          out->act[r + w] |= draw_mask(in, ba, p->p_act, ta, shape, w, y, z);
      }
      if (shift) {
        shift_row(out->hum + r, W, nx, shift);
        shift_row(out->act + r, W, nx, shift);
        shift_row(out->cld + r, W, nx, shift);
      }
    }
}

/* One thread's planes of a step. Every row is stepped on its own (its growth reads 'in' only,
 * its draws hash its own cells, the wind shifts it along x), so planes split freely. */
typedef struct step_part {
  const cloud_cells_t *in;
  cloud_cells_t *out;
  const cloud_params_t *p;
  uint32_t z0, z1;
} step_part_t;

static void *step_planes(void *arg) {
  step_part_t *sp = arg;
  grow(sp->in, sp->out, sp->z0, sp->z1);
  if (sp->p->rules == CLOUD_DOBASHI)
    dobashi(sp->in, sp->out, sp->p, sp->z0, sp->z1);
  return NULL;
}

void cloud_step(const cloud_cells_t *in, cloud_cells_t *out, const cloud_params_t *p) {
  uint32_t nz = in->n[2];
  /* On a thread per core where that pays: a Dobashi step (hashes and shapes per cell) from
   * 64³, 0.4 ms there on one core; the bit-parallel Kuromiya step from 128³. */
  size_t cells = (size_t)in->n[0] * in->n[1] * nz;
  int n = par_parts(p->rules == CLOUD_DOBASHI ? cells * 8 : cells, (size_t)1 << 21);
  if (nz < (uint32_t)n)
    n = 1;
  step_part_t parts[PAR_MAX];
  for (int i = 0; i < n; i++)
    parts[i] = (step_part_t){in, out, p, (uint32_t)((uint64_t)nz * i / n),
                             (uint32_t)((uint64_t)nz * (i + 1) / n)};
  par_run(step_planes, parts, sizeof *parts, n);
  out->step = in->step + 1;
}

/* ---- Density ---- */

int cloud_kernel_half(double r) {
  if (!(r >= 1))
    return 0;
  return r > CLOUD_MAX_RADIUS ? CLOUD_MAX_RADIUS : (int)floor(r);
}

int cloud_kernel(double r, float *w) {
  int K = cloud_kernel_half(r);
  if (K == 0) {
    w[0] = 1;
    return 0;
  }
  double sigma = r / 3, sum = 0, tmp[2 * CLOUD_MAX_RADIUS + 1];
  for (int d = -K; d <= K; d++)
    sum += tmp[d + K] = exp(-(double)d * d / (2 * sigma * sigma));
  for (int i = 0; i <= 2 * K; i++)
    w[i] = (float)(tmp[i] / sum);
  return K;
}

/* y += a × x over 'n' floats. */
static inline void axpy(float *restrict y, float a, const float *restrict x, uint32_t n) {
  for (uint32_t i = 0; i < n; i++)
    y[i] += a * x[i];
}

/* Sixteen floats as one value (one AVX-512 register; two or four narrower ones elsewhere). */
typedef float v16 __attribute__((vector_size(64)));

/*
 * o[j] = the sum over k < 'm' of wk[k][j] × src[k], for the four output rows j, over 'n'
 * floats. Four neighbouring outputs of a 1-D pass read almost the same source rows, so each
 * source vector is loaded once for all four, and the sums stay in registers until written.
 */
__attribute__((always_inline)) static inline void gather4(float *const *o, const float *const *src,
                                                          const float (*wk)[4], int m, uint32_t n) {
  uint32_t i = 0;
  for (; i + 16 <= n; i += 16) {
    v16 a0 = {0}, a1 = {0}, a2 = {0}, a3 = {0};
    for (int k = 0; k < m; k++) {
      v16 x;
      memcpy(&x, src[k] + i, sizeof x);
      a0 += wk[k][0] * x;
      a1 += wk[k][1] * x;
      a2 += wk[k][2] * x;
      a3 += wk[k][3] * x;
    }
    memcpy(o[0] + i, &a0, sizeof a0);
    memcpy(o[1] + i, &a1, sizeof a1);
    memcpy(o[2] + i, &a2, sizeof a2);
    memcpy(o[3] + i, &a3, sizeof a3);
  }
  for (; i < n; i++)
    for (int j = 0; j < 4; j++) {
      float a = 0;
      for (int k = 0; k < m; k++)
        a += wk[k][j] * src[k][i];
      o[j][i] = a;
    }
}

/*
 * One 1-D pass across rows: output row t (at out + t × 'ostride') is the sum over input rows u
 * within K of t (at in + u × 'istride') whose flag fin[u × 'fstride'] is set, weighted by
 * w[u - t + K]; 'count' rows, each 'nx' floats. Sets fout[t] (when not NULL) to whether row t
 * got anything; rows that got nothing are written as zeros only when 'fout' is NULL. 'dummy'
 * (nx floats) takes the outputs past the last row.
 */
__attribute__((always_inline)) static inline void
pass_rows(float *out, size_t ostride, const float *in, size_t istride, const uint8_t *fin,
          size_t fstride, uint8_t *fout, uint32_t count, const float *w, int K, uint32_t nx,
          float *dummy) {
  const float *src[2 * CLOUD_MAX_RADIUS + 4];
  float wk[2 * CLOUD_MAX_RADIUS + 4][4];
  for (uint32_t t = 0; t < count; t += 4) {
    long lo = (long)t - K < 0 ? 0 : (long)t - K;
    long hi = (long)t + 3 + K >= (long)count ? (long)count - 1 : (long)t + 3 + K;
    int m = 0, got[4] = {0, 0, 0, 0};
    for (long u = lo; u <= hi; u++) {
      if (!fin[(size_t)u * fstride])
        continue;
      src[m] = in + (size_t)u * istride;
      for (int j = 0; j < 4; j++) {
        long d = u - ((long)t + j);
        int inside = d >= -K && d <= K && t + j < count;
        wk[m][j] = inside ? w[d + K] : 0;
        got[j] |= inside;
      }
      m++;
    }
    float *o[4];
    for (int j = 0; j < 4; j++) {
      o[j] = t + j < count ? out + (size_t)(t + j) * ostride : dummy;
      if (fout && t + j < count)
        fout[t + j] = (uint8_t)got[j];
    }
    if (m)
      gather4(o, src, (const float(*)[4])wk, m, nx);
    else if (!fout)
      for (int j = 0; j < 4; j++)
        memset(o[j], 0, nx * sizeof *o[j]);
  }
}

/*
 * The x pass reads the cells a byte at a time: 'tab' holds, for each of the 256 bytes, the
 * kernel summed over its set bits, TAB_W(K) floats from 8 p - K for the byte of cells 8 p ..
 * 8 p + 7, so a byte costs one short vector add however many cells it holds.
 */
#define TAB_W(K) ((8 + 2 * (uint32_t)(K) + 15) / 16 * 16)

static void x_table(const float *w, int K, float *tab) {
  uint32_t tw = TAB_W(K);
  for (uint32_t v = 0; v < 256; v++) {
    float *t = tab + v * tw;
    memset(t, 0, tw * sizeof *t);
    for (int b = 0; b < 8; b++)
      if (v >> b & 1)
        for (int j = 0; j <= 2 * K; j++)
          t[b + j] += w[j];
  }
}

/* The passes over one z plane 'z' with cloud cells: x then y into 'b', flags in 'fb'. Returns
 * whether any row of 'b' is non-empty. */
CLONES static int plane_xy(const cloud_cells_t *c, uint32_t z, const float *restrict w, int K,
                           const float *restrict tab, float *restrict a, float *restrict b,
                           float *restrict row, uint8_t *restrict fa, uint8_t *restrict fb) {
  uint32_t nx = c->n[0], ny = c->n[1], W = c->words, tw = TAB_W(K);
  int any = 0;
  for (uint32_t y = 0; y < ny; y++) {
    const uint64_t *bits = c->cld + ((size_t)z * ny + y) * W;
    uint64_t set = 0;
    for (uint32_t i = 0; i < W; i++)
      set |= bits[i];
    fa[y] = set != 0;
    if (!set)
      continue;
    /* 'row' starts K cells before x = 0 and reaches past the last byte's reach. */
    memset(row, 0, ((size_t)W * 64 + tw) * sizeof *row);
    for (uint32_t i = 0; i < W; i++) {
      if (!bits[i])
        continue;
      for (uint32_t p = 0; p < 8; p++) {
        uint32_t v = (uint32_t)(bits[i] >> (8 * p)) & 255;
        if (v)
          axpy(row + i * 64 + 8 * p, 1.0f, tab + v * tw, tw);
      }
    }
    memcpy(a + (size_t)y * nx, row + K, nx * sizeof *row);
  }
  for (uint32_t y = 0; y < ny; y++)
    any |= fa[y];
  if (any)
    pass_rows(b, nx, a, nx, fa, 1, fb, ny, w, K, nx, row);
  else
    memset(fb, 0, ny);
  return any;
}

/* The planes after the y pass lie this many floats apart: one cache line more than a plane, so
 * that the same row of successive planes, which the z pass reads together, does not fall into
 * one cache set when a plane is a power of two bytes. */
#define BSTRIDE(plane) ((plane) + 16)

/* The z pass into output rows (t, y) for every t and y0 <= y < y1: the sum over the planes z within
 * reach of w × b[z] row y, over the rows flagged in 'fb' (ny flags per plane). Row y of every plane
 * is handled together so that the 2K + 1 rows read for each output row stay in cache. */
CLONES static void pass_z(const cloud_cells_t *c, const float *restrict w, int K,
                          const float *restrict b, const uint8_t *restrict fb, float *restrict out,
                          uint32_t y0, uint32_t y1, float *dummy) {
  uint32_t nx = c->n[0], ny = c->n[1], nz = c->n[2];
  size_t plane = (size_t)nx * ny;
  for (uint32_t y = y0; y < y1; y++)
    pass_rows(out + (size_t)y * nx, plane, b + (size_t)y * nx, BSTRIDE(plane), fb + y, ny, NULL, nz,
              w, K, nx, dummy);
}

/* One thread's share of the density: planes [z0, z1) through the x and y passes, then, after
 * every thread is done with those, rows [y0, y1) through the z pass. */
typedef struct part {
  const cloud_cells_t *c;
  const float *w, *tab;
  int K;
  float *a, *row, *b, *out; /* 'a', 'row' and 'fa' are the part's own scratch. */
  uint8_t *fa, *flags;
  uint32_t z0, z1, y0, y1;
} part_t;

static void *part_xy(void *arg) {
  part_t *p = arg;
  size_t plane = (size_t)p->c->n[0] * p->c->n[1];
  uint32_t ny = p->c->n[1];
  for (uint32_t z = p->z0; z < p->z1; z++)
    if (!plane_xy(p->c, z, p->w, p->K, p->tab, p->a, p->b + z * BSTRIDE(plane), p->row, p->fa,
                  p->flags + (size_t)z * ny))
      memset(p->flags + (size_t)z * ny, 0, ny);
  return NULL;
}

static void *part_z(void *arg) {
  part_t *p = arg;
  pass_z(p->c, p->w, p->K, p->b, p->flags, p->out, p->y0, p->y1, p->row);
  return NULL;
}

int cloud_density(const cloud_cells_t *c, double r, float *out) {
  uint32_t nx = c->n[0], ny = c->n[1], nz = c->n[2];
  float w[2 * CLOUD_MAX_RADIUS + 1];
  int K = cloud_kernel(r, w);
  size_t plane = (size_t)nx * ny;
  /* Not worth a thread below about 32³. */
  int n = par_parts(plane * nz, 32768);
  if (nz < (uint32_t)n || ny < (uint32_t)n)
    n = 1;
  /* 'b' holds every plane after the x and y passes; each part has a plane 'a' after the x
   * pass and a padded row. */
  size_t rowlen = (size_t)c->words * 64 + TAB_W(K), tablen = 256 * (size_t)TAB_W(K);
  /* As big as the grid: taken back from the last step's (reclaim.h) when it can be. */
  size_t bytes = (BSTRIDE(plane) * nz + tablen + (size_t)n * (plane + rowlen)) * sizeof(float);
  float *mem = reclaim_alloc(bytes);
  uint8_t *flags = malloc((size_t)ny * (nz + (size_t)n));
  if (!mem || !flags) {
    reclaim_free(mem, bytes);
    free(flags);
    return -1;
  }
  float *b = mem, *tab = b + BSTRIDE(plane) * nz, *scratch = tab + tablen;
  x_table(w, K, tab);
  part_t parts[PAR_MAX];
  for (int i = 0; i < n; i++) {
    parts[i] = (part_t){.c = c,
                        .w = w,
                        .tab = tab,
                        .K = K,
                        .a = scratch + (size_t)i * (plane + rowlen),
                        .b = b,
                        .out = out,
                        .fa = flags + (size_t)ny * (nz + (size_t)i),
                        .flags = flags,
                        .z0 = (uint32_t)((uint64_t)nz * i / n),
                        .z1 = (uint32_t)((uint64_t)nz * (i + 1) / n),
                        .y0 = (uint32_t)((uint64_t)ny * i / n),
                        .y1 = (uint32_t)((uint64_t)ny * (i + 1) / n)};
    parts[i].row = parts[i].a + plane;
  }
  par_run(part_xy, parts, sizeof *parts, n);
  par_run(part_z, parts, sizeof *parts, n);
  reclaim_free(mem, bytes);
  free(flags);
  return 0;
}

void cloud_blend_shifted(float *restrict target, const float *restrict shown, const uint32_t n[3],
                         long s, float keep) {
  size_t nx = n[0], rows = (size_t)n[1] * n[2];
  size_t k = (size_t)(s < 0 ? -s : s);
  if (k > nx)
    k = nx;
  /* Along a row, target x blends shown x - s; the k cells nothing moves into blend 0. */
  size_t lo = s > 0 ? k : 0, hi = s > 0 ? nx : nx - k;
  ptrdiff_t from = s > 0 ? -(ptrdiff_t)k : (ptrdiff_t)k;
  for (size_t r = 0; r < rows; r++) {
    float *t = target + r * nx;
    const float *src = shown + r * nx + from;
    for (size_t x = 0; x < lo; x++)
      t[x] -= keep * t[x];
    for (size_t x = lo; x < hi; x++)
      t[x] += keep * (src[x] - t[x]);
    for (size_t x = hi; x < nx; x++)
      t[x] -= keep * t[x];
  }
}

long cloud_wind_shift(const cloud_params_t *p, uint64_t from, uint64_t to) {
  if (p->rules != CLOUD_DOBASHI)
    return 0;
  return (long)(floor((double)to * p->wind) - floor((double)from * p->wind));
}

double cloud_wind_fraction(const cloud_params_t *p, uint64_t step) {
  if (p->rules != CLOUD_DOBASHI)
    return 0;
  double x = (double)step * p->wind;
  return x - floor(x);
}
