/*
 * Field descriptions: one static tree per method's params and one for the scene document.
 * The same tree validates a JSON value (types, ranges, finiteness, unknown members), fills in
 * defaults, and is published as JSON Schema by rpc.discover, so checks and docs never drift.
 */
#ifndef VOLFX_SCHEMA_H
#define VOLFX_SCHEMA_H

#include <cjson/cJSON.h>
#include <stddef.h>

#include "proto_error.h"

typedef enum {
  SCH_NUMBER,  /* Finite double within [min, max]. */
  SCH_INTEGER, /* Integral double within [min, max]. */
  SCH_BOOL,
  SCH_STRING, /* UTF-8 string of at most 'max' bytes (0: no limit but the line). */
  SCH_ENUM,   /* One of 'enum_values'. */
  SCH_VEC3,   /* Array of three finite numbers, each within [min, max]. */
  SCH_OBJECT, /* Object with the members in 'fields'; unknown members are refused. */
  SCH_ARRAY,  /* Array of at most 'max' items, each described by 'items'. */
  SCH_ANY     /* Any JSON value of at most 'max' bytes printed compactly (0: no limit); the
                 handler checks the rest. */
} sch_type_t;

enum {
  SCH_REQUIRED = 1 << 0,    /* Must be present (no default is filled). */
  SCH_UNIT_VEC = 1 << 1,    /* VEC3 normalised to length 1; a zero vector is refused. */
  SCH_POSITIVE = 1 << 2,    /* Number must be > min rather than >= min. */
  SCH_NO_DEFAULT = 1 << 3,  /* Optional, and left absent when absent. */
  SCH_OPEN = 1 << 4,        /* OBJECT that also accepts members it does not describe. */
  SCH_SHOW_DEFAULT = 1 << 5 /* With SCH_NO_DEFAULT: the default is published but not filled in,
                               because it applies to some uses of the object only; the owner
                               fills it where it does. */
};

/*
 * How a field's value is stored when a document is compiled (sch_compile) into a C struct: at
 * 'offset' from the base of the struct its enclosing object compiles into. Each field's storage
 * is declared once, in its schema entry, and the compiler is the one walk over the table.
 */
typedef enum {
  SCH_STORE_NONE,    /* Not compiled (read by its owner, or not at all). */
  SCH_STORE_F32,     /* NUMBER or INTEGER as float. */
  SCH_STORE_F64,     /* NUMBER or INTEGER as double. */
  SCH_STORE_INT,     /* INTEGER as int. */
  SCH_STORE_U32,     /* INTEGER as uint32_t. */
  SCH_STORE_U64,     /* INTEGER as uint64_t. */
  SCH_STORE_BOOL,    /* BOOL as int, 0 or 1. */
  SCH_STORE_ENUM,    /* ENUM as an int: its index in 'enum_values', or enum_codes[index]. */
  SCH_STORE_VEC3F,   /* VEC3 as float[3]. */
  SCH_STORE_VEC3D,   /* VEC3 as double[3]. */
  SCH_STORE_VEC3U32, /* VEC3 of whole numbers as uint32_t[3]. */
  SCH_STORE_UNIT3F,  /* VEC3 as float[3], divided by its length in double first. */
  SCH_STORE_MEMBERS  /* OBJECT whose stored members go into the same struct, at base + offset. */
} sch_store_t;

typedef struct sch_field {
  const char *name; /* Member name; NULL ends a 'fields' list. */
  sch_type_t type;
  const char *desc; /* One sentence for the docs. */
  const char *unit; /* "degrees", "world units", "seconds", ... or NULL. */
  double min, max;  /* Range (numbers, vec3 components); max length/items for strings/arrays. */
  double def;       /* Default for NUMBER, INTEGER, BOOL (0/1). */
  const double *def_vec;          /* Default for VEC3. */
  const char *def_str;            /* Default for STRING and ENUM. */
  const char *const *enum_values; /* NULL-terminated list for ENUM. */
  const struct sch_field *fields; /* Members of an OBJECT. */
  const struct sch_field *items;  /* Item of an ARRAY. */
  unsigned flags;
  sch_store_t store;     /* How sch_compile stores the value; SCH_STORE_NONE: it does not. */
  size_t offset;         /* Where, from the base sch_compile writes the enclosing object to. */
  const int *enum_codes; /* ENUM with SCH_STORE_ENUM: the int stored for each value, in order;
                            NULL stores the index. */
} sch_field_t;

