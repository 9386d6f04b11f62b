/*
 * Definitions shared by the volume kernels (kernels/volume.cl) and the host side of the volume
 * pass (render/render_volume.c): the layout of a volume record, the shadow map's constants and
 * the packet width. Valid OpenCL C and valid C11, like common.h.
 *
 * A volume reaches the kernel as VOL_STRIDE floats, and its grid as dims voxels (x fastest) of a
 * float2 buffer, one voxel more than the grid (zero): voxel i holds (d[i], T[i]), the density d
 * and the light transmittance T (from the voxel centre towards the light through the volume),
 * so that the x-pair (d[i], T[i], d[i + 1], T[i + 1]) is one 16-byte load and the sixteen values
 * a trilinear lookup of both needs lie in four 16-byte runs instead of sixteen places. A grid
 * spans the volume's box, voxel centres at box_min + (i + 0.5) * cell, and is interpolated
 * trilinearly with the edge voxels extended to the faces. The kernel samples only inside the
 * 'tight' box, the part of the volume where the density can be non-zero (empty-space skipping).
 */
#ifndef VOLFX_KERNELS_VOLUME_H
#define VOLFX_KERNELS_VOLUME_H

#define VOL_TMIN 0    /* Tight box: where the interpolated density can be non-zero. */
#define VOL_TMAX 3    /* Its upper corner. */
#define VOL_BMIN 6    /* The grid's box (the volume's bounds). */
#define VOL_INV 9     /* Grid voxels per world unit, per axis. */
#define VOL_DIMS 12   /* Grid dims, int bits. */
#define VOL_OFF 15    /* Offset of the grid's first voxel in the data buffer (float2s), int bits. */
#define VOL_SIGMA 16  /* Extinction per world unit at density 1. */
#define VOL_ALBEDO 17 /* Single-scattering albedo, linear RGB. */
#define VOL_SAMPLES 20 /* Samples per ray, int bits. */
#define VOL_PHASE_G 21 /* Henyey-Greenstein asymmetry g in (-1, 1). */
#define VOL_EDGE 22    /* 1 when the tight box reaches past the outer voxel centres, int bits. */
#define VOL_STRIDE 32

/* The pixels a volume work-item shades, one per vector lane (a float16): a block of
 * VOL_PACKET_W x VOL_PACKET_H. */
#define VOL_PACKET 16
#define VOL_PACKET_W 4
#define VOL_PACKET_H 4

/* Shadow-map tests per sample segment where it holds a shadow edge, and the first tests that
 * decide whether it does (kernels/volume.cl, vol_shadow). */
#define VOL_SHADOW_TAPS 8
#define VOL_SHADOW_FIRST 2

/* volume_up blends the low-resolution pixels around a pixel where their opaque depths lie
 * within this fraction of its own (kernels/volume.cl). */
#define VOL_UP_DEPTH 0.05f
/* Work-group of volume_depth_down, in pixels of a row. */
#define VOL_UP_LX 16
/* Pixels of a row per volume_up work-item (a float16). */
#define VOL_UP_PACKET 16

/* A packet stops marching once every ray lets less than this fraction through. */
#define VOL_T_MIN (1.0f / 512.0f)

/*
 * The shadow map of the opaque objects, seen from the directional light: an orthographic
 * 'size' x 'size' grid of texels over the plane through 'origin' spanned by the unit vectors
 * 'u' and 'v', both across the light direction. A texel holds the distance along 'w' (the
 * direction the light travels, -light.direction) from that plane to the first opaque surface
 * met by the line through the texel centre, or +INFINITY when the line meets nothing; the line
 * is taken whole (from -infinity), so occluders on either side of the plane count. Texel
 * (i, j) covers [i, i + 1) x [j, j + 1) of s = (P - origin).u * inv_texel and r = (P -
 * origin).v * inv_texel. 'enabled' 0 means nothing casts a shadow (every lookup is lit).
 */
typedef struct vfx_shadow {
  float origin[3];
  float u[3], v[3], w[3];
  float inv_texel; /* Texels per world unit. */
  float bias;      /* A point counts as lit up to this far behind the stored depth. */
  int size;
  int enabled;
} vfx_shadow_t;

/* Texels a shadow-map work-item renders, one per lane (a float16). */
#define SHADOW_PACKET 16

#endif
