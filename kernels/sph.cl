/*
 * SPH after Müller et al. 2003 for server/sim_fluid.c. sph_density sums the density with
 * the spiky kernel W = 15 / (pi h^6) (h - r)^3 and turns it into p / rho^2 with
 * p = k (rho - rho0), never negative. sph_forces applies the pressure force with the
 * gradient of that same kernel in the symmetric form m (p_i / rho_i^2 + p_j / rho_j^2),
 * Müller's viscosity Laplacian and gravity, then takes a symplectic Euler step and applies
 * the colliders. Müller's paper uses poly6 for the density and spiky for the pressure; with
 * one kernel for both the pressure force is the exact gradient of the compression energy,
 * and a closed tank keeps its energy instead of slowly gaining it (docs/fluid-validation.md).
 *
 * The host sorts the particles by grid cell before every substep, so a particle's neighbours
 * are nine contiguous runs of the arrays (three x-adjacent cells are adjacent in memory),
 * read eight at a time, and every sum runs in the same order on every run: the results are
 * deterministic.
 *
 * State layout: one float buffer of 6 * stride floats, px | py | pz | vx | vy | vz.
 * 'cell_start' has nx * ny * nz + 1 entries: cell c holds particles cell_start[c] up to
 * cell_start[c + 1]. Cells are at least h across in y and z and half that in x, keyed
 * ((z * ny) + y) * nx + x from floor((p - origin) * inv_cell) (inv_cell_x for x), computed
 * exactly as the host does. A particle's run in a row then spans only the cells that reach
 * within h of it in x: 2 to 2.5 h instead of 3 h.
 */

#define SPH_LOCAL 64 /* The local size of both kernels; sim_fluid.c uses the same. */

/* Collider records of SPHC_STRIDE floats: kind, centre, the rotation R (row-major, world =
 * R * object), semi extents (box) or semi-axes (ellipsoid). A tetrahedron's record is its kind
 * and, from SPHC_PLANES, its four face planes in the world: unit outward normal n and offset d,
 * the solid being n . x < d for all four. */
#define SPHC_KIND 0
#define SPHC_CENTER 1
#define SPHC_ROT 4
#define SPHC_HALF 13
#define SPHC_PLANES 1
#define SPHC_STRIDE 20
#define SPHC_SPHERE 0
#define SPHC_BOX 1
#define SPHC_PLANE 2
#define SPHC_TETRA 3

#define SPH_WALL_N 64 /* Intervals of the wall tables over [0, h]; sim_fluid.c uses the same. */

/* Grid cell of one coordinate, clamped to the grid. */
inline int sph_cell(float p, float origin, float inv_cell, int n) {
  int c = (int)floor((p - origin) * inv_cell);
  return clamp(c, 0, n - 1);
}

/*
 * Table 'tab' (SPH_WALL_N + 1 samples over [0, h]) at distance 'd' from a wall, linearly
 * interpolated; 0 from h on.
 */
inline float sph_wall(__global const float *tab, float d, float inv_h) {
  float u = clamp(d * inv_h, 0.0f, 1.0f) * SPH_WALL_N;
  int k = min((int)u, SPH_WALL_N - 1);
  float f = u - (float)k;
  return tab[k] + f * (tab[k + 1] - tab[k]);
}

/* Per axis, the fraction of a particle's density that the fluid beyond the walls adds. */
inline float3 sph_fill(__global const float *wall, float x, float y, float z, float inv_h,
                       float bx0, float by0, float bz0, float bx1, float by1, float bz1,
                       float rest_density) {
  float3 f = (float3)(sph_wall(wall, x - bx0, inv_h) + sph_wall(wall, bx1 - x, inv_h),
                      sph_wall(wall, y - by0, inv_h) + sph_wall(wall, by1 - y, inv_h),
                      sph_wall(wall, z - bz0, inv_h) + sph_wall(wall, bz1 - z, inv_h));
  return fmin(f / rest_density, 1.0f);
}

/* Lane numbers of a float8 run of particles. */
#define SPH_LANES ((int8)(0, 1, 2, 3, 4, 5, 6, 7))

/* The sum of a float8's lanes, always in the same order. */
inline float sph_sum8(float8 v) {
  float4 a = v.lo + v.hi;
  float2 b = a.lo + a.hi;
  return b.x + b.y;
}

