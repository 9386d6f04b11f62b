/*
 * The animation engine behind the "animate" arrays: checks entries against the field they
 * animate, evaluates keyframes and moves values toward targets. Values are one number or a
 * vec3; a unit vector (SCH_UNIT_VEC, a wave's direction) is never interpolated through the
 * inside of the sphere, where it could pass through zero, but turned along the great circle,
 * so that every intermediate value is again a unit vector. Any other value moves along the
 * straight line and is kept between its two end points, so an animation between two valid
 * values never leaves the field's range.
 */
#include "anim.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <string.h>

/* A field value: one number (n = 1) or a vec3 (n = 3). */
typedef struct value {
  double v[3];
  int n;
} value_t;

static cJSON *member(const cJSON *obj, const char *name) {
  return cJSON_GetObjectItemCaseSensitive(obj, name);
}

/* The description of the member 'name' among 'fields', or NULL. */
static const sch_field_t *field_named(const sch_field_t *fields, const char *name) {
  for (const sch_field_t *f = fields; f && f->name; f++)
    if (strcmp(f->name, name) == 0)
      return f;
  return NULL;
}

/* Reads a validated number or vec3. */
static value_t read_value(const cJSON *j) {
  value_t x = {{0, 0, 0}, 1};
  if (cJSON_IsNumber(j)) {
    x.v[0] = j->valuedouble;
    return x;
  }
  x.n = 3;
  int i = 0;
  for (const cJSON *it = j ? j->child : NULL; it && i < 3; it = it->next)
    x.v[i++] = it->valuedouble;
  return x;
}

/* Stores 'x' into 'j', which has the same shape; setting numbers never allocates. */
static void write_value(cJSON *j, const value_t *x) {
  if (cJSON_IsNumber(j)) {
    cJSON_SetNumberValue(j, x->v[0]);
    return;
  }
  int i = 0;
  for (cJSON *it = j ? j->child : NULL; it && i < 3; it = it->next, i++)
    cJSON_SetNumberValue(it, x->v[i]);
}

static double dot3(const double a[3], const double b[3]) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static void normalise3(double v[3]) {
  double len = sqrt(dot3(v, v));
  if (len > 0)
    for (int i = 0; i < 3; i++)
      v[i] /= len;
}

/* The angle between unit vectors 'a' and 'b'; atan2 stays accurate near 0 and pi, where acos
 * of the dot product does not. */
