/*
 * The volumes pass (SPEC §5.3): the scene's volumes[] (layer "volumes") and the cloud (layer
 * "cloud") ray-marched over the objects, with the opaque objects' shadows from a shadow map
 * (light shafts). The kernels are in kernels/volume.cl; this file prepares what they read:
 *
 * - per volume, its density grid (a density_grid_t as given, or the procedural noise baked
 *   into a grid on the host), a light grid holding the transmittance from each voxel towards
 *   the light through the volume (one sweep across the grid, slice by slice from the light's
 *   side), both interleaved, a (density, light) pair a voxel, as the kernel reads them (volume.h),
 *   and the tight box
 *   where the density can be non-zero. These are cached per volume and
 *   rebuilt only when the volume, its grid or the light changes, so a still scene uploads
 *   nothing;
 * - the shadow map of the objects, orthographic along the light and fitted to the volumes'
 *   tight boxes, rendered by the shadow_map kernel from the object records and BVH the objects
 *   pass uploaded, and kept while objects, light and fit stay the same.
 *
 * Volumes are composited nearest first (by the distance from the eye to the box centre);
 * overlapping volumes are sampled one after the other, not merged.
 */
#include <math.h>
#include <sched.h>
#include <stdatomic.h>

#include "parallel.h"
#include "render_internal.h"
#include "../kernels/volume.h"

#define NOISE_MAX_SIDE 96  /* Largest side of a baked noise grid. */
#define NOISE_PER_SCALE 16 /* Baked voxels per noise_scale. */
#define NOISE_OCTAVES 4    /* fBm octaves of the value noise. */
#define NOISE_FADE 0.15    /* Noise volumes fade to zero over this fraction of the box. */

/* One volume's prepared data, keyed by everything it was made from. */
typedef struct vol_entry {
  int valid;
  /* The key. */
  volume_source_t source;
  density_grid_t *grid; /* A counted reference (VOLUME_GRID). */
  uint32_t seed;
  float noise_scale, sigma;
  float min[3], max[3], light[3];
  /* The data. */
  float *baked; /* VOLUME_NOISE: the baked density (owned); NULL for grids. */
  uint32_t dims[3];
  float *scratch;         /* The light, a float a voxel (owned), packed with the density into
                             the device buffer at upload. */
  size_t scratch_cap;     /* Floats 'scratch' holds room for. */
  float tmin[3], tmax[3]; /* Tight box. */
  int empty;              /* No voxel is above zero. */
  size_t off;             /* Offset in the device buffer, voxels (float2s). */
} vol_entry_t;

/* What the cached shadow map was rendered from. */
typedef struct shadow_key {
  vfx_shadow_t sh;
  int nsph, nconv, ntri;
  float *objs; /* The sphere and convex records. */
  size_t nobjs, cap_objs;
  mesh_key_t *bvh;
  int nbvh;
} shadow_key_t;

struct vol_state {
  cl_kernel kvol, kshadow, kdown, kup;
  cl_mem recs, data, smap;
  size_t cap_recs, cap_data, cap_smap;
  cl_mem low_depth, low_linear; /* The low-resolution pass's depth and RGBA (volume_div > 1). */
  size_t cap_low_depth, cap_low_linear;
  vol_entry_t *ents;
  int nents;
  size_t data_floats; /* Floats uploaded to 'data'. */
  float *host_recs;
  size_t host_recs_cap;
  shadow_key_t skey;
  int smap_valid;
  int smap_pitch;
};

/* ---- Noise --------------------------------------------------------------------------------- */

static uint32_t hash3(int32_t x, int32_t y, int32_t z, uint32_t seed) {
  uint32_t h = seed * 0x9E3779B1u ^ (uint32_t)x * 0x85EBCA77u ^ (uint32_t)y * 0xC2B2AE3Du ^
               (uint32_t)z * 0x27D4EB2Fu;
  h ^= h >> 15;
  h *= 0x2C1B3C6Du;
  h ^= h >> 12;
  h *= 0x297A2D39u;
  h ^= h >> 15;
  return h;
}

static double fade(double t) {
  return t * t * t * (t * (t * 6 - 15) + 10);
}

/* Value noise in [0, 1): hashed lattice values blended with the quintic fade. */
static double value_noise(double x, double y, double z, uint32_t seed) {
  double fx = floor(x), fy = floor(y), fz = floor(z);
  int32_t ix = (int32_t)fx, iy = (int32_t)fy, iz = (int32_t)fz;
  double u = fade(x - fx), v = fade(y - fy), w = fade(z - fz);
  double c[8];
  for (int k = 0; k < 8; k++)
    c[k] = hash3(ix + (k & 1), iy + ((k >> 1) & 1), iz + (k >> 2), seed) * (1.0 / 4294967296.0);
  double x00 = c[0] + u * (c[1] - c[0]), x10 = c[2] + u * (c[3] - c[2]);
  double x01 = c[4] + u * (c[5] - c[4]), x11 = c[6] + u * (c[7] - c[6]);
  double y0 = x00 + v * (x10 - x00), y1 = x01 + v * (x11 - x01);
  return y0 + w * (y1 - y0);
}

/*
 * The density of a noise volume at world point 'p': fBm of NOISE_OCTAVES octaves of value
 * noise with feature size 'scale' (halving each octave, weights halving), in [0, 1], times a
 * fade to zero over the outer NOISE_FADE of the box on each axis so the box's faces do not show.
 */
static double noise_density(const rvolume_t *v, const double p[3]) {
  double sum = 0, amp = 1, norm = 0, freq = 1.0 / v->noise_scale, edge = 1;
  for (int o = 0; o < NOISE_OCTAVES; o++) {
    sum += amp * value_noise(p[0] * freq, p[1] * freq, p[2] * freq, v->seed + 1013u * o);
    norm += amp;
    amp *= 0.5, freq *= 2;
  }
  for (int k = 0; k < 3; k++) {
    double u = (p[k] - v->min[k]) / ((double)v->max[k] - v->min[k]);
    double d = fmin(u, 1 - u) / NOISE_FADE;
    d = d < 0 ? 0 : d > 1 ? 1 : d;
    edge *= d * d * (3 - 2 * d);
  }
  return sum / norm * edge;
}

/* Bakes the noise of 'v' into e->baked. Returns 0, or -1 when out of memory. */
static int bake_noise(const rvolume_t *v, vol_entry_t *e) {
  size_t n = 1;
  for (int k = 0; k < 3; k++) {
    double cells = ceil(((double)v->max[k] - v->min[k]) / v->noise_scale * NOISE_PER_SCALE);
    e->dims[k] = (uint32_t)(cells < 4 ? 4 : cells > NOISE_MAX_SIDE ? NOISE_MAX_SIDE : cells);
    n *= e->dims[k];
  }
  e->baked = malloc(n * sizeof(float));
  if (e->baked == NULL)
    return -1;
  float *out = e->baked;
  for (uint32_t z = 0; z < e->dims[2]; z++)
    for (uint32_t y = 0; y < e->dims[1]; y++)
      for (uint32_t x = 0; x < e->dims[0]; x++) {
        uint32_t i[3] = {x, y, z};
        double p[3];
        for (int k = 0; k < 3; k++)
          p[k] = v->min[k] + (i[k] + 0.5) * ((double)v->max[k] - v->min[k]) / e->dims[k];
        *out++ = (float)noise_density(v, p);
      }
  return 0;
}

/* ---- Light grid ---------------------------------------------------------------------------- */

/* Voxels from which the light sweep runs on a thread per core (64³ and up). */
#define SWEEP_THREAD_MIN ((size_t)1 << 18)

/* A barrier for the sweep's threads that spins, then yields: they meet it once a slice, and a
 * sleeping wait costs more than a slice of a small grid. */
typedef struct sweep_barrier {
  atomic_uint count, phase;
  unsigned n;
} sweep_barrier_t;

