/*
 * The cloud automaton and its density (server/sim_cloud.c) against a deliberately naive
 * reference written straight from the equations: one byte per cell and per state, every
 * neighbour read through a bounds-checked accessor, the Dobashi draws taken per cell with
 * cloud_hash, and the density as a direct sum over every pair of cloud cell and voxel in
 * double precision. The bit-packed automaton must agree bit for bit over many steps on odd
 * grid sizes (sides not multiples of 64, below and above one word).
 */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "check.h"
#include "proto.h"
#include "scene.h"
#include "sim_cloud.h"

/* ---- The reference ---- */

typedef struct ref {
  int n[3];
  uint64_t step;
  uint8_t *hum, *act, *cld;
} ref_t;

static size_t ref_count(const ref_t *r) {
  return (size_t)r->n[0] * r->n[1] * r->n[2];
}

static ref_t ref_new(const uint32_t n[3]) {
  ref_t r = {{(int)n[0], (int)n[1], (int)n[2]}, 0, NULL, NULL, NULL};
  size_t c = ref_count(&r);
  r.hum = calloc(c, 1);
  r.act = calloc(c, 1);
  r.cld = calloc(c, 1);
  return r;
}

static void ref_free(ref_t *r) {
  free(r->hum);
  free(r->act);
  free(r->cld);
}

/* The value of 'v' at (i, j, k); 0 outside the grid. */
static int at(const ref_t *r, const uint8_t *v, int i, int j, int k) {
  if (i < 0 || j < 0 || k < 0 || i >= r->n[0] || j >= r->n[1] || k >= r->n[2])
    return 0;
  return v[i + r->n[0] * (j + r->n[1] * k)];
}

/* One step of SPEC §5.4 (and, for Dobashi, of sim_cloud.h's description). */
static void ref_step(ref_t *r, const cloud_params_t *p) {
  size_t c = ref_count(r);
  uint8_t *hum = malloc(c), *act = malloc(c), *cld = malloc(c);
  for (int k = 0; k < r->n[2]; k++)
    for (int j = 0; j < r->n[1]; j++)
      for (int i = 0; i < r->n[0]; i++) {
        size_t id = (size_t)i + r->n[0] * ((size_t)j + r->n[1] * k);
        const uint8_t *A = r->act;
        int f = at(r, A, i + 1, j, k) || at(r, A, i - 1, j, k) || at(r, A, i, j + 1, k) ||
                at(r, A, i, j - 1, k) || at(r, A, i, j, k + 1) || at(r, A, i, j, k - 1) ||
                at(r, A, i - 2, j, k) || at(r, A, i, j - 2, k) || at(r, A, i, j, k - 2);
        int a = r->act[id], h = r->hum[id], cl = r->cld[id];
        cld[id] = (uint8_t)(cl || a);
        hum[id] = (uint8_t)(h && !a);
        act[id] = (uint8_t)(!a && h && f);
        if (p->rules == CLOUD_DOBASHI) {
          uint32_t cell = (uint32_t)id;
          double s = cloud_shape(p, i, j, k);
          if (cloud_hash(p->seed, r->step, CLOUD_DRAW_EXT, cell) < cloud_threshold(p->p_ext))
            cld[id] = 0;
          if (s > 0 &&
              cloud_hash(p->seed, r->step, CLOUD_DRAW_HUM, cell) < cloud_threshold(p->p_hum * s))
            hum[id] = 1;
          if (s > 0 &&
              cloud_hash(p->seed, r->step, CLOUD_DRAW_ACT, cell) < cloud_threshold(p->p_act * s))
            act[id] = 1;
        }
      }
  if (p->rules == CLOUD_DOBASHI) {
    long shift = (long)(floor((double)(r->step + 1) * p->wind) - floor((double)r->step * p->wind));
    uint8_t *planes[3] = {hum, act, cld};
    uint8_t *tmp = malloc(c);
    for (int q = 0; q < 3; q++) {
      memcpy(tmp, planes[q], c);
      for (int k = 0; k < r->n[2]; k++)
        for (int j = 0; j < r->n[1]; j++)
          for (int i = 0; i < r->n[0]; i++) {
            long src = i - shift;
            size_t row = (size_t)r->n[0] * ((size_t)j + r->n[1] * k);
            planes[q][row + i] = src >= 0 && src < r->n[0] ? tmp[row + src] : 0;
          }
    }
    free(tmp);
  }
  ref_free(r);
  r->hum = hum;
  r->act = act;
  r->cld = cld;
  r->step++;
}

