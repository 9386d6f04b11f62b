/*
 * The volume pass (SPEC §5.3 and the rendering half of §5.4) and the shadow map it reads.
 *
 * volumes: every pixel's camera ray is sampled, volume by volume (the host orders them by
 * distance), only between where it enters the volume's tight box and min(where it leaves it,
 * the opaque depth of the objects pass): N samples at the midpoints of N equal segments of that
 * interval (paper 002, eqs. 2-4), so neither the box's faces nor the objects cutting the volume
 * can produce slice stripes. Front to back (eqs. 5-7, 9), a sample of extinction sigma over a
 * segment of length dt has opacity 1 - exp(-sigma dt) exactly, rather than the paper's linear
 * correction (eq. 8). Each sample scatters the light once: the light's colour, times the
 * transmittance from the sample towards the light through the volume (a precomputed light
 * grid), times the fraction of the light the opaque objects let through (the shadow map), times
 * a Henyey-Greenstein phase; plus the ambient term. The march stops once every ray of the
 * packet is nearly opaque, and the light and shadow lookups are skipped where every ray of the
 * packet sees zero density.
 *
 * Light shafts (paper 002, §3.3): the shadow term of sample i is the mean of VOL_SHADOW_TAPS
 * shadow-map tests spread along its segment [t_(i-1/2), t_(i+1/2)], alternately half a pixel's
 * footprint either side of the ray across the view and the light (eq. 10), where the first
 * VOL_SHADOW_FIRST of them disagree for some ray of the packet; else the first alone, which
 * agree. The paper takes four such points, at the segment's ends, shared with the neighbours;
 * a ray crossing the slanted sheets of light between occluders meets a shadow edge in many
 * segments, and with only the ends tested the error of each crossing depends on where the
 * edge falls between them, which draws bands that follow the sample spacing. Tests inside the
 * segment are cheap (one load each) and shrink that error to 1 / (2 VOL_SHADOW_TAPS) of a
 * segment where it matters, below what the eye sees, while the lateral offsets blend a shaft's
 * edge across the pixel. Each tap is also moved by its own fraction of a texel across the map
 * (an 8 x 8 grid, every row and column once), so that their mean filters the staircase a
 * slanted occluder's edge makes of the map's texels over about one texel, as a
 * percentage-closer filter would, without its four loads a test: rays crossing many shaft
 * edges otherwise sum those steps into streaks. And every pixel of a 4 x 4 tile turns its tests
 * around its segments by its own phase (interleaved sampling, below), so the error of a
 * segment's tests, which otherwise follows the depth in smooth rings, differs from pixel to
 * pixel and averages out over a few.
 *
 * A work-item shades a 4 x 4 block of pixels (VOL_PACKET_W x VOL_PACKET_H) in the lanes of a
 * float16, so that PoCL's code is vector code filling AVX-512's registers. Sixteen lanes rather
 * than eight took a third off the pass: the loads per pixel stay, the
 * arithmetic and the spills of the values that live across the sample loop are shared by twice
 * the pixels. A square block rather than sixteen pixels of a row keeps the lanes' samples close
 * together, so that they fall in fewer voxels of a grid, each of which is loaded once for the
 * packet (vol_trilinear): 30% off a cloud frame. Shadow-map lookups are per-lane loads.
 */
#include "common.h"
#include "volume.h"
#include "ellipsoid.h"

typedef float16 vf;
typedef int16 vi;

#define VOL_LANES                                                                                  \
  ((vf)(0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f, 8.5f, 9.5f, 10.5f, 11.5f, 12.5f, 13.5f,    \
        14.5f, 15.5f))
/* A packet's pixels: lane k is column k % 4 and row k / 4 of a 4 x 4 block. */
#define VOL_LANE_X                                                                                 \
  ((vf)(0.5f, 1.5f, 2.5f, 3.5f, 0.5f, 1.5f, 2.5f, 3.5f, 0.5f, 1.5f, 2.5f, 3.5f, 0.5f, 1.5f, 2.5f,  \
        3.5f))
#define VOL_LANE_Y                                                                                 \
  ((vf)(0.5f, 0.5f, 0.5f, 0.5f, 1.5f, 1.5f, 1.5f, 1.5f, 2.5f, 2.5f, 2.5f, 2.5f, 3.5f, 3.5f, 3.5f,  \
        3.5f))
#define convert_vi convert_int16
#define convert_vf convert_float16
#define as_vf as_float16
#define VOL_GATHER(p, i)                                                                           \
  ((vf)(p[(i).s0], p[(i).s1], p[(i).s2], p[(i).s3], p[(i).s4], p[(i).s5], p[(i).s6], p[(i).s7],    \
        p[(i).s8], p[(i).s9], p[(i).sa], p[(i).sb], p[(i).sc], p[(i).sd], p[(i).se], p[(i).sf]))

