/*
 * The cellular-automaton cloud (SPEC §5.4): three bits per cell (hum, act, cld), packed 64
 * cells to a word along x, stepped by the rules of Kuromiya et al. (exactly) or of Dobashi et
 * al. 2000 (extinction, supply of humidity and activation, wind), and turned into a float
 * density by summing a truncated Gaussian metaball around every cloud cell in three separable
 * passes. Plain C on the host: a bit-packed step is a few word operations per 64 cells, cheaper
 * than an OpenCL launch (docs/architecture.md). Nothing here touches the server.
 */
#ifndef VOLFX_SIM_CLOUD_H
#define VOLFX_SIM_CLOUD_H

#include <stdatomic.h>
#include <stddef.h>
#include <stdint.h>

#include "render_scene.h"

#define CLOUD_MAX_SIDE 1024     /* No grid side may exceed this, whatever the limits say. */
#define CLOUD_MAX_ELLIPSOIDS 16 /* Shapes of the supply (Dobashi's ellipsoids). */
#define CLOUD_MAX_RADIUS 128    /* Largest metaball radius, voxels. */

typedef enum { CLOUD_HUM, CLOUD_ACT, CLOUD_CLD } cloud_field_t;
typedef enum { CLOUD_KUROMIYA, CLOUD_DOBASHI } cloud_rules_t;

/*
 * The automaton's state: immutable once published, shared by the scene and the step jobs,
 * freed with the last reference. Row (y, z) of a plane starts at word (y + ny z) × 'words';
 * cell x is bit x % 64 of word x / 64 of its row. Bits at x >= nx are always 0.
 */
typedef struct cloud_cells {
  atomic_int refs;
  uint32_t n[3];  /* nx, ny, nz. */
  uint32_t words; /* 64-bit words per row: ceil(nx / 64). */
  uint64_t step;  /* Automaton steps taken since the cells were seeded or set. */
  uint64_t *hum, *act, *cld;
} cloud_cells_t;

/* An ellipsoid in cell coordinates (cell (i, j, k) has its centre at (i, j, k)). */
typedef struct cloud_ellipsoid {
  float center[3];
  float radii[3]; /* Each > 0. */
} cloud_ellipsoid_t;

typedef struct cloud_params {
  cloud_rules_t rules;
  double p_ext, p_hum, p_act; /* Dobashi: probabilities per cell and step, in [0, 1]. */
  double wind;                /* Dobashi: cells per step along +x (may be negative). */
  uint64_t seed;
  int nellipsoids; /* 0: supply everywhere. */
  cloud_ellipsoid_t ellipsoids[CLOUD_MAX_ELLIPSOIDS];
} cloud_params_t;

/* Zeroed cells of the given dimensions (each 1..CLOUD_MAX_SIDE), one reference; NULL on OOM or
 * bad dimensions. */
cloud_cells_t *cloud_cells_new(const uint32_t n[3]);
/* A copy with one reference, or NULL on OOM. */
cloud_cells_t *cloud_cells_copy(const cloud_cells_t *c);
cloud_cells_t *cloud_cells_ref(cloud_cells_t *c);
/* Drops a reference; NULL is fine. */
void cloud_cells_unref(cloud_cells_t *c);
/* Cells in the grid: nx × ny × nz. */
size_t cloud_cells_count(const cloud_cells_t *c);
/* The plane of 'f'. */
uint64_t *cloud_cells_plane(const cloud_cells_t *c, cloud_field_t f);
/* Bit of plane 'f' at cell (x, y, z), which must be inside the grid. */
int cloud_cell(const cloud_cells_t *c, cloud_field_t f, uint32_t x, uint32_t y, uint32_t z);
/* Whether any cell of plane 'f' is set. */
int cloud_cells_any(const cloud_cells_t *c, cloud_field_t f);
/* Unpacks plane 'f' into one byte (0 or 1) per cell, x fastest, then y, then z. */
void cloud_cells_export(const cloud_cells_t *c, cloud_field_t f, uint8_t *out);
/* Packs one byte per cell (non-zero: 1) into plane 'f'. */
void cloud_cells_import(cloud_cells_t *c, cloud_field_t f, const uint8_t *in);

/*
 * The random number of cell 'cell' (x + nx (y + ny z)) for draw 'which' at automaton step
 * 'step' under 'seed': a hash of the four, so every cell's draws are independent of the
 * order cells are visited in and of how they are packed. A cell takes an event of probability
 * p when cloud_hash(...) < p × 2^32.
 */
