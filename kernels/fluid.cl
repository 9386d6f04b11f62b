/*
 * The fluid pass (SPEC §5.2): particles drawn as metaballs. The field of particle j at a point
 * is P_j = s_j^2 with s_j = max(1 - r_j / h, 0); the surface is where I = sqrt(F) - T crosses
 * zero, F = sum of P_j. Each camera ray walks the host's uniform grid (vfx_fluid_t in
 * common.h) with a 3-D DDA, samples the field only in cells whose list is not empty (elsewhere
 * F is exactly zero), and ends the search at the opaque depth. The first crossing is bracketed
 * by a safe step, refined by regula falsi and placed by the linear interpolation of the
 * paper's eq. 5. The hit is shaded as water over the objects' colour and its distance written
 * to the depth buffer, so the passes after it are clipped by the fluid.
 *
 * A work-item traces a packet of FLUID_PW x FLUID_PH (4 x 4) neighbouring pixels, one per lane
 * of a float16, so that the grid walk, the step logic, the refinement and the shading are
 * vector code. Every ray keeps its own state (its cell, its march, its bracket); the rays of a
 * packet march together, a ray's lane masked off once it is done. Each round picks one list
 * that some rays need a sample from (the lowest list start among them) and evaluates the field
 * for every ray whose pending sample uses that list, looping over its particles one at a time
 * with the rays in the lanes: neighbouring rays mostly sit in the same cell, so one pass over a
 * list serves many of them. The other rays wait for their own list's round. The walk of every
 * ray is the one a lone ray would take, so the image does not depend on the packets.
 */
#include "common.h"

typedef float16 pf;
typedef int16 pi;

#define FLUID_LANES 16
_Static_assert((FLUID_PW * FLUID_PH) == FLUID_LANES, "a fluid packet fills a float16");

/* What a ray of the packet is doing. */
#define FL_DONE 0   /* Finished: hit or missed. */
#define FL_CELL 1   /* Walking the grid to the next cell with a list. */
#define FL_MARCH 2  /* A march sample at ts is due. */
#define FL_LOOK 3   /* A look past the tangent's crossing at ts is due. */
#define FL_REFINE 4 /* A regula falsi sample at ts is due. */

/*
 * 1 / sqrt(x) for finite x > 0. The pragma lets LLVM use the CPU's reciprocal estimate with a
 * Newton step (vrsqrt14ps), which runs beside the rest of the maths, instead of vsqrtps and
 * vdivps, which share one slow divider and were most of the field sums' time. It also lets LLVM
 * assume no infinities or NaNs, so it is kept to this helper, whose callers keep x finite and
 * positive.
 */
static inline pf fluid_rsqrt(pf x) {
#pragma float_control(precise, off)
  return 1.0f / sqrt(x);
}

/*
 * Bounding the field ahead along the ray. Let x be a point of the ray e + t d (|d| = 1) and
 * r_j, sigma_j = 1 - r_j / h the distance to particle j and its unclamped s_j there. Along the
 * ray, r_j(x + u d) is the norm of an affine function of u, hence convex, so it lies above its
 * tangent: r_j(x + u d) >= r_j - u k_j with k_j = d . (p_j - x) / r_j in [-1, 1] (the cosine
 * between the ray and the direction to the particle). So at u = delta h along the ray,
 *   s_j <= max(sigma_j + delta k_j, 0)  and  F <= G(delta) = sum of max(sigma_j + delta k_j, 0)^2.
 * G is a sum of squares of clamped linear functions, hence convex in delta, so over a whole
 * step [0, D] it never exceeds the larger of G(0) = F and G(D): with both below T^2, F stays
 * below T^2 at every point of the step. G is tangent to F at delta = 0 (its slope there is
 * 2A, A = sum of s_j k_j, exactly F's) and lies above it: a step D with G(D) below T^2 is
 * safe, and as the ray closes in on the surface the longest such step approaches the true
 * distance.
 * (Bounding every k_j by 1 instead, as fluid_step's cruder bound does, cuts the steps near a
 * dense block to a few hundredths of h.)
 */

/* What one pass over a list gives the rays of a packet, per lane: F, S = sum of s_j, A = sum
 * of s_j k_j, the nearest particle's sigma_j (-2 when none is within 3h) and G at the four
 * steps of the lane's ladder (units of h). */