/*
 * exp(-x) for finite x >= 0, to about 2e-7 relative, in vector code. The builtin exp became a
 * call into the C library per lane, and a call inside the sample loop makes the compiler spill
 * every live vector register around it. Here exp(-x) = 2^y with y = -x log2(e) split into the
 * nearest integer n (by the add-and-subtract rounding trick, exact for |y| < 2^22) and f in
 * [-1/2, 1/2], 2^f from Cephes' degree-6 polynomial (exp2f) and 2^n put into the exponent bits.
 * x is capped at 87, where exp(-x) is below 2^-125 and a medium is opaque anyway.
 */
static inline vf vol_exp_neg(vf x) {
  vf y = fmin(x, 87.0f) * -1.44269504088896341f;
  vf n = (y + 12582912.0f) - 12582912.0f;
  vf f = y - n;
  vf p = fma(f, 1.535336188319500e-4f, 1.339887440266574e-3f);
  p = fma(p, f, 9.618437357674640e-3f);
  p = fma(p, f, 5.550332471162809e-2f);
  p = fma(p, f, 2.402264791363012e-1f);
  p = fma(p, f, 6.931472028550421e-1f);
  p = fma(p, f, 1.0f);
  return p * as_vf((convert_vi(n) + 127) << 23);
}

/*
 * 1 - exp(-x) for finite x >= 0, a segment's opacity, to under 1e-6 relative: below 1/8 from
 * its series, since 1 - vol_exp_neg(x) loses the digits there (about 1e-7 / x relative: 0.65%
 * of a thin slab's light at 1024 samples per ray, where more samples should only do better).
 * The series to x^6 leaves x^7 / 5040 out, below 1e-9 of x there; above, the difference is
 * within 5e-7 relative.
 */
static inline vf vol_opacity(vf x) {
  vf s = fma(x, -1.0f / 720.0f, 1.0f / 120.0f);
  s = fma(s, x, -1.0f / 24.0f);
  s = fma(s, x, 1.0f / 6.0f);
  s = fma(s, x, -0.5f);
  s = fma(s, x, 1.0f);
  return select(1.0f - vol_exp_neg(x), s * x, x < 0.125f);
}

/*
 * The trilinear interpolation of the density (*d) and light (*l) of grid 'g' (n[0] x n[1] x
 * n[2]) at grid coordinates (x, y, z), in which voxel i's centre is at i. For the density the
 * coordinates are clamped to the centres of the edge voxels, so the edge values extend to the
 * box's faces. The light, which the sweep gives at the centres, is extended linearly over the
 * last half-voxel to the faces instead, from the two outer centres (held there, it was up to
 * 1 - exp(-sigma h / 2) off at a face for a voxel of side h: along the edges of a uniform 32³
 * box of density 0.8 lit obliquely, 10%), and kept in [0, 1].
 */