__kernel __attribute__((reqd_work_group_size(SPH_LOCAL, 1, 1))) void
sph_density(__global const float *state, int stride, int n, __global const int *cell_start, int nx,
            int ny, int nz, float ox, float oy, float oz, float inv_cell, float inv_cell_x, float h,
            float mass_kernel, float rest_density, float stiffness, __global const float *wall,
            float inv_h, float bx0, float by0, float bz0, float bx1, float by1, float bz1,
            __global float *inv_rho_out, __global float *pr2_out) {
  int i = get_global_id(0);
  if (i >= n)
    return;
  __global const float *px = state, *py = state + stride, *pz = state + 2 * stride;
  float xi = px[i], yi = py[i], zi = pz[i];
  int cy = sph_cell(yi, oy, inv_cell, ny), cz = sph_cell(zi, oz, inv_cell, nz);
  int x0 = sph_cell(xi - h, ox, inv_cell_x, nx), x1 = sph_cell(xi + h, ox, inv_cell_x, nx);
  /* Each run of three x-adjacent cells is contiguous; it is read eight particles at a time,
   * lanes past its end masked off (the buffers have room for the overreach). */
  float8 acc = 0.0f;
  for (int z = max(cz - 1, 0); z <= min(cz + 1, nz - 1); z++) {
    for (int y = max(cy - 1, 0); y <= min(cy + 1, ny - 1); y++) {
      int row = (z * ny + y) * nx;
      int end = cell_start[row + x1 + 1];
      for (int j = cell_start[row + x0]; j < end; j += 8) {
        float8 dx = xi - vload8(0, px + j), dy = yi - vload8(0, py + j),
               dz = zi - vload8(0, pz + j);
        float8 w = fmax(h - sqrt(dx * dx + dy * dy + dz * dz), 0.0f);
        w = select((float8)0.0f, w, (j + SPH_LANES) < end);
        acc += w * w * w;
      }
    }
  }
  float sum = sph_sum8(acc);
  /* The tank's walls stand for the fluid that would lie beyond them (the wall weight of
   * Harada et al. 2007), so particles beside a wall are not thinned out. Per axis, f is the
   * fraction of a full neighbourhood that lies beyond that axis' walls; near an edge or a
   * corner the regions beyond two walls overlap, and 1 - (1 - fx)(1 - fy)(1 - fz) counts
   * the overlap once (exactly so for a separable kernel, closely for ours). */
  float3 f = sph_fill(wall, xi, yi, zi, inv_h, bx0, by0, bz0, bx1, by1, bz1, rest_density);
  float rho =
      mass_kernel * sum + rest_density * (1.0f - (1.0f - f.x) * (1.0f - f.y) * (1.0f - f.z));
  inv_rho_out[i] = 1.0f / rho;
  pr2_out[i] = fmax(stiffness * (rho - rest_density), 0.0f) / (rho * rho);
}

/* Pushes (x, v) out of tetrahedron record 'c' through the face it is least deep behind and
 * removes the velocity into that face. Returns whether it was inside. */
inline int sph_collide_tetra(__global const float *c, float3 *x, float3 *v) {
  float best = -INFINITY;
  float3 n = (float3)(0.0f);
  for (int k = 0; k < 4; k++) {
    __global const float *pl = c + SPHC_PLANES + 4 * k;
    float3 nk = (float3)(pl[0], pl[1], pl[2]);
    float s = dot(nk, *x) - pl[3];
    if (s >= 0.0f)
      return 0;
    if (s > best)
      best = s, n = nk;
  }
  *x -= best * n;
  float vn = dot(*v, n);
  if (vn < 0.0f)
    *v -= vn * n;
  return 1;
}

/* Pushes (x, v) out of collider record 'c' and removes the velocity into its surface. Returns
 * whether it was inside. */