/* A pseudo-random pattern independent of sim_cloud's hash (xorshift). */
static uint32_t xs(uint32_t *s) {
  *s ^= *s << 13;
  *s ^= *s >> 17;
  *s ^= *s << 5;
  return *s;
}

/* Cells and reference filled alike: hum with probability ~'ph', act ~'pa', cld ~'pc'. */
static void fill_random(cloud_cells_t *c, ref_t *r, uint32_t seed, int ph, int pa, int pc) {
  size_t n = ref_count(r);
  for (size_t i = 0; i < n; i++) {
    r->hum[i] = (uint8_t)(xs(&seed) % 100 < (uint32_t)ph);
    r->act[i] = (uint8_t)(xs(&seed) % 1000 < (uint32_t)pa);
    r->cld[i] = (uint8_t)(xs(&seed) % 100 < (uint32_t)pc);
  }
  cloud_cells_import(c, CLOUD_HUM, r->hum);
  cloud_cells_import(c, CLOUD_ACT, r->act);
  cloud_cells_import(c, CLOUD_CLD, r->cld);
}

/* Number of cells where the packed plane 'f' and 'ref' differ. */
static size_t diff_plane(const cloud_cells_t *c, cloud_field_t f, const uint8_t *ref) {
  size_t n = cloud_cells_count(c), d = 0;
  uint8_t *u = malloc(n);
  cloud_cells_export(c, f, u);
  for (size_t i = 0; i < n; i++)
    d += u[i] != ref[i];
  free(u);
  return d;
}

/* Runs both automata 'steps' steps from the same random start; every plane must agree after
 * every step, and the padding bits beyond nx must stay 0. */
static void compare(const uint32_t n[3], const cloud_params_t *p, int steps, uint32_t seed) {
  cloud_cells_t *a = cloud_cells_new(n), *b = cloud_cells_new(n);
  ref_t r = ref_new(n);
  CHECK(a && b, "allocation");
  fill_random(a, &r, seed, 55, 8, 5);
  size_t bad = 0;
  size_t cld_end = 0;
  int first_bad = -1;
  for (int s = 0; s < steps; s++) {
    cloud_step(a, b, p);
    ref_step(&r, p);
    size_t d = diff_plane(b, CLOUD_HUM, r.hum) + diff_plane(b, CLOUD_ACT, r.act) +
               diff_plane(b, CLOUD_CLD, r.cld);
    if (d && first_bad < 0)
      first_bad = s;
    bad += d;
    CHECK(b->step == a->step + 1, "step counter %llu after %llu", (unsigned long long)b->step,
          (unsigned long long)a->step);
    cloud_cells_t *t = a;
    a = b;
    b = t;
  }
  for (size_t i = 0; i < ref_count(&r); i++)
    cld_end += r.cld[i];
  /* Padding: bits at x >= nx of every row are 0. */
  size_t pad = 0;
  if (n[0] % 64)
    for (size_t row = 0; row < (size_t)n[1] * n[2]; row++) {
      uint64_t m = ~(((uint64_t)1 << (n[0] % 64)) - 1);
      size_t w = row * a->words + a->words - 1;
      pad += (a->hum[w] & m) != 0 || (a->act[w] & m) != 0 || (a->cld[w] & m) != 0;
    }
  printf("%s %ux%ux%u, %d steps: %zu cells differ (first at step %d), %zu cld cells, "
         "%zu rows with padding set\n",
         p->rules == CLOUD_DOBASHI ? "dobashi" : "kuromiya", n[0], n[1], n[2], steps, bad,
         first_bad, cld_end, pad);
  CHECK(bad == 0, "%zu cell states differ from the reference (first at step %d)", bad, first_bad);
  CHECK(pad == 0, "%zu rows have bits set beyond nx", pad);
  /* Too small a grid, or a wind that blows everything out, leaves nothing worth checking. */
  if (ref_count(&r) > 8 && fabs(p->wind) < n[0] / 4.0)
    CHECK(cld_end > 0 && cld_end < ref_count(&r), "the test should grow some cloud (%zu cells)",
          cld_end);
  cloud_cells_unref(a);
  cloud_cells_unref(b);
  ref_free(&r);
}