static inline void vol_trilinear(__global const float2 *restrict g, int nx, int ny, int nz,
                                 int edge, vf x, vf y, vf z, vf *d, vf *l) {
  /* Clamped first, the coordinates are non-negative, so conversion (which truncates) is floor:
   * the builtin floor costs a dozen instructions here. fmax also turns a NaN into 0. */
  vf ux = x, uy = y, uz = z;
  x = fmin(fmax(x, 0.0f), (float)(nx - 1));
  y = fmin(fmax(y, 0.0f), (float)(ny - 1));
  z = fmin(fmax(z, 0.0f), (float)(nz - 1));
  /* The lower corner of the voxel pair along each axis holding the point: at the last centre
   * the pair below it, with weight 1 on the upper. A grid one voxel thick along y or z pairs it
   * with itself; along x with the next voxel in memory, at weight 0 (the buffer holds one
   * voxel more than the grids, finite). */
  int y1 = ny > 1 ? nx : 0, z1 = nz > 1 ? nx * ny : 0;
  vi ix = min(convert_vi(x), max(nx - 2, 0)), iy = min(convert_vi(y), max(ny - 2, 0)),
     iz = min(convert_vi(z), max(nz - 2, 0));
  vf fx = x - convert_vf(ix), fy = y - convert_vf(iy), fz = z - convert_vf(iz);
  /* The light's weights, past [0, 1] in the outer half-voxels when the samples can lie there
   * ('edge'); a grid one voxel thick along an axis has no slope there (along x its pair is
   * another voxel: the density's weight, 0). */
  vf gx = fx, gy = fy, gz = fz;
  if (edge) {
    ux = fmin(fmax(ux, -0.5f), (float)nx - 0.5f);
    uy = fmin(fmax(uy, -0.5f), (float)ny - 0.5f);
    uz = fmin(fmax(uz, -0.5f), (float)nz - 0.5f);
    gx = nx > 1 ? ux - convert_vf(ix) : fx, gy = uy - convert_vf(iy), gz = uz - convert_vf(iz);
  }
  vi b = ix + nx * (iy + ny * iz);
  /*
   * The packet's rays are neighbouring pixels, so their lanes fall in one voxel or a few: each
   * of those voxels' four x-pairs are loaded once and blended into the lanes inside it, instead
   * of sixteen per-lane gathers (a vgatherdps apiece) for every lookup. Each round takes the
   * voxel of a lane not served yet. Finding that lane is the loop's critical path: with
   * AVX-512DQ the lanes left are a bit mask (vpmovd2m) and the next is its lowest set bit; else
   * the corners of the 4 x 4 block first (lane 0, then 15, 3 and 12), then the smallest voxel
   * left. The mask took a quarter off a cloud frame, the corners a tenth.
   */
  vf d00 = 0.0f, d10 = 0.0f, d01 = 0.0f, d11 = 0.0f;
  vf l00 = 0.0f, l10 = 0.0f, l01 = 0.0f, l11 = 0.0f;
#ifdef __AVX512DQ__
  int lane_voxel[VOL_PACKET];
  vstore16(b, 0, lane_voxel);
  unsigned left = 0xffffu;
#else
  vi left = (vi)-1;
  int v0 = b.s0;
#endif
  for (;;) {
#ifdef __AVX512DQ__
    int v0 = lane_voxel[__builtin_ctz(left)];
    vi in = b == v0;
    left &= ~(unsigned)__builtin_ia32_cvtd2mask512(in);
#else
    vi in = b == v0;
    left &= ~in;
#endif
    /* (d[i], T[i], d[i + 1], T[i + 1]) at each of the four corners' x-pairs. */
    __global const float *c = (__global const float *)(g + v0);
    float4 q00 = vload4(0, c), q10 = vload4(0, c + 2 * y1), q01 = vload4(0, c + 2 * z1),
           q11 = vload4(0, c + 2 * (y1 + z1));
    d00 = select(d00, mix((vf)q00.x, (vf)q00.z, fx), in);
    l00 = select(l00, mix((vf)q00.y, (vf)q00.w, gx), in);
    d10 = select(d10, mix((vf)q10.x, (vf)q10.z, fx), in);
    l10 = select(l10, mix((vf)q10.y, (vf)q10.w, gx), in);
    d01 = select(d01, mix((vf)q01.x, (vf)q01.z, fx), in);
    l01 = select(l01, mix((vf)q01.y, (vf)q01.w, gx), in);
    d11 = select(d11, mix((vf)q11.x, (vf)q11.z, fx), in);
    l11 = select(l11, mix((vf)q11.y, (vf)q11.w, gx), in);
#ifdef __AVX512DQ__
    if (!left)
      break;
#else
    if (!any(left))
      break;
    v0 = left.sf ? b.sf : left.s3 ? b.s3 : left.sc ? b.sc : lanes_min(select((vi)INT_MAX, b, left));
#endif
  }
  *d = mix(mix(d00, d10, fy), mix(d01, d11, fy), fz);
  vf lv = mix(mix(l00, l10, gy), mix(l01, l11, gy), gz);
  *l = edge ? fmin(fmax(lv, 0.0f), 1.0f) : lv;
}

/* 1 where the shadow-map texel containing (s, r) does not hold a surface nearer the light than
 * 'z' (less the bias), else 0. */
static inline vf vol_lit(__global const float *restrict smap, int pitch, const vfx_shadow_t *sh,
                         vf s, vf r, vf z) {
  float top = (float)(sh->size - 1);
  /* Clamped to [0, top] first, truncation is floor (see vol_trilinear). */
  vi i = convert_vi(fmin(fmax(s, 0.0f), top)), j = convert_vi(fmin(fmax(r, 0.0f), top));
  vi at = j * pitch + i;
  vf stored = VOL_GATHER(smap, at);
  return select((vf)0.0f, (vf)1.0f, z - sh->bias <= stored);
}

/*
 * The shadow test of the points at fraction (k + 0.5) / VOL_SHADOW_TAPS of the segments
 * [t - dt / 2, t + dt / 2], half a pixel to one side of the ray or the other by (k / 2) % 2,
 * and moved across the map by a fraction of a texel of its own: 1 lit, 0 shadowed. On the ray the
 * map position is linear in t: (s0 + t ds, r0 + t dr, z0 + t dz), s0, r0 and z0 those of the eye;
 * (os, or) is the half-pixel offset per unit of t.
 */
static inline vf vol_tap(__global const float *restrict smap, int pitch, const vfx_shadow_t *sh,
                         int k, vf t, vf dt, vf phase, float s0, vf ds, float r0, vf dr, float z0,
                         vf dz, vf os, vf or_) {
  vf u = (k + 0.5f) / VOL_SHADOW_TAPS + phase;
  vf tk = t + dt * (select(u, u - 1.0f, u >= 1.0f) - 0.5f);
  vf s = k & 2 ? ds - os : ds + os, r = k & 2 ? dr - or_ : dr + or_;
  /* Each tap a different fraction of a texel across the map, every row and column of a
   * VOL_SHADOW_TAPS-square grid once (3 and 5 are prime to 8). */
  float fs = ((float)((3 * k) % VOL_SHADOW_TAPS) + 0.5f) / VOL_SHADOW_TAPS - 0.5f;
  float fr = ((float)((5 * k) % VOL_SHADOW_TAPS) + 0.5f) / VOL_SHADOW_TAPS - 0.5f;
  return vol_lit(smap, pitch, sh, s0 + fs + tk * s, r0 + fr + tk * r, z0 + tk * dz);
}

