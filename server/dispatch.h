/*
 * The method table. Each method is described once — name, summary, params schema, result,
 * errors, handler — and that description drives both dispatch (params are validated and
 * defaulted before the handler runs) and the OpenRPC document of rpc.discover.
 */
#ifndef VOLFX_DISPATCH_H
#define VOLFX_DISPATCH_H

#include "schema.h"
#include "server.h"

enum {
  METHOD_NO_AUTH = 1 << 0,  /* Callable before 'auth' succeeds. */
  METHOD_SCENE_TAG = 1 << 1 /* Its 'tag' param (PARAM_TAG) is recorded on its scene when the call
                               succeeds, and echoed by the frames that show it; the scene's
                               idle subscriptions tick at once (frames.c). */
};

struct method {
  const char *name;
  const char *summary;
  const sch_field_t *params; /* An OBJECT; its members are the named params. */
  const char *result;        /* One sentence describing the result. */
  const int *errors;         /* Codes the method may return besides -32602, 0-terminated. */
  void (*handler)(call_t *call);
  unsigned flags;
};

/* The "scene" param shared by most methods. */
#define PARAM_SCENE                                                                                \
  {                                                                                                \
    .name = "scene", .type = SCH_STRING, .desc = "Name of the scene.", .max = 63,                  \
    .def_str = PROTO_DEFAULT_SCENE                                                                 \
  }

/* The 'tag' param of the calls that change what a scene's frames show. */
#define PARAM_TAG                                                                                  \
  {                                                                                                \
    .name = "tag", .type = SCH_ANY,                                                                \
    .desc = "Any JSON value of at most 256 bytes, echoed as 'tag' by the first frames that show "  \
            "this change.",                                                                        \
    .max = 256, .flags = SCH_NO_DEFAULT                                                            \
  }

/* A method's params: the OBJECT whose members are the fields 'f' (ended by {0}). */
#define METHOD_PARAMS(f) (&(sch_field_t){.type = SCH_OBJECT, .fields = (f)})

/* Every method, NULL-terminated (methods.c). */
extern const method_t *const method_table[];

const method_t *method_find(const char *name);

/* The OpenRPC document of every method (discover.c). The caller owns it. */
cJSON *discover_document(const server_t *s);

/* Resolves the "scene" param of 'call'; on failure answers the call with -32004 and returns
 * NULL. */
scene_entry_t *call_scene(call_t *call);

#endif