static void test_kuromiya(void) {
  cloud_params_t p = {.rules = CLOUD_KUROMIYA};
  compare((uint32_t[3]){7, 13, 5}, &p, 12, 1);
  compare((uint32_t[3]){33, 17, 65}, &p, 10, 2);
  compare((uint32_t[3]){64, 64, 64}, &p, 8, 3);
  compare((uint32_t[3]){129, 3, 9}, &p, 10, 4);
  compare((uint32_t[3]){130, 129, 126}, &p, 3, 12); /* Stepped on several threads. */
  compare((uint32_t[3]){1, 1, 1}, &p, 3, 5);
}

/* A single act cell in a field of hum: after one step exactly the cells of eq. 4's stencil
 * (mirrored: a cell activates when its -1/-2/+1 neighbour is active) are active. */
static void test_stencil(void) {
  uint32_t n[3] = {9, 9, 9};
  cloud_cells_t *a = cloud_cells_new(n), *b = cloud_cells_new(n);
  size_t cnt = cloud_cells_count(a);
  uint8_t *ones = malloc(cnt), *act = calloc(cnt, 1);
  memset(ones, 1, cnt);
  act[4 + 9 * (4 + 9 * 4)] = 1;
  cloud_cells_import(a, CLOUD_HUM, ones);
  cloud_cells_import(a, CLOUD_ACT, act);
  cloud_params_t p = {.rules = CLOUD_KUROMIYA};
  cloud_step(a, b, &p);
  /* act(i,j,k) reads act at i±1, i-2 (and likewise in j, k): a cell at +2 sees the centre as
   * its i-2 neighbour, a cell at -2 would need i+2, which is not in the stencil. */
  int want[][3] = {{5, 4, 4}, {3, 4, 4}, {6, 4, 4}, {4, 5, 4}, {4, 3, 4},
                   {4, 6, 4}, {4, 4, 5}, {4, 4, 3}, {4, 4, 6}};
  int count = 0;
  for (uint32_t z = 0; z < 9; z++)
    for (uint32_t y = 0; y < 9; y++)
      for (uint32_t x = 0; x < 9; x++)
        count += cloud_cell(b, CLOUD_ACT, x, y, z);
  CHECK(count == 9, "%d active cells after one step, want 9", count);
  for (int i = 0; i < 9; i++)
    CHECK(cloud_cell(b, CLOUD_ACT, want[i][0], want[i][1], want[i][2]),
          "(%d, %d, %d) should be active", want[i][0], want[i][1], want[i][2]);
  CHECK(!cloud_cell(b, CLOUD_ACT, 2, 4, 4), "(2, 4, 4) must not be active (no i+2 term)");
  CHECK(cloud_cell(b, CLOUD_CLD, 4, 4, 4) && !cloud_cell(b, CLOUD_HUM, 4, 4, 4) &&
            !cloud_cell(b, CLOUD_ACT, 4, 4, 4),
        "the active cell becomes cloud, loses its humidity and its activation");
  free(ones);
  free(act);
  cloud_cells_unref(a);
  cloud_cells_unref(b);
}