/*
 * The shadow term of the segments [t - dt / 2, t + dt / 2] of the packet's rays (paper 002,
 * §3.3, with more points than its four). First two tests, at 3/16 and 13/16 of each segment and
 * on either side of the ray: where they agree for every ray of the packet (32 points over its
 * segments), the segments are taken to be wholly lit or wholly shadowed, as most are. Otherwise
 * a segment holds a shadow edge, and the term is the mean of all VOL_SHADOW_TAPS tests spread
 * along it. Two first tests instead of four took a quarter off the paper-002 frame; its images
 * moved by at most 11/255, in a few hundred of its million pixels.
 */
static inline vf vol_shadow(__global const float *restrict smap, int pitch, const vfx_shadow_t *sh,
                            vf t, vf dt, vf phase, float s0, vf ds, float r0, vf dr, float z0,
                            vf dz, vf os, vf or_) {
  vf sum =
      vol_tap(smap, pitch, sh, 1, t, dt, phase, s0, ds, r0, dr, z0, dz, os, or_) +
      vol_tap(smap, pitch, sh, VOL_SHADOW_TAPS - 2, t, dt, phase, s0, ds, r0, dr, z0, dz, os, or_);
  if (all((sum == 0.0f) | (sum == (float)VOL_SHADOW_FIRST)))
    return sum * (1.0f / VOL_SHADOW_FIRST);
  for (int k = 0; k < VOL_SHADOW_TAPS; k++)
    if (k != 1 && k != VOL_SHADOW_TAPS - 2)
      sum += vol_tap(smap, pitch, sh, k, t, dt, phase, s0, ds, r0, dr, z0, dz, os, or_);
  return sum * (1.0f / VOL_SHADOW_TAPS);
}

/* Sixteen RGBA pixels held as four float16 of four pixels each (q[0] the first four), split
 * into one float16 per channel, and joined back. */
static inline void vol_split(const float16 q[4], vf *r, vf *g, vf *b, vf *a) {
  *r = (vf)(q[0].s048c, q[1].s048c, q[2].s048c, q[3].s048c);
  *g = (vf)(q[0].s159d, q[1].s159d, q[2].s159d, q[3].s159d);
  *b = (vf)(q[0].s26ae, q[1].s26ae, q[2].s26ae, q[3].s26ae);
  *a = (vf)(q[0].s37bf, q[1].s37bf, q[2].s37bf, q[3].s37bf);
}

static inline void vol_join(vf r, vf g, vf b, vf a, float16 q[4]) {
  q[0] = (float16)(r.s0, g.s0, b.s0, a.s0, r.s1, g.s1, b.s1, a.s1, r.s2, g.s2, b.s2, a.s2, r.s3,
                   g.s3, b.s3, a.s3);
  q[1] = (float16)(r.s4, g.s4, b.s4, a.s4, r.s5, g.s5, b.s5, a.s5, r.s6, g.s6, b.s6, a.s6, r.s7,
                   g.s7, b.s7, a.s7);
  q[2] = (float16)(r.s8, g.s8, b.s8, a.s8, r.s9, g.s9, b.s9, a.s9, r.sa, g.sa, b.sa, a.sa, r.sb,
                   g.sb, b.sb, a.sb);
  q[3] = (float16)(r.sc, g.sc, b.sc, a.sc, r.sd, g.sd, b.sd, a.sd, r.se, g.se, b.se, a.se, r.sf,
                   g.sf, b.sf, a.sf);
}

/*
 * One packet of 4 x 4 pixels per work-item, its top left pixel at (4 global x, 4 global y),
 * over the padded buffers of the frame 'f' that the objects pass set up. 'vols' holds 'nvol'
 * records (volume.h) nearest first, 'data' their grids; the result is composited over
 * 'linear' (colour and alpha) in place.
 *
 * Register pressure decides the speed here more than arithmetic: every per-lane value that
 * lives across the sample loop is a vector register, and once they spill each sample pays for
 * it. So only the ray direction, the interval, the half-pixel offset, the phase and the
 * accumulators cross the loop; grid and shadow-map coordinates are rebuilt from the direction
 * at each sample, and whatever depends only on the eye stays scalar.
 */
