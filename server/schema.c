/*
 * The schema engine: walks a static tree of sch_field_t to validate a cJSON value in place
 * (types, finiteness, ranges, lengths, enums, unknown members), fill in the defaults of absent
 * members and normalise unit vectors; publishes the same tree as JSON Schema; and follows
 * dotted paths ("objects.2.color.1") through documents and through the tree itself.
 *
 * Range convention: a NUMBER, INTEGER or VEC3 field whose 'min' and 'max' are both 0 has no
 * range beyond finiteness, and an infinite bound is no bound. Every error names the dotted path
 * of the offending value, both in sch_error_t.path and at the start of the message.
 */
#include "schema.h"

#include <ctype.h>
#include <float.h>
#include <stdint.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "proto.h"

/* Longest path component we build; longer member names are cut in error paths only. */
#define PATH_MAX_LEN 256

static int has_range(const sch_field_t *f) {
  return !(f->min == 0 && f->max == 0);
}

/* Writes 'v' as the shortest decimal that reads back as the same double, so messages show
 * "0.1" rather than "0.10000000000000001" and "500" rather than "500.000000". */
void sch_format_number(char *buf, size_t len, double v) {
  if (isnan(v)) {
    snprintf(buf, len, "NaN");
    return;
  }
  if (isinf(v)) {
    snprintf(buf, len, v > 0 ? "inf" : "-inf");
    return;
  }
  int prec = 1;
  while (prec < 17) {
    snprintf(buf, len, "%.*g", prec, v);
    if (strtod(buf, NULL) == v)
      break;
    prec++;
  }
  /* %g switches to an exponent once it exceeds the precision; integers up to 17 digits read
   * better written out ("500", not "5e+02"). */
  int digits = v == 0 ? 1 : (int)floor(log10(fabs(v))) + 1;
  if (digits > prec && digits <= 17)
    prec = digits;
  snprintf(buf, len, "%.*g", prec, v);
}

/* Fills 'err' with 'path' and a message that starts with 'shown' (when not empty). The two
 * differ only for an unknown member, whose message reads best from its container. */
static int vfail_at(sch_error_t *err, const char *path, const char *shown, const char *fmt,
                    va_list ap) {
  char what[224];
  vsnprintf(what, sizeof what, fmt, ap);
  if (shown[0])
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, path, "%s: %s", shown, what);
  return proto_error_set(err, PROTO_E_INVALID_PARAMS, path, "%s", what);
}

static int fail_at(sch_error_t *err, const char *path, const char *shown, const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  vfail_at(err, path, shown, fmt, ap);
  va_end(ap);
  return -1;
}

int sch_error_set(sch_error_t *err, const char *path, const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  vfail_at(err, path, path, fmt, ap);
  va_end(ap);
  return -1;
}

/* The JSON type name of 'v', with its article, for "expected X, got Y" messages. */
static const char *json_kind(const cJSON *v) {
  if (cJSON_IsNull(v))
    return "null";
  if (cJSON_IsBool(v))
    return "a boolean";
  if (cJSON_IsNumber(v))
    return "a number";
  if (cJSON_IsString(v))
    return "a string";
  if (cJSON_IsArray(v))
    return "an array";
  if (cJSON_IsObject(v))
    return "an object";
  return "an invalid value";
}

/* Joins 'prefix' and a member name or index into 'out' ("camera" + "fov_y" = "camera.fov_y"). */
static void join_path(char *out, size_t len, const char *prefix, const char *name) {
  if (prefix[0])
    snprintf(out, len, "%s.%s", prefix, name);
  else
    snprintf(out, len, "%s", name);
}

static void join_index(char *out, size_t len, const char *prefix, int i) {
  char idx[16];
  snprintf(idx, sizeof idx, "%d", i);
  join_path(out, len, prefix, idx);
}