static void sweep_wait(sweep_barrier_t *b) {
  unsigned ph = atomic_load_explicit(&b->phase, memory_order_acquire);
  if (atomic_fetch_add_explicit(&b->count, 1, memory_order_acq_rel) == b->n - 1) {
    atomic_store_explicit(&b->count, 0, memory_order_relaxed);
    atomic_store_explicit(&b->phase, ph + 1, memory_order_release);
    return;
  }
  for (unsigned spins = 0; atomic_load_explicit(&b->phase, memory_order_acquire) == ph; spins++)
    if (spins >= 256)
      sched_yield();
}

/*
 * exp(x) for finite x <= 0, to about 2e-7 relative, as the kernels' vol_exp_neg does it: 2^y
 * for y = x log2(e), split into the nearest integer n and f in [-1/2, 1/2], 2^f from Cephes'
 * degree-6 polynomial and 2^n put into the exponent bits. Unlike expf it is inlined, so the
 * sweep's rows vectorise.
 */
static inline float exp_neg(float x) {
  float y = (x > -87.0f ? x : -87.0f) * 1.44269504088896341f;
  float n = (y + 12582912.0f) - 12582912.0f, f = y - n;
  float p = f * 1.535336188319500e-4f + 1.339887440266574e-3f;
  p = p * f + 9.618437357674640e-3f;
  p = p * f + 5.550332471162809e-2f;
  p = p * f + 2.402264791363012e-1f;
  p = p * f + 6.931472028550421e-1f;
  p = p * f + 1.0f;
  int32_t bits = ((int32_t)n + 127) << 23;
  float scale;
  memcpy(&scale, &bits, sizeof scale);
  return p * scale;
}

/*
 * The points first + j - off, j = 0 .. count - 1, along an axis of 'n' voxels, all at the same
 * fraction f past a voxel centre: those between two voxels of the grid, j in [lo, hi), lie
 * between voxel base + j and the next.
 */
typedef struct span {
  int base, lo, hi;
  float f;
} span_t;

static span_t span_of(int first, double off, uint32_t n, int count) {
  double x0 = first - off;
  span_t sp = {.base = (int)floor(x0)};
  sp.f = (float)(x0 - sp.base);
  sp.lo = -sp.base > 0 ? -sp.base : 0;
  sp.hi = (int)n - 1 - sp.base < count ? (int)n - 1 - sp.base : count;
  if (sp.lo > count)
    sp.lo = count;
  if (sp.hi < sp.lo)
    sp.hi = sp.lo;
  return sp;
}

/*
 * The light sweep (light_grid) follows the light's rays through the grid, slice by slice along
 * the axis a on which the light moves fastest in voxels, from the light's side. A ray that
 * meets the first slice at lateral voxel coordinates (b, c) = (J_b + jb, J_c + jc) meets slice k
 * (k slices from the light) at (J_b + jb - k db, J_c + jc - k dc): a lattice of rays, sheared
 * slice by slice, whose optical depth from the light each slice adds to (the trapezoid rule on
 * the extinction, bilinear in the slice, 0 beside the grid). A voxel of slice k takes the
 * lattice's optical depth at slice k - 1 interpolated where its own ray meets that slice, once,
 * plus the last step, from there to its centre, by the trapezoid rule on its own extinction.
 * (Carrying the transmittance from slice to slice instead, interpolated in each slice, blurs it
 * sideways a little more at every slice: up to 18% off at the far side of a uniform 32³ box
 * under an oblique light, where the ray's exit changes from one face to another.)
 */
typedef struct sweep {
  const uint32_t *n;
  int a, b, c, dir;
  size_t stride[3];
  double db, dc; /* Lateral voxels the rays move per slice towards the light. */
  int jb0, jc0;  /* Lattice coordinates of its first row and column (J_b, J_c). */
  int wb, wc;    /* Its rows and columns. */
  float *tau[2]; /* Per lattice ray, its optical depth: at even slices, at odd ones. */
  float *ext;    /* Per lattice ray, the extinction it met at the last slice. */
  /* Where a voxel's ray meets the slice before, (ib + db, ic + dc): lattice_taps, and along c
   * the span between two voxels (span_t, below). */
  uint32_t *ub0, *ub1, *uc0, *uc1;
  float *ubw0, *ubw1, *ucw0, *ucw1;
  span_t up;
  const float *sg; /* The density: sigma times it is the extinction. */
  float *lg;
  float half;           /* sigma times 1/2 the world length of a step between slices: the
                           extinctions below are in units of sigma. */
  sweep_barrier_t *bar; /* Between the threads' phases, or NULL with one thread. */
} sweep_t;

/* A thread's share: part 'index' of 'parts' of the lattice rows of every slice (sweep_rows),
 * voxel rows [v0, v1) (axis b) of every slice, and its own taps of the lattice into the slice,
 * rebuilt per slice (lattice_taps). */
typedef struct sweep_part {
  const sweep_t *w;
  int index, parts, v0, v1;
  uint32_t *bi0, *bi1, *ci0, *ci1;
  float *bw0, *bw1, *cw0, *cw1;
} sweep_part_t;

/*
 * Where the lattice's 'count' rays (j = 0 ..) meet a slice along one lateral axis of 'n' voxels
 * 'stride' apart, at voxel coordinate first + j - off: the two voxels (as offsets) and weights
 * that blend the extinction there, edges clamped, and both weights 0 beside the grid.
 */
static void lattice_taps(uint32_t *i0, uint32_t *i1, float *w0, float *w1, int count, int first,
                         double off, uint32_t n, size_t stride) {
  for (int j = 0; j < count; j++) {
    double x = first + j - off;
    if (x < -0.5 || x > n - 0.5) {
      i0[j] = i1[j] = 0, w0[j] = w1[j] = 0;
      continue;
    }
    double q = x < 0 ? 0 : x > n - 1.0 ? n - 1.0 : x;
    uint32_t k0 = (uint32_t)q, k1 = k0 + 1 < n ? k0 + 1 : k0;
    i0[j] = (uint32_t)(k0 * stride), i1[j] = (uint32_t)(k1 * stride);
    w1[j] = (float)(q - k0), w0[j] = 1 - w1[j];
  }
}

/* One lattice row of slice k: the extinction 'e' met now, added to the optical depth 'in' of
 * the slice before into 'out' (from nothing at the first slice). Between two voxels of the row
 * ('sp') the weights are the same for every ray and the loads contiguous; beside them the taps
 * take the clamped edges, and 0 beside the grid. */
PAR_CLONES static void lattice_row(float *restrict out, const float *restrict in,
                                   float *restrict ext, const float *restrict r0,
                                   const float *restrict r1, float b0, float b1,
                                   const sweep_part_t *p, span_t sp, int in0, int in1, size_t sc,
                                   int wc, int first, float half) {
  const uint32_t *restrict c0 = p->ci0, *restrict c1 = p->ci1;
  const float *restrict w0 = p->cw0, *restrict w1 = p->cw1;
  float f = sp.f, g = 1 - f;
#define LATTICE_RAY(e)                                                                             \
  do {                                                                                             \
    float e_ = (e);                                                                                \
    out[j] = first ? half * e_ : in[j] + half * (ext[j] + e_);                                     \
    ext[j] = e_;                                                                                   \
  } while (0)
#define LATTICE_TAPS(j)                                                                            \
  (b0 * (w0[j] * r0[c0[j]] + w1[j] * r0[c1[j]]) + b1 * (w0[j] * r1[c0[j]] + w1[j] * r1[c1[j]]))
  if (b0 == 0 && b1 == 0) { /* A row beside the grid meets no medium. */
    for (int j = 0; j < wc; j++)
      LATTICE_RAY(0.0f);
    return;
  }
  /* Rays beside the slice along c (j < in0, j >= in1) meet nothing either; the contiguous span
   * lies between them. */
  int zl = in0 < sp.lo ? in0 : sp.lo, zh = in1 > sp.hi ? in1 : sp.hi;
  for (int j = 0; j < zl; j++)
    LATTICE_RAY(0.0f);
  for (int j = zl; j < sp.lo; j++)
    LATTICE_RAY(LATTICE_TAPS(j));
  const float *q0 = r0 + (ptrdiff_t)sp.base * (ptrdiff_t)sc,
              *q1 = r1 + (ptrdiff_t)sp.base * (ptrdiff_t)sc;
  if (sc == 1)
    for (int j = sp.lo; j < sp.hi; j++)
      LATTICE_RAY(b0 * (g * q0[j] + f * q0[j + 1]) + b1 * (g * q1[j] + f * q1[j + 1]));
  else
    for (int j = sp.lo; j < sp.hi; j++)
      LATTICE_RAY(b0 * (g * q0[j * sc] + f * q0[(j + 1) * sc]) +
                  b1 * (g * q1[j * sc] + f * q1[(j + 1) * sc]));
  for (int j = sp.hi; j < zh; j++)
    LATTICE_RAY(LATTICE_TAPS(j));
  for (int j = zh; j < wc; j++)
    LATTICE_RAY(0.0f);
#undef LATTICE_TAPS
#undef LATTICE_RAY
}