__kernel void volumes(vfx_frame_t f, vfx_shadow_t sh, __global const float *restrict vols, int nvol,
                      __global const float2 *restrict data, __global const float *restrict smap,
                      int smap_pitch, __global const float *restrict depth,
                      __global float *restrict linear) {
  int x0 = VOL_PACKET_W * get_global_id(0), y0 = VOL_PACKET_H * get_global_id(1);
  int o = y0 * f.pitch + x0, row = f.pitch;

  float ex = f.eye[0], ey = f.eye[1], ez = f.eye[2];
  vf px = (float)x0 + VOL_LANE_X, py = (float)y0 + VOL_LANE_Y;
  vf dx = f.base[0] + px * f.step_x[0] + py * f.step_y[0];
  vf dy = f.base[1] + px * f.step_x[1] + py * f.step_y[1];
  vf dz = f.base[2] + px * f.step_x[2] + py * f.step_y[2];
  vf il = 1.0f / sqrt(dx * dx + dy * dy + dz * dz);
  dx *= il, dy *= il, dz *= il;
  vf tend = fmin((vf)(vload4(0, depth + o), vload4(0, depth + o + row),
                      vload4(0, depth + o + 2 * row), vload4(0, depth + o + 3 * row)),
                 f.far_);

  float lx = f.light_dir[0], ly = f.light_dir[1], lz = f.light_dir[2];
  /* The shadow map's coordinates of the eye (scalars), and the half-pixel offset across the
   * view and the light (eq. 10) in texels per unit of t: half a pixel's footprint at unit
   * distance. */
  float pix = 0.5f * length((float3)(f.step_x[0], f.step_x[1], f.step_x[2]));
  float ox = ex - sh.origin[0], oy = ey - sh.origin[1], oz = ez - sh.origin[2];
  float su[3] = {sh.u[0] * sh.inv_texel, sh.u[1] * sh.inv_texel, sh.u[2] * sh.inv_texel};
  float sv[3] = {sh.v[0] * sh.inv_texel, sh.v[1] * sh.inv_texel, sh.v[2] * sh.inv_texel};
  float s0 = ox * su[0] + oy * su[1] + oz * su[2];
  float r0 = ox * sv[0] + oy * sv[1] + oz * sv[2];
  float z0 = ox * sh.w[0] + oy * sh.w[1] + oz * sh.w[2];
  /* Interleaved shadow tests: each pixel of a 4 x 4 tile, by its index c in Bayer order
   * (neighbours far apart), turns its tests around its segments (wrapping at the segment's end)
   * by (c mod 8) / 8 + c / 128 of a segment: the first two tests fall at eight different places
   * and the eight tests' lattice at sixteen. The error of a segment's tests is then no longer
   * the same in neighbouring pixels, where it drew rings that follow the depth at few samples
   * per ray (a shaft edge that the first two tests miss, the eighths of the others), but a fine
   * grain that a mean over a few pixels (render.antialias, or the eye) smooths: a 4 x 4 tile's
   * mean comes 3.4 times closer to the frame with 16 times the samples. */
  vi bx = convert_vi(px) & 3, bq = bx ^ (convert_vi(py) & 3);
  vi cell = ((bq & 1) << 3) | ((bx & 1) << 2) | (bq & 2) | ((bx & 2) >> 1);
  vf tphase = convert_vf(cell & 7) / 8.0f + convert_vf(cell) / 128.0f;
  vf os, or_;
  {
    vf nx = dy * lz - dz * ly, ny = dz * lx - dx * lz, nz = dx * ly - dy * lx;
    vf nl = sqrt(nx * nx + ny * ny + nz * nz);
    /* A ray along the light has no preferred side: any direction across it will do. */
    vi along = nl < 1e-6f;
    nl = pix / fmax(nl, 1e-6f);
    nx = select(nx * nl, (vf)(sh.u[0] * pix), along);
    ny = select(ny * nl, (vf)(sh.u[1] * pix), along);
    nz = select(nz * nl, (vf)(sh.u[2] * pix), along);
    os = nx * su[0] + ny * su[1] + nz * su[2];
    or_ = nx * sv[0] + ny * sv[1] + nz * sv[2];
  }

  /* trc: what rounding took from tr (compensated summation): near 1, tr's last bit is 6e-8,
   * and over a thousand thin segments the rounding of tr -= w added up to 3e-5. */
  vf tr = 1.0f, trc = 0.0f, cr = 0.0f, cg = 0.0f, cb = 0.0f;
  for (int v = 0; v < nvol; v++) {
    __global const float *rec = vols + v * VOL_STRIDE;
    /* The rays' interval inside the tight box, clipped to [near, opaque depth]. */
    vf t0 = f.near_, t1 = tend;
    {
      vf e[3] = {(vf)ex, (vf)ey, (vf)ez}, d[3] = {dx, dy, dz};
      for (int k = 0; k < 3; k++) {
        vf inv = 1.0f / d[k];
        vf ta = (rec[VOL_TMIN + k] - e[k]) * inv, tb = (rec[VOL_TMAX + k] - e[k]) * inv;
        /* A ray parallel to the slab is inside it everywhere or nowhere. */
        vi par = d[k] == 0.0f;
        vi in = (e[k] >= rec[VOL_TMIN + k]) & (e[k] <= rec[VOL_TMAX + k]);
        ta = select(ta, select((vf)INFINITY, (vf)-INFINITY, in), par);
        tb = select(tb, select((vf)-INFINITY, (vf)INFINITY, in), par);
        t0 = fmax(t0, fmin(ta, tb));
        t1 = fmin(t1, fmax(ta, tb));
      }
    }
    vi act = (t0 < t1) & (tr > VOL_T_MIN);
    if (!any(act))
      continue;
    int n = as_int(rec[VOL_SAMPLES]);
    vf dt = select((vf)0.0f, (t1 - t0) / (float)n, act);
    t0 = select((vf)0.0f, t0, act);

    int gx = as_int(rec[VOL_DIMS]), gy = as_int(rec[VOL_DIMS + 1]), gz = as_int(rec[VOL_DIMS + 2]);
    int edge = as_int(rec[VOL_EDGE]);
    __global const float2 *grid = data + as_int(rec[VOL_OFF]);
    /* Grid coordinates of the eye, in which voxel i's centre is at i. */
    float ix = rec[VOL_INV], iy = rec[VOL_INV + 1], iz = rec[VOL_INV + 2];
    float g0x = (ex - rec[VOL_BMIN]) * ix - 0.5f, g0y = (ey - rec[VOL_BMIN + 1]) * iy - 0.5f,
          g0z = (ez - rec[VOL_BMIN + 2]) * iz - 0.5f;

    float sigma = rec[VOL_SIGMA], g = rec[VOL_PHASE_G];
    /* Henyey-Greenstein, scaled by 4 pi so that an isotropic medium (g = 0) has phase 1. */
    vf hg = 1.0f + g * g - 2.0f * g * (dx * lx + dy * ly + dz * lz);
    vf phase = (1.0f - g * g) / (hg * sqrt(hg));
    float lr = f.light_rgb[0] * rec[VOL_ALBEDO], lg = f.light_rgb[1] * rec[VOL_ALBEDO + 1],
          lb = f.light_rgb[2] * rec[VOL_ALBEDO + 2];
    float ar = f.ambient * rec[VOL_ALBEDO], ag = f.ambient * rec[VOL_ALBEDO + 1],
          ab = f.ambient * rec[VOL_ALBEDO + 2];

    for (int i = 0; i < n; i++) {
      vf t = t0 + ((float)i + 0.5f) * dt;
      vf sig, tl;
      vol_trilinear(grid, gx, gy, gz, edge, g0x + t * (dx * ix), g0y + t * (dy * iy),
                    g0z + t * (dz * iz), &sig, &tl);
      sig = select((vf)0.0f, sigma * sig, act);
      if (!any(sig > 0.0f))
        continue;
      vf direct = tl * phase;
      if (sh.enabled) {
        vf ds = dx * su[0] + dy * su[1] + dz * su[2];
        vf dr = dx * sv[0] + dy * sv[1] + dz * sv[2];
        vf dw = dx * sh.w[0] + dy * sh.w[1] + dz * sh.w[2];
        direct *= vol_shadow(smap, smap_pitch, &sh, t, dt, tphase, s0, ds, r0, dr, z0, dw, os, or_);
      }
      vf w = tr * vol_opacity(sig * dt);
      cr += w * fma(lr, direct, ar);
      cg += w * fma(lg, direct, ag);
      cb += w * fma(lb, direct, ab);
      vf y = -w - trc, tn = tr + y;
      trc = (tn - tr) - y;
      tr = tn;
      if (all((tr <= VOL_T_MIN) | ~act))
        break;
    }
  }

  /* Over what the earlier passes drew (eq. 9): C = T * behind + the volume's light. A packet
   * that took no sample leaves the pixels as they are (tr = 1, no light) without the load and
   * store, most of the frame outside the volumes. */
  if (all((tr == 1.0f) & (cr == 0.0f) & (cg == 0.0f) & (cb == 0.0f)))
    return;
  __global float *out = linear + 4 * o;
  float16 q[4] = {vload16(0, out), vload16(0, out + 4 * row), vload16(0, out + 8 * row),
                  vload16(0, out + 12 * row)};
  vf br, bg, bb, ba;
  vol_split(q, &br, &bg, &bb, &ba);
  vol_join(fma(tr, br, cr), fma(tr, bg, cg), fma(tr, bb, cb), fma(tr, ba, 1.0f - tr), q);
  for (int k = 0; k < 4; k++)
    vstore16(q[k], 0, out + 4 * k * row);
}

