/*
 * The compiled, immutable form of a scene that the render worker reads: plain C structs in
 * world units, made from the validated JSON document by scene.c. A render job holds its own
 * reference, so the loop thread may replace the scene's snapshot while a frame is rendering.
 */
#ifndef VOLFX_RENDER_SCENE_H
#define VOLFX_RENDER_SCENE_H

#include <stdatomic.h>
#include <stddef.h>
#include <stdint.h>

typedef enum { SHAPE_BOX, SHAPE_SPHERE, SHAPE_TETRAHEDRON, SHAPE_PLANE, SHAPE_MESH } shape_t;
typedef enum { TONE_NONE, TONE_REINHARD, TONE_ACES } tone_map_t;

typedef struct rcamera {
  float eye[3], target[3], up[3];
  float fov_y; /* Degrees, vertical. */
  float near_, far_;
} rcamera_t;

/* A triangle mesh in object space, shared between snapshots; immutable once built. */
typedef struct mesh {
  atomic_int refs;
  uint32_t ntri;
  float *tri; /* 9 floats per triangle: v0, v1, v2. */
} mesh_t;

mesh_t *mesh_ref(mesh_t *m);
void mesh_unref(mesh_t *m);

/*
 * Shapes in object space, before scale, rotation (degrees, applied X then Y then Z) and
 * translation: box [-0.5, 0.5]³; sphere of radius 0.5 at the origin; regular tetrahedron
 * inscribed in the same sphere of radius 0.5, one vertex at +y; plane y = 0 (infinite, scale
 * ignored); mesh as loaded.
 */
typedef struct robject {
  shape_t shape;
  float position[3], scale[3], rotation[3], color[3];
  mesh_t *mesh; /* SHAPE_MESH only; a counted reference. */
} robject_t;

/*
 * An energy wave (SPEC §5.1): sphere term a/sqrt(r²+ε²) around the centre M plus beam term
 * b/sqrt(q²+ε²) along the segment [M, M + length·direction], zero outside the capsule of
 * 'radius' around that segment. The pixel shows min(H, clamp) mapped to 'color', added to
 * what is behind.
 */
typedef struct rwave {
  float center[3];
  float direction[3]; /* Unit. */
  float a, b;         /* Sphere and beam strengths. */
  float length;       /* Beam length L >= 0 (world units). */
  float radius;       /* Support radius R > 0 (world units). */
  float softening;    /* epsilon > 0 (world units). */
  float clamp;        /* c > 0: the largest H shown. */
  float color[3];     /* Linear RGB at H = clamp. */
} rwave_t;

/*
 * Particles of a fluid drawn as metaballs (SPEC §5.2): the field of particle j at distance r
 * is P(r) = (1 - r/h)² for r <= h, else 0; the surface is where sqrt(ΣP) = threshold.
 */
typedef struct rfluid {
  uint32_t count;
  const float *positions; /* count × xyz, world units; shared, immutable (see 'owner'). */
  void *owner;            /* A particles_t reference keeping 'positions' alive, dropped by
                             render_scene_unref; NULL when the scene owns nothing here. */
  float h;                /* Metaball radius, world units (0.61 in the paper). */
  float threshold;        /* T (0.765625 in the paper). */
  float color[3];         /* Transmission tint, linear RGB. */
  float ior;              /* Index of refraction for the Fresnel term (1.33). */
  float roughness;        /* Specular spread, 0..1. */
} rfluid_t;

/*
 * A fluid's particles on the host: immutable once published, shared by the scene, its
 * snapshots and the fluid jobs, freed with the last reference. 'pos' and 'vel' hold
 * count × xyz each.
 */
typedef struct particles {
  atomic_int refs;
  uint32_t count;
  float *pos, *vel;
} particles_t;

/* A buffer of 'n' particles, positions and velocities zeroed, with one reference; NULL on
 * OOM. */
particles_t *particles_new(uint32_t n);
particles_t *particles_ref(particles_t *p);
/* Drops a reference; NULL is fine. */
void particles_unref(particles_t *p);

/*
 * A grid of densities on the host (a cloud's density, a volume file's data): immutable once
 * published, shared by snapshots and jobs, freed with the last reference. 'data' holds
 * dims[0] × dims[1] × dims[2] non-negative floats, x fastest, then y, then z.
 */
typedef struct density_grid {
  atomic_int refs;
  uint32_t dims[3];
  float *data;
} density_grid_t;