/*
 * One voxel row of a slice, 'nc' voxels 'sc' apart of extinction 'here': the lattice's optical
 * depth at the slice before, blended from its rows t0 and t1 (weights 1 - fb, fb) and along
 * them from columns k and k + 1 (1 - fc, fc), plus the step from there: the extinction there
 * blended from the slice before's rows r0 and r1 (b0, b1) by the column taps, and 'here'. With
 * no slice before (t0 NULL), the step from the grid's face.
 */
PAR_CLONES static void voxel_row(float *restrict out, const float *restrict here, size_t sc,
                                 uint32_t nc, const float *restrict t0, const float *restrict t1,
                                 float fb, float fc, const float *restrict r0,
                                 const float *restrict r1, float b0, float b1, const sweep_t *w,
                                 float half) {
  if (!t0) {
    for (uint32_t k = 0; k < nc; k++)
      out[k * sc] = exp_neg(-half * here[k * sc]);
    return;
  }
  const uint32_t *restrict c0 = w->uc0, *restrict c1 = w->uc1;
  const float *restrict w0 = w->ucw0, *restrict w1 = w->ucw1;
  float gb = 1 - fb, gc = 1 - fc;
  /* The points up the light between two voxels of the row (w->up) share their weights. */
  span_t sp = w->up;
  float f = sp.f, g = 1 - f;
  const float *q0 = r0 + (ptrdiff_t)sp.base * (ptrdiff_t)sc,
              *q1 = r1 + (ptrdiff_t)sp.base * (ptrdiff_t)sc;
#define SWEEP_VOXEL(at, u)                                                                         \
  do {                                                                                             \
    float t = gb * (gc * t0[k] + fc * t0[k + 1]) + fb * (gc * t1[k] + fc * t1[k + 1]);             \
    out[at] = exp_neg(-(t + half * (here[at] + (u))));                                             \
  } while (0)
#define SWEEP_TAPS                                                                                 \
  (b0 * (w0[k] * r0[c0[k]] + w1[k] * r0[c1[k]]) + b1 * (w0[k] * r1[c0[k]] + w1[k] * r1[c1[k]]))
  for (int k = 0; k < sp.lo; k++)
    SWEEP_VOXEL(k * sc, SWEEP_TAPS);
  /* Rows along x (the usual case) are contiguous: that loop vectorises. */
  if (sc == 1)
    for (int k = sp.lo; k < sp.hi; k++)
      SWEEP_VOXEL(k, b0 * (g * q0[k] + f * q0[k + 1]) + b1 * (g * q1[k] + f * q1[k + 1]));
  else
    for (int k = sp.lo; k < sp.hi; k++)
      SWEEP_VOXEL(k * sc, b0 * (g * q0[k * sc] + f * q0[(k + 1) * sc]) +
                              b1 * (g * q1[k * sc] + f * q1[(k + 1) * sc]));
  for (int k = sp.hi; k < (int)nc; k++)
    SWEEP_VOXEL(k * sc, SWEEP_TAPS);
#undef SWEEP_TAPS
#undef SWEEP_VOXEL
}

/* The lattice's rays j in [*j0, *j1) of 'count' along a lateral axis of 'n' voxels, at voxel
 * coordinate first + j - off in the slice, that meet it (lattice_taps' weights not both 0). */
static void lattice_inside(double off, int first, uint32_t n, int count, int *j0, int *j1) {
  int a = (int)ceil(off - 0.5 - first), b = (int)floor(off + n - 0.5 - first) + 1;
  *j0 = a < 0 ? 0 : a > count ? count : a;
  *j1 = b < *j0 ? *j0 : b > count ? count : b;
}

static void *sweep_rows(void *arg) {
  sweep_part_t *p = arg;
  const sweep_t *w = p->w;
  const uint32_t *n = w->n;
  const size_t *stride = w->stride;
  int a = w->a, b = w->b, c = w->c;
  for (int k = 0; k < (int)n[a]; k++) {
    int s = w->dir > 0 ? (int)n[a] - 1 - k : k;
    const float *slice = w->sg + s * stride[a];
    /* The slice before, towards the light; the first slice has none. */
    const float *before = k ? slice + w->dir * (ptrdiff_t)stride[a] : NULL;
    const float *in = w->tau[(k + 1) & 1];
    float *out = w->tau[k & 1];
    double ob = k * w->db, oc = k * w->dc;
    /* The voxels of this slice, from the lattice at the slice before: voxel (ib, ic)'s ray meets
     * it at lattice (ib + ob - J_b, ic + oc - J_c). */
    double qb = ob - w->jb0, qc = oc - w->jc0;
    int fb0 = (int)floor(qb), fc0 = (int)floor(qc);
    float fb = (float)(qb - fb0), fc = (float)(qc - fc0);
    for (int ib = p->v0; ib < p->v1; ib++) {
      size_t at = s * stride[a] + ib * stride[b];
      const float *t0 = before ? in + (size_t)(ib + fb0) * w->wc + fc0 : NULL;
      voxel_row(w->lg + at, w->sg + at, stride[c], n[c], t0, t0 ? t0 + w->wc : NULL, fb, fc,
                before ? before + w->ub0[ib] : NULL, before ? before + w->ub1[ib] : NULL,
                w->ubw0[ib], w->ubw1[ib], w, w->half);
    }
    /* The lattice's rays where they meet this slice, into the other buffer: the voxels above, on
     * every thread, read the slice before's. */
    lattice_taps(p->bi0, p->bi1, p->bw0, p->bw1, w->wb, w->jb0, ob, n[b], stride[b]);
    lattice_taps(p->ci0, p->ci1, p->cw0, p->cw1, w->wc, w->jc0, oc, n[c], stride[c]);
    span_t sp = span_of(w->jc0, oc, n[c], w->wc);
    /* The rows whose rays cross the slice, [in0, in1), cost more than those beside it, and
     * which they are moves from slice to slice: each thread takes its share of both. Along a
     * row, the rays [cin0, cin1) cross it. */
    int in0, in1, cin0, cin1;
    lattice_inside(ob, w->jb0, n[b], w->wb, &in0, &in1);
    lattice_inside(oc, w->jc0, n[c], w->wc, &cin0, &cin1);
    int cut[4] = {0, in0, in1, w->wb};
    for (int r = 0; r < 3; r++) {
      int64_t len = cut[r + 1] - cut[r];
      int j0 = cut[r] + (int)(len * p->index / p->parts),
          j1 = cut[r] + (int)(len * (p->index + 1) / p->parts);
      for (int jb = j0; jb < j1; jb++) {
        size_t row = (size_t)jb * w->wc;
        lattice_row(out + row, in + row, w->ext + row, slice + p->bi0[jb], slice + p->bi1[jb],
                    p->bw0[jb], p->bw1[jb], p, sp, cin0, cin1, stride[c], w->wc, k == 0, w->half);
      }
    }
    if (w->bar)
      sweep_wait(w->bar);
  }
  return NULL;
}

