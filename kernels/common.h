/*
 * Definitions shared by the kernels and the host renderer: the per-frame constants passed by
 * value to the objects kernel, and the layout of the object, BVH node and triangle records in
 * their float buffers. It is valid OpenCL C and valid C11, so render.c includes the same file
 * and the two sides cannot drift; device-only helpers sit under VFX_DEVICE_CODE (OpenCL C, which
 * every OpenCL compiler marks with __OPENCL_VERSION__ or __OPENCL_C_VERSION__).
 *
 * Coordinates. Objects are placed by world = T * Rz * Ry * Rx * S * object: scale first, then
 * the rotations about X, Y and Z in that order (degrees), then the translation. The host
 * turns every object into world-space data before a frame, so kernels never see a rotation.
 * Ray parameters are distances along unit world-space rays.
 */
#ifndef VOLFX_KERNELS_COMMON_H
#define VOLFX_KERNELS_COMMON_H

/*
 * Constants of one frame. Only scalars and scalar arrays, so the layout is the same on the host
 * and on every device. Per-pixel buffers have 'pitch' pixels per row and the height rounded up
 * to the local size, so work-items outside the image write padding instead of testing bounds. The
 * camera ray of pixel (x, y) has the direction normalize(base + (x + 0.5) * step_x + (y + 0.5) *
 * step_y).
 */
typedef struct vfx_frame {
  int width, height; /* Image size. */
  int pitch;         /* Pixels per row of the per-pixel buffers: width rounded up. */
  int nsph;          /* Ellipsoid records at objs[0]. */
  int nconv;         /* Convex records (boxes, tetrahedra, planes) at objs[conv_off]. */
  int conv_off;      /* Float offset of the first convex record. */
  int mesh_off;      /* Float offset of the mesh colours, three per mesh object. */
  int ntri;          /* Triangles in the mesh BVH; 0 skips the meshes. */
  float eye[3];
  float base[3];   /* Direction through the image plane's top-left corner. */
  float step_x[3]; /* Image-plane step per pixel to the right. */
  float step_y[3]; /* Image-plane step per pixel down. */
  float near_, far_;
  float light_dir[3]; /* Unit, towards the light. */
  float light_rgb[3]; /* Light colour times intensity. */
  float ambient;
  float bg[4];  /* Background pixels: linear RGB and alpha; (0, 0, 0, 0) when transparent. */
  float sky[3]; /* The scene's background colour as light that surfaces reflect (the fluid). */
} vfx_frame_t;

/*
 * An ellipsoid (a scaled, rotated sphere) in 16 floats: centre, then the 3x3 matrix, row-major,
 * that maps a world offset from the centre to object space, where the surface is the sphere
 * of radius 0.5; then the linear colour and the radius of a sphere about the centre that
 * contains the ellipsoid.
 */
#define SPH_CENTER 0
#define SPH_MINV 3
#define SPH_COLOR 12
#define SPH_RADIUS 15
#define SPH_STRIDE 16

/*
 * A convex polyhedron in 32 floats: up to six world-space half-spaces n.x <= d as
 * (nx, ny, nz, d) with unit n, the linear colour, the number of half-spaces used (int bits),
 * and a bounding sphere (centre, radius; the radius is INFINITY for a plane). A box uses six
 * half-spaces, a tetrahedron four and an infinite plane one: the plane is the boundary of the
 * half-space below it, so it is seen, and casts shadows, from both sides.
 */
#define CONV_PLANES 6
#define CONV_COLOR 24
#define CONV_NPLANES 27
#define CONV_BOUND 28
#define CONV_STRIDE 32

/*
 * A BVH node in 8 floats: bounds min xyz, max xyz, then two ints stored as float bits. A leaf
 * has count > 0 and 'first' indexes its first triangle; an inner node has count 0, its left
 * child right after it and its right child at 'first'.
 */
#define NODE_FIRST 6
#define NODE_COUNT 7
#define NODE_STRIDE 8
#define BVH_MAX_DEPTH                                                                              \
  40 /* The host stops splitting here, so a traversal stack of this depth suffices. */

/* A triangle in 10 floats: v0, e1 = v1 - v0, e2 = v2 - v0, and as int bits the index of its
 * mesh object, whose colour is at objs[mesh_off + 3 * index]. */
#define TRI_COLOR 9
#define TRI_STRIDE 10