static double angle3(const double a[3], const double b[3]) {
  double c[3] = {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
  return atan2(sqrt(dot3(c, c)), dot3(a, b));
}

/*
 * Turns unit vector 'a' by 'angle' radians toward unit vector 'b' in their common plane,
 * into 'out'. Opposite vectors share no plane, so one through the axis least aligned with
 * 'a' is taken: the turn is then still well defined and reaches 'b' after pi radians.
 */
static void turn_toward(const double a[3], const double b[3], double angle, double out[3]) {
  double d = dot3(a, b);
  double p[3];
  for (int i = 0; i < 3; i++)
    p[i] = b[i] - d * a[i];
  if (sqrt(dot3(p, p)) < 1e-12) {
    int k = 0;
    for (int i = 1; i < 3; i++)
      if (fabs(a[i]) < fabs(a[k]))
        k = i;
    double e[3] = {0, 0, 0};
    e[k] = 1;
    for (int i = 0; i < 3; i++)
      p[i] = e[i] - a[k] * a[i];
  }
  normalise3(p);
  for (int i = 0; i < 3; i++)
    out[i] = a[i] * cos(angle) + p[i] * sin(angle);
  normalise3(out);
}

/* The point a fraction 'u' (0 to 1) of the way from 'a' to 'b': along the great circle when
 * 'unit', else along the straight line, each component kept between its end points. */
static value_t mix(const value_t *a, const value_t *b, double u, int unit) {
  value_t r = *b;
  if (u >= 1)
    return r;
  if (unit && a->n == 3) {
    turn_toward(a->v, b->v, u * angle3(a->v, b->v), r.v);
    return r;
  }
  for (int i = 0; i < a->n; i++) {
    double x = a->v[i] + (b->v[i] - a->v[i]) * u;
    r.v[i] = fmin(fmax(x, fmin(a->v[i], b->v[i])), fmax(a->v[i], b->v[i]));
  }
  return r;
}

/* The distance from 'a' to 'b' along the line, or the great circle when 'unit'. */
static double distance(const value_t *a, const value_t *b, int unit) {
  if (unit && a->n == 3)
    return angle3(a->v, b->v);
  double s = 0;
  for (int i = 0; i < a->n; i++)
    s += (b->v[i] - a->v[i]) * (b->v[i] - a->v[i]);
  return sqrt(s);
}

/* 'cur' moved by 'step' toward 'target' (radians along the great circle when 'unit'), ending
 * exactly on the target when the step reaches it. */
static value_t move_toward(const value_t *cur, const value_t *target, double step, int unit) {
  double dist = distance(cur, target, unit);
  if (!(dist > step))
    return *target;
  return mix(cur, target, step / dist, unit);
}

/* The value of keyframe entry 'e' at time 'now'. */
static value_t eval_keys(const cJSON *e, double now, int unit) {
  const cJSON *keys = member(e, "keys");
  const cJSON *first = keys->child, *last = first;
  while (last->next)
    last = last->next;
  double t0 = member(first, "t")->valuedouble, t1 = member(last, "t")->valuedouble;
  if (cJSON_IsTrue(member(e, "loop")) && t1 > t0 && now > t1)
    now = t0 + fmod(now - t0, t1 - t0);
  if (now <= t0)
    return read_value(member(first, "value"));
  if (now >= t1)
    return read_value(member(last, "value"));
  const cJSON *k = first;
  while (k->next && member(k->next, "t")->valuedouble <= now)
    k = k->next;
  double ta = member(k, "t")->valuedouble, tb = member(k->next, "t")->valuedouble;
  double u = (now - ta) / (tb - ta);
  const cJSON *interp = member(e, "interp");
  if (interp && strcmp(interp->valuestring, "smooth") == 0)
    u = u * u * (3 - 2 * u);
  value_t a = read_value(member(k, "value")), b = read_value(member(k->next, "value"));
  return mix(&a, &b, u, unit);
}

/* Checks one toward-target entry 'e' at 'path' animating field 'f'. */
static int check_target(cJSON *e, const sch_field_t *f, const char *path, sch_error_t *err) {
  char sub[256];
  if (!member(e, "rate")) {
    snprintf(sub, sizeof sub, "%s.rate", path);
    return sch_error_set(err, sub, "required member is missing (a target is approached at a rate)");
  }
  static const char *const keys_only[] = {"interp", "loop"};
  for (int i = 0; i < 2; i++)
    if (member(e, keys_only[i])) {
      snprintf(sub, sizeof sub, "%s.%s", path, keys_only[i]);
      return sch_error_set(err, sub, "applies to keyframes only, not to a target");
    }
  snprintf(sub, sizeof sub, "%s.target", path);
  return sch_validate(f, member(e, "target"), sub, err);
}

/* Checks one keyframe entry 'e' at 'path' animating field 'f', and fills its defaults. */
static int check_keys(cJSON *e, const sch_field_t *f, const char *path, sch_error_t *err) {
  char sub[256];
  if (member(e, "rate")) {
    snprintf(sub, sizeof sub, "%s.rate", path);
    return sch_error_set(err, sub, "applies to a target only, not to keyframes");
  }
  cJSON *keys = member(e, "keys");
  if (!keys->child) {
    snprintf(sub, sizeof sub, "%s.keys", path);
    return sch_error_set(err, sub, "needs at least one key");
  }
  int k = 0;
  double prev = 0;
  for (cJSON *key = keys->child; key; key = key->next, k++) {
    double t = member(key, "t")->valuedouble;
    if (k > 0 && !(t > prev)) {
      snprintf(sub, sizeof sub, "%s.keys.%d.t", path, k);
      return sch_error_set(err, sub, "%g must be greater than the previous key's t (%g)", t, prev);
    }
    prev = t;
    snprintf(sub, sizeof sub, "%s.keys.%d.value", path, k);
    if (sch_validate(f, member(key, "value"), sub, err) != 0)
      return -1;
  }
  /* Fill the defaults the schema publishes but cannot fill (SCH_SHOW_DEFAULT), keeping the
   * schema's member order: interp, then loop. */
  cJSON *loop = cJSON_DetachItemFromObjectCaseSensitive(e, "loop");
  if (!loop)
    loop = cJSON_CreateFalse();
  if (!member(e, "interp") && !cJSON_AddStringToObject(e, "interp", "linear")) {
    cJSON_Delete(loop);
    return sch_error_set(err, path, "out of memory");
  }
  if (!loop || !cJSON_AddItemToObject(e, "loop", loop)) {
    cJSON_Delete(loop);
    return sch_error_set(err, path, "out of memory");
  }
  return 0;
}

int anim_check(cJSON *obj, const sch_field_t *fields, const char *prefix, sch_error_t *err) {
  char path[192], sub[256]; /* Room for a suffix after any path. */
  cJSON *anim = member(obj, "animate");
  int m = 0;
  for (cJSON *e = anim ? anim->child : NULL; e; e = e->next, m++) {
    snprintf(path, sizeof path, "%s.animate.%d", prefix, m);
    snprintf(sub, sizeof sub, "%s.field", path);
    const char *name = member(e, "field")->valuestring;
    const sch_field_t *f = field_named(fields, name);
    if (!f || (f->type != SCH_NUMBER && f->type != SCH_VEC3))
      return sch_error_set(err, sub, "\"%.40s\" is not a numeric field", name);
    int j = 0;
    for (const cJSON *p = anim->child; p != e; p = p->next, j++)
      if (strcmp(member(p, "field")->valuestring, name) == 0)
        return sch_error_set(err, sub, "\"%s\" is already animated by %s.animate.%d", name, prefix,
                             j);
    int has_target = member(e, "target") != NULL, has_keys = member(e, "keys") != NULL;
    if (has_target && has_keys) {
      snprintf(sub, sizeof sub, "%s.keys", path);
      return sch_error_set(err, sub,
                           "an animation has either a target and a rate, or keys, not both");
    }
    if (!has_target && !has_keys)
      return sch_error_set(err, path, "needs either a target and a rate, or keys");
    int rc = has_target ? check_target(e, f, path, err) : check_keys(e, f, path, err);
    if (rc != 0)
      return -1;
  }
  return 0;
}

int anim_animates(const cJSON *obj, const char *name) {
  const cJSON *anim = member(obj, "animate");
  for (const cJSON *e = anim ? anim->child : NULL; e; e = e->next) {
    const cJSON *f = member(e, "field");
    if (cJSON_IsString(f) && strcmp(f->valuestring, name) == 0)
      return 1;
  }
  return 0;
}

/*
 * 'cur' after 'steps' steps of 'step' toward 'target', each taken as one step alone would be,
 * so that the value after n steps does not depend on how they were grouped. Once the target is
 * surely reached (the steps cover the distance with two to spare) it is the target, exactly
 * what the steps one by one end on.
 */
static value_t move_steps(value_t cur, const value_t *target, double step, uint64_t steps,
                          int unit) {
  if ((double)steps > 2 && ((double)steps - 2) * step > distance(&cur, target, unit) * (1 + 1e-6))
    return *target;
  for (uint64_t k = 0; k < steps; k++) {
    cur = move_toward(&cur, target, step, unit);
    if (memcmp(cur.v, target->v, sizeof cur.v) == 0)
      break;
  }
  return cur;
}

/* Applies the entries of 'obj': keyframes at 'now' always, targets only when 'steps' > 0. */
static void apply(cJSON *obj, const sch_field_t *fields, uint64_t steps, double dt, double now) {
  cJSON *anim = member(obj, "animate");
  for (cJSON *e = anim ? anim->child : NULL; e; e = e->next) {
    const char *name = member(e, "field")->valuestring;
    const sch_field_t *f = field_named(fields, name);
    cJSON *cur = member(obj, name);
    if (!f || !cur)
      continue;
    int unit = (f->flags & SCH_UNIT_VEC) != 0;
    value_t x;
    if (member(e, "keys")) {
      x = eval_keys(e, now, unit);
    } else if (steps > 0) {
      value_t c = read_value(cur), t = read_value(member(e, "target"));
      x = move_steps(c, &t, member(e, "rate")->valuedouble * dt, steps, unit);
    } else {
      continue;
    }
    write_value(cur, &x);
  }
}

void anim_apply_keys(cJSON *obj, const sch_field_t *fields, double now) {
  apply(obj, fields, 0, 0, now);
}

void anim_advance(cJSON *obj, const sch_field_t *fields, uint64_t steps, double dt, double now) {
  apply(obj, fields, steps, dt, now);
}