/* The first lattice coordinate and the count along a lateral axis of 'n' voxels whose rays
 * move 'd' voxels a slice over 'slices' slices, with one to spare for the interpolation. */
static void lattice_span(uint32_t n, double d, uint32_t slices, int *first, int *count) {
  double reach = d * (slices - 1.0);
  *first = (int)floor(fmin(0, reach));
  *count = (int)ceil(n - 1.0 + fmax(0, reach)) - *first + 2;
}

/*
 * Fills 'lg' with the transmittance from each voxel centre towards the light
 * (direction 'l', unit) through the volume, for extinction sigma * density, by one sweep along
 * the light's rays (sweep_t). Returns 0, or -1 when out of memory.
 */
static int light_grid(vol_entry_t *e, const float *dens, float sigma, const float l[3], float *lg) {
  uint32_t *n = e->dims;
  size_t nl = (size_t)n[0] * n[1] * n[2];
  /* The light's direction in voxels per world unit. */
  double cell[3], lv[3];
  for (int k = 0; k < 3; k++) {
    cell[k] = ((double)e->max[k] - e->min[k]) / n[k];
    lv[k] = l[k] / cell[k];
  }
  int a = 0;
  for (int k = 1; k < 3; k++)
    if (fabs(lv[k]) > fabs(lv[a]))
      a = k;
  /* The rows of a slice run along c, x when x is not the sweep's axis, so that they are
   * contiguous and vectorise. */
  int b = a == 0 ? 1 : a == 1 ? 2 : 1, c = a == 0 ? 2 : 0;
  if (!(fabs(lv[a]) > 0)) {
    for (size_t i = 0; i < nl; i++)
      lg[i] = 1;
    return 0;
  }
  double step = 1 / fabs(lv[a]); /* World length of one slice's step along the light. */
  sweep_t w = {.n = n,
               .a = a,
               .b = b,
               .c = c,
               .dir = lv[a] > 0 ? 1 : -1, /* The light lies towards increasing a when 1. */
               .stride = {1, n[0], (size_t)n[0] * n[1]},
               .db = lv[b] * step,
               .dc = lv[c] * step,
               .sg = dens,
               .lg = lg,
               .half = (float)(0.5 * step * sigma)};
  lattice_span(n[b], w.db, n[a], &w.jb0, &w.wb);
  lattice_span(n[c], w.dc, n[a], &w.jc0, &w.wc);
  size_t cells = (size_t)w.wb * w.wc;
  w.tau[0] = malloc(cells * sizeof *w.tau[0]), w.tau[1] = malloc(cells * sizeof *w.tau[1]);
  w.ext = malloc(cells * sizeof *w.ext);
  w.ub0 = malloc(n[b] * sizeof *w.ub0), w.ub1 = malloc(n[b] * sizeof *w.ub1);
  w.ubw0 = malloc(n[b] * sizeof *w.ubw0), w.ubw1 = malloc(n[b] * sizeof *w.ubw1);
  w.uc0 = malloc(n[c] * sizeof *w.uc0), w.uc1 = malloc(n[c] * sizeof *w.uc1);
  w.ucw0 = malloc(n[c] * sizeof *w.ucw0), w.ucw1 = malloc(n[c] * sizeof *w.ucw1);
  int parts = par_parts(nl, SWEEP_THREAD_MIN);
  if ((uint32_t)parts > n[b])
    parts = 1;
  sweep_part_t part[PAR_MAX];
  memset(part, 0, sizeof part);
  int rc = w.tau[0] && w.tau[1] && w.ext && w.ub0 && w.ub1 && w.ubw0 && w.ubw1 && w.uc0 && w.uc1 &&
                   w.ucw0 && w.ucw1
               ? 0
               : -1;
  if (rc == 0) { /* A voxel's ray meets the slice before at (ib + db, ic + dc). */
    lattice_taps(w.ub0, w.ub1, w.ubw0, w.ubw1, (int)n[b], 0, -w.db, n[b], w.stride[b]);
    lattice_taps(w.uc0, w.uc1, w.ucw0, w.ucw1, (int)n[c], 0, -w.dc, n[c], w.stride[c]);
    w.up = span_of(0, -w.dc, n[c], (int)n[c]);
  }
  for (int i = 0; i < parts; i++) {
    sweep_part_t *q = &part[i];
    *q = (sweep_part_t){.w = &w,
                        .index = i,
                        .parts = parts,
                        .v0 = (int)((uint64_t)n[b] * i / parts),
                        .v1 = (int)((uint64_t)n[b] * (i + 1) / parts)};
    q->bi0 = malloc(w.wb * sizeof *q->bi0), q->bi1 = malloc(w.wb * sizeof *q->bi1);
    q->bw0 = malloc(w.wb * sizeof *q->bw0), q->bw1 = malloc(w.wb * sizeof *q->bw1);
    q->ci0 = malloc(w.wc * sizeof *q->ci0), q->ci1 = malloc(w.wc * sizeof *q->ci1);
    q->cw0 = malloc(w.wc * sizeof *q->cw0), q->cw1 = malloc(w.wc * sizeof *q->cw1);
    if (!q->bi0 || !q->bi1 || !q->bw0 || !q->bw1 || !q->ci0 || !q->ci1 || !q->cw0 || !q->cw1)
      rc = -1;
  }
  if (rc == 0) {
    sweep_barrier_t bar = {.n = (unsigned)parts};
    w.bar = &bar;
    if (parts == 1 || par_run_together(sweep_rows, part, sizeof *part, parts) != 0) {
      w.bar = NULL;
      sweep_part_t *q = &part[0];
      q->index = 0, q->parts = 1, q->v0 = 0, q->v1 = (int)n[b];
      sweep_rows(q);
    }
  }
  for (int i = 0; i < parts; i++) {
    sweep_part_t *q = &part[i];
    free(q->bi0), free(q->bi1), free(q->bw0), free(q->bw1);
    free(q->ci0), free(q->ci1), free(q->cw0), free(q->cw1);
  }
  free(w.tau[0]), free(w.tau[1]), free(w.ext);
  free(w.ub0), free(w.ub1), free(w.ubw0), free(w.ubw1);
  free(w.uc0), free(w.uc1), free(w.ucw0), free(w.ucw1);
  return rc;
}

/*
 * Makes room for 'n' floats in '*buf' of capacity '*cap', keeping an allocation that is large
 * enough: a cloud rebuilds its grids every step, and fresh allocations of this size come from
 * the kernel as untouched pages, whose first writes cost more than the writing itself (12 ms of
 * page faults for a 128³ cloud's 32 MB). Returns 0, or -1 when out of memory.
 */
static int reserve(float **buf, size_t *cap, size_t n) {
  if (*buf != NULL && *cap >= n)
    return 0;
  free(*buf);
  *buf = malloc(n * sizeof(float));
  *cap = *buf ? n : 0;
  return *buf ? 0 : -1;
}

/* Rows (of dims[0] voxels) of a grid from which pack runs on a thread per core (64³ and up). */
#define PACK_THREAD_MIN ((size_t)1 << 12)

/* The rows [row0, row1) of pack's work, and the voxel bounds of their non-zero density. */
typedef struct pack_part {
  vol_entry_t *e;
  const float *dens, *lg;
  float *dst;
  size_t row0, row1;
  int lo[3], hi[3];
} pack_part_t;