/* Pixels a tonemap work-item converts: the pass launches pitch / TONEMAP_PACKET work-items per
 * row. */
#define TONEMAP_PACKET 16

/* Tone-map operators, matching tone_map_t in render_scene.h. */
#define TONE_OP_NONE 0
#define TONE_OP_REINHARD 1
#define TONE_OP_ACES 2

/*
 * An energy wave (SPEC §5.1) in WAVE_STRIDE floats, made by the host for one frame's eye S,
 * in double and then rounded, so that the kernel never subtracts large coordinates: w = S - M,
 * the unit axis D, w' = w - (w.D) D (the part of w across the axis), s0 = w.D, the beam length
 * L, R^2, eps^2, the strengths a and b, |w'|^2, the clamp c and 1/c, the linear colour and R.
 */
#define WAVE_W 0
#define WAVE_D 3
#define WAVE_WP 6
#define WAVE_S0 9
#define WAVE_L 10
#define WAVE_R2 11
#define WAVE_EPS2 12
#define WAVE_A 13
#define WAVE_B 14
#define WAVE_GP 15
#define WAVE_CLAMP 16
#define WAVE_INV_CLAMP 17
#define WAVE_COLOR 18
#define WAVE_RADIUS 21
#define WAVE_STRIDE 24

/* Pixels of a row that a waves work-item shades, one per vector lane: 16 fills AVX-512's
 * registers. The waves pass launches pitch / WAVES_PACKET work-items per row. */
#define WAVES_PACKET 16

/* Bits of the waves kernels' 'mode'. */
#define WAVES_ADD 1     /* Add the clamped glow to the linear image. */
#define WAVES_STORE_H 2 /* Write the summed unclamped H to the f32 buffer. */
#define WAVES_TONEMAP 4 /* Add the glow and tone-map every pixel into the RGBA8 buffer instead. */
#define WAVES_EMPTY 8   /* No objects pass ran: every ray is the background's, to infinity. */

/*
 * The fluid pass's constants (SPEC §5.2), passed by value. The host sorts the particles into a
 * uniform grid of cubic cells of side 'cell' >= h from 'origin', dims[0] x dims[1] x dims[2]
 * cells, x fastest. Cell c lists every particle within h of its box (a particle is listed in
 * each cell it can reach), so the field anywhere in a cell needs only that cell's list. Lists
 * follow one another in cell order, an entry i being the particle's x, y, z at pos[3i], pos[3i +
 * 1], pos[3i + 2]. cells[2c] is the start (in entries) of cell c's list and cells[2c + 1] the
 * number of particles in it.
 */
typedef struct vfx_fluid {
  float origin[3];
  float cell, inv_cell;
  int dims[3];
  int entries; /* Entries in all the lists, three floats each. */
  float inv_h; /* 1 / h. */
  float h;
  float threshold;  /* T. */
  float min_step;   /* The marching step's floor along the ray (world units). */
  float tol;        /* The crossing's refinement tolerance (world units). */
  float color[3];   /* Transmission tint. */
  float f0;         /* Fresnel reflectance at normal incidence, ((ior - 1) / (ior + 1))^2. */
  float shininess;  /* Blinn-Phong exponent from the roughness. */
  float box_min[3]; /* The grid's bounds. */
  float box_max[3];
  int rows; /* Rows of the per-pixel buffers: packets below them are not traced. */
} vfx_fluid_t;

#define FLUID_PW 4 /* A fluid work-item traces a packet of FLUID_PW x FLUID_PH pixels, */
#define FLUID_PH 4 /* one per lane of a float16. */
#define FLUID_LX 2 /* Work-group of the fluid pass, in packets. */
#define FLUID_LY 2

#if defined(__OPENCL_VERSION__) || defined(__OPENCL_C_VERSION__)
#define VFX_DEVICE_CODE 1
#endif

#ifdef VFX_DEVICE_CODE

/* Moves a shadow ray's origin off its surface by this much per unit of distance from the eye,
 * plus the same amount, so rounding in the hit point cannot make a surface shadow itself. */
#define SHADOW_BIAS 2e-4f

/* The smallest and largest of the sixteen lanes of a packet's values (the float16 kernels). */
static inline int lanes_min(int16 v) {
  int8 a = min(v.lo, v.hi);
  int4 b = min(a.lo, a.hi);
  int2 c = min(b.lo, b.hi);
  return min(c.x, c.y);
}