/* Checks one number against the field's range; 'path' names it. */
static int check_number(const sch_field_t *f, double v, const char *path, sch_error_t *err) {
  char a[32], lo[32], hi[32];
  /* cJSON never parses NaN or Inf from JSON text, but a value built in C can hold either, and
   * no such number may reach a kernel. */
  if (!isfinite(v)) {
    sch_format_number(a, sizeof a, v);
    return sch_error_set(err, path, "%s is not a finite number", a);
  }
  if (f->type == SCH_INTEGER && v != floor(v)) {
    sch_format_number(a, sizeof a, v);
    return sch_error_set(err, path, "%s is not an integer", a);
  }
  if (!has_range(f))
    return 0;
  int below = (f->flags & SCH_POSITIVE) ? !(v > f->min) : !(v >= f->min);
  int above = !(v <= f->max);
  if (!below && !above)
    return 0;
  sch_format_number(a, sizeof a, v);
  sch_format_number(lo, sizeof lo, f->min);
  sch_format_number(hi, sizeof hi, f->max);
  const char *u0 = f->unit ? " (" : "", *u = f->unit ? f->unit : "", *u1 = f->unit ? ")" : "";
  /* A bound left open (a limit the server applies later, such as limits.frame_side) is not
   * printed as an infinity. */
  if (isinf(f->max) && below)
    return sch_error_set(err, path, "%s is below the %s %s%s%s%s", a,
                         (f->flags & SCH_POSITIVE) ? "exclusive minimum" : "minimum", lo, u0, u,
                         u1);
  if (isinf(f->min) && above)
    return sch_error_set(err, path, "%s is above the maximum %s%s%s%s", a, hi, u0, u, u1);
  return sch_error_set(err, path, "%s is out of range %c%s, %s%c%s%s%s", a,
                       (f->flags & SCH_POSITIVE) || isinf(f->min) ? '(' : '[', lo, hi,
                       isinf(f->max) ? ')' : ']', f->unit ? " (" : "", f->unit ? f->unit : "",
                       f->unit ? ")" : "");
}

static int validate(const sch_field_t *f, cJSON *v, const char *path, sch_error_t *err);

/* The raw default of 'f' before validation: objects start empty and arrays empty, so that
 * validating them fills in every nested default. NULL when 'f' has none (ANY) or on OOM. */
static cJSON *raw_default(const sch_field_t *f) {
  static const double zero[3] = {0, 0, 0};
  switch (f->type) {
  case SCH_NUMBER:
  case SCH_INTEGER:
    return cJSON_CreateNumber(f->def);
  case SCH_BOOL:
    return cJSON_CreateBool(f->def != 0);
  case SCH_STRING:
    return cJSON_CreateString(f->def_str ? f->def_str : "");
  case SCH_ENUM:
    if (f->def_str)
      return cJSON_CreateString(f->def_str);
    return f->enum_values && f->enum_values[0] ? cJSON_CreateString(f->enum_values[0]) : NULL;
  case SCH_VEC3:
    return cJSON_CreateDoubleArray(f->def_vec ? f->def_vec : zero, 3);
  case SCH_OBJECT:
    return cJSON_CreateObject();
  case SCH_ARRAY:
    return cJSON_CreateArray();
  case SCH_ANY:
    break;
  }
  return NULL;
}

/* The validated default of 'f' at 'path', or NULL with 'err' set. A default that does not pass
 * its own field is a bug in the schema, and reported as such rather than silently stored. */
static cJSON *make_default(const sch_field_t *f, const char *path, sch_error_t *err) {
  cJSON *d = raw_default(f);
  if (!d) {
    sch_error_set(err, path, "has no default value");
    return NULL;
  }
  if (validate(f, d, path, err) != 0) {
    cJSON_Delete(d);
    return NULL;
  }
  return d;
}