static void *pack_rows(void *arg) {
  pack_part_t *p = arg;
  uint32_t nx = p->e->dims[0], ny = p->e->dims[1];
  const float *dens = p->dens, *lg = p->lg;
  for (int k = 0; k < 3; k++)
    p->lo[k] = INT32_MAX, p->hi[k] = -1;
  for (size_t r = p->row0; r < p->row1; r++) {
    size_t row = r * nx;
    float *q = p->dst + 2 * row;
    int xl = -1, xh = -1;
    for (uint32_t x = 0; x < nx; x++, q += 2) {
      size_t i = row + x;
      q[0] = dens[i], q[1] = lg[i];
      if (dens[i] > 0) {
        xl = xl < 0 ? (int)x : xl;
        xh = (int)x;
      }
    }
    if (xl < 0)
      continue;
    int at[3] = {xl, (int)(r % ny), (int)(r / ny)}, ah[3] = {xh, at[1], at[2]};
    for (int k = 0; k < 3; k++) {
      p->lo[k] = at[k] < p->lo[k] ? at[k] : p->lo[k];
      p->hi[k] = ah[k] > p->hi[k] ? ah[k] : p->hi[k];
    }
  }
  return NULL;
}

/*
 * Interleaves density 'dens' and light 'lg' into 'dst' (the device buffer, mapped) as the
 * kernel reads them (volume.h) and sets the tight box, the part of the box where the
 * interpolated density can be non-zero, and e->empty when there is none.
 */
static void pack(vol_entry_t *e, const float *dens, const float *lg, float *dst) {
  size_t n = (size_t)e->dims[0] * e->dims[1] * e->dims[2], rows = n / e->dims[0];
  int parts = par_parts(rows, PACK_THREAD_MIN);
  pack_part_t part[PAR_MAX];
  for (int i = 0; i < parts; i++)
    part[i] = (pack_part_t){e, dens, lg, dst, rows * i / parts, rows * (i + 1) / parts, {0}, {0}};
  par_run(pack_rows, part, sizeof *part, parts);
  for (int i = 1; i < parts; i++)
    for (int k = 0; k < 3; k++) {
      part[0].lo[k] = part[i].lo[k] < part[0].lo[k] ? part[i].lo[k] : part[0].lo[k];
      part[0].hi[k] = part[i].hi[k] > part[0].hi[k] ? part[i].hi[k] : part[0].hi[k];
    }
  const int *lo = part[0].lo, *hi = part[0].hi;
  e->empty = hi[0] < 0;
  for (int k = 0; k < 3 && !e->empty; k++) {
    double cell = ((double)e->max[k] - e->min[k]) / e->dims[k];
    double a = e->min[k] + (lo[k] - 0.5) * cell, b = e->min[k] + (hi[k] + 1.5) * cell;
    e->tmin[k] = (float)(a < e->min[k] ? e->min[k] : a);
    e->tmax[k] = (float)(b > e->max[k] ? e->max[k] : b);
  }
}

static void entry_clear(vol_entry_t *e) {
  density_grid_unref(e->grid);
  free(e->baked);
  free(e->scratch);
  memset(e, 0, sizeof *e);
}

/* Empties 'e' for a rebuild, keeping its allocations (see reserve). */
static void entry_reset(vol_entry_t *e) {
  float *scratch = e->scratch;
  size_t scratch_cap = e->scratch_cap;
  e->scratch = NULL;
  entry_clear(e);
  e->scratch = scratch, e->scratch_cap = scratch_cap;
}

static int entry_matches(const vol_entry_t *e, const rvolume_t *v, float sigma, const float l[3]) {
  if (!e->valid || e->source != v->source || e->sigma != sigma)
    return 0;
  if (v->source == VOLUME_GRID ? e->grid != v->grid
                               : e->seed != v->seed || e->noise_scale != v->noise_scale)
    return 0;
  return memcmp(e->min, v->min, sizeof e->min) == 0 && memcmp(e->max, v->max, sizeof e->max) == 0 &&
         memcmp(e->light, l, sizeof e->light) == 0;
}

/* (Re)builds entry 'e' for volume 'v'. Returns 0, or -1 when out of memory. */
static int entry_build(vol_entry_t *e, const rvolume_t *v, float sigma, const float l[3]) {
  entry_reset(e);
  e->source = v->source;
  e->seed = v->seed;
  e->noise_scale = v->noise_scale;
  e->sigma = sigma;
  memcpy(e->min, v->min, sizeof e->min);
  memcpy(e->max, v->max, sizeof e->max);
  memcpy(e->light, l, sizeof e->light);
  const float *dens;
  if (v->source == VOLUME_GRID) {
    e->grid = density_grid_ref(v->grid);
    memcpy(e->dims, v->grid->dims, sizeof e->dims);
    dens = v->grid->data;
  } else {
    if (bake_noise(v, e) != 0)
      return -1;
    dens = e->baked;
  }
  size_t n = (size_t)e->dims[0] * e->dims[1] * e->dims[2], first = 0;
  while (first < n && !(dens[first] > 0))
    first++;
  e->empty = first == n;
  if (e->empty) { /* Nothing to draw, and nothing to allocate for it. */
    e->valid = 1;
    return 0;
  }
  if (reserve(&e->scratch, &e->scratch_cap, n) != 0 ||
      light_grid(e, dens, sigma, l, e->scratch) != 0)
    return -1;
  e->valid = 1;
  return 0;
}

/* A volume the pass can draw: finite positive box, grid present, samples >= 1. */
static int usable(const rvolume_t *v) {
  for (int k = 0; k < 3; k++)
    if (!(v->max[k] > v->min[k]) || !isfinite(v->min[k]) || !isfinite(v->max[k]))
      return 0;
  if (!(v->density > 0) || !isfinite(v->density) || v->samples < 1)
    return 0;
  if (v->source == VOLUME_GRID)
    return v->grid != NULL && v->grid->data != NULL && v->grid->dims[0] > 0 &&
           v->grid->dims[1] > 0 && v->grid->dims[2] > 0;
  return v->noise_scale > 0 && isfinite(v->noise_scale);
}

/* ---- Shadow map ---------------------------------------------------------------------------- */

/* The shadow map's fit is rounded out to a lattice of at most 1/SHADOW_FIT_LATTICE of its side. */
#define SHADOW_FIT_LATTICE 64

/*
 * Fits the shadow map's plane to the tight boxes of the 'n' entries at 'ents' (those not
 * empty), seen along the light 'l' (unit, towards the light): a square of 'size' texels with a
 * margin of two texels.
 *
 * The fitted bounds are rounded out to multiples of a power of two q, the least one that is at
 * least 1/SHADOW_FIT_LATTICE of the square's side. A playing cloud's tight box changes by a
 * voxel or so at most steps; the rounded fit moves only when that crosses a multiple of q, so
 * the map (about 4 ms at 1024², more than the volumes themselves) is kept across most steps
 * (shadow_cached) rather than rendered again for every frame. The fit depends on the frame's own
 * boxes only, never on earlier frames, so that a frame is the same however it was reached. It
 * costs at most 2q of the side, 1/16 of the map's resolution at worst.
 */