/* ---- Volumes at a lower resolution ------------------------------------------------------- */

/*
 * With render.volume_resolution below full, the volumes kernel runs on a frame 'd' times
 * smaller each way, over a buffer that starts transparent (so it receives the volumes' light
 * and 1 - their transmittance), and volume_up composites that over the full frame. Low pixel
 * (i, j) stands for full pixel (d i, d j): its ray is that pixel's, and so is its opaque depth
 * (the last column and row, one past the frame's edge, take the edge pixels' depths), so every
 * low pixel is exactly what the full pass gives at one full pixel, every full pixel lies
 * between four low ones (the frame's edges included), and a full pixel beside an object's edge
 * finds low pixels of either side among them.
 *
 * volume_depth_down: the opaque depth of low pixel (global x, global y), that of its full pixel
 * (clamped to the frame).
 */
__kernel void volume_depth_down(__global const float *restrict depth, int pitch, int width,
                                int height, int d, __global float *restrict low, int low_pitch) {
  int x = get_global_id(0), y = get_global_id(1);
  low[y * low_pitch + x] = depth[min(y * d, height - 1) * pitch + min(x * d, width - 1)];
}

/*
 * volume_up: VOL_UP_PACKET full pixels of a row per work-item, at pixel (VOL_UP_PACKET global x,
 * global y). Each
 * takes the volumes' light and opacity from the four low pixels around it, bilinearly over
 * those that saw about the same opaque depth as it does (within VOL_UP_DEPTH of it, relative;
 * their weights renormalised), so that a volume in front of an object's edge does not bleed
 * across it, and from the one whose depth is nearest its own where none does; then composites
 * them over what the earlier passes drew: C = (1 - A) behind + L.
 */
