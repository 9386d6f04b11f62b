/*
 * The particle fluid of SPEC §5.2, simulated: weakly compressible SPH after Müller et al. 2003
 * (spiky-kernel density and pressure gradient, viscosity Laplacian, gravity) on the OpenCL device
 * of the renderer, with a uniform neighbour grid sorted on the host, the tank's bounds and the
 * scene's opaque objects as colliders, and emitters. docs/fluid-validation.md explains the
 * choices and the dam-break validation.
 *
 * A simulation borrows a cl_dev_t whose program holds kernels/sph.cl; one thread uses it at a
 * time. Nothing here logs; failures come back as -1 with a message in 'err'.
 */
#ifndef VOLFX_SIM_FLUID_H
#define VOLFX_SIM_FLUID_H

#include <stddef.h>
#include <stdint.h>

#include "cl_device.h"
#include "render_scene.h"

#define FLUID_MAX_EMITTERS 16
#define FLUID_MAX_PARTICLES (1u << 22) /* Largest 'max_particles' accepted. */
#define FLUID_MAX_SUBSTEPS 256         /* Most substeps one fluid_sim_step takes. */

typedef enum { FLUID_EMIT_SPHERE, FLUID_EMIT_BOX } fluid_emit_shape_t;

/* A source of new particles, spread uniformly over its shape with its velocity. */
typedef struct fluid_emitter {
  fluid_emit_shape_t shape;
  float position[3]; /* Centre. */
  float size[3];     /* Sphere: radius in size[0]; box: edge lengths. World units. */
  float rate;        /* Particles per second of simulated time, >= 0. */
  float velocity[3]; /* Initial velocity of every particle emitted. */
} fluid_emitter_t;

typedef struct fluid_params {
  float h;             /* SPH support radius (world units); particles sit about h/2 apart. */
  float particle_mass; /* kg; fluid_lattice_mass gives the one that matches rest_density. */
  float rest_density;  /* kg/m³. */
  float stiffness;     /* k of p = k (rho - rest_density), m²/s²; the sound speed is sqrt(k). */
  float viscosity;     /* Dynamic viscosity mu of Müller's viscosity term, Pa·s. */
  float wall_friction; /* The tank walls' drag, 0 (free slip) to 1 (no slip, like fluid at rest). */
  float gravity[3];    /* m/s². */
  float bounds_min[3], bounds_max[3]; /* The tank: particles never leave it. */
  uint64_t seed;                      /* Seeds the emitters' random positions. */
  uint32_t max_particles;             /* Capacity: set_particles and emitters stop here. */
  int nemitters;
  fluid_emitter_t emitters[FLUID_MAX_EMITTERS];
} fluid_params_t;

typedef struct fluid_sim fluid_sim_t;

/*
 * Fills 'p' with the defaults: h = 0.61 (the metaball radius of SPEC §5.2), water at
 * rest_density 1000 with the lattice mass for spacing h/2, stiffness 1000 (sound speed 31.6
 * m/s), viscosity 50, no-slip walls, gravity (0, -9.81, 0), bounds [-5, 5]³, seed 1, 65536
 * particles, no emitters.
 */
void fluid_params_default(fluid_params_t *p);

/*
 * The particle mass for which a particle inside a cubic lattice of 'spacing' has exactly
 * the density 'rest_density' with support radius 'h' (the spiky sum over the lattice).
 */
float fluid_lattice_mass(float h, float spacing, float rest_density);

/*
 * Creates an empty simulation on 'dev', whose program must hold kernels/sph.cl. 'p' is
 * validated and copied. Returns NULL with a message in 'err'.
 */
fluid_sim_t *fluid_sim_create(cl_dev_t *dev, const fluid_params_t *p, char *err, size_t errlen);

/* Frees 'sim' and its device buffers; NULL is fine. The device stays open. */
void fluid_sim_destroy(fluid_sim_t *sim);

/*
 * Replaces the parameters (the particles and the frame kept). Returns -1 with a message
 * and nothing changed if 'p' is invalid, changes 'max_particles' or leaves particles outside
 * the new bounds.
 */
int fluid_sim_set_params(fluid_sim_t *sim, const fluid_params_t *p, char *err, size_t errlen);

/*
 * Replaces every particle: 'n' positions at 'pos_xyz' (x, y, z each) and velocities at
 * 'vel_xyz' (NULL for rest). Refuses, with nothing changed, n > max_particles, any value
 * that is not finite and any position outside the bounds. Returns 0 or -1 with a message.
 */
int fluid_sim_set_particles(fluid_sim_t *sim, const float *pos_xyz, const float *vel_xyz,
                            uint32_t n, char *err, size_t errlen);

/* Copies the particles, in the order they were set or emitted, into 'pos' and 'vel' (3 floats
 * each per particle; either may be NULL). */
void fluid_sim_get_particles(const fluid_sim_t *sim, float *pos, float *vel);

/* Sets the frame the next step starts from (0 for a new simulation); each step adds one. The
 * emitters' particles in a step depend on that frame and the seed alone. */
void fluid_sim_set_frame(fluid_sim_t *sim, uint64_t frame);

/* The number of particles. */
uint32_t fluid_sim_count(const fluid_sim_t *sim);

/*
 * Sets the colliders from the scene's opaque objects: spheres (ellipsoids when scaled), boxes,
 * planes and tetrahedra (their four face planes), placed as render_scene.h says; meshes do not
 * collide, and past the first 256 that do, the rest are ignored. The array is copied. Returns 0, or
 * -1 with a message if an object's numbers are unusable.
 */
int fluid_sim_set_colliders(fluid_sim_t *sim, const robject_t *objs, int n, char *err,
                            size_t errlen);

/*
 * Advances the simulation by 'dt' seconds: first the emitters, then substeps of at most
 * 0.4 h / (sqrt(stiffness) + the fastest particle's speed), no longer than 0.25 sqrt(h / |g|)
 * and 0.125 h² rest_density / viscosity, and never more than FLUID_MAX_SUBSTEPS (beyond that
 * the substeps grow, and the speed limit of sqrt(stiffness) keeps the fluid bounded).
 * Returns 0, or -1 with a message if dt is not in (0, 1] or the device fails.
 */
int fluid_sim_step(fluid_sim_t *sim, double dt, char *err, size_t errlen);

/* Substeps taken by the last fluid_sim_step. */
int fluid_sim_last_substeps(const fluid_sim_t *sim);

#endif