static void fit_shadow(vfx_shadow_t *sh, const vol_entry_t *const *ents, int n, const float l[3],
                       int size) {
  double w[3] = {-l[0], -l[1], -l[2]}, a[3] = {0, 0, 0}, u[3], v[3];
  int least = 0;
  for (int k = 1; k < 3; k++)
    if (fabs(w[k]) < fabs(w[least]))
      least = k;
  a[least] = 1;
  u[0] = a[1] * w[2] - a[2] * w[1], u[1] = a[2] * w[0] - a[0] * w[2],
  u[2] = a[0] * w[1] - a[1] * w[0];
  double ul = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
  for (int k = 0; k < 3; k++)
    u[k] /= ul;
  v[0] = w[1] * u[2] - w[2] * u[1], v[1] = w[2] * u[0] - w[0] * u[2],
  v[2] = w[0] * u[1] - w[1] * u[0];
  double lo[3] = {INFINITY, INFINITY, INFINITY}, hi[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (int i = 0; i < n; i++)
    for (int c = 0; c < 8; c++) {
      double p[3] = {c & 1 ? ents[i]->tmax[0] : ents[i]->tmin[0],
                     c & 2 ? ents[i]->tmax[1] : ents[i]->tmin[1],
                     c & 4 ? ents[i]->tmax[2] : ents[i]->tmin[2]};
      double q[3] = {p[0] * u[0] + p[1] * u[1] + p[2] * u[2],
                     p[0] * v[0] + p[1] * v[1] + p[2] * v[2],
                     p[0] * w[0] + p[1] * w[1] + p[2] * w[2]};
      for (int k = 0; k < 3; k++)
        lo[k] = fmin(lo[k], q[k]), hi[k] = fmax(hi[k], q[k]);
    }
  double side = fmax(hi[0] - lo[0], hi[1] - lo[1]);
  double q = exp2(ceil(log2(side / SHADOW_FIT_LATTICE)));
  if (q > 0 && isfinite(q)) {
    for (int k = 0; k < 3; k++)
      lo[k] = floor(lo[k] / q) * q, hi[k] = ceil(hi[k] / q) * q;
    side = fmax(hi[0] - lo[0], hi[1] - lo[1]);
  }
  double texel = side / (size - 4);
  if (!(texel > 0))
    texel = 1e-6;
  double ou = lo[0] - 2 * texel, ov = lo[1] - 2 * texel;
  for (int k = 0; k < 3; k++) {
    sh->origin[k] = (float)(ou * u[k] + ov * v[k] + lo[2] * w[k]);
    sh->u[k] = (float)u[k], sh->v[k] = (float)v[k], sh->w[k] = (float)w[k];
  }
  sh->inv_texel = (float)(1 / texel);
  /* A texel's depth stands for the whole texel, so on a surface sloping away from the light the
   * true depth under a sample differs from it by up to a texel or two: samples just in front
   * of such a surface must not fall into its shadow (acne). Leaking light two texels behind an
   * occluder's face cannot be seen in a medium. */
  sh->bias = (float)(2 * texel + 1e-5 * (1 + fabs(lo[2]) + fabs(hi[2])));
  sh->size = size;
  sh->enabled = 1;
}

/* Whether the cached shadow map was made from the same objects and fit; otherwise records the
 * new key. Returns 1 on a match, 0 on a miss, -1 when out of memory. */
static int shadow_cached(renderer_t *r, struct vol_state *vs, const vfx_shadow_t *sh) {
  shadow_key_t *k = &vs->skey;
  const vfx_frame_t *f = &r->frame.consts;
  size_t nobjs = (size_t)f->nsph * SPH_STRIDE + (size_t)f->nconv * CONV_STRIDE;
  int same = vs->smap_valid && memcmp(&k->sh, sh, sizeof *sh) == 0 && k->nsph == f->nsph &&
             k->nconv == f->nconv && k->ntri == f->ntri && k->nobjs == nobjs &&
             (nobjs == 0 || memcmp(k->objs, r->frame.host_objs, nobjs * sizeof(float)) == 0) &&
             k->nbvh == r->frame.bvh_nkeys &&
             (r->frame.bvh_nkeys == 0 ||
              memcmp(k->bvh, r->frame.bvh_keys, r->frame.bvh_nkeys * sizeof *k->bvh) == 0);
  if (same)
    return 1;
  vs->smap_valid = 0;
  if (grow_staging((void **)&k->objs, &k->cap_objs, nobjs ? nobjs : 1, sizeof(float)) != 0)
    return -1;
  mesh_key_t *bvh = realloc(k->bvh, (r->frame.bvh_nkeys ? r->frame.bvh_nkeys : 1) * sizeof *bvh);
  if (bvh == NULL)
    return -1;
  k->bvh = bvh;
  if (nobjs)
    memcpy(k->objs, r->frame.host_objs, nobjs * sizeof(float));
  if (r->frame.bvh_nkeys)
    memcpy(k->bvh, r->frame.bvh_keys, r->frame.bvh_nkeys * sizeof *bvh);
  k->sh = *sh, k->nsph = f->nsph, k->nconv = f->nconv, k->ntri = f->ntri, k->nobjs = nobjs;
  k->nbvh = r->frame.bvh_nkeys;
  return 0;
}

/* Renders the shadow map for 'sh' into vs->smap unless the cached one is the same. */
static int render_shadow(renderer_t *r, struct vol_state *vs, const vfx_shadow_t *sh, char *err,
                         size_t errlen) {
  int c = shadow_cached(r, vs, sh);
  if (c < 0) {
    proto_error_format(err, errlen, "[render] out of memory for the shadow map's key");
    return PROTO_E_INTERNAL;
  }
  if (c == 1)
    return 0;
  size_t lx = r->group[0], ly = r->group[1];
  size_t pitch = round_up((size_t)sh->size, SHADOW_PACKET * lx), rows = round_up(sh->size, ly);
  if (render_ensure_buffer(r, &vs->smap, &vs->cap_smap, pitch * rows, sizeof(float),
                           CL_MEM_READ_WRITE, 0, err, errlen))
    return PROTO_E_DEVICE;
  vs->smap_pitch = (int)pitch;
  cl_int ip = (cl_int)pitch;
  cl_kernel k = vs->kshadow;
  cl_int cr =
      KERNEL_ARGS(CL_SUCCESS, k, 0, {sizeof r->frame.consts, &r->frame.consts}, {sizeof *sh, sh},
                  {sizeof(cl_mem), &r->frame.objs}, {sizeof(cl_mem), &r->frame.nodes},
                  {sizeof(cl_mem), &r->frame.tris}, {sizeof(cl_mem), &vs->smap}, {sizeof ip, &ip});
  size_t global[2] = {pitch / SHADOW_PACKET, rows}, local[2] = {lx, ly};
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, global, local, 0, NULL, NULL);
  if (cr != CL_SUCCESS) {
    proto_error_format(err, errlen, "[render] shadow map failed on %s: %s", r->dev.device_name,
                       cl_dev_strerror(cr));
    return PROTO_E_DEVICE;
  }
  vs->smap_valid = 1;
  return 0;
}

/* ---- The pass ------------------------------------------------------------------------------ */

/* Drops the caches: the entries and the grid references they hold, and the shadow map's key. */
static void volume_reset(renderer_t *r, void *state) {
  (void)r;
  struct vol_state *vs = state;
  for (int i = 0; i < vs->nents; i++)
    entry_clear(&vs->ents[i]);
  free(vs->ents);
  vs->ents = NULL;
  vs->nents = 0;
  vs->data_floats = 0;
  free(vs->skey.objs);
  free(vs->skey.bvh);
  memset(&vs->skey, 0, sizeof vs->skey);
  vs->smap_valid = 0;
}

static void volume_free(renderer_t *r, void *state) {
  struct vol_state *vs = state;
  if (vs == NULL)
    return;
  volume_reset(r, vs);
  render_release((cl_kernel[]){vs->kvol, vs->kshadow, vs->kdown, vs->kup}, 4,
                 (cl_mem[]){vs->recs, vs->data, vs->smap, vs->low_depth, vs->low_linear}, 5);
  free(vs->host_recs);
  free(vs);
}

static int volume_init(renderer_t *r, void **state, char *err, size_t errlen) {
  struct vol_state *vs = render_state_new(state, sizeof *vs, err, errlen);
  if (vs == NULL)
    return -1;
  if ((vs->kvol = cl_dev_kernel(&r->dev, "volumes", err, errlen)) == NULL ||
      (vs->kshadow = cl_dev_kernel(&r->dev, "shadow_map", err, errlen)) == NULL ||
      (vs->kdown = cl_dev_kernel(&r->dev, "volume_depth_down", err, errlen)) == NULL ||
      (vs->kup = cl_dev_kernel(&r->dev, "volume_up", err, errlen)) == NULL)
    return -1;
  /* The shadow map and the volumes work on packets of VOL_PACKET_H rows. */
  render_frame_require(r, 1, VOL_PACKET_H);
  return 0;
}