__kernel void volume_up(__global const float *restrict low, int low_pitch, int low_w, int low_h,
                        __global const float *restrict low_depth, int d, float far_,
                        __global const float *restrict depth, int pitch,
                        __global float *restrict linear) {
  int x0 = VOL_UP_PACKET * get_global_id(0), y = get_global_id(1);
  float inv = 1.0f / d;
  /* Low coordinates, in which low pixel i is at i (it stands for full pixel d i); they are not
   * negative, so truncation is floor. */
  vf u = ((float)x0 + VOL_LANES - 0.5f) * inv;
  float v = (float)y * inv;
  vi i0 = min(convert_vi(u), low_w - 1), i1 = min(i0 + 1, low_w - 1);
  int j0 = min((int)v, low_h - 1), j1 = min(j0 + 1, low_h - 1);
  vf fx = clamp(u - convert_vf(i0), 0.0f, 1.0f);
  float fy = clamp(v - (float)j0, 0.0f, 1.0f);
  /* The four low pixels around each lane: depth, then R, G, B and A (1 - transmittance). */
  vf q00[5], q10[5], q01[5], q11[5];
  int first = x0 / d, span = d == 2 ? 8 : 4;
  if ((d == 2 || d == 4) && first >= 0 && first + span <= low_w - 1) {
    /* No lane is clamped: the packet's low pixels are first .. first + span of rows j0 and j1,
     * loaded whole and handed to the lanes by fixed swizzles, instead of twenty gathers. */
    for (int r = 0; r < 2; r++) {
      int row = (r ? j1 : j0) * low_pitch + first;
      __global const float *p = low + 4 * row;
      float16 q[4] = {vload16(0, p), vload16(1, p), vload16(2, p), vload16(3, p)};
      vf w[5];
      w[0] = vload16(0, low_depth + row);
      vol_split(q, &w[1], &w[2], &w[3], &w[4]);
      for (int k = 0; k < 5; k++) {
        vf at0 = d == 2 ? w[k].s0011223344556677 : w[k].s0000111122223333;
        vf at1 = d == 2 ? w[k].s1122334455667788 : w[k].s1111222233334444;
        if (r)
          q01[k] = at0, q11[k] = at1;
        else
          q00[k] = at0, q10[k] = at1;
      }
    }
  } else {
    vi a00 = j0 * low_pitch + i0, a10 = j0 * low_pitch + i1;
    vi a01 = j1 * low_pitch + i0, a11 = j1 * low_pitch + i1;
    q00[0] = VOL_GATHER(low_depth, a00), q10[0] = VOL_GATHER(low_depth, a10);
    q01[0] = VOL_GATHER(low_depth, a01), q11[0] = VOL_GATHER(low_depth, a11);
    for (int k = 0; k < 4; k++) {
      q00[k + 1] = VOL_GATHER(low, 4 * a00 + k), q10[k + 1] = VOL_GATHER(low, 4 * a10 + k);
      q01[k + 1] = VOL_GATHER(low, 4 * a01 + k), q11[k + 1] = VOL_GATHER(low, 4 * a11 + k);
    }
  }
  int o = y * pitch + x0;
  vf z = fmin(vload16(0, depth + o), far_), tol = VOL_UP_DEPTH * z;
  vf d00 = fabs(fmin(q00[0], far_) - z), d10 = fabs(fmin(q10[0], far_) - z);
  vf d01 = fabs(fmin(q01[0], far_) - z), d11 = fabs(fmin(q11[0], far_) - z);
  /* Bilinear weights, kept only for the low pixels whose depth agrees with this pixel's. */
  vf w00 = select(0.0f, (1.0f - fx) * (1.0f - fy), d00 <= tol);
  vf w10 = select(0.0f, fx * (1.0f - fy), d10 <= tol);
  vf w01 = select(0.0f, (1.0f - fx) * fy, d01 <= tol);
  vf w11 = select(0.0f, fx * fy, d11 <= tol);
  vf sum = w00 + w10 + w01 + w11;
  vi some = sum > 0.0f;
  vf inv_sum = 1.0f / select(1.0f, sum, some);
  /* Where none agrees, the nearest in depth, ties to the first. */
  vi n10 = d10 < d00;
  vf best = fmin(d00, d10);
  vi n01 = d01 < best;
  best = fmin(best, d01);
  vi n11 = d11 < best;
  vf c[4];
  for (int k = 0; k < 4; k++) {
    vf c00 = q00[k + 1], c10 = q10[k + 1], c01 = q01[k + 1], c11 = q11[k + 1];
    vf near = select(select(select(c00, c10, n10), c01, n01), c11, n11);
    vf mixed = (w00 * c00 + w10 * c10 + w01 * c01 + w11 * c11) * inv_sum;
    c[k] = select(near, mixed, some);
  }
  __global float *out = linear + 4 * o;
  float16 q[4] = {vload16(0, out), vload16(1, out), vload16(2, out), vload16(3, out)};
  vf br, bg, bb, ba;
  vol_split(q, &br, &bg, &bb, &ba);
  vf t = 1.0f - c[3];
  vol_join(fma(t, br, c[0]), fma(t, bg, c[1]), fma(t, bb, c[2]), fma(t, ba, c[3]), q);
  for (int k = 0; k < 4; k++)
    vstore16(q[k], k, out);
}

