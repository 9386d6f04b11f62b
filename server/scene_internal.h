/*
 * What the files of the scene module share and nobody else calls: scene.c commits a document
 * after scene_check.c has checked it and scene_budget.c has let it in, and scene_compile.c
 * turns it into the renderer's snapshot; scene_edit.c builds the documents scene.c commits.
 */
#ifndef VOLFX_SCENE_INTERNAL_H
#define VOLFX_SCENE_INTERNAL_H

#include "scene.h"

/* ---- scene_check.c ---- */

/*
 * Validates 'doc' in place against scene_schema (defaults, normalisation), checks it across
 * fields and sets each keyframed wave field to its value at the document's sim.time (keyframes
 * own their field: a value written there is replaced). Returns 0, or -1 with 'err' set.
 */
int scene_check_document(cJSON *doc, scene_error_t *err);
/* The most animation keys a document may hold (limits.keyframes). */
void scene_check_set_keyframes(uint32_t keyframes);

/* ---- scene_budget.c ---- */

/* Whether scene 's' may take checked 'doc' with the particles it will bring ('saved''s, or
 * fluid.initial's when that changes, or the scene's) within the memory budget. Returns 0, or -1
 * with 'err' (PROTO_E_LIMIT) naming the part that grew most. */
int scene_budget_fits(const scene_t *s, const cJSON *doc, const scene_saved_t *saved,
                      scene_error_t *err);
/* Counts the scene, with its document, for 'particles' particles from now on. */
void scene_budget_account(scene_t *s, uint64_t particles);
/* Stops counting the scene (it is being destroyed). */
void scene_budget_release(scene_t *s);

/* ---- scene_compile.c ---- */

/* Builds the snapshot of checked 'doc' with the fluid's 'particles' (NULL: none) and the cloud
 * density 'cloud' (that of 'cells'), loading meshes and volume files; NULL with 'err' set. */
render_scene_t *scene_compile(const cJSON *doc, particles_t *particles, const cloud_cells_t *cells,
                              density_grid_t *cloud, scene_error_t *err);
/* A new snapshot equal to 'old' but for the clock, the fluid's particles and the waves,
 * compiled afresh from 'doc' (animation moves them); the renderer may still hold 'old', so it
 * is copied rather than changed. NULL on OOM. */
render_scene_t *scene_compile_advanced(const render_scene_t *old, const cJSON *doc,
                                       particles_t *particles, uint64_t frame, double time);
/* Replaces rs->cloud (its grid already released) with the cloud of 'doc' showing 'density' (a
 * reference is taken; NULL: no cloud), that of 'cells'. */
void scene_compile_cloud(const cJSON *doc, const cloud_cells_t *cells, density_grid_t *density,
                         render_scene_t *rs);
/* The cloud settings of checked 'doc'. Returns 0, or -1 when the cloud is disabled. */
int scene_cloud_of(const cJSON *doc, scene_cloud_t *c);
/*
 * Looks up every mesh and volume file of checked 'doc' once before the seedings of a commit
 * (the cloud's cells, the particles; seeding.h): a file that must first be read off the loop
 * thread (a deferral, scene_files.h) then stops the commit before a seeding is looked up, so
 * that a seeding made for the retry is made with the files in hand. Returns 0, or -1 with
 * 'err' set.
 */
int scene_compile_files_ready(const cJSON *doc, scene_error_t *err);

/* ---- scene_edit.c ---- */

/* Sets 'err' for a dotted path that names nothing in 'doc' (PROTO_E_NOT_FOUND), saying what is
 * missing and what was likely meant. Returns -1. */
int scene_path_missing(cJSON *doc, const char *path, scene_error_t *err);

/* ---- scene.c ---- */

/*
 * Makes 'doc' (owned, taken in every case) the scene's document if it is valid, with its
 * snapshot, particles and cloud (scene.c). Returns 0, or -1 with 'err' set, having changed
 * nothing.
 */
int scene_commit(scene_t *s, cJSON *doc, const scene_saved_t *saved, scene_error_t *err);

#endif