/* The volumes a frame draws: the scene's (layer volumes) and the cloud (layer cloud). */
static int frame_volumes(const render_scene_t *scene, unsigned layers, const rvolume_t **out,
                         int cap) {
  int n = 0;
  for (int i = 0; (layers & LAYER_VOLUMES) && i < scene->nvolumes && n < cap; i++)
    if (usable(&scene->volumes[i]))
      out[n++] = &scene->volumes[i];
  if ((layers & LAYER_CLOUD) && scene->cloud.grid != NULL && usable(&scene->cloud) && n < cap)
    out[n++] = &scene->cloud;
  return n;
}

typedef struct order {
  double dist;
  int index;
} order_t;

static int by_dist(const void *a, const void *b) {
  const order_t *x = a, *y = b;
  return x->dist < y->dist ? -1 : x->dist > y->dist;
}

/* Enqueues the volumes kernel over the 'pitch' x 'rows' frame 'f' with its opaque 'depth',
 * compositing into 'linear'. */
static cl_int run_volumes(renderer_t *r, struct vol_state *vs, const vfx_frame_t *f,
                          const vfx_shadow_t *sh, cl_int nv, cl_mem smap, cl_int spitch,
                          cl_mem depth, cl_mem linear, size_t pitch, size_t rows,
                          const size_t local[2]) {
  cl_kernel k = vs->kvol;
  cl_int cr =
      KERNEL_ARGS(CL_SUCCESS, k, 0, {sizeof *f, f}, {sizeof *sh, sh}, {sizeof(cl_mem), &vs->recs},
                  {sizeof nv, &nv}, {sizeof(cl_mem), &vs->data}, {sizeof(cl_mem), &smap},
                  {sizeof spitch, &spitch}, {sizeof(cl_mem), &depth}, {sizeof(cl_mem), &linear});
  size_t global[2] = {pitch / VOL_PACKET_W, rows / VOL_PACKET_H};
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, global, local, 0, NULL, NULL);
  return cr;
}

/*
 * The volumes pass at 1/d of the frame's width and height (render.volume_resolution): the
 * opaque depth brought down (volume_depth_down), the volumes kernel on a frame of wider pixels
 * over a transparent buffer, and the result composited over the full frame (volume_up).
 */
static cl_int run_low_volumes(renderer_t *r, struct vol_state *vs, int d, const vfx_shadow_t *sh,
                              cl_int nv, cl_mem smap, cl_int spitch, const size_t local[2],
                              char *err, size_t errlen) {
  vfx_frame_t f = r->frame.consts;
  /* Low pixel i stands for full pixel d i, up to one past the frame's last (kernels/volume.cl). */
  cl_int lw = (f.width - 1) / d + 2, lh = (f.height - 1) / d + 2;
  size_t lp = round_up((size_t)lw, local[0] * VOL_PACKET_W),
         lr = round_up((size_t)lh, local[1] * VOL_PACKET_H);
  /* A row's worth of slack: volume_up loads sixteen low pixels from a packet's first. */
  size_t lpix = lp * lr + VOL_UP_PACKET;
  if (render_ensure_buffer(r, &vs->low_depth, &vs->cap_low_depth, lpix, sizeof(float),
                           CL_MEM_READ_WRITE, 0, err, errlen) ||
      render_ensure_buffer(r, &vs->low_linear, &vs->cap_low_linear, lpix, 4 * sizeof(float),
                           CL_MEM_READ_WRITE, 0, err, errlen))
    return CL_OUT_OF_RESOURCES;
  cl_int pitch = (cl_int)r->frame.pitch, clp = (cl_int)lp, cd = d;
  size_t wg[2] = {VOL_UP_LX, 1}, down[2] = {lp, lr};
  /* volume_up in the objects pass's work-groups, whose pixels the pitch and rows are whole
   * multiples of. */
  size_t up[2] = {r->frame.pitch / VOL_UP_PACKET, r->frame.rows},
         up_wg[2] = {r->group[0], r->group[1] ? r->group[1] : 1};
  cl_kernel k = vs->kdown;
  cl_int cr =
      KERNEL_ARGS(CL_SUCCESS, k, 0, {sizeof(cl_mem), &r->frame.depth}, {sizeof pitch, &pitch},
                  {sizeof f.width, &f.width}, {sizeof f.height, &f.height}, {sizeof cd, &cd},
                  {sizeof(cl_mem), &vs->low_depth}, {sizeof clp, &clp});
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, down, wg, 0, NULL, NULL);
  const float clear = 0.0f;
  if (cr == CL_SUCCESS)
    cr = clEnqueueFillBuffer(r->dev.queue, vs->low_linear, &clear, sizeof clear, 0,
                             lpix * 4 * sizeof(float), 0, NULL, NULL);
  /* Pixel (x, y) of the low frame looks through the centre of full pixel (d x, d y),
   * (d x + 0.5, d y + 0.5) of the image plane, where the kernel puts it at (x + 0.5) d of steps
   * d times longer from a base moved by (1 - d) / 2 steps. */
  f.width = lw, f.height = lh, f.pitch = clp;
  for (int i = 0; i < 3; i++) {
    f.base[i] += (float)(0.5 - 0.5 * d) * (f.step_x[i] + f.step_y[i]);
    f.step_x[i] *= (float)d, f.step_y[i] *= (float)d;
  }
  if (cr == CL_SUCCESS)
    cr = run_volumes(r, vs, &f, sh, nv, smap, spitch, vs->low_depth, vs->low_linear, lp, lr, local);
  k = vs->kup;
  float far_ = r->frame.consts.far_;
  cr = KERNEL_ARGS(cr, k, 0, {sizeof(cl_mem), &vs->low_linear}, {sizeof clp, &clp},
                   {sizeof lw, &lw}, {sizeof lh, &lh}, {sizeof(cl_mem), &vs->low_depth},
                   {sizeof cd, &cd}, {sizeof far_, &far_}, {sizeof(cl_mem), &r->frame.depth},
                   {sizeof pitch, &pitch}, {sizeof(cl_mem), &r->frame.linear});
  if (cr == CL_SUCCESS)
    cr = clEnqueueNDRangeKernel(r->dev.queue, k, 2, NULL, up, up_wg, 0, NULL, NULL);
  return cr;
}

/* The scene's volumes (LAYER_VOLUMES in the frame's layers) and the cloud (LAYER_CLOUD), lit
 * through the objects' shadow map and composited over r->frame.linear up to r->frame.depth. */