static int validate_vec3(const sch_field_t *f, cJSON *v, const char *path, sch_error_t *err) {
  char sub[PATH_MAX_LEN];
  double c[3];
  if (!cJSON_IsArray(v))
    return sch_error_set(err, path, "expected an array of 3 numbers, got %s", json_kind(v));
  int n = cJSON_GetArraySize(v);
  if (n != 3)
    return sch_error_set(err, path, "expected an array of 3 numbers, got %d item%s", n,
                         n == 1 ? "" : "s");
  int i = 0;
  for (cJSON *it = v->child; it; it = it->next, i++) {
    join_index(sub, sizeof sub, path, i);
    if (!cJSON_IsNumber(it))
      return sch_error_set(err, sub, "expected a number, got %s", json_kind(it));
    if (check_number(f, it->valuedouble, sub, err) != 0)
      return -1;
    c[i] = it->valuedouble;
  }
  if (!(f->flags & SCH_UNIT_VEC))
    return 0;
  /* A vector already of unit length, up to rounding, is left as it is: normalising it again
   * could move its last bits, and a document validated twice must not change. */
  if (fabs(c[0] * c[0] + c[1] * c[1] + c[2] * c[2] - 1) <= 4 * DBL_EPSILON)
    return 0;
  /* Scale by the largest component first so that the squares cannot overflow. */
  double m = fmax(fabs(c[0]), fmax(fabs(c[1]), fabs(c[2])));
  if (m == 0)
    return sch_error_set(err, path, "a direction cannot be the zero vector");
  double x = c[0] / m, y = c[1] / m, z = c[2] / m;
  double len = sqrt(x * x + y * y + z * z);
  i = 0;
  for (cJSON *it = v->child; it; it = it->next, i++) {
    double u = (i == 0 ? x : i == 1 ? y : z) / len;
    cJSON_SetNumberValue(it, u);
  }
  return 0;
}

static int validate_object(const sch_field_t *f, cJSON *v, const char *path, sch_error_t *err) {
  char sub[PATH_MAX_LEN];
  if (!cJSON_IsObject(v))
    return sch_error_set(err, path, "expected an object, got %s", json_kind(v));
  int nf = 0;
  while (f->fields && f->fields[nf].name)
    nf++;
  /* 'slot[k]' is the member for field k: it finds duplicates, and afterwards puts the members
   * back in schema order so every document reads the same way whatever built it. */
  cJSON **slot = calloc((size_t)nf + 1, sizeof *slot);
  if (!slot)
    return sch_error_set(err, path, "out of memory");
  int rc = -1;
  for (cJSON *m = v->child; m; m = m->next) {
    /* Only an object built in C can have a nameless member; parsed JSON never does. */
    if (!m->string) {
      sch_error_set(err, path, "has a member without a name");
      goto out;
    }
    int k = 0;
    while (k < nf && strcmp(f->fields[k].name, m->string) != 0)
      k++;
    join_path(sub, sizeof sub, path, m->string);
    if (k == nf) {
      if (f->flags & SCH_OPEN)
        continue;
      /* The path names the member itself, for a client to point at; the message reads from
       * its container: 'objects.2: unknown member "colour"'. */
      const char *near = sch_suggest_field(f, m->string);
      fail_at(err, sub, path, "unknown member \"%s\"%s%s%s", m->string,
              near ? "; did you mean \"" : "", near ? near : "", near ? "\"?" : "");
      goto out;
    }
    if (slot[k]) {
      sch_error_set(err, sub, "member appears twice");
      goto out;
    }
    slot[k] = m;
    if (validate(&f->fields[k], m, sub, err) != 0)
      goto out;
  }
  for (int k = 0; k < nf; k++) {
    const sch_field_t *mf = &f->fields[k];
    if (slot[k])
      continue;
    join_path(sub, sizeof sub, path, mf->name);
    if (mf->flags & SCH_REQUIRED) {
      sch_error_set(err, sub, "required member is missing");
      goto out;
    }
    if (mf->flags & SCH_NO_DEFAULT || mf->type == SCH_ANY)
      continue;
    cJSON *d = make_default(mf, sub, err);
    if (!d)
      goto out;
    if (!cJSON_AddItemToObject(v, mf->name, d)) {
      cJSON_Delete(d);
      sch_error_set(err, sub, "out of memory");
      goto out;
    }
    slot[k] = d;
  }
  /* Re-append the described members in schema order; undescribed ones (SCH_OPEN) stay first.
   * Re-adding under the item's own key is safe: cJSON copies the key before freeing it. */
  for (int k = 0; k < nf; k++) {
    if (!slot[k])
      continue;
    cJSON_DetachItemViaPointer(v, slot[k]);
    if (!cJSON_AddItemToObject(v, slot[k]->string, slot[k])) {
      cJSON_Delete(slot[k]);
      sch_error_set(err, path, "out of memory");
      goto out;
    }
  }
  rc = 0;
out:
  free(slot);
  return rc;
}