static void test_dobashi(void) {
  cloud_params_t p = {
      .rules = CLOUD_DOBASHI, .p_ext = 0.1, .p_hum = 0.05, .p_act = 0.01, .wind = 0.7, .seed = 42};
  compare((uint32_t[3]){7, 13, 5}, &p, 12, 6);
  compare((uint32_t[3]){33, 17, 65}, &p, 10, 7);
  p.wind = -2.5;
  compare((uint32_t[3]){130, 9, 11}, &p, 10, 8);
  p.wind = 70; /* More than a word per step. */
  compare((uint32_t[3]){150, 5, 4}, &p, 4, 9);
  p.wind = 0.25;
  p.nellipsoids = 2;
  p.ellipsoids[0] = (cloud_ellipsoid_t){{10, 8, 30}, {12, 6, 20}};
  p.ellipsoids[1] = (cloud_ellipsoid_t){{25, 3, 50}, {5, 9, 9}};
  compare((uint32_t[3]){33, 17, 65}, &p, 10, 10);
  /* Big enough to be stepped on several threads (planes split unevenly: 61 of them). */
  p.ellipsoids[0] = (cloud_ellipsoid_t){{30, 30, 30}, {25, 20, 22}};
  p.wind = 1.5;
  compare((uint32_t[3]){70, 65, 61}, &p, 4, 11);
  p.p_ext = 1; /* Everything dies, everything is supplied. */
  p.p_hum = 1;
  p.p_act = 0;
  p.nellipsoids = 0;
  p.wind = 0;
  cloud_cells_t *a = cloud_cells_new((uint32_t[3]){70, 3, 3}), *b = cloud_cells_new(a->n);
  uint8_t ones[70 * 9];
  memset(ones, 1, sizeof ones);
  cloud_cells_import(a, CLOUD_CLD, ones);
  cloud_step(a, b, &p);
  uint8_t out[70 * 9];
  cloud_cells_export(b, CLOUD_CLD, out);
  int any = 0;
  for (int i = 0; i < 70 * 9; i++)
    any |= out[i];
  CHECK(!any, "p_ext = 1 clears every cloud cell");
  cloud_cells_export(b, CLOUD_HUM, out);
  int all = 1;
  for (int i = 0; i < 70 * 9; i++)
    all &= out[i];
  CHECK(all, "p_hum = 1 gives every cell humidity");
  cloud_cells_unref(a);
  cloud_cells_unref(b);
}

/* The same seed gives the same cells, a different seed different ones, both for the seeding
 * and for the steps. */