inline int sph_collide(__global const float *c, float3 *x, float3 *v) {
  if ((int)c[SPHC_KIND] == SPHC_TETRA)
    return sph_collide_tetra(c, x, v);
  float3 ctr = (float3)(c[SPHC_CENTER], c[SPHC_CENTER + 1], c[SPHC_CENTER + 2]);
  float3 r0 = (float3)(c[SPHC_ROT], c[SPHC_ROT + 1], c[SPHC_ROT + 2]);
  float3 r1 = (float3)(c[SPHC_ROT + 3], c[SPHC_ROT + 4], c[SPHC_ROT + 5]);
  float3 r2 = (float3)(c[SPHC_ROT + 6], c[SPHC_ROT + 7], c[SPHC_ROT + 8]);
  float3 semi = (float3)(c[SPHC_HALF], c[SPHC_HALF + 1], c[SPHC_HALF + 2]);
  float3 d = *x - ctr;
  /* Object-space offset q = R^T d; R's columns are the object's axes in the world. */
  float3 q = r0 * d.x + r1 * d.y + r2 * d.z;
  int kind = (int)c[SPHC_KIND];
  float3 qn;  /* The surface point, object space. */
  float3 nrm; /* Outward normal, object space (unnormalised). */
  int inside;
  if (kind == SPHC_SPHERE) {
    float3 u = q / semi;
    float len = length(u);
    inside = len < 1.0f;
    float3 dir = len > 1e-12f ? u / len : (float3)(0.0f, 1.0f, 0.0f);
    qn = dir * semi;
    nrm = dir / semi;
  } else if (kind == SPHC_BOX) {
    float3 pen = semi - fabs(q);
    inside = pen.x > 0.0f && pen.y > 0.0f && pen.z > 0.0f;
    qn = q;
    nrm = (float3)(0.0f);
    if (pen.x <= pen.y && pen.x <= pen.z) {
      qn.x = copysign(semi.x, q.x);
      nrm.x = copysign(1.0f, q.x);
    } else if (pen.y <= pen.z) {
      qn.y = copysign(semi.y, q.y);
      nrm.y = copysign(1.0f, q.y);
    } else {
      qn.z = copysign(semi.z, q.z);
      nrm.z = copysign(1.0f, q.z);
    }
  } else {
    inside = q.y < 0.0f;
    qn = (float3)(q.x, 0.0f, q.z);
    nrm = (float3)(0.0f, 1.0f, 0.0f);
  }
  if (!inside)
    return 0;
  /* Back to the world: world = R * object. */
  float3 c0 = (float3)(r0.x, r1.x, r2.x), c1 = (float3)(r0.y, r1.y, r2.y),
         c2 = (float3)(r0.z, r1.z, r2.z);
  *x = ctr + c0 * qn.x + c1 * qn.y + c2 * qn.z;
  float3 n = normalize(c0 * nrm.x + c1 * nrm.y + c2 * nrm.z);
  float vn = dot(*v, n);
  if (vn < 0.0f)
    *v -= vn * n;
  return 1;
}

/* The most rounds of pushes out of the colliders per substep (see sph_forces). */
#define SPH_COLLIDE_ROUNDS 8