static inline int lanes_max(int16 v) {
  int8 a = max(v.lo, v.hi);
  int4 b = max(a.lo, a.hi);
  int2 c = max(b.lo, b.hi);
  return max(c.x, c.y);
}

static inline float lanes_fmin(float16 v) {
  float8 a = fmin(v.lo, v.hi);
  float4 b = fmin(a.lo, a.hi);
  float2 c = fmin(b.lo, b.hi);
  return fmin(c.x, c.y);
}

/*
 * Sixteen lines from per-lane origins (ox, oy, oz) along one shared direction d (shadow rays,
 * and the lines of the shadow map), as objects.cl and volume.cl test them against convex
 * objects and walk the mesh BVH. node_span16: the distances along d inside the box of BVH node 'n'
 * (its lower corner, then its upper), [*lo, *hi], empty where *lo > *hi; (ix, iy, iz) is 1 / d, and
 * fmin / fmax drop the NaN of 0 * inf, which leaves that axis unbounded. tri_line16: the distance
 * along d of the plane of triangle 'tr' (a vertex, then two edges), any sign, with the lanes whose
 * line crosses the triangle in '*inside' (Moller-Trumbore, double-sided; the terms in d alone
 * are scalars, and a degenerate triangle gives NaNs, which fail every comparison).
 */
static inline void node_span16(__global const float *n, float16 ox, float16 oy, float16 oz,
                               float ix, float iy, float iz, float16 *lo, float16 *hi) {
  float16 t0x = (n[0] - ox) * ix, t1x = (n[3] - ox) * ix;
  float16 t0y = (n[1] - oy) * iy, t1y = (n[4] - oy) * iy;
  float16 t0z = (n[2] - oz) * iz, t1z = (n[5] - oz) * iz;
  *lo = fmax(fmax(fmin(t0x, t1x), fmin(t0y, t1y)), fmin(t0z, t1z));
  *hi = fmin(fmin(fmax(t0x, t1x), fmax(t0y, t1y)), fmax(t0z, t1z));
}

/* convex_span16: the distances along d inside the convex record 'c' (CONV_NPLANES planes
 * n.x <= w, outward normals): [*tin, *tout], empty where *tin > *tout; returns the lanes whose
 * line runs parallel to a plane outside it, which miss whatever the span says. */
static inline int16 convex_span16(__global const float *c, float16 ox, float16 oy, float16 oz,
                                  float dx, float dy, float dz, float16 *tin, float16 *tout) {
  int16 miss = 0;
  *tin = -INFINITY, *tout = INFINITY;
  int np = as_int(c[CONV_NPLANES]);
  for (int k = 0; k < np; k++) {
    float pnx = c[4 * k], pny = c[4 * k + 1], pnz = c[4 * k + 2];
    float den = pnx * dx + pny * dy + pnz * dz;
    float16 num = c[4 * k + 3] - (pnx * ox + pny * oy + pnz * oz);
    float16 t = num / den;
    if (den < 0.0f)
      *tin = fmax(*tin, t);
    else if (den > 0.0f)
      *tout = fmin(*tout, t);
    else
      miss |= num < 0.0f;
  }
  return miss;
}

static inline float16 tri_line16(__global const float *tr, float16 ox, float16 oy, float16 oz,
                                 float dx, float dy, float dz, int16 *inside) {
  float e1x = tr[3], e1y = tr[4], e1z = tr[5];
  float e2x = tr[6], e2y = tr[7], e2z = tr[8];
  float px = dy * e2z - dz * e2y, py = dz * e2x - dx * e2z, pz = dx * e2y - dy * e2x;
  float inv = 1.0f / (e1x * px + e1y * py + e1z * pz);
  float16 sx = ox - tr[0], sy = oy - tr[1], sz = oz - tr[2];
  float16 u = (sx * px + sy * py + sz * pz) * inv;
  float16 qx = sy * e1z - sz * e1y, qy = sz * e1x - sx * e1z, qz = sx * e1y - sy * e1x;
  float16 v = (dx * qx + dy * qy + dz * qz) * inv;
  *inside = (u >= 0.0f) & (v >= 0.0f) & (u + v <= 1.0f);
  return (e2x * qx + e2y * qy + e2z * qz) * inv;
}

#endif

#endif
