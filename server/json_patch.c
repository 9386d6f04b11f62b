/*
 * RFC 6902 JSON Patch over cJSON (json_patch.h): each operation resolves its JSON Pointer to a
 * parent container and a last token, then adds, removes, replaces, moves, copies or tests the
 * value there. Errors name the operation by its index in the list ("ops.2.path").
 */
#include "json_patch.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "proto.h"
#include "schema.h"

#define TOKEN_MAX 256

/* Where a pointer leads: the container holding the last token and that token, unescaped. */
typedef struct spot {
  cJSON *parent; /* NULL for the pointer "", the whole document. */
  char token[TOKEN_MAX];
} spot_t;

/* Copies the token at 'p' (up to the next '/' or the end) into 'out', undoing ~1 and ~0.
 * Returns the length read from 'p', or -1 for a '~' not followed by 0 or 1 or a long token. */
static int token_read(const char *p, char *out) {
  size_t n = 0;
  int i = 0;
  for (; p[i] && p[i] != '/'; i++) {
    char c = p[i];
    if (c == '~') {
      if (p[i + 1] != '0' && p[i + 1] != '1')
        return -1;
      c = p[++i] == '0' ? '~' : '/';
    }
    if (n + 1 >= TOKEN_MAX)
      return -1;
    out[n++] = c;
  }
  out[n] = '\0';
  return i;
}

/* RFC 6901's array index: "0", or digits without a leading zero; -1 for anything else. */
static long token_index(const char *t) {
  size_t n = strlen(t);
  if (n == 0 || n > 9 || (n > 1 && t[0] == '0') || strspn(t, "0123456789") != n)
    return -1;
  return strtol(t, NULL, 10);
}

/* The child of 'c' named by token 't': a member, an item by index or by id; NULL for none. */
static cJSON *token_child(const cJSON *c, const char *t) {
  if (cJSON_IsObject(c))
    return cJSON_GetObjectItemCaseSensitive(c, t);
  if (!cJSON_IsArray(c))
    return NULL;
  long i = token_index(t);
  return i >= 0 ? cJSON_GetArrayItem(c, (int)i) : sch_item_by_id(c, t);
}

/* Names the member 'field' of operation 'i' in 'at' ("ops.2.path"). */
static const char *op_path(char *at, size_t len, int i, const char *field) {
  snprintf(at, len, field ? "ops.%d.%s" : "ops.%d", i, field ? field : "");
  return at;
}

/* Sets 'err' for pointer 'ptr' (of operation member 'at') that leads nowhere: token 'token' is
 * not in 'container', with the member or id it was likely meant to be. Returns -1. */
static int missing(proto_error_t *err, const char *at, const char *ptr, const cJSON *container,
                   const char *token) {
  const char *near = sch_suggest_json(container, token);
  return proto_error_set(err, PROTO_E_NOT_FOUND, at,
                         "%s: nothing at \"%.60s\" (no \"%.40s\")%s%.40s%s", at, ptr, token,
                         near ? "; did you mean \"" : "", near ? near : "", near ? "\"?" : "");
}

/* Resolves 'ptr' to the container of its last token. Returns 0, or -1 with 'err' when the
 * pointer is malformed or a container on the way does not exist. */
static int spot_find(cJSON *doc, const char *ptr, const char *at, spot_t *s, proto_error_t *err) {
  s->parent = NULL;
  s->token[0] = '\0';
  if (!ptr[0])
    return 0;
  if (ptr[0] != '/')
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, at,
                           "%s: \"%.60s\" is not a JSON Pointer (it starts with '/')", at, ptr);
  cJSON *cur = doc;
  const char *p = ptr;
  for (;;) {
    int n = token_read(p + 1, s->token);
    if (n < 0)
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, at,
                             "%s: \"%.60s\" has a '~' not followed by 0 or 1, or a token "
                             "longer than %d bytes",
                             at, ptr, TOKEN_MAX - 1);
    p += 1 + n;
    if (!*p) {
      s->parent = cur;
      return 0;
    }
    cJSON *next = token_child(cur, s->token);
    if (!next)
      return missing(err, at, ptr, cur, s->token);
    cur = next;
  }
}

/* The value a spot names, or NULL. */
static cJSON *spot_value(cJSON *doc, const spot_t *s) {
  return s->parent ? token_child(s->parent, s->token) : doc;
}

