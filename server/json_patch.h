/*
 * RFC 6902 JSON Patch over cJSON: add, remove, replace, move, copy and test, their locations
 * written as RFC 6901 JSON Pointers ("/objects/0/scale", "~1" for '/' and "~0" for '~'). One
 * extension: in an array, a token that is neither an index nor "-" names the item whose member
 * "id" is that string ("/objects/orb/scale").
 */
#ifndef VOLFX_JSON_PATCH_H
#define VOLFX_JSON_PATCH_H

#include <cjson/cJSON.h>

#include "proto_error.h"

/*
 * Applies the operations of 'ops' (an array) to 'doc' (an object) in order. Returns 0, or -1
 * with 'err' naming the operation ("ops.2", "ops.2.path") when one is malformed (-32602), a
 * location does not exist (-32004) or a test fails (-32602); 'doc' is then partly changed, and
 * the caller, which works on a copy, discards it.
 */
int json_patch_apply(cJSON *doc, const cJSON *ops, proto_error_t *err);

#endif