typedef struct {
  pf f, s, a, near_sigma, g0, g1, g2, g3;
} fluid_sums_t;

/* A march sample evaluates G at the steps FLUID_RUNG0-2 and 1 times D (units of h), where D is
 * the distance to the end of the sample's cell, at most FLUID_REACH: beyond that end the cell's
 * list no longer bounds the field, and a ladder that ends there lets a step reach it whenever
 * that is safe, so that the rays of a packet cross cell faces together. */
#define FLUID_REACH 1.0f
#define FLUID_RUNG0 0.1f
#define FLUID_RUNG1 0.25f
#define FLUID_RUNG2 0.55f

/* The sums of fluid_sums_t at the points (x, y, z) of the lanes along the directions (ux, uy,
 * uz), over the 'm' particles of the list at 'first', with G at the steps l0-l3. */
static inline fluid_sums_t fluid_sums(__global const float *restrict pos, int first, int m, pf x,
                                      pf y, pf z, pf ux, pf uy, pf uz, float inv_h, pf l0, pf l1,
                                      pf l2, pf l3) {
  pf f = 0.0f, s = 0.0f, a = 0.0f, near = -2.0f, g0 = 0.0f, g1 = 0.0f, g2 = 0.0f, g3 = 0.0f;
  __global const float *p = pos + 3 * first;
  for (int i = 0; i < m; i++, p += 3) {
    pf vx = p[0] - x, vy = p[1] - y, vz = p[2] - z;
    pf r2 = vx * vx + vy * vy + vz * vz;
    pf ir = fluid_rsqrt(max(r2, 1e-30f));
    /* sigma_j and k_j. A hair is added to the cosine so that rounding can only lengthen G's
     * reach. */
    pf sg = 1.0f - r2 * ir * inv_h;
    pf kp = (vx * ux + vy * uy + vz * uz) * ir + 1e-3f;
    pf sj = max(sg, 0.0f);
    f += sj * sj;
    s += sj;
    a += sj * kp;
    near = max(near, sg);
    pf u0 = max(sg + l0 * kp, 0.0f), u1 = max(sg + l1 * kp, 0.0f);
    pf u2 = max(sg + l2 * kp, 0.0f), u3 = max(sg + l3 * kp, 0.0f);
    g0 += u0 * u0, g1 += u1 * u1, g2 += u2 * u2, g3 += u3 * u3;
  }
  return (fluid_sums_t){f, s, a, near, g0, g1, g2, g3};
}

/* F alone at the lanes' points, over the list at 'first'. */
static inline pf fluid_field(__global const float *restrict pos, int first, int m, pf x, pf y, pf z,
                             float inv_h) {
  pf f = 0.0f;
  __global const float *p = pos + 3 * first;
  for (int i = 0; i < m; i++, p += 3) {
    pf vx = p[0] - x, vy = p[1] - y, vz = p[2] - z;
    pf r2 = max(vx * vx + vy * vy + vz * vz, 1e-30f);
    pf sj = max(1.0f - r2 * fluid_rsqrt(r2) * inv_h, 0.0f);
    f += sj * sj;
  }
  return f;
}

/*
 * A safe step (units of h) from the sums 'q' at the current point; the list holds 'm'
 * particles. The longest of: the ladder's steps l0-l3 with G below t2 = T^2; the distance
 * -near_sigma no particle reaches within, which keeps F = 0; and, bounding every k_j by 1,
 * G(delta) <= F + 2 delta S + m delta^2, below t2 for delta < (t2 - F) / (S + sqrt(S^2 + m
 * (t2 - F))) (the positive root, written without cancellation).
 */
static inline pf fluid_step(fluid_sums_t q, float t2, pf m, pf l0, pf l1, pf l2, pf l3) {
  pf gap = t2 - q.f;
  pf best = fmax(gap / (q.s + sqrt(q.s * q.s + m * gap)), -q.near_sigma);
  pf l01 = select(select((pf)0.0f, l0, q.g0 < t2), l1, q.g1 < t2);
  pf l23 = select(select((pf)0.0f, l2, q.g2 < t2), l3, q.g3 < t2);
  return fmax(best, fmax(l01, l23));
}

/* The tangent's predicted distance to the surface (units of h) under which the march looks
 * FLUID_PAST times as far ahead for the crossing. */
#define FLUID_CLOSE 0.2f
#define FLUID_PAST 1.3f
/* Regula falsi samples at most per crossing. */
#define FLUID_REFINE_MAX 40