uint32_t cloud_hash(uint64_t seed, uint64_t step, uint32_t which, uint32_t cell);

/* What cloud_hash draws: numbered so tests can reproduce them. */
enum {
  CLOUD_DRAW_EXT = 0,      /* Extinction of cld (p_ext). */
  CLOUD_DRAW_HUM = 1,      /* Supply of hum (p_hum × shape). */
  CLOUD_DRAW_ACT = 2,      /* Supply of act (p_act × shape). */
  CLOUD_DRAW_INIT_HUM = 3, /* Initial hum (cloud_cells_seed, at step 0). */
  CLOUD_DRAW_INIT_ACT = 4  /* Initial act (cloud_cells_seed, at step 0). */
};

/* The threshold cloud_hash is compared with for probability 'p' (clamped to [0, 1]):
 * floor(p × 2^32), so p = 1 always happens and p = 0 never. */
uint64_t cloud_threshold(double p);

/* The supply shape at cell coordinates (x, y, z): 1 with no ellipsoids, else the largest
 * 1 - q² over the ellipsoids (q the ellipsoid's normalised distance), 0 outside all. */
double cloud_shape(const cloud_params_t *p, double x, double y, double z);

/*
 * Seeds 'c' (its planes overwritten, its step set to 0): every cell gets hum with probability
 * 'hum' × [inside an ellipsoid, or everywhere when there are none], and every cell with hum
 * also gets act with probability 'act'; cld is cleared. Draws CLOUD_DRAW_INIT_* at step 0.
 */
void cloud_cells_seed(cloud_cells_t *c, const cloud_params_t *p, double hum, double act);

/*
 * One step from 'in' into 'out' (same dimensions, a different buffer; out->step becomes
 * in->step + 1). Kuromiya (SPEC §5.4): cld' = cld | act, hum' = hum & !act,
 * act' = !act & hum & f_act, f_act the OR of act at x±1, y±1, z±1, x-2, y-2, z-2, cells outside
 * reading 0. Dobashi: the same, then cld' cleared where the EXT draw < p_ext, hum' set where
 * the HUM draw < p_hum × shape, act' set where the ACT draw < p_act × shape (draws at in->step),
 * then all three planes moved along x by floor((s + 1) w) - floor(s w) cells (s = in->step,
 * w = wind), cells moved in from outside reading 0.
 */
void cloud_step(const cloud_cells_t *in, cloud_cells_t *out, const cloud_params_t *p);

/* The cells the wind moves the cloud along +x from step 'from' to step 'to' (Dobashi:
 * floor(to w) - floor(from w); Kuromiya: 0). */
long cloud_wind_shift(const cloud_params_t *p, uint64_t from, uint64_t to);

/* The fraction of a cell the wind has carried the cells of step 'step' beyond the whole cells
 * it has moved them (s w - floor(s w), in [0, 1); 0 for Kuromiya): the renderer draws the cloud
 * that far along +x, so that it drifts smoothly instead of jumping a cell every 1 / w steps. */
double cloud_wind_fraction(const cloud_params_t *p, uint64_t step);

/* The number of taps either side of the centre for metaball radius 'r' voxels: floor(r). */
int cloud_kernel_half(double r);
/*
 * The 1-D kernel of radius 'r' into 'w' (2 × cloud_kernel_half(r) + 1 floats): w[K + d] ∝
 * exp(-d² / (2 σ²)) with σ = r / 3, normalised to sum 1, so that a cloud cell's metaball is the
 * product of three of them (a Gaussian of effective radius r, cut off at |d| > r on each axis)
 * and a region full of cloud cells has density 1. Returns K.
 */
int cloud_kernel(double r, float *w);

/*
 * The density of the cld plane of 'c' into 'out' (nx × ny × nz floats, x fastest): the sum over
 * cloud cells of the separable metaball of radius 'r' voxels (cloud_kernel), computed as three
 * 1-D passes that skip empty rows. Returns 0, or -1 on OOM ('out' then undefined).
 */
int cloud_density(const cloud_cells_t *c, double r, float *out);

/* The density shown after a step, in place of 'target' (a grid of dimensions 'n', x fastest):
 * the new density 'target' with the fraction 'keep' of the difference from the density 'shown'
 * before it kept, shown moved by 's' cells along x first (the wind; 0 where nothing moves in):
 * target[x] = target[x] + keep × (shown[x - s] - target[x]). */
void cloud_blend_shifted(float *restrict target, const float *restrict shown, const uint32_t n[3],
                         long s, float keep);

#endif