static int validate_array(const sch_field_t *f, cJSON *v, const char *path, sch_error_t *err) {
  char sub[PATH_MAX_LEN];
  if (!cJSON_IsArray(v))
    return sch_error_set(err, path, "expected an array, got %s", json_kind(v));
  int n = cJSON_GetArraySize(v);
  if (f->max > 0 && n > f->max)
    return sch_error_set(err, path, "%d items is more than the limit of %.0f", n, f->max);
  if (!f->items)
    return 0;
  int i = 0;
  for (cJSON *it = v->child; it; it = it->next, i++) {
    join_index(sub, sizeof sub, path, i);
    if (validate(f->items, it, sub, err) != 0)
      return -1;
  }
  return 0;
}

/* Any value, of at most f->max bytes printed compactly when 'max' is set. */
static int validate_any(const sch_field_t *f, const cJSON *v, const char *path, sch_error_t *err) {
  if (!(f->max > 0))
    return 0;
  char *text = cJSON_PrintUnformatted(v);
  if (!text)
    return sch_error_set(err, path, "out of memory");
  size_t n = strlen(text);
  free(text);
  if ((double)n > f->max)
    return sch_error_set(err, path, "value of %zu bytes of JSON is longer than the limit of %.0f",
                         n, f->max);
  return 0;
}

static int validate(const sch_field_t *f, cJSON *v, const char *path, sch_error_t *err) {
  switch (f->type) {
  case SCH_NUMBER:
  case SCH_INTEGER:
    if (!cJSON_IsNumber(v))
      return sch_error_set(err, path, "expected %s, got %s",
                           f->type == SCH_INTEGER ? "an integer" : "a number", json_kind(v));
    return check_number(f, v->valuedouble, path, err);
  case SCH_BOOL:
    if (!cJSON_IsBool(v))
      return sch_error_set(err, path, "expected true or false, got %s", json_kind(v));
    return 0;
  case SCH_STRING:
    if (!cJSON_IsString(v) || !v->valuestring)
      return sch_error_set(err, path, "expected a string, got %s", json_kind(v));
    if (f->max > 0 && (double)strlen(v->valuestring) > f->max)
      return sch_error_set(err, path, "string of %zu bytes is longer than the limit of %.0f",
                           strlen(v->valuestring), f->max);
    return 0;
  case SCH_ENUM: {
    if (!cJSON_IsString(v) || !v->valuestring)
      return sch_error_set(err, path, "expected a string, got %s", json_kind(v));
    char list[160] = "";
    size_t used = 0;
    for (int i = 0; f->enum_values && f->enum_values[i]; i++) {
      if (strcmp(v->valuestring, f->enum_values[i]) == 0)
        return 0;
      int w = snprintf(list + used, sizeof list - used, "%s%s", i ? ", " : "", f->enum_values[i]);
      if (w > 0 && (size_t)w < sizeof list - used)
        used += (size_t)w;
    }
    /* Quote at most a prefix of what the client sent, so the message stays readable. */
    return sch_error_set(err, path, "\"%.40s\" is not one of %s", v->valuestring, list);
  }
  case SCH_VEC3:
    return validate_vec3(f, v, path, err);
  case SCH_OBJECT:
    return validate_object(f, v, path, err);
  case SCH_ARRAY:
    return validate_array(f, v, path, err);
  case SCH_ANY:
    return validate_any(f, v, path, err);
  }
  return sch_error_set(err, path, "has an unknown schema type");
}

int sch_validate(const sch_field_t *f, cJSON *v, const char *prefix, sch_error_t *err) {
  proto_error_clear(err);
  if (!f || !v)
    return sch_error_set(err, prefix ? prefix : "", "missing value");
  return validate(f, v, prefix ? prefix : "", err);
}

cJSON *sch_defaults(const sch_field_t *f) {
  sch_error_t err;
  return f ? make_default(f, "", &err) : NULL;
}

/* Adds the number 'v' to 's' as 'name'. cJSON prints doubles with 15 significant digits when
 * they read back within its tolerance, which turns 2^53 - 1 into 9007199254740990: integers
 * from 10^15 up are printed whole instead. */