/*
 * The march of one ray, as each lane runs it. Inside a cell whose list ('first', 'm' particles)
 * holds every particle that reaches it, the ray looks over [t, tb] for the first t with
 * F >= T^2. It only takes steps over which G, and so F, provably stays below T^2: no point of
 * the surface, however thin the sheet, lies strictly inside a step, so nothing is skipped and
 * no sample count is capped. Each sample takes fluid_step's step (the longest of G's ladder
 * below T^2, the reach of the nearest particle, or the cruder bound), so the remaining
 * distance shrinks several-fold per sample. Once G's tangent, which reaches T^2 at
 * delta_lin = (T^2 - F) / 2A, puts the surface closer than FLUID_CLOSE h, one field sample
 * FLUID_PAST times as far ahead is tried: if it lies inside, the crossing is bracketed at once.
 * That look can only end the march on a crossing, never carry it past one, so it cannot make
 * a hole; at worst, when a sliver of fluid thinner than the look lies in front of the
 * surface, the refinement may settle on the surface just behind the sliver. Near a tangent of
 * the surface the safe step still shrinks, so it has a floor, 'min_step' (h / 2000): a floor
 * step can pass over only a piece of the ray shorter than it that is inside the fluid, i.e. a
 * graze of the surface whose chord is under h / 2000, far below a pixel at any distance we
 * render.
 *
 * A step that is safe to the cell's end leaves the sample there to the next cell's first one;
 * when that one is already inside, the crossing lies in the last step of the cell before, whose
 * list covers that step, and is refined there. The crossing in [a, b], F(a) < T^2 <= F(b), is
 * refined on I = sqrt(F) - T (close to linear near the surface, exactly so for a lone
 * particle, where sqrt(F) = 1 - r / h) by regula falsi (Illinois) to 'tol', then placed by
 * linear interpolation (the paper's eq. 5); or sooner, once the chord from a new sample to the
 * bracket's other end crosses zero within tol / 10 of that sample, at that chord's zero. On the
 * Table 1 block that takes a sample or two per crossing instead of three to four, and the depth
 * stays within 5e-5 h of a refinement to tol / 1000.
 */
