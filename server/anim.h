/*
 * Motion and deformation of an object's numeric fields (thesis §2.3), driven by the object's
 * "animate" array: each entry moves one field toward a target at a rate, or sets it from
 * keyframes at the simulation time. The animated value is written into the object itself, so
 * the document always shows the current state. The schema checks each entry's shape; these
 * functions check what it cannot and do the stepping. Waves use it today; any object whose
 * schema has an "animate" array of the same form can.
 */
#ifndef VOLFX_ANIM_H
#define VOLFX_ANIM_H

#include <stdint.h>
#include <cjson/cJSON.h>

#include "schema.h"

/*
 * Checks the "animate" array of 'obj', a member-wise valid object whose members 'fields'
 * describes, at dotted path 'prefix' ("waves.3"): each entry names a NUMBER or VEC3 field not
 * named by an earlier entry, and is either toward-target (target and rate) or keyframes (at
 * least one key, t strictly increasing, no rate); targets and key values are validated in
 * place against the animated field (so a direction target is normalised). Fills in "interp"
 * and "loop" of keyframe entries. Returns 0, or -1 with 'err' naming the offending path.
 */
int anim_check(cJSON *obj, const sch_field_t *fields, const char *prefix, sch_error_t *err);

/* True when the "animate" array of 'obj' has an entry for the member 'name'. */
int anim_animates(const cJSON *obj, const char *name);

/*
 * Writes into 'obj' the value of each keyframed field at time 'now' (seconds). Used when a
 * document is committed, so that a scene shows the keyframed values of its current time.
 */
void anim_apply_keys(cJSON *obj, const sch_field_t *fields, double now);

/*
 * Advances the animations of 'obj' by 'steps' steps of 'dt' seconds: each toward-target field
 * moves by rate * dt a step, step by step (so the value after n steps is the same however the
 * steps were grouped), and stops exactly at its target; each keyframed field takes its value
 * at 'now'. Values are written in place and nothing is allocated, so this cannot fail.
 */
void anim_advance(cJSON *obj, const sch_field_t *fields, uint64_t steps, double dt, double now);

#endif