static void test_reproducible(void) {
  uint32_t n[3] = {48, 40, 36};
  cloud_params_t p = {
      .rules = CLOUD_DOBASHI, .p_ext = 0.05, .p_hum = 0.02, .p_act = 0.002, .wind = 0.5, .seed = 7};
  cloud_cells_t *r[3];
  for (int run = 0; run < 3; run++) {
    p.seed = run == 2 ? 8 : 7;
    cloud_cells_t *a = cloud_cells_new(n), *b = cloud_cells_new(n);
    cloud_cells_seed(a, &p, 0.5, 0.01);
    for (int s = 0; s < 20; s++) {
      cloud_step(a, b, &p);
      cloud_cells_t *t = a;
      a = b;
      b = t;
    }
    cloud_cells_unref(b);
    r[run] = a;
  }
  size_t words = 3 * (size_t)r[0]->words * n[1] * n[2];
  CHECK(memcmp(r[0]->hum, r[1]->hum, words * 8) == 0, "the same seed gives the same cells");
  size_t differ = 0, cld = 0;
  uint8_t *u0 = malloc(cloud_cells_count(r[0])), *u2 = malloc(cloud_cells_count(r[0]));
  cloud_cells_export(r[0], CLOUD_CLD, u0);
  cloud_cells_export(r[2], CLOUD_CLD, u2);
  for (size_t i = 0; i < cloud_cells_count(r[0]); i++) {
    differ += u0[i] != u2[i];
    cld += u0[i];
  }
  printf("dobashi seeds 7 and 8: %zu of %zu cld cells differ (%zu cloud cells)\n", differ,
         cloud_cells_count(r[0]), cld);
  CHECK(cld > 100, "the seeded automaton should make cloud (%zu cells)", cld);
  CHECK(differ > cld / 4, "another seed should give another cloud (%zu cells differ)", differ);
  /* The seeding's fractions: about half of the cells humid, about 1% of those active. */
  cloud_cells_t *s = cloud_cells_new(n);
  cloud_cells_seed(s, &p, 0.5, 0.01);
  uint8_t *h = malloc(cloud_cells_count(s)), *a = malloc(cloud_cells_count(s));
  cloud_cells_export(s, CLOUD_HUM, h);
  cloud_cells_export(s, CLOUD_ACT, a);
  size_t nh = 0, na = 0, stray = 0;
  for (size_t i = 0; i < cloud_cells_count(s); i++) {
    nh += h[i];
    na += a[i];
    stray += a[i] && !h[i];
  }
  double fh = (double)nh / cloud_cells_count(s), fa = (double)na / nh;
  printf("seeding: %.4f humid, %.4f of those active\n", fh, fa);
  CHECK(fabs(fh - 0.5) < 0.01, "hum fraction %.4f, want 0.5", fh);
  CHECK(fabs(fa - 0.01) < 0.003, "act fraction %.4f, want 0.01", fa);
  CHECK(stray == 0, "%zu active cells without humidity", stray);
  free(h);
  free(a);
  free(u0);
  free(u2);
  cloud_cells_unref(s);
  for (int i = 0; i < 3; i++)
    cloud_cells_unref(r[i]);
}

/* The density against the direct sum over every cloud cell and voxel, in double. */
static void test_density(const uint32_t n[3], double radius, int percent) {
  cloud_cells_t *c = cloud_cells_new(n);
  ref_t r = ref_new(n);
  fill_random(c, &r, 99 + (uint32_t)radius, 0, 0, percent);
  size_t cnt = ref_count(&r);
  float *got = malloc(cnt * sizeof *got);
  CHECK(cloud_density(c, radius, got) == 0, "density");
  int K = radius >= 1 ? (int)floor(radius) : 0;
  double sigma = radius / 3, norm = 0;
  for (int d = -K; d <= K; d++)
    norm += K ? exp(-(double)d * d / (2 * sigma * sigma)) : 1;
  /* Splatted cell by cell: every voxel within K on each axis gets the Gaussian of its
   * distance, in double. */
  double *want = calloc(cnt, sizeof *want);
  for (int kk = 0; kk < r.n[2]; kk++)
    for (int jj = 0; jj < r.n[1]; jj++)
      for (int ii = 0; ii < r.n[0]; ii++) {
        if (!at(&r, r.cld, ii, jj, kk))
          continue;
        for (int k = kk - K; k <= kk + K; k++)
          for (int j = jj - K; j <= jj + K; j++)
            for (int i = ii - K; i <= ii + K; i++) {
              if (i < 0 || j < 0 || k < 0 || i >= r.n[0] || j >= r.n[1] || k >= r.n[2])
                continue;
              int dx = ii - i, dy = jj - j, dz = kk - k;
              double d2 = (double)dx * dx + (double)dy * dy + (double)dz * dz;
              want[(size_t)i + r.n[0] * ((size_t)j + r.n[1] * k)] +=
                  K ? exp(-d2 / (2 * sigma * sigma)) / (norm * norm * norm) : 1;
            }
      }
  double worst = 0, peak = 0;
  for (size_t id = 0; id < cnt; id++) {
    worst = fmax(worst, fabs(got[id] - want[id]));
    peak = fmax(peak, want[id]);
  }
  free(want);
  printf("density %ux%ux%u radius %.1f: peak %.4f, worst error %.2e\n", n[0], n[1], n[2], radius,
         peak, worst);
  CHECK(peak > 0, "some density");
  CHECK(worst < 1e-5 * fmax(1, peak), "density differs from the direct sum by %.3e", worst);
  free(got);
  cloud_cells_unref(c);
  ref_free(&r);
}