static void add_number(cJSON *s, const char *name, double v) {
  char text[32];
  if (fabs(v) >= 1e15 && fabs(v) < 9.2e18 && v == floor(v)) {
    snprintf(text, sizeof text, "%.0f", v);
    cJSON_AddRawToObject(s, name, text);
  } else {
    cJSON_AddNumberToObject(s, name, v);
  }
}

/* Adds the range keywords of 'f' to the JSON Schema 's'; infinite bounds are left out since
 * JSON cannot carry them. */
static void add_range(cJSON *s, const sch_field_t *f) {
  if (!has_range(f))
    return;
  if (isfinite(f->min))
    add_number(s, (f->flags & SCH_POSITIVE) ? "exclusiveMinimum" : "minimum", f->min);
  if (isfinite(f->max))
    add_number(s, "maximum", f->max);
}

cJSON *sch_to_json_schema(const sch_field_t *f) {
  if (!f)
    return NULL;
  cJSON *s = cJSON_CreateObject();
  if (!s)
    return NULL;
  switch (f->type) {
  case SCH_NUMBER:
  case SCH_INTEGER:
    cJSON_AddStringToObject(s, "type", f->type == SCH_INTEGER ? "integer" : "number");
    add_range(s, f);
    break;
  case SCH_BOOL:
    cJSON_AddStringToObject(s, "type", "boolean");
    break;
  case SCH_STRING:
    cJSON_AddStringToObject(s, "type", "string");
    if (f->max > 0)
      cJSON_AddNumberToObject(s, "maxLength", f->max);
    break;
  case SCH_ENUM: {
    cJSON_AddStringToObject(s, "type", "string");
    cJSON *e = cJSON_AddArrayToObject(s, "enum");
    for (int i = 0; e && f->enum_values && f->enum_values[i]; i++)
      cJSON_AddItemToArray(e, cJSON_CreateString(f->enum_values[i]));
    break;
  }
  case SCH_VEC3: {
    cJSON_AddStringToObject(s, "type", "array");
    cJSON *it = cJSON_AddObjectToObject(s, "items");
    if (it) {
      cJSON_AddStringToObject(it, "type", "number");
      add_range(it, f);
    }
    cJSON_AddNumberToObject(s, "minItems", 3);
    cJSON_AddNumberToObject(s, "maxItems", 3);
    break;
  }
  case SCH_OBJECT: {
    cJSON_AddStringToObject(s, "type", "object");
    cJSON *props = cJSON_AddObjectToObject(s, "properties");
    cJSON *req = NULL;
    for (const sch_field_t *m = f->fields; m && m->name; m++) {
      if (props)
        cJSON_AddItemToObject(props, m->name, sch_to_json_schema(m));
      if (m->flags & SCH_REQUIRED) {
        if (!req)
          req = cJSON_CreateArray();
        cJSON_AddItemToArray(req, cJSON_CreateString(m->name));
      }
    }
    if (!(f->flags & SCH_OPEN))
      cJSON_AddFalseToObject(s, "additionalProperties");
    if (req)
      cJSON_AddItemToObject(s, "required", req);
    break;
  }
  case SCH_ARRAY:
    cJSON_AddStringToObject(s, "type", "array");
    if (f->items)
      cJSON_AddItemToObject(s, "items", sch_to_json_schema(f->items));
    if (f->max > 0)
      cJSON_AddNumberToObject(s, "maxItems", f->max);
    break;
  case SCH_ANY:
    break;
  }
  /* Objects carry their defaults in their properties; every other field shows the value an
   * absent member gets, already validated (so a unit vector's default appears normalised). */
  int shows_default =
      !(f->flags & (SCH_REQUIRED | SCH_NO_DEFAULT)) || (f->flags & SCH_SHOW_DEFAULT);
  if (f->type != SCH_OBJECT && f->type != SCH_ANY && shows_default) {
    cJSON *d = sch_defaults(f);
    if (d)
      cJSON_AddItemToObject(s, "default", d);
  }
  if (f->desc)
    cJSON_AddStringToObject(s, "description", f->desc);
  if (f->unit)
    cJSON_AddStringToObject(s, "x-unit", f->unit);
  return s;
}

/* Reads the decimal array index in [p, p+n): digits only, no sign, no leading zero (other than
 * "0" itself), so each index has one spelling. Returns -1 for anything else. */