__kernel __attribute__((reqd_work_group_size(SPH_LOCAL, 1, 1))) void
sph_forces(__global const float *state, int stride, int n, __global const int *cell_start, int nx,
           int ny, int nz, float ox, float oy, float oz, float inv_cell, float inv_cell_x, float h,
           __global const float *inv_rho, __global const float *pr2, float mass_spiky,
           float mass_visc, float gx, float gy, float gz, float dt, float vmax,
           __global const float *colliders, int ncolliders, float bx0, float by0, float bz0,
           float bx1, float by1, float bz1, __global const float *wall, float inv_h,
           float rest_density, float viscosity, __global float *out) {
  int i = get_global_id(0);
  if (i >= n)
    return;
  __global const float *px = state, *py = state + stride, *pz = state + 2 * stride;
  __global const float *vx = state + 3 * stride, *vy = state + 4 * stride, *vz = state + 5 * stride;
  float xi = px[i], yi = py[i], zi = pz[i];
  float uxi = vx[i], uyi = vy[i], uzi = vz[i];
  float pi_r2 = pr2[i], inv_rho_i = inv_rho[i];
  int cy = sph_cell(yi, oy, inv_cell, ny), cz = sph_cell(zi, oz, inv_cell, nz);
  int x0 = sph_cell(xi - h, ox, inv_cell_x, nx), x1 = sph_cell(xi + h, ox, inv_cell_x, nx);
  /* Pressure and viscosity force sums, without the constant factors, eight lanes wide. */
  float8 fpx = 0.0f, fpy = 0.0f, fpz = 0.0f, fvx = 0.0f, fvy = 0.0f, fvz = 0.0f;
  for (int z = max(cz - 1, 0); z <= min(cz + 1, nz - 1); z++) {
    for (int y = max(cy - 1, 0); y <= min(cy + 1, ny - 1); y++) {
      int row = (z * ny + y) * nx;
      int end = cell_start[row + x1 + 1];
      for (int j = cell_start[row + x0]; j < end; j += 8) {
        float8 dx = xi - vload8(0, px + j), dy = yi - vload8(0, py + j),
               dz = zi - vload8(0, pz + j);
        float8 r2 = dx * dx + dy * dy + dz * dz;
        /* r = 0 (i itself, or a particle exactly on top of it) pushes nowhere. */
        float8 inv_r = select((float8)0.0f, rsqrt(r2), r2 > 1e-18f);
        float8 q = fmax(h - r2 * inv_r, 0.0f);
        q = select((float8)0.0f, q, (j + SPH_LANES) < end);
        float8 ir = vload8(0, inv_rho + j);
        /* The spiky gradient along (xi - xj) / r pushes i away from j. */
        float8 s = (pi_r2 + vload8(0, pr2 + j)) * q * q * inv_r;
        fpx += s * dx, fpy += s * dy, fpz += s * dz;
        float8 t = q * ir;
        fvx += t * (vload8(0, vx + j) - uxi), fvy += t * (vload8(0, vy + j) - uyi);
        fvz += t * (vload8(0, vz + j) - uzi);
      }
    }
  }
  /* The walls push back with the pressure of the fluid they stand for, taken equal to this
   * particle's: -p / rho² times the gradient of the density they add. An axis' push is
   * scaled by the fractions not beyond the other axes' walls, as in sph_density. */
  __global const float *grad = wall + SPH_WALL_N + 1;
  float3 f = 1.0f - sph_fill(wall, xi, yi, zi, inv_h, bx0, by0, bz0, bx1, by1, bz1, rest_density);
  float3 fw = (float3)(sph_wall(grad, xi - bx0, inv_h) - sph_wall(grad, bx1 - xi, inv_h),
                       sph_wall(grad, yi - by0, inv_h) - sph_wall(grad, by1 - yi, inv_h),
                       sph_wall(grad, zi - bz0, inv_h) - sph_wall(grad, bz1 - zi, inv_h)) *
              (float3)(f.y * f.z, f.x * f.z, f.x * f.y);
  /* The walls drag like fluid at rest (no slip): Müller's viscosity with v_j = 0. */
  __global const float *lap = wall + 2 * (SPH_WALL_N + 1);
  float drag = sph_wall(lap, xi - bx0, inv_h) + sph_wall(lap, bx1 - xi, inv_h) +
               sph_wall(lap, yi - by0, inv_h) + sph_wall(lap, by1 - yi, inv_h) +
               sph_wall(lap, zi - bz0, inv_h) + sph_wall(lap, bz1 - zi, inv_h);
  float kv = viscosity * drag * inv_rho_i * inv_rho_i;
  float3 fp = (float3)(sph_sum8(fpx), sph_sum8(fpy), sph_sum8(fpz));
  float3 fv = (float3)(sph_sum8(fvx), sph_sum8(fvy), sph_sum8(fvz));
  float3 a = (float3)(gx, gy, gz) + pi_r2 * fw - kv * (float3)(uxi, uyi, uzi) + mass_spiky * fp +
             inv_rho_i * mass_visc * fv;
  float3 v = (float3)(uxi, uyi, uzi) + dt * a;
  /* The speed limit (the sound speed) keeps a broken state from blowing up. */
  float speed = length(v);
  if (speed > vmax)
    v *= vmax / speed;
  float3 x = (float3)(xi, yi, zi) + dt * v;
  /* Where two colliders meet (a sphere resting on a floor), pushing out of one can push into
   * the other: the pushes repeat until a round moves nothing, which ends on the seam. */
  for (int round = 0; round < SPH_COLLIDE_ROUNDS; round++) {
    int moved = 0;
    for (int k = 0; k < ncolliders; k++)
      moved |= sph_collide(colliders + k * SPHC_STRIDE, &x, &v);
    if (!moved)
      break;
  }
  /* The tank comes last, so nothing can leave it: clamp, and stop the motion into a wall. */
  float3 lo = (float3)(bx0, by0, bz0), hi = (float3)(bx1, by1, bz1);
  if (x.x <= lo.x && v.x < 0.0f)
    v.x = 0.0f;
  if (x.x >= hi.x && v.x > 0.0f)
    v.x = 0.0f;
  if (x.y <= lo.y && v.y < 0.0f)
    v.y = 0.0f;
  if (x.y >= hi.y && v.y > 0.0f)
    v.y = 0.0f;
  if (x.z <= lo.z && v.z < 0.0f)
    v.z = 0.0f;
  if (x.z >= hi.z && v.z > 0.0f)
    v.z = 0.0f;
  x = clamp(x, lo, hi);
  out[i] = x.x, out[stride + i] = x.y, out[2 * stride + i] = x.z;
  out[3 * stride + i] = v.x, out[4 * stride + i] = v.y, out[5 * stride + i] = v.z;
}