__kernel void fluid(vfx_frame_t f, vfx_fluid_t fl, __global const int *restrict cells,
                    __global const float *restrict pos, __global float *restrict linear,
                    __global float *restrict depth) {
  const pi lane = (pi)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
  pi px = (int)get_global_id(0) * FLUID_PW + lane % FLUID_PW;
  pi py = (int)get_global_id(1) * FLUID_PH + lane / FLUID_PW;
  pi o = py * f.pitch + px;
  pi valid = (py < fl.rows) & (px < f.pitch);
  int ol[FLUID_LANES], vl[FLUID_LANES];
  vstore16(o, 0, ol);
  vstore16(valid, 0, vl);
  float opq[FLUID_LANES];
  for (int l = 0; l < FLUID_LANES; l++)
    opq[l] = vl[l] ? depth[ol[l]] : 0.0f;
  pf opaque = vload16(0, opq);

  float ex = f.eye[0], ey = f.eye[1], ez = f.eye[2];
  pf cx = convert_float16(px) + 0.5f, cy = convert_float16(py) + 0.5f;
  pf dx = f.base[0] + cx * f.step_x[0] + cy * f.step_y[0];
  pf dy = f.base[1] + cx * f.step_x[1] + cy * f.step_y[1];
  pf dz = f.base[2] + cx * f.step_x[2] + cy * f.step_y[2];
  pf il = 1.0f / sqrt(dx * dx + dy * dy + dz * dz);
  dx *= il, dy *= il, dz *= il;

  /* The part of [near, min(opaque depth, far)] inside the grid's box. */
  pf ix = 1.0f / dx, iy = 1.0f / dy, iz = 1.0f / dz;
  pf t0x = (fl.box_min[0] - ex) * ix, t1x = (fl.box_max[0] - ex) * ix;
  pf t0y = (fl.box_min[1] - ey) * iy, t1y = (fl.box_max[1] - ey) * iy;
  pf t0z = (fl.box_min[2] - ez) * iz, t1z = (fl.box_max[2] - ez) * iz;
  pf t = fmax(fmax(fmin(t0x, t1x), fmin(t0y, t1y)), fmax(fmin(t0z, t1z), (pf)f.near_));
  pf tend = fmin(fmin(fmax(t0x, t1x), fmax(t0y, t1y)), fmin(fmax(t0z, t1z), fmin(opaque, f.far_)));
  pi mode = select((pi)FL_DONE, (pi)FL_CELL, valid & (t <= tend));
  if (!any(mode != FL_DONE))
    return;

  /* 3-D DDA from the cell holding the entry point. */
  pi kx =
      clamp(convert_int16(floor((ex + t * dx - fl.origin[0]) * fl.inv_cell)), 0, fl.dims[0] - 1);
  pi ky =
      clamp(convert_int16(floor((ey + t * dy - fl.origin[1]) * fl.inv_cell)), 0, fl.dims[1] - 1);
  pi kz =
      clamp(convert_int16(floor((ez + t * dz - fl.origin[2]) * fl.inv_cell)), 0, fl.dims[2] - 1);
  pi sx = select((pi)-1, (pi)1, dx > 0.0f), sy = select((pi)-1, (pi)1, dy > 0.0f);
  pi sz = select((pi)-1, (pi)1, dz > 0.0f);
  pf tdx = fabs(fl.cell * ix), tdy = fabs(fl.cell * iy), tdz = fabs(fl.cell * iz);
  pf nx = (fl.origin[0] + convert_float16(kx + select((pi)0, (pi)1, sx > 0)) * fl.cell - ex) * ix;
  pf ny = (fl.origin[1] + convert_float16(ky + select((pi)0, (pi)1, sy > 0)) * fl.cell - ey) * iy;
  pf nz = (fl.origin[2] + convert_float16(kz + select((pi)0, (pi)1, sz > 0)) * fl.cell - ez) * iz;
  nx = select(nx, (pf)INFINITY, dx == 0.0f);
  ny = select(ny, (pf)INFINITY, dy == 0.0f);
  nz = select(nz, (pf)INFINITY, dz == 0.0f);

  float t2 = fl.threshold * fl.threshold, h = fl.h;
  /* The cell being marched: its end tb, whether it is the ray's last, its list. */
  pf tb = 0.0f;
  pi last = 0, first = 0, lm = 0;
  /* The march's last sample t (F = fa there), the pending sample ts, whether it is the
   * cell's first, and where the march goes on if a look misses. */
  pf fa = 0.0f, ts = 0.0f, tnext = 0.0f;
  pi entry = 0;
  /* The last sample of the cell before, when the march stepped to that cell's end: its t
   * (negative when there is none), F there and its list. */
  pf pt = -1.0f, pfv = 0.0f;
  pi pfirst = 0, pm = 0;
  /* The bracket being refined. */
  pf ra = 0.0f, rb = 0.0f, ga = 0.0f, gb = 0.0f, va = 0.0f, vb = 0.0f;
  pi side = 0, iter = 0;
  pf hit = INFINITY;

  for (;;) {
    /* Rays between cells walk to their next cell with a list, or to the end. */
    while (any(mode == FL_CELL)) {
      pi in = mode == FL_CELL;
      pi c = (kz * fl.dims[1] + ky) * fl.dims[0] + kx;
      int cl[FLUID_LANES], il_[FLUID_LANES], st[FLUID_LANES], mm[FLUID_LANES];
      vstore16(c, 0, cl);
      vstore16(in, 0, il_);
      for (int l = 0; l < FLUID_LANES; l++) {
        st[l] = il_[l] ? cells[2 * cl[l]] : 0;
        mm[l] = il_[l] ? cells[2 * cl[l] + 1] : 0;
      }
      pi cst = vload16(0, st), cm = vload16(0, mm);
      pf tbv = fmin(fmin(nx, ny), fmin(nz, tend));
      pi enter = in & (cm > 0) & (tbv >= t);
      mode = select(mode, (pi)FL_MARCH, enter);
      ts = select(ts, t, enter);
      entry = select(entry, (pi)-1, enter);
      first = select(first, cst, enter);
      lm = select(lm, cm, enter);
      tb = select(tb, tbv, in);
      last = select(last, tbv >= tend, enter);
      /* F is 0 all over an empty cell, so nothing carries across it. */
      pi skip = in & ~enter;
      pt = select(pt, (pf)-1.0f, skip);
      pi fin = skip & (tbv >= tend);
      mode = select(mode, (pi)FL_DONE, fin);
      pi mv = skip & ~fin;
      t = select(t, fmax(t, tbv), mv);
      pi bx = mv & (nx <= ny) & (nx <= nz), by = mv & ~bx & (ny <= nz), bz = mv & ~bx & ~by;
      kx = select(kx, kx + sx, bx), nx = select(nx, nx + tdx, bx);
      ky = select(ky, ky + sy, by), ny = select(ny, ny + tdy, by);
      kz = select(kz, kz + sz, bz), nz = select(nz, nz + tdz, bz);
      pi out = mv & ((convert_uint16(kx) >= (uint)fl.dims[0]) |
                     (convert_uint16(ky) >= (uint)fl.dims[1]) |
                     (convert_uint16(kz) >= (uint)fl.dims[2]));
      mode = select(mode, (pi)FL_DONE, out);
    }
    pi busy = mode != FL_DONE;
    if (!any(busy))
      break;

    /* One round: the rays whose pending sample uses the list of the ray furthest behind. */
    float tmin = lanes_fmin(select((pf)INFINITY, ts, busy));
    int key = lanes_min(select((pi)INT_MAX, first, busy & (ts == tmin)));
    pi g = busy & (first == key);
    int m = lanes_max(select((pi)0, lm, g));
    pi gm = g & (mode == FL_MARCH), gl = g & (mode == FL_LOOK), gr = g & (mode == FL_REFINE);
    pf x = ex + ts * dx, y = ey + ts * dy, z = ez + ts * dz;
    pf l3 = clamp((tb - ts) * fl.inv_h, 0.0f, FLUID_REACH);
    pf l0 = l3 * FLUID_RUNG0, l1 = l3 * FLUID_RUNG1, l2 = l3 * FLUID_RUNG2;
    fluid_sums_t q;
    if (any(gm))
      q = fluid_sums(pos, key, m, x, y, z, dx, dy, dz, fl.inv_h, l0, l1, l2, l3);
    else
      q = (fluid_sums_t){
          fluid_field(pos, key, m, x, y, z, fl.inv_h), 0.0f, 0.0f, -2.0f, 0.0f, 0.0f, 0.0f, 0.0f};
    pi inside = q.f >= t2;

    /* March samples. Inside at a cell's first sample: the crossing lies in the cell before's
     * last step when it has one, or is the entry point itself. */
    pi ent_in = gm & inside & entry;
    pi from_prev = ent_in & (pt >= 0.0f) & (pt < ts);
    pi at_entry = ent_in & ~from_prev;
    hit = select(hit, ts, at_entry);
    mode = select(mode, (pi)FL_DONE, at_entry);
    /* Brackets to refine: [pt, ts] in the list before, or [t, ts] here. */
    pi bracket = (gm & inside & ~entry) | from_prev | (gl & inside);
    ra = select(ra, select(t, pt, from_prev), bracket);
    rb = select(rb, ts, bracket);
    ga = select(ga, sqrt(select(fa, pfv, from_prev)) - fl.threshold, bracket);
    gb = select(gb, sqrt(q.f) - fl.threshold, bracket);
    va = select(va, ga, bracket);
    vb = select(vb, gb, bracket);
    side = select(side, (pi)0, bracket);
    iter = select(iter, (pi)0, bracket);
    first = select(first, pfirst, from_prev);
    lm = select(lm, pm, from_prev);

    /* A march sample outside: the safe step, and a look past the tangent's crossing when the
     * surface seems close. */
    pi ahead = gm & ~inside;
    t = select(t, ts, ahead);
    fa = select(fa, q.f, ahead);
    pf step = fmax(fluid_step(q, t2, convert_float16(lm), l0, l1, l2, l3) * h, fl.min_step);
    pf lin = select((pf)INFINITY, (t2 - q.f) / (2.0f * q.a), q.a > 0.0f);
    pf tl = t + FLUID_PAST * h * lin;
    pi look = ahead & (lin < FLUID_CLOSE) & (tl < tb);
    mode = select(mode, (pi)FL_LOOK, look);
    ts = select(ts, tl, look);
    tnext = select(tnext, t + step, look);

    /* The march goes on from t to tn: to the next cell when the step is safe to this one's
     * end, else to a sample at min(tn, tb); a miss at the end of the last cell ends it. */
    pi go = (ahead & ~look) | (gl & ~inside);
    pf tn = select(tnext, t + step, ahead);
    pi leave = go & (tn >= tb) & ~last;
    pi ended = go & ~leave & (t >= tb);
    pi on = go & ~leave & ~ended;
    mode = select(mode, (pi)FL_DONE, ended);
    mode = select(mode, (pi)FL_MARCH, on);
    ts = select(ts, fmin(tn, tb), on);
    entry = select(entry, (pi)0, on);
    pt = select(pt, t, leave);
    pfv = select(pfv, fa, leave);
    pfirst = select(pfirst, first, leave);
    pm = select(pm, lm, leave);
    /* Leaving: the next cell starts at tb (not the last cell, so within the grid's interval). */
    t = select(t, fmax(t, tb), leave);
    pi bx = leave & (nx <= ny) & (nx <= nz), by = leave & ~bx & (ny <= nz);
    pi bz = leave & ~bx & ~by;
    kx = select(kx, kx + sx, bx), nx = select(nx, nx + tdx, bx);
    ky = select(ky, ky + sy, by), ny = select(ny, ny + tdy, by);
    kz = select(kz, kz + sz, bz), nz = select(nz, nz + tdz, bz);
    pi out = leave &
             ((convert_uint16(kx) >= (uint)fl.dims[0]) | (convert_uint16(ky) >= (uint)fl.dims[1]) |
              (convert_uint16(kz) >= (uint)fl.dims[2]));
    mode = select(mode, (pi)FL_CELL, leave & ~out);
    mode = select(mode, (pi)FL_DONE, out);

    /* Regula falsi samples (Illinois). */
    pf gc = sqrt(q.f) - fl.threshold;
    pi up = gr & (gc >= 0.0f), down = gr & ~up;
    rb = select(rb, ts, up);
    ga = select(ga, ga * 0.5f, up & (side == 1));
    ra = select(ra, ts, down);
    gb = select(gb, gb * 0.5f, down & (side == -1));
    gb = select(gb, gc, up);
    ga = select(ga, gc, down);
    side = select(side, (pi)1, up);
    side = select(side, (pi)-1, down);
    iter = select(iter, iter + 1, gr);
    vb = select(vb, gc, up);
    va = select(va, gc, down);
    /* The chord from the new sample to the bracket's other end (unhalved values) crosses zero
     * within tol / 10 of the sample: placed there. */
    pf oe = select(rb, ra, up), ov = select(vb, va, up);
    pf corr = gc * (ts - oe) / (gc - ov);
    pi close = gr & (fabs(corr) <= 0.1f * fl.tol);

    /* New and refined brackets: placed by eq. 5 once within tol, else sampled again. */
    pi ref = bracket | gr;
    pf w = ga / (ga - gb);
    pi done = ref & ((rb - ra <= fl.tol) | (iter >= FLUID_REFINE_MAX));
    pf wc = select((pf)0.5f, w, (w >= 0.0f) & (w <= 1.0f));
    hit = select(hit, ra + (rb - ra) * wc, done);
    hit = select(hit, ts - corr, close);
    done |= close;
    mode = select(mode, (pi)FL_DONE, done);
    pi again = ref & ~done;
    pf c = ra + (rb - ra) * w;
    c = select(0.5f * (ra + rb), c, (c > ra) & (c < rb));
    ts = select(ts, c, again);
    mode = select(mode, (pi)FL_REFINE, again);
  }

  pi found = hit < INFINITY;
  if (!any(found))
    return;

  /* The outward normal, -grad F / 2h = sum of s_j (x - p_j) / r_j (not unit), in the list the
   * crossing was found in, a round per list as above. */
  pf hx = ex + hit * dx, hy = ey + hit * dy, hz = ez + hit * dz;
  pf gx = 0.0f, gy = 0.0f, gz = 0.0f;
  pi todo = found;
  while (any(todo)) {
    int key = lanes_min(select((pi)INT_MAX, first, todo));
    pi g = todo & (first == key);
    int m = lanes_max(select((pi)0, lm, g));
    pf ax = 0.0f, ay = 0.0f, az = 0.0f;
    __global const float *p = pos + 3 * key;
    for (int i = 0; i < m; i++, p += 3) {
      pf vx = hx - p[0], vy = hy - p[1], vz = hz - p[2];
      pf r2 = max(vx * vx + vy * vy + vz * vz, 1e-30f), ir = fluid_rsqrt(r2);
      pf wj = max(1.0f - r2 * ir * fl.inv_h, 0.0f) * ir;
      ax += wj * vx, ay += wj * vy, az += wj * vz;
    }
    gx = select(gx, ax, g), gy = select(gy, ay, g), gz = select(gz, az, g);
    todo &= ~g;
  }

  /* Water: Schlick's Fresnel mixes the reflected background (brighter towards the zenith, as
   * a sky would be; the scene has no environment map) with the transmitted colour behind,
   * tinted; a Blinn-Phong highlight of the light sits on top. */
  pf nl = sqrt(gx * gx + gy * gy + gz * gz);
  pi flat = !(nl > 0.0f);
  pf inl = 1.0f / select(nl, (pf)1.0f, flat);
  gx = select(gx * inl, -dx, flat), gy = select(gy * inl, -dy, flat);
  gz = select(gz * inl, -dz, flat);
  pf cosv = -(gx * dx + gy * dy + gz * dz);
  pi back = cosv < 0.0f;
  gx = select(gx, -gx, back), gy = select(gy, -gy, back), gz = select(gz, -gz, back);
  cosv = fabs(cosv);
  pf k = 1.0f - cosv, k2 = k * k;
  pf fr = fl.f0 + (1.0f - fl.f0) * k2 * k2 * k;
  pf ry = dy + 2.0f * cosv * gy;
  pf sky = 0.7f + 0.6f * clamp(ry, 0.0f, 1.0f);
  float lx = f.light_dir[0], ly = f.light_dir[1], lz = f.light_dir[2];
  pf hvx = lx - dx, hvy = ly - dy, hvz = lz - dz;
  pf hl = sqrt(hvx * hvx + hvy * hvy + hvz * hvz);
  pf nh = select((pf)0.0f, fmax((gx * hvx + gy * hvy + gz * hvz) / hl, 0.0f), hl > 0.0f);
  pf spec = select((pf)0.0f,
                   native_exp2(fl.shininess * native_log2(nh)) * (fl.shininess + 8.0f) * 0.0398f,
                   gx * lx + gy * ly + gz * lz > 0.0f);
  /* Absorption as through water reaching back to the opaque surface behind, at most 3h of it
   * (we do not trace the exit point): thin sheets over the floor stay clear, deep water and
   * drops against the sky take the tint's full colour. */
  pf depth_h = clamp((fmin(opaque, hit + 3.0f * h) - hit) * fl.inv_h, 0.35f, 3.0f);
  pf tr = native_exp2(depth_h * native_log2(fl.color[0]));
  pf tg = native_exp2(depth_h * native_log2(fl.color[1]));
  pf tbl = native_exp2(depth_h * native_log2(fl.color[2]));
  pf refl = 1.0f - fr;
  pf cr = fr * (f.sky[0] * sky + spec * f.light_rgb[0]);
  pf cg = fr * (f.sky[1] * sky + spec * f.light_rgb[1]);
  pf cb = fr * (f.sky[2] * sky + spec * f.light_rgb[2]);
  pf wr = refl * tr, wg = refl * tg, wb = refl * tbl;
  float hr[FLUID_LANES], hg[FLUID_LANES], hb[FLUID_LANES], kr[FLUID_LANES], kg[FLUID_LANES],
      kb[FLUID_LANES], ht[FLUID_LANES];
  int fd[FLUID_LANES];
  vstore16(cr, 0, hr), vstore16(cg, 0, hg), vstore16(cb, 0, hb);
  vstore16(wr, 0, kr), vstore16(wg, 0, kg), vstore16(wb, 0, kb);
  vstore16(hit, 0, ht), vstore16(found, 0, fd);
  for (int l = 0; l < FLUID_LANES; l++) {
    if (!fd[l])
      continue;
    /* Premultiplied over what lies behind: the water lets through its transmittance of it, and
     * its coverage is 1 minus that (the channels' mean, as alpha is one number). */
    float4 behind = vload4(ol[l], linear);
    float through = (kr[l] + kg[l] + kb[l]) * (1.0f / 3.0f);
    vstore4((float4)(hr[l] + kr[l] * behind.x, hg[l] + kg[l] * behind.y, hb[l] + kb[l] * behind.z,
                     1.0f - through * (1.0f - behind.w)),
            ol[l], linear);
    depth[ol[l]] = ht[l];
  }
}