/* A zeroed grid of the given dimensions with one reference; NULL on OOM or a zero side. */
density_grid_t *density_grid_new(const uint32_t dims[3]);
/* The same with the densities not set, for a caller that writes every one. */
density_grid_t *density_grid_alloc(const uint32_t dims[3]);
density_grid_t *density_grid_ref(density_grid_t *g);
/* Drops a reference; NULL is fine. */
void density_grid_unref(density_grid_t *g);

typedef enum { VOLUME_NOISE, VOLUME_GRID } volume_source_t;

/*
 * A participating medium in an axis-aligned box (SPEC §5.3): extinction σ(P) = density ×
 * d(P) per world unit, where d is the procedural noise (VOLUME_NOISE) or the grid trilinearly
 * interpolated over the box (VOLUME_GRID, d = 0 outside). Rays are sampled only between where
 * they enter the box and min(where they leave it, the opaque depth), 'samples' evenly spaced
 * samples; single scattering of the light with the given albedo. Grid voxel (i, j, k) is centred
 * at min + (i + 0.5, j + 0.5, k + 0.5) * (max - min) / dims, and the edge voxels extend to the
 * faces. The renderer skips a volume whose box is empty, whose density is not positive, whose
 * samples are below 1 or whose grid is missing (render_volume.c, usable()), and it rebuilds its
 * light grid whenever 'grid' is a different pointer, so a changed density must come as a new
 * grid rather than be written into a published one.
 */
typedef struct rvolume {
  volume_source_t source;
  float min[3], max[3]; /* World-space bounds. */
  float density;        /* Extinction per world unit where d = 1. */
  float albedo[3];      /* Single-scattering albedo, linear RGB in [0, 1]. */
  int samples;          /* Samples per ray inside the box. */
  density_grid_t *grid; /* VOLUME_GRID: a counted reference; NULL otherwise. */
  uint32_t seed;        /* VOLUME_NOISE: the noise's seed. */
  float noise_scale;    /* VOLUME_NOISE: feature size, world units. */
  float phase_g;        /* Henyey-Greenstein asymmetry in (-1, 1); 0 scatters evenly. */
} rvolume_t;

typedef struct render_scene {
  atomic_int refs;
  rcamera_t camera;
  float background[3]; /* Linear RGB. */
  struct {
    float direction[3]; /* Unit, towards the light. */
    float color[3];
    float intensity;
    float ambient;  /* Fraction of light reaching surfaces in shadow or facing away. */
    int shadow_map; /* Shadow map size (used by volume passes). */
  } light;
  robject_t *objects;
  int nobjects;
  rwave_t *waves; /* Owned by the snapshot (freed with it). */
  int nwaves;
  rfluid_t fluid;     /* count 0: no fluid. */
  rvolume_t *volumes; /* Owned by the snapshot; their grids are counted references. */
  int nvolumes;
  rvolume_t cloud; /* The cloud's density as a VOLUME_GRID volume; grid NULL: no cloud. */
  float exposure;  /* Stops: pixel = tone_map(linear * 2^exposure). */
  tone_map_t tone_map;
  int transparent_background; /* Background pixels get alpha 0 instead of 1. */
  int volume_div;             /* The volumes pass runs at 1 / volume_div of the frame's width
                                 and height (render.volume_resolution): 1 (or 0), 2 or 4. */
  int antialias;              /* Samples per pixel along each axis of a beauty frame
                                 (render.antialias): 1 (or 0) to 4. */
  uint64_t frame;             /* Simulation frame and time at the snapshot. */
  double time;
} render_scene_t;

render_scene_t *render_scene_ref(render_scene_t *s);
/* Drops a reference; frees the scene and its mesh references with the last one. */
void render_scene_unref(render_scene_t *s);

/* Loads a Wavefront OBJ file (v and f records; polygons fanned into triangles; negative
 * indices allowed). Returns NULL with a message naming the file and line in 'err'. */
mesh_t *mesh_load_obj(const char *path, char *err, size_t errlen);
/* The largest OBJ file mesh_load_obj reads. */
#define MESH_OBJ_MAX_BYTES (64u << 20)
/* Parses the OBJ text 'text' ('len' bytes, NUL-terminated, overwritten while parsed) as
 * mesh_load_obj does, naming it 'name' in messages. The caller keeps 'text'. */
mesh_t *mesh_parse_obj(char *text, size_t len, const char *name, char *err, size_t errlen);

/* The rotation Rz * Ry * Rx of an object's 'rotation' (degrees about x, y, z; X applied first),
 * the one the renderer, the fluid's colliders and the seeding of particles all use
 * (render_objects.c). */
void rotation_zyx(const double deg[3], double r[3][3]);

#endif