/* ---- The shadow map ---------------------------------------------------------------------- */

/*
 * Nearest mesh triangle along lines from per-lane origins o in the shared direction d, at any
 * distance below *best (lines are whole: negative distances count); updates *best.
 */
static void vol_mesh_nearest(__global const float *restrict nodes,
                             __global const float *restrict tris, vf ox, vf oy, vf oz, float dx,
                             float dy, float dz, vf *best) {
  float ix = 1.0f / dx, iy = 1.0f / dy, iz = 1.0f / dz;
  int stack[BVH_MAX_DEPTH];
  int sp = 0, node = 0;
  for (;;) {
    __global const float *nd = nodes + node * NODE_STRIDE;
    vf lo, hi;
    node_span16(nd, ox, oy, oz, ix, iy, iz, &lo, &hi);
    hi = fmin(hi, *best);
    if (any(lo <= hi)) {
      int count = as_int(nd[NODE_COUNT]), first = as_int(nd[NODE_FIRST]);
      if (count == 0) {
        stack[sp++] = first;
        node++;
        continue;
      }
      for (int i = first; i < first + count; i++) {
        vi inside;
        vf t = tri_line16(tris + i * TRI_STRIDE, ox, oy, oz, dx, dy, dz, &inside);
        *best = select(*best, t, inside & (t < *best));
      }
    }
    if (sp == 0)
      return;
    node = stack[--sp];
  }
}

/*
 * The shadow map (volume.h): SHADOW_PACKET texels of a row per work-item at texel
 * (SHADOW_PACKET * global x, global y), 'pitch' texels per row. Each texel's line, in the
 * direction the light travels, is tested against the objects the objects pass uploaded
 * (counts and offsets in 'f') and the nearest surface along the whole line is kept.
 */
__kernel void shadow_map(vfx_frame_t f, vfx_shadow_t sh, __global const float *restrict objs,
                         __global const float *restrict nodes, __global const float *restrict tris,
                         __global float *restrict smap, int pitch) {
  int x0 = SHADOW_PACKET * get_global_id(0), y = get_global_id(1);
  float texel = 1.0f / sh.inv_texel;
  vf s = ((float)x0 + VOL_LANES) * texel, r = (y + 0.5f) * texel;
  vf ox = sh.origin[0] + s * sh.u[0] + r * sh.v[0];
  vf oy = sh.origin[1] + s * sh.u[1] + r * sh.v[1];
  vf oz = sh.origin[2] + s * sh.u[2] + r * sh.v[2];
  float dx = sh.w[0], dy = sh.w[1], dz = sh.w[2];
  vf best = INFINITY;

  for (int i = 0; i < f.nsph; i++) {
    __global const float *sp = objs + i * SPH_STRIDE;
    vf wx = ox - sp[0], wy = oy - sp[1], wz = oz - sp[2];
    /* Lines farther from the centre than the bounding radius miss. */
    vf cx = wy * dz - wz * dy, cy = wz * dx - wx * dz, cz = wx * dy - wy * dx;
    float rad = sp[SPH_RADIUS];
    if (!any(cx * cx + cy * cy + cz * cz <= rad * rad))
      continue;
    float a;
    vf b, disc = ellipsoid_disc(sp + SPH_MINV, wx, wy, wz, dx, dy, dz, &a, &b);
    vf t = (-b - sqrt(fmax(disc, 0.0f))) / a;
    best = select(best, t, (disc >= 0.0f) & (t < best));
  }
  for (int i = 0; i < f.nconv; i++) {
    __global const float *c = objs + f.conv_off + i * CONV_STRIDE;
    vf tin, tout;
    vi miss = convex_span16(c, ox, oy, oz, dx, dy, dz, &tin, &tout);
    best = select(best, tin, ~miss & (tin <= tout) & (tin < best));
  }
  if (f.ntri > 0)
    vol_mesh_nearest(nodes, tris, ox, oy, oz, dx, dy, dz, &best);
  vstore16(best, 0, smap + y * pitch + x0);
}