static long parse_index(const char *p, size_t n) {
  if (n == 0 || n > 9 || (n > 1 && p[0] == '0'))
    return -1;
  long v = 0;
  for (size_t i = 0; i < n; i++) {
    if (p[i] < '0' || p[i] > '9')
      return -1;
    v = v * 10 + (p[i] - '0');
  }
  return v;
}

/* Finds the member of 'obj' named by [p, p+n), case-sensitively (cJSON_GetObjectItem is not). */
static cJSON *member_n(cJSON *obj, const char *p, size_t n) {
  for (cJSON *m = obj->child; m; m = m->next)
    if (m->string && strlen(m->string) == n && memcmp(m->string, p, n) == 0)
      return m;
  return NULL;
}

/* The item of array 'arr' whose member "id" is the string [p, p+n); NULL when none is, and
 * for the empty id, which names no item. */
static cJSON *item_by_id_n(const cJSON *arr, const char *p, size_t n) {
  if (n == 0)
    return NULL;
  for (cJSON *it = arr->child; it; it = it->next) {
    const cJSON *id = cJSON_IsObject(it) ? member_n(it, "id", 2) : NULL;
    if (cJSON_IsString(id) && strlen(id->valuestring) == n && memcmp(id->valuestring, p, n) == 0)
      return it;
  }
  return NULL;
}

cJSON *sch_item_by_id(const cJSON *arr, const char *id) {
  return cJSON_IsArray(arr) && id ? item_by_id_n(arr, id, strlen(id)) : NULL;
}

/* One step of a dotted path: the member [p, p+n) of an object, or the item of an array at that
 * decimal index or, for any other word, with that id. NULL when there is none. */
static cJSON *path_step(cJSON *cur, const char *p, size_t n) {
  if (n == 0)
    return NULL;
  if (cJSON_IsObject(cur))
    return member_n(cur, p, n);
  if (!cJSON_IsArray(cur))
    return NULL;
  long i = parse_index(p, n);
  return i >= 0 ? cJSON_GetArrayItem(cur, (int)i) : item_by_id_n(cur, p, n);
}

cJSON *sch_path_get(cJSON *root, const char *path) {
  if (!path || !path[0])
    return root;
  cJSON *cur = root;
  const char *p = path;
  while (cur) {
    const char *dot = strchr(p, '.');
    size_t n = dot ? (size_t)(dot - p) : strlen(p);
    cur = path_step(cur, p, n);
    if (!dot)
      return cur;
    p = dot + 1;
  }
  return NULL;
}

/* The edit distance between 'a' and 'b' ignoring case (insertions, deletions, substitutions
 * and swaps of two neighbours each count 1); words over 63 bytes count as far apart. */
static size_t edit_distance(const char *a, const char *b) {
  size_t na = strlen(a), nb = strlen(b);
  if (na > 63 || nb > 63)
    return SIZE_MAX;
  size_t d[64][64];
  for (size_t i = 0; i <= na; i++)
    d[i][0] = i;
  for (size_t j = 0; j <= nb; j++)
    d[0][j] = j;
  for (size_t i = 1; i <= na; i++)
    for (size_t j = 1; j <= nb; j++) {
      int ca = tolower((unsigned char)a[i - 1]), cb = tolower((unsigned char)b[j - 1]);
      size_t best = d[i - 1][j - 1] + (ca != cb);
      if (d[i - 1][j] + 1 < best)
        best = d[i - 1][j] + 1;
      if (d[i][j - 1] + 1 < best)
        best = d[i][j - 1] + 1;
      if (i > 1 && j > 1 && ca == tolower((unsigned char)b[j - 2]) &&
          tolower((unsigned char)a[i - 2]) == cb && d[i - 2][j - 2] + 1 < best)
        best = d[i - 2][j - 2] + 1;
      d[i][j] = best;
    }
  return d[na][nb];
}

/* A suggestion being chosen: the nearest candidate so far to 'word'. */
typedef struct suggestion {
  const char *word, *best;
  size_t distance;
} suggestion_t;

/* Keeps 'candidate' when it is nearer to the word than the best so far and near enough to be
 * what was meant: at most a third of the longer word's letters differ ("fovy" for "fov_y"). */