/* A grid full of cloud has density 1 in the middle (the kernel is normalised). */
static void test_density_full(void) {
  uint32_t n[3] = {40, 40, 40};
  cloud_cells_t *c = cloud_cells_new(n);
  uint8_t *ones = malloc(cloud_cells_count(c));
  memset(ones, 1, cloud_cells_count(c));
  cloud_cells_import(c, CLOUD_CLD, ones);
  float *d = malloc(cloud_cells_count(c) * sizeof *d);
  cloud_density(c, 9, d);
  float mid = d[20 + 40 * (20 + 40 * 20)], corner = d[0];
  printf("full grid: density %.6f in the middle, %.4f in a corner\n", mid, corner);
  CHECK(fabsf(mid - 1) < 1e-5f, "density %.6f in a full grid, want 1", mid);
  CHECK(corner > 0.1f && corner < 0.2f, "a corner sees an eighth of the kernel: %.4f", corner);
  free(ones);
  free(d);
  cloud_cells_unref(c);
}

/* The blend with the density before, moved by the wind, against the same written out cell by
 * cell: shifts of 0, 2, -3 and more than a row along x, on a 5 x 2 x 2 grid. */
static void test_blend(void) {
  float shown[3] = {0, 1, 2}, target[3] = {2, 1, 0};
  const uint32_t line[3] = {3, 1, 1}, n[3] = {5, 2, 2};
  cloud_blend_shifted(target, shown, line, 0, 0.25f);
  CHECK(target[0] == 1.5f && target[1] == 1 && target[2] == 0.5f, "blend %g %g %g", target[0],
        target[1], target[2]);
  const long shifts[] = {0, 2, -3, 7, -9};
  for (size_t k = 0; k < sizeof shifts / sizeof shifts[0]; k++) {
    long s = shifts[k];
    float before[20], got[20];
    for (int i = 0; i < 20; i++)
      before[i] = (float)(i + 1), got[i] = (float)(100 - 3 * i);
    cloud_blend_shifted(got, before, n, s, 0.5f);
    int bad = 0;
    for (int i = 0; i < 20 && !bad; i++) {
      long x = i % 5 - s;
      float moved = x >= 0 && x < 5 ? before[i - i % 5 + x] : 0;
      float want = (float)(100 - 3 * i) + 0.5f * (moved - (float)(100 - 3 * i));
      bad = got[i] != want;
      CHECK(!bad, "shift %ld: cell %d is %g, want %g", s, i, got[i], want);
    }
  }
}

/* Applies the merge patch 'json' to 's'; returns scene_patch's result with 'err'. */
static int patch(scene_t *s, const char *json, scene_error_t *err) {
  cJSON *p = cJSON_Parse(json);
  int rc = scene_patch(s, p, err);
  cJSON_Delete(p);
  return rc;
}

/* The cloud in the scene model: compiled into the snapshot with its box and knobs, cells kept
 * across unrelated changes and seeded afresh by grid, seed or init, the grid limit refused with
 * -32003 and nothing changed, and scene_set_cloud publishing a new density. */