/* A validation error: the carrier of proto_error.h, its code PROTO_E_INVALID_PARAMS, its path
 * the dotted path of the offending value ("objects.2.scale") and its message naming that path. */
typedef proto_error_t sch_error_t;

/* Fills 'err' as the engine does for an invalid value: code PROTO_E_INVALID_PARAMS, 'path', and
 * a message "path: ..." from 'fmt'. NULL is fine. Returns -1. */
int sch_error_set(sch_error_t *err, const char *path, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));

/*
 * Validates 'v' against 'f' in place: fills absent members that have defaults, normalises unit
 * vectors. 'prefix' is the dotted path of 'v' ("" at the root). Returns 0, or -1 with 'err'
 * naming the first offending path.
 */
int sch_validate(const sch_field_t *f, cJSON *v, const char *prefix, sch_error_t *err);

/* The JSON Schema (draft 2020-12 subset) of 'f', with "default", "minimum", "maximum",
 * "description" and the unit in "x-unit". The caller owns the result. */
cJSON *sch_to_json_schema(const sch_field_t *f);

/* A document holding every default of 'f' (an OBJECT). The caller owns the result. */
cJSON *sch_defaults(const sch_field_t *f);

/*
 * Compiles the validated object 'v' described by 'f' (an OBJECT) into the struct at 'base':
 * every member with a store kind is converted and written at base + its offset; members
 * without one, absent ones and arrays are left to the caller, which compiles an array's items
 * by calling this on each with the item's own struct.
 */
void sch_compile(const sch_field_t *f, const cJSON *v, void *base);

/* Reads of a validated document: member 'name' of 'obj' (case-sensitive; NULL when absent),
 * and the components of a VEC3 as doubles or floats (zeros for a missing one). */
cJSON *sch_member(const cJSON *obj, const char *name);
void sch_vec3d(const cJSON *v, double out[3]);
void sch_vec3f(const cJSON *v, float out[3]);

/* The index among f->enum_values (f an ENUM) of the string 'v', or -1 when it is none of them. */
int sch_enum_index(const sch_field_t *f, const cJSON *v);
/* The same for member 'name' of 'obj', described by the member of that name of 'f' (an OBJECT);
 * -1 when either is missing. */
int sch_member_enum(const sch_field_t *f, const cJSON *obj, const char *name);

/* Follows a dotted path ("waves.0.a", "objects.orb.scale") inside 'root'; NULL if absent. In an
 * array a decimal component is an index (one spelling: no sign, no leading zero) and any other
 * names the item whose member "id" is that string. */
cJSON *sch_path_get(cJSON *root, const char *path);
/* The item of array 'arr' whose member "id" is the string 'id' (not empty), or NULL. */
cJSON *sch_item_by_id(const cJSON *arr, const char *id);
/* Why sch_path_get finds nothing at 'path' in 'root', as a phrase for a message: 'camera has no
 * member "fovy"; did you mean "fov_y"?', 'objects has 8 items', 'waves has no item with id
 * "spak"; did you mean "spark"?'. */
void sch_path_explain(cJSON *root, const char *path, char *buf, size_t len);
/* The field description at a dotted path, or NULL; an array's items are reached by index, and by
 * any other word when they have an "id" member. */
const sch_field_t *sch_path_field(const sch_field_t *root, const char *path);
/* The member 'name' of 'f' (an OBJECT), or NULL. */
const sch_field_t *sch_field_member(const sch_field_t *f, const char *name);

/* The name nearest to 'word' that it is likely a misspelling of ("fov_y" for "fovy"), or NULL:
 * among the members 'f' (an OBJECT) describes, or the member names of JSON object 'container'
 * or the ids of the items of JSON array 'container'. */
const char *sch_suggest_field(const sch_field_t *f, const char *word);
const char *sch_suggest_json(const cJSON *container, const char *word);

/* Writes 'v' as the shortest decimal that reads back as the same double ("0.1", "500",
 * "16.000001"), for messages. */
void sch_format_number(char *buf, size_t len, double v);

#endif