/* Drops the member name a copied or detached value still carries, for a place without one
 * (an array's item). Returns 'v'. */
static cJSON *unnamed(cJSON *v) {
  if (v && v->string && !(v->type & cJSON_StringIsConst))
    cJSON_free(v->string);
  if (v)
    v->string = NULL;
  return v;
}

/* Replaces the members of object 'doc' with those of 'v' (taken; an object). */
static int doc_swap(cJSON *doc, cJSON *v, const char *at, proto_error_t *err) {
  if (!cJSON_IsObject(v)) {
    cJSON_Delete(v);
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, at, "%s: the document must be an object",
                           at);
  }
  while (doc->child)
    cJSON_Delete(cJSON_DetachItemViaPointer(doc, doc->child));
  doc->child = v->child;
  v->child = NULL;
  cJSON_Delete(v);
  return 0;
}

/* RFC 6902 "add" of 'v' (taken) at spot 's': a member is set, an array item inserted before
 * the index (or appended at "-" or the length). */
static int spot_add(cJSON *doc, const spot_t *s, cJSON *v, const char *at, proto_error_t *err) {
  if (!s->parent)
    return doc_swap(doc, v, at, err);
  int ok = 0;
  if (cJSON_IsObject(s->parent)) {
    ok = cJSON_GetObjectItemCaseSensitive(s->parent, s->token)
             ? cJSON_ReplaceItemInObjectCaseSensitive(s->parent, s->token, v)
             : cJSON_AddItemToObject(s->parent, s->token, v);
  } else if (cJSON_IsArray(s->parent)) {
    int n = cJSON_GetArraySize(s->parent);
    long i = strcmp(s->token, "-") == 0 ? n : token_index(s->token);
    const cJSON *before = i < 0 ? sch_item_by_id(s->parent, s->token) : NULL;
    for (const cJSON *c = s->parent->child; before && c; c = c->next) {
      i++; /* From -1: the index of the item with that id, which the value goes before. */
      if (c == before)
        break;
    }
    if (i < 0 || i > n) {
      cJSON_Delete(v);
      return proto_error_set(err, PROTO_E_NOT_FOUND, at,
                             "%s: the array has %d items; \"%.40s\" is not an index up to %d, "
                             "\"-\" or an item's id",
                             at, n, s->token, n);
    }
    ok = i == n ? cJSON_AddItemToArray(s->parent, unnamed(v))
                : cJSON_InsertItemInArray(s->parent, (int)i, unnamed(v));
  } else {
    cJSON_Delete(v);
    return proto_error_set(err, PROTO_E_NOT_FOUND, at, "%s: \"%.40s\" is inside a %s", at, s->token,
                           "value that is neither an object nor an array");
  }
  if (!ok) {
    cJSON_Delete(v);
    return proto_error_set(err, PROTO_E_INTERNAL, at, "out of memory");
  }
  return 0;
}

/* Detaches the value at spot 's' (not the document) and returns it, or NULL with 'err'. */
static cJSON *spot_take(cJSON *doc, const spot_t *s, const char *ptr, const char *at,
                        proto_error_t *err) {
  cJSON *v = s->parent ? spot_value(doc, s) : NULL;
  if (!s->parent) {
    proto_error_set(err, PROTO_E_INVALID_PARAMS, at, "%s: the whole document cannot be removed",
                    at);
    return NULL;
  }
  if (!v) {
    missing(err, at, ptr, s->parent, s->token);
    return NULL;
  }
  return cJSON_DetachItemViaPointer(s->parent, v);
}

/* The operations, by name. */
typedef enum { OP_ADD, OP_REMOVE, OP_REPLACE, OP_MOVE, OP_COPY, OP_TEST, OP_COUNT } op_kind_t;

static const struct {
  const char *name;
  int wants_value, wants_from;
} op_table[OP_COUNT] = {
    [OP_ADD] = {"add", 1, 0},   [OP_REMOVE] = {"remove", 0, 0}, [OP_REPLACE] = {"replace", 1, 0},
    [OP_MOVE] = {"move", 0, 1}, [OP_COPY] = {"copy", 0, 1},     [OP_TEST] = {"test", 1, 0},
};

/* The kind of operation 'op' names, or OP_COUNT. */
static op_kind_t op_kind(const char *op) {
  int k = 0;
  while (k < OP_COUNT && (!op || strcmp(op, op_table[k].name) != 0))
    k++;
  return (op_kind_t)k;
}