static int volume_run(renderer_t *r, void *state, const render_scene_t *scene,
                      const render_params_t *p, const char **ran, char *err, size_t errlen) {
  const char *name = *ran;
  *ran = NULL;
  unsigned layers = p->layers;
  struct vol_state *vs = state;
  int cap = scene->nvolumes + 1;
  const rvolume_t **list = malloc(cap * sizeof *list);
  order_t *ord = malloc(cap * sizeof *ord);
  const vol_entry_t **drawn = malloc(cap * sizeof *drawn);
  int rc = 0;
  if (list == NULL || ord == NULL || drawn == NULL) {
    proto_error_format(err, errlen, "[render] out of memory for %d volumes", scene->nvolumes);
    rc = PROTO_E_INTERNAL;
    goto done;
  }
  int n = frame_volumes(scene, layers, list, cap);
  if (n == 0)
    goto done;
  if (n > vs->nents) {
    vol_entry_t *e = realloc(vs->ents, n * sizeof *e);
    if (e == NULL) {
      proto_error_format(err, errlen, "[render] out of memory for %d volumes", n);
      rc = PROTO_E_INTERNAL;
      goto done;
    }
    memset(e + vs->nents, 0, (n - vs->nents) * sizeof *e);
    vs->ents = e, vs->nents = n;
  }
  const float *l = r->frame.consts.light_dir;
  int changed = 0;

  for (int i = 0; i < n; i++) {
    float sigma = list[i]->density;
    if (entry_matches(&vs->ents[i], list[i], sigma, l))
      continue;
    changed = 1;
    if (entry_build(&vs->ents[i], list[i], sigma, l) != 0) {
      entry_clear(&vs->ents[i]);
      proto_error_format(err, errlen, "[render] out of memory preparing volume %d", i);
      rc = PROTO_E_INTERNAL;
      goto done;
    }
  }
  /* Lay the grids out in one buffer and upload them when anything changed. */
  size_t total = 0;
  for (int i = 0; i < n; i++) {
    vol_entry_t *e = &vs->ents[i];
    size_t nd = (size_t)e->dims[0] * e->dims[1] * e->dims[2];
    if (e->empty)
      continue;
    changed |= e->off != total;
    e->off = total;
    total += nd + 1; /* One voxel more, zero: the x-pair of the last is read at weight 0. */
  }
  changed |= total != vs->data_floats;
  if (total == 0)
    goto done;
  if (render_ensure_buffer(r, &vs->data, &vs->cap_data, total, 2 * sizeof(float), CL_MEM_READ_ONLY,
                           1, err, errlen)) {
    rc = PROTO_E_DEVICE;
    goto done;
  }
  cl_int cr = CL_SUCCESS;
  if (changed) {
    vs->data_floats = 0;
    /* Each grid is packed straight into the mapped buffer (on a CPU device, the buffer's own
     * memory): no copy of 16 bytes a voxel on the host, and none on upload. */
    for (int i = 0; i < n && cr == CL_SUCCESS; i++) {
      vol_entry_t *e = &vs->ents[i];
      if (e->empty)
        continue;
      size_t nd = (size_t)e->dims[0] * e->dims[1] * e->dims[2];
      float *dst = clEnqueueMapBuffer(r->dev.queue, vs->data, CL_TRUE,
                                      CL_MAP_WRITE_INVALIDATE_REGION, e->off * 2 * sizeof(float),
                                      (nd + 1) * 2 * sizeof(float), 0, NULL, NULL, &cr);
      if (cr != CL_SUCCESS)
        break;
      pack(e, e->grid ? e->grid->data : e->baked, e->scratch, dst);
      dst[2 * nd] = dst[2 * nd + 1] = 0;
      cr = clEnqueueUnmapMemObject(r->dev.queue, vs->data, dst, 0, NULL, NULL);
    }
    if (cr == CL_SUCCESS)
      vs->data_floats = total;
  }

  /* Records, nearest box first. */
  int nd = 0;
  for (int i = 0; i < n; i++) {
    vol_entry_t *e = &vs->ents[i];
    if (e->empty)
      continue;
    double d2 = 0;
    for (int k = 0; k < 3; k++) {
      double c = 0.5 * ((double)e->tmin[k] + e->tmax[k]) - r->frame.consts.eye[k];
      d2 += c * c;
    }
    ord[nd].dist = d2, ord[nd].index = i;
    nd++;
  }
  qsort(ord, nd, sizeof *ord, by_dist);
  if (grow_staging((void **)&vs->host_recs, &vs->host_recs_cap, (size_t)nd * VOL_STRIDE,
                   sizeof(float)) != 0) {
    proto_error_format(err, errlen, "[render] out of memory for %d volumes", nd);
    rc = PROTO_E_INTERNAL;
    goto done;
  }
  for (int j = 0; j < nd; j++) {
    const vol_entry_t *e = &vs->ents[ord[j].index];
    const rvolume_t *v = list[ord[j].index];
    float *rec = vs->host_recs + (size_t)j * VOL_STRIDE;
    memset(rec, 0, VOL_STRIDE * sizeof(float));
    for (int k = 0; k < 3; k++) {
      double ext = (double)e->max[k] - e->min[k];
      int32_t di = (int32_t)e->dims[k];
      rec[VOL_TMIN + k] = e->tmin[k];
      rec[VOL_TMAX + k] = e->tmax[k];
      rec[VOL_BMIN + k] = e->min[k];
      rec[VOL_INV + k] = (float)(e->dims[k] / ext);
      memcpy(&rec[VOL_DIMS + k], &di, sizeof di);
      rec[VOL_ALBEDO + k] = v->albedo[k];
    }
    int32_t off = (int32_t)e->off, ns = v->samples, edge = 0;
    for (int k = 0; k < 3; k++) {
      double half = 0.5 * ((double)e->max[k] - e->min[k]) / e->dims[k];
      edge |= e->tmin[k] < e->min[k] + half || e->tmax[k] > e->max[k] - half;
    }
    memcpy(&rec[VOL_EDGE], &edge, sizeof edge);
    memcpy(&rec[VOL_OFF], &off, sizeof off);
    memcpy(&rec[VOL_SAMPLES], &ns, sizeof ns);
    rec[VOL_SIGMA] = v->density;
    rec[VOL_PHASE_G] = v->phase_g;
    drawn[j] = e;
  }
  if (render_ensure_buffer(r, &vs->recs, &vs->cap_recs, (size_t)nd * VOL_STRIDE, sizeof(float),
                           CL_MEM_READ_ONLY, 1, err, errlen)) {
    rc = PROTO_E_DEVICE;
    goto done;
  }
  if (cr == CL_SUCCESS)
    cr =
        clEnqueueWriteBuffer(r->dev.queue, vs->recs, CL_FALSE, 0,
                             (size_t)nd * VOL_STRIDE * sizeof(float), vs->host_recs, 0, NULL, NULL);
  if (cr != CL_SUCCESS) {
    proto_error_format(err, errlen, "[render] volume upload failed on %s: %s", r->dev.device_name,
                       cl_dev_strerror(cr));
    rc = PROTO_E_DEVICE;
    goto done;
  }

  /* The shadow map, when something can cast a shadow. */
  vfx_shadow_t sh;
  memset(&sh, 0, sizeof sh);
  sh.size = 1;
  int casters = r->frame.consts.nsph + r->frame.consts.nconv + r->frame.consts.ntri > 0;
  int lit = l[0] != 0 || l[1] != 0 || l[2] != 0;
  if (casters && lit) {
    int size = scene->light.shadow_map > 0 ? scene->light.shadow_map : 1024;
    fit_shadow(&sh, drawn, nd, l, size < 8 ? 8 : size);
    if ((rc = render_shadow(r, vs, &sh, err, errlen)) != 0)
      goto done;
  }
  cl_mem smap = sh.enabled ? vs->smap : vs->data;
  cl_int spitch = sh.enabled ? vs->smap_pitch : 0;
  /* The objects work-group's pixels, or fewer if the device shrank it below one packet. */
  size_t local[2] = {r->group[0] * PACKET / VOL_PACKET_W, r->group[1] / VOL_PACKET_H};
  if (local[1] == 0)
    local[1] = 1;
  int d = scene->volume_div > 1 ? scene->volume_div : 1;
  if (d == 1)
    cr = run_volumes(r, vs, &r->frame.consts, &sh, nd, smap, spitch, r->frame.depth,
                     r->frame.linear, r->frame.pitch, r->frame.rows, local);
  else
    cr = run_low_volumes(r, vs, d, &sh, nd, smap, spitch, local, err, errlen);
  if (cr == CL_SUCCESS)
    cr = clFinish(r->dev.queue);
  if (cr != CL_SUCCESS) {
    proto_error_format(err, errlen, "[render] volumes pass failed on %s: %s", r->dev.device_name,
                       cl_dev_strerror(cr));
    rc = PROTO_E_DEVICE;
    goto done;
  }
  *ran = name;

done:
  free(list);
  free(ord);
  free(drawn);
  return rc;
}

/* Volumes are drawn in the beauty picture only. */
static int volume_wants(const renderer_t *r, const render_scene_t *scene,
                        const render_params_t *p) {
  (void)r;
  return (p->layers & (LAYER_VOLUMES | LAYER_CLOUD)) && p->aov == AOV_BEAUTY &&
         (scene->nvolumes > 0 || scene->cloud.grid != NULL);
}

const render_pass_t render_pass_volumes = {.name = "volumes",
                                           .layers = LAYER_VOLUMES | LAYER_CLOUD,
                                           .init = volume_init,
                                           .free = volume_free,
                                           .wants = volume_wants,
                                           .run = volume_run,
                                           .reset = volume_reset};