static void suggestion_consider(suggestion_t *s, const char *candidate) {
  if (!candidate || !candidate[0])
    return;
  size_t d = edit_distance(s->word, candidate);
  size_t longer = strlen(s->word) > strlen(candidate) ? strlen(s->word) : strlen(candidate);
  if (d == SIZE_MAX || 3 * d > longer || d >= s->distance)
    return;
  s->best = candidate;
  s->distance = d;
}

const char *sch_suggest_field(const sch_field_t *f, const char *word) {
  suggestion_t s = {word, NULL, SIZE_MAX};
  for (const sch_field_t *m = f && f->type == SCH_OBJECT ? f->fields : NULL; m && m->name; m++)
    suggestion_consider(&s, m->name);
  return s.best;
}

const char *sch_suggest_json(const cJSON *container, const char *word) {
  suggestion_t s = {word, NULL, SIZE_MAX};
  for (const cJSON *c = container ? container->child : NULL; c; c = c->next) {
    if (cJSON_IsObject(container))
      suggestion_consider(&s, c->string);
    else if (cJSON_IsArray(container))
      suggestion_consider(&s, cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(c, "id")));
  }
  return s.best;
}

/* Appends '; did you mean "X"?' to 'buf' when 'best' is a suggestion. */
static void append_suggestion(char *buf, size_t len, const char *best) {
  size_t used = strlen(buf);
  if (best && used < len)
    snprintf(buf + used, len - used, "; did you mean \"%s\"?", best);
}

void sch_path_explain(cJSON *root, const char *path, char *buf, size_t len) {
  char word[PATH_MAX_LEN], where[PATH_MAX_LEN];
  cJSON *cur = root;
  const char *p = path ? path : "";
  for (;;) {
    const char *dot = strchr(p, '.');
    size_t n = dot ? (size_t)(dot - p) : strlen(p);
    snprintf(word, sizeof word, "%.*s", (int)(n < sizeof word ? n : sizeof word - 1), p);
    /* The path up to this component: where the search stopped. */
    int upto = p > path ? (int)(p - path - 1) : 0;
    if (upto)
      snprintf(where, sizeof where, "%.*s", upto < PATH_MAX_LEN - 1 ? upto : PATH_MAX_LEN - 1,
               path);
    else
      snprintf(where, sizeof where, "the document");
    cJSON *next = path_step(cur, p, n);
    if (!next) {
      if (n == 0)
        snprintf(buf, len, "an empty name after %s", where);
      else if (cJSON_IsObject(cur)) {
        snprintf(buf, len, "%s has no member \"%s\"", where, word);
        append_suggestion(buf, len, sch_suggest_json(cur, word));
      } else if (cJSON_IsArray(cur) && parse_index(p, n) >= 0)
        snprintf(buf, len, "%s has %d item%s", where, cJSON_GetArraySize(cur),
                 cJSON_GetArraySize(cur) == 1 ? "" : "s");
      else if (cJSON_IsArray(cur)) {
        snprintf(buf, len, "%s has no item with id \"%s\"", where, word);
        append_suggestion(buf, len, sch_suggest_json(cur, word));
      } else
        snprintf(buf, len, "%s is %s, which has no members", where, json_kind(cur));
      return;
    }
    if (!dot) {
      snprintf(buf, len, "it exists");
      return;
    }
    cur = next;
    p = dot + 1;
  }
}

const sch_field_t *sch_path_field(const sch_field_t *root, const char *path) {
  if (!path || !path[0])
    return root;
  const sch_field_t *cur = root;
  const char *p = path;
  while (cur) {
    const char *dot = strchr(p, '.');
    size_t n = dot ? (size_t)(dot - p) : strlen(p);
    if (n == 0)
      return NULL;
    const sch_field_t *next = NULL;
    if (cur->type == SCH_OBJECT) {
      for (const sch_field_t *m = cur->fields; m && m->name; m++)
        if (strlen(m->name) == n && memcmp(m->name, p, n) == 0) {
          next = m;
          break;
        }
    } else if (cur->type == SCH_ARRAY) {
      /* An index, or the id of an item whose kind has one. */
      if (parse_index(p, n) >= 0 || sch_field_member(cur->items, "id"))
        next = cur->items;
    }
    /* A vec3 component has no field description of its own, so such a path ends here. */
    cur = next;
    if (!dot)
      return cur;
    p = dot + 1;
  }
  return NULL;
}