/* Applies operation 'i' ('o') to 'doc'. Returns 0, or -1 with 'err'. */
static int op_apply(cJSON *doc, const cJSON *o, int i, proto_error_t *err) {
  char at[64], at_path[64], at_from[64];
  op_path(at, sizeof at, i, NULL);
  op_path(at_path, sizeof at_path, i, "path");
  op_path(at_from, sizeof at_from, i, "from");
  if (!cJSON_IsObject(o))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, at,
                           "%s: an operation is an object {op, path, ...}", at);
  const char *name = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(o, "op"));
  op_kind_t k = op_kind(name);
  if (k == OP_COUNT)
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, at,
                           "%s: op must be one of add, remove, replace, move, copy, test", at);
  const char *path = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(o, "path"));
  const char *from = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(o, "from"));
  const cJSON *value = cJSON_GetObjectItemCaseSensitive(o, "value");
  if (!path)
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, at_path,
                           "%s: a JSON Pointer string is required", at_path);
  if (op_table[k].wants_value && !value)
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, at, "%s: %s needs a value", at, name);
  if (op_table[k].wants_from && !from)
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, at_from,
                           "%s: a JSON Pointer string is required", at_from);
  spot_t to, src;
  if (spot_find(doc, path, at_path, &to, err) != 0 ||
      (from && op_table[k].wants_from && spot_find(doc, from, at_from, &src, err) != 0))
    return -1;
  cJSON *target = spot_value(doc, &to);
  cJSON *v = NULL;
  switch (k) {
  case OP_TEST:
    if (!target)
      return missing(err, at_path, path, to.parent, to.token);
    if (!cJSON_Compare(target, value, 1))
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, at,
                             "%s: test failed: the value at \"%.60s\" differs", at, path);
    return 0;
  case OP_REMOVE:
    v = spot_take(doc, &to, path, at_path, err);
    cJSON_Delete(v);
    return v ? 0 : -1;
  case OP_REPLACE:
    if (!target)
      return missing(err, at_path, path, to.parent, to.token);
    v = cJSON_Duplicate(value, 1);
    if (to.parent && v &&
        !(cJSON_IsObject(to.parent) ? cJSON_ReplaceItemInObjectCaseSensitive(to.parent, to.token, v)
                                    : cJSON_ReplaceItemViaPointer(to.parent, target, unnamed(v)))) {
      cJSON_Delete(v);
      v = NULL;
    } else if (!to.parent && v) {
      return doc_swap(doc, v, at_path, err);
    }
    return v ? 0 : proto_error_set(err, PROTO_E_INTERNAL, at, "out of memory");
  case OP_ADD:
    v = cJSON_Duplicate(value, 1);
    break;
  case OP_COPY: {
    cJSON *s = spot_value(doc, &src);
    if (!s)
      return missing(err, at_from, from, src.parent, src.token);
    v = cJSON_Duplicate(s, 1);
    break;
  }
  case OP_MOVE: {
    size_t n = strlen(from);
    if (strncmp(path, from, n) == 0 && path[n] == '/')
      return proto_error_set(err, PROTO_E_INVALID_PARAMS, at_path,
                             "%s: a value cannot move into itself", at_path);
    if (strcmp(path, from) == 0 && spot_value(doc, &src))
      return 0;
    v = spot_take(doc, &src, from, at_from, err);
    if (!v)
      return -1;
    /* Taking the value out may have moved the destination's array index. */
    if (spot_find(doc, path, at_path, &to, err) != 0) {
      cJSON_Delete(v);
      return -1;
    }
    break;
  }
  default:
    return -1;
  }
  if (!v)
    return proto_error_set(err, PROTO_E_INTERNAL, at, "out of memory");
  return spot_add(doc, &to, v, at_path, err);
}

int json_patch_apply(cJSON *doc, const cJSON *ops, proto_error_t *err) {
  proto_error_clear(err);
  if (!cJSON_IsArray(ops))
    return proto_error_set(err, PROTO_E_INVALID_PARAMS, "ops",
                           "ops must be an array of JSON Patch operations (RFC 6902)");
  int i = 0;
  for (const cJSON *o = ops->child; o; o = o->next, i++)
    if (op_apply(doc, o, i, err) != 0)
      return -1;
  return 0;
}
