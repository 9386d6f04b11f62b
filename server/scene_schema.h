/*
 * The scene document's schema (scene_schema.c) and the compiled forms its fields are stored
 * into: render_scene_t and its items (render_scene.h) for what the renderer draws, and
 * scene_cloud_t for the cloud's automaton. Each field of the schema declares its own storage
 * (sch_field_t.store, .offset), so compiling a section is one sch_compile over the table.
 */
#ifndef VOLFX_SCENE_SCHEMA_H
#define VOLFX_SCENE_SCHEMA_H

#include <stdint.h>

#include "render_scene.h"
#include "schema.h"
#include "sim_cloud.h"

/* The cloud settings of a validated document, in cells (ellipsoids converted). */
typedef struct scene_cloud {
  cloud_params_t params;
  uint32_t n[3];
  double radius;            /* Metaball radius in cells, 0 resolved. */
  float keep;               /* smoothing */
  unsigned steps_per_frame; /* Automaton steps per simulation step. */
  double init_hum, init_act;
  unsigned init_steps; /* Automaton steps taken at seeding. */
  int enabled;         /* cloud.enabled */
  double origin[3];    /* The grid's lowest corner and the edge of a cell, world units. */
  double voxel;
  rvolume_t look; /* density, albedo and samples as the renderer draws the cloud. */
} scene_cloud_t;

/* The schema of a whole scene document (SPEC §4), for validation, compilation and
 * rpc.discover. */
extern const sch_field_t scene_schema;

/* The description of one item of the scene's arrays (objects, waves, volumes) and of its
 * sections (fluid, cloud), as sch_compile takes them. */
const sch_field_t *scene_schema_at(const char *path);

#endif