const sch_field_t *sch_field_member(const sch_field_t *f, const char *name) {
  for (const sch_field_t *m = f && f->type == SCH_OBJECT ? f->fields : NULL; m && m->name; m++)
    if (strcmp(m->name, name) == 0)
      return m;
  return NULL;
}

int sch_enum_index(const sch_field_t *f, const cJSON *v) {
  if (!f || f->type != SCH_ENUM || !cJSON_IsString(v) || !v->valuestring)
    return -1;
  for (int i = 0; f->enum_values && f->enum_values[i]; i++)
    if (strcmp(v->valuestring, f->enum_values[i]) == 0)
      return i;
  return -1;
}

int sch_member_enum(const sch_field_t *f, const cJSON *obj, const char *name) {
  for (const sch_field_t *m = f ? f->fields : NULL; m && m->name; m++)
    if (strcmp(m->name, name) == 0)
      return sch_enum_index(m, cJSON_GetObjectItemCaseSensitive(obj, name));
  return -1;
}

cJSON *sch_member(const cJSON *obj, const char *name) {
  return cJSON_GetObjectItemCaseSensitive(obj, name);
}

void sch_vec3d(const cJSON *v, double out[3]) {
  int i = 0;
  out[0] = out[1] = out[2] = 0;
  for (const cJSON *it = v ? v->child : NULL; it && i < 3; it = it->next)
    out[i++] = it->valuedouble;
}

void sch_vec3f(const cJSON *v, float out[3]) {
  double d[3];
  sch_vec3d(v, d);
  for (int i = 0; i < 3; i++)
    out[i] = (float)d[i];
}

/* Stores the validated value 'v' of field 'f' at 'at' as f->store says. */
static void store_value(const sch_field_t *f, const cJSON *v, char *at) {
  double d = v->valuedouble, c[3];
  switch (f->store) {
  case SCH_STORE_NONE:
  case SCH_STORE_MEMBERS:
    break;
  case SCH_STORE_F32:
    *(float *)(void *)at = (float)d;
    break;
  case SCH_STORE_F64:
    *(double *)(void *)at = d;
    break;
  case SCH_STORE_INT:
    *(int *)(void *)at = (int)d;
    break;
  case SCH_STORE_U32:
    *(uint32_t *)(void *)at = (uint32_t)d;
    break;
  case SCH_STORE_U64:
    *(uint64_t *)(void *)at = (uint64_t)d;
    break;
  case SCH_STORE_BOOL:
    *(int *)(void *)at = cJSON_IsTrue(v);
    break;
  case SCH_STORE_ENUM: {
    int i = sch_enum_index(f, v);
    *(int *)(void *)at = i >= 0 && f->enum_codes ? f->enum_codes[i] : i < 0 ? 0 : i;
    break;
  }
  case SCH_STORE_VEC3F:
  case SCH_STORE_UNIT3F: {
    sch_vec3d(v, c);
    double len = f->store == SCH_STORE_UNIT3F ? sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]) : 1;
    for (int k = 0; k < 3; k++)
      ((float *)(void *)at)[k] = (float)(f->store == SCH_STORE_UNIT3F ? c[k] / len : c[k]);
    break;
  }
  case SCH_STORE_VEC3D:
    sch_vec3d(v, (double *)(void *)at);
    break;
  case SCH_STORE_VEC3U32:
    sch_vec3d(v, c);
    for (int k = 0; k < 3; k++)
      ((uint32_t *)(void *)at)[k] = (uint32_t)c[k];
    break;
  }
}

void sch_compile(const sch_field_t *f, const cJSON *v, void *base) {
  for (const sch_field_t *m = f->fields; m && m->name; m++) {
    if (m->store == SCH_STORE_NONE)
      continue;
    const cJSON *mv = cJSON_GetObjectItemCaseSensitive(v, m->name);
    if (!mv)
      continue;
    char *at = (char *)base + m->offset;
    if (m->store == SCH_STORE_MEMBERS)
      sch_compile(m, mv, at);
    else
      store_value(m, mv, at);
  }
}