static void test_scene_cloud(void) {
  scene_error_t err;
  scene_t *s = scene_create("c", NULL, &err);
  CHECK(s && !s->cloud_cells && !s->snapshot->cloud.grid, "no cloud by default");
  CHECK(patch(s,
              "{\"cloud\": {\"enabled\": true, \"grid\": [20, 10, 8], \"origin\": [1, 2, 3], "
              "\"voxel\": 0.5, \"density\": 3, \"samples\": 40}}",
              &err) == 0,
        "enable the cloud: %s", err.message);
  const rvolume_t *v = &s->snapshot->cloud;
  CHECK(v->grid && v->grid->dims[0] == 20 && v->grid->dims[1] == 10 && v->grid->dims[2] == 8,
        "the snapshot shows a 20x10x8 density grid");
  CHECK(v->source == VOLUME_GRID && v->min[0] == 1 && v->min[1] == 2 && v->min[2] == 3 &&
            v->max[0] == 11 && v->max[1] == 7 && v->max[2] == 7,
        "cloud box %g %g %g .. %g %g %g, want 1 2 3 .. 11 7 7", v->min[0], v->min[1], v->min[2],
        v->max[0], v->max[1], v->max[2]);
  CHECK(v->density == 3 && v->samples == 40 && v->albedo[0] > 0.9f, "density, samples, albedo");
  cloud_cells_t *cells = s->cloud_cells;
  uint64_t gen = s->cloud_gen;
  CHECK(cells && gen != 0, "cells and a generation");
  CHECK(patch(s, "{\"cloud\": {\"p_ext\": 0.5, \"density\": 5}}", &err) == 0, "patch knobs");
  CHECK(s->cloud_cells == cells && s->cloud_gen == gen, "unrelated changes keep the cells");
  CHECK(s->snapshot->cloud.density == 5, "the new density knob is compiled");
  CHECK(patch(s, "{\"cloud\": {\"seed\": 2}}", &err) == 0, "new seed");
  CHECK(s->cloud_cells != cells && s->cloud_gen != gen, "a new seed seeds fresh cells");
  cells = s->cloud_cells;
  gen = s->cloud_gen;
  unsigned long version = s->version;
  CHECK(patch(s, "{\"cloud\": {\"grid\": [300, 10, 8]}}", &err) != 0 && err.code == PROTO_E_LIMIT &&
            strcmp(err.path, "cloud.grid.0") == 0,
        "a grid over the limit: code %d path '%s'", err.code, err.path);
  CHECK(patch(s, "{\"cloud\": {\"grid\": [20.5, 10, 8]}}", &err) != 0 &&
            err.code == PROTO_E_INVALID_PARAMS && strcmp(err.path, "cloud.grid.0") == 0,
        "a fractional grid: code %d path '%s'", err.code, err.path);
  CHECK(s->cloud_cells == cells && s->cloud_gen == gen && s->version == version,
        "refused patches change nothing");
  scene_set_cloud_side(512);
  CHECK(patch(s, "{\"cloud\": {\"grid\": [300, 2, 2]}}", &err) == 0,
        "a raised limit admits the grid: %s", err.message);
  scene_set_cloud_side(256);
  density_grid_t *d = density_grid_new(s->cloud_cells->n);
  d->data[0] = 7;
  CHECK(scene_set_cloud(s, cloud_cells_ref(s->cloud_cells), d, 0) == 0, "scene_set_cloud");
  CHECK(s->snapshot->cloud.grid == d && s->cloud_density == d, "the snapshot shows the new grid");
  CHECK(patch(s, "{\"cloud\": {\"enabled\": false}}", &err) == 0 && !s->cloud_cells &&
            !s->snapshot->cloud.grid && s->cloud_gen == 0,
        "disabling drops the cloud");
  scene_destroy(s);
}

int main(void) {
  test_stencil();
  test_kuromiya();
  test_dobashi();
  test_reproducible();
  test_density((uint32_t[3]){7, 13, 5}, 3, 20);
  test_density((uint32_t[3]){17, 9, 11}, 4.5, 10);
  test_density((uint32_t[3]){70, 6, 5}, 9, 5);
  test_density((uint32_t[3]){5, 6, 4}, 0.5, 30);
  test_density((uint32_t[3]){48, 40, 37}, 6, 3); /* Large enough to be split among threads. */
  test_density_full();
  test_blend();
  test_scene_cloud();
  printf("%d checks, %d failures\n", checks, failures);
  return failures != 0;
}
