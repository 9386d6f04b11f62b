/*
 * volfx: the command-line client of volfxd. Each invocation opens one connection (TCP or a
 * Unix socket), authenticates when a token is given, runs one command (or, with `script`, one
 * command per line of a file) and exits non-zero on the first error, printing the server's
 * message and data.path to stderr. Results are printed as JSON; `render` and `watch` write
 * attachment bytes to files and print a one-line summary.
 */
#include <errno.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>

#include "cli_batch.h"
#include "farm.h"
#include "proto.h"
#include "volfx.h"

#define EXIT_FAIL 1  /* The server or the connection reported an error. */
#define EXIT_USAGE 2 /* The command line was wrong; nothing was sent. */
#define MAX_WORDS 128
#define DEFAULT_TIMEOUT_MS 60000

static const char usage_text[] =
    "usage: volfx [GLOBAL OPTIONS] COMMAND [ARGS]\n"
    "\n"
    "Global options (before the command):\n"
    "  --host H        server host (default 127.0.0.1)\n"
    "  --port P        server port (default 7878)\n"
    "  --unix PATH     connect to a Unix socket instead of TCP\n"
    "  --token T       send `auth` first (default: $VOLFX_TOKEN)\n"
    "  --scene NAME    scene for scene commands (default main); commands accept it too\n"
    "  --timeout S     seconds one request, or the wait for one frame, may take\n"
    "                  (default 60; 0 waits forever)\n"
    "\n"
    "Commands:\n"
    "  info                          server.info\n"
    "  get [PATH]                    scene.get, the whole scene or a dotted path (camera.fov_y)\n"
    "  set PATH=VALUE...             scene.set; VALUE is JSON when it parses as JSON, else a\n"
    "                                string. PATH is dotted; array items by index or id\n"
    "                                (objects.0.color, objects.orb.color). All assignments are\n"
    "                                ONE change, applied in order and atomically (one scene\n"
    "                                version, or nothing on any error): a null VALUE deletes\n"
    "                                the member (or removes the array item), an object VALUE\n"
    "                                merges into the value at PATH, any other VALUE replaces it\n"
    "  set --patch JSON              scene.set with an RFC 7386 merge patch (items of objects,\n"
    "                                waves and volumes that carry an id merge by id)\n"
    "  set --ops JSON                scene.set with an RFC 6902 JSON Patch (array of ops)\n"
    "  step N [--dt S]               sim.step: N steps of S seconds (default sim.dt)\n"
    "  play [RATE]                   sim.play at RATE steps per second (server default 60)\n"
    "  pause                         sim.pause\n"
    "  render -o FILE [-W W] [-H H] [--format F] [--aov A] [--layers a,b] [--camera JSON]\n"
    "         [--encoding binary|base64] [--quality Q]\n"
    "                                render one frame into FILE (- for stdout) and print a\n"
    "                                summary with work_ms; --aov depth|wave_h defaults to f32,\n"
    "                                a FILE ending .jpg, .jpeg or .webp to that format;\n"
    "                                F: png, rgba8, rgbaf32, jpeg, webp (Q 1-100; webp 100 is\n"
    "                                lossless), f32\n"
    "  watch [--fps F] [-W W] [-H H] [--format F] [--aov A] [--layers a,b] [--count N]\n"
    "        [-o PATTERN] [--seq] [-v]\n"
    "                                frames.subscribe; writes each frame to PATTERN with %d or\n"
    "                                %06d replaced by the frame number, or only counts them;\n"
    "                                stops after N frames or on Ctrl-C, then unsubscribes and\n"
    "                                prints received and dropped; -v prints a line per frame.\n"
    "                                The frame number is the scene's (sim.frame), the same for\n"
    "                                every frame of a paused scene: --seq numbers the files\n"
    "                                1, 2, ... in order of arrival instead\n"
    "  sequence FIRST LAST --dir DIR [--step N] [-W W] [-H H] [--format F] [--aov A]\n"
    "           [--layers a,b] [--camera JSON] [-v]\n"
    "                                render.sequence: the server steps the scene and writes\n"
    "                                frames FIRST..LAST as DIR/frame_NNNNNN.EXT under its data\n"
    "                                directory; waits for the job to end (Ctrl-C cancels it),\n"
    "                                -v prints each file as it is written\n"
    "  script FILE                   run one command per line on one connection; blank lines\n"
    "                                and words starting with # are skipped; words split as in\n"
    "                                the shell ('...', \"...\", \\); stops at the first error\n"
    "  stats                         stats\n"
    "  discover                      rpc.discover (the OpenRPC document)\n"
    "  scenes                        scene.list\n"
    "  scene list | presets          scene.list, scene.presets\n"
    "  scene create NAME [--preset P]\n"
    "                                scene.create from preset P, or defaults\n"
    "  scene delete NAME             scene.delete\n"
    "  scene save FILE | load FILE   scene.save, scene.load (FILE under the server's data dir)\n"
    "  scene reset [--preset P]      delete the scene (--scene, default main) and create it\n"
    "                                again from P, or from the preset it was made from\n"
    "                                (defaults when none): frame 0, its subscriptions end\n"
    "  call METHOD [JSON_PARAMS]     any method, params given raw\n"
    "  shutdown                      server.shutdown\n"
    "  help                          this text\n"
    "\n"
    "Render-farm commands (each starts a private volfxd, the one beside volfx or\n"
    "$VOLFX_VOLFXD, and always stops it; the global options do not apply to them):\n"
    "  batch SCENE -s FIRST -e LAST [-j STEP] -o PATTERN [--bake DIR] [-W W] [-H H]\n"
    "        [--format F] [--aov A] [--layers a,b] [--camera JSON] [--antialias N]\n"
    "        [--png-level L] [--quality Q] [--overwrite] [--presets DIR] [--device D] [-v]\n"
    "                                render frames FIRST, FIRST+STEP, ... up to LAST of SCENE\n"
    "                                (a preset, a SCENE.json or a snapshot file) into PATTERN,\n"
    "                                each run of # the zero-padded frame number\n"
    "                                ('shots/a/f_####.png'; without --format, a PATTERN ending\n"
    "                                .jpg or .webp gives jpeg or webp, and one naming another\n"
    "                                format than --format is refused). A file is written\n"
    "                                whole or not at all; frames whose file is complete are\n"
    "                                skipped unless --overwrite. --bake DIR starts from the\n"
    "                                nearest snapshot of a bake of the same SCENE instead of\n"
    "                                simulating from its start\n"
    "  bake SCENE -e LAST [-k EVERY] -o DIR [--presets DIR] [--device D] [-v]\n"
    "                                simulate SCENE once up to frame LAST, saving\n"
    "                                DIR/frame_NNNNNN.snap every EVERY frames (default 24) and\n"
    "                                at LAST; run again, it resumes from DIR's latest snapshot\n"
    "\n"
    "Exit status: 0 on success, 1 when the server or the connection reported an error (its\n"
    "message and data.path go to stderr), 2 on a command-line error. batch and bake stopped\n"
    "by SIGINT or SIGTERM stop their server first, then end by the same signal.\n";

/* State shared by the commands of one invocation. */
typedef struct cli {
  volfx_conn_t *conn;
  const char *scene;     /* Default scene of this invocation. */
  int timeout_ms;        /* 0: no timeout. */
  const char *script;    /* Script file being run, or NULL. */
  int line;              /* Its current line number. */
  const char *cmd_scene; /* --scene given to the current command, or NULL. */
} cli_t;

static volatile sig_atomic_t interrupted;

static void on_sigint(int sig) {
  (void)sig;
  interrupted = 1;
}

/* Prints "volfx: [FILE:LINE: ]" to stderr: the prefix of every diagnostic. */
static void diag_prefix(const cli_t *cli) {
  fputs("volfx: ", stderr);
  if (cli->script != NULL) {
    fprintf(stderr, "%s:%d: ", cli->script, cli->line);
  }
}

/* Reports a command-line mistake and returns EXIT_USAGE. */
static int usage_error(const cli_t *cli, const char *fmt, const char *arg) {
  diag_prefix(cli);
  fprintf(stderr, fmt, arg != NULL ? arg : "");
  fputs(" (see volfx --help)\n", stderr);
  return EXIT_USAGE;
}

/*
 * 1 when 'message' already says where the error is, so that " (path P)" would only repeat it:
 * it names 'path' as its subject ("camera.fov_y: 500 is out of range"), or 'path' is "path",
 * the member of scene.get and scene.set whose scene path the message quotes.
 */
static int names_path(const char *message, const char *path) {
  size_t n = strlen(path);
  if (strcmp(path, "path") == 0) {
    return 1;
  }
  for (const char *m = strstr(message, path); m != NULL; m = strstr(m + 1, path)) {
    char before = m > message ? m[-1] : ' ';
    if ((before == ' ' || m == message) && m[n] == ':' && m[n + 1] == ' ') {
      return 1;
    }
  }
  return 0;
}

/*
 * Reports error 'rc': the kind of a JSON-RPC error, then the server's message and data.path
 * when the message does not already name it, e.g. "invalid params: camera.fov_y: 500 is out of
 * range [1, 179] (degrees)" or "invalid params: patch must be a JSON object (path patch)".
 */
static int report(const cli_t *cli, int rc, const volfx_error_t *e) {
  diag_prefix(cli);
  const char *kind = proto_err_message(rc);
  if (rc <= -32000 && strncmp(e->message, kind, strlen(kind)) != 0) {
    fprintf(stderr, "%s: %s", kind, e->message);
  } else if (rc <= -32000) {
    fputs(e->message, stderr); /* The message already says what kind of error it is. */
  } else {
    fputs(e->message[0] != '\0' ? e->message : volfx_strerror(rc), stderr);
  }
  if (e->path[0] != '\0' && !names_path(e->message, e->path)) {
    fprintf(stderr, " (path %s)", e->path);
  }
  fputc('\n', stderr);
  return EXIT_FAIL;
}

/* One call; on failure prints the error. Returns 0 or EXIT_FAIL. 'params' is taken. */
static int rpc(const cli_t *cli, const char *method, cJSON *params, cJSON **result,
               volfx_attachment_t *att) {
  volfx_error_t e;
  int rc = volfx_call(cli->conn, method, params, result, att, &e);
  return rc == 0 ? 0 : report(cli, rc, &e);
}

/* Prints scalar 'v' (or an empty container) compactly; without its siblings. Numbers get the
 * digits that read back exactly (proto_print_line), not cJSON's fifteen. */
static void print_scalar(const cJSON *v) {
  cJSON *alone = cJSON_Duplicate(v, 1);
  size_t len = 0;
  char *s = alone ? proto_print_line(alone, &len) : NULL;
  cJSON_Delete(alone);
  if (s != NULL && len > 0)
    s[len - 1] = '\0'; /* Without the line's newline. */
  fputs(s != NULL ? s : "null", stdout);
  free(s);
}

/* 1 when 'v' is an array of scalars only: printed on one line, as vectors read best. */
static int is_flat_array(const cJSON *v) {
  if (!cJSON_IsArray(v) || cJSON_GetArraySize(v) > 16) {
    return 0;
  }
  for (const cJSON *c = v->child; c != NULL; c = c->next) {
    if (cJSON_IsArray(c) || cJSON_IsObject(c)) {
      return 0;
    }
  }
  return 1;
}

/* Prints 'v' indented by two spaces per 'depth', the way `jq .` would. */
static void print_pretty(const cJSON *v, int depth) {
  int obj = cJSON_IsObject(v);
  if ((!obj && !cJSON_IsArray(v)) || v->child == NULL) {
    print_scalar(v);
    return;
  }
  if (is_flat_array(v)) {
    putchar('[');
    for (const cJSON *c = v->child; c != NULL; c = c->next) {
      print_scalar(c);
      fputs(c->next != NULL ? ", " : "", stdout);
    }
    putchar(']');
    return;
  }
  puts(obj ? "{" : "[");
  for (const cJSON *c = v->child; c != NULL; c = c->next) {
    printf("%*s", 2 * (depth + 1), "");
    if (obj) {
      cJSON *key = cJSON_CreateStringReference(c->string != NULL ? c->string : "");
      print_scalar(key);
      cJSON_Delete(key);
      fputs(": ", stdout);
    }
    print_pretty(c, depth + 1);
    puts(c->next != NULL ? "," : "");
  }
  printf("%*s%c", 2 * depth, "", obj ? '}' : ']');
}

/* Prints 'v' as indented JSON followed by a newline. */
static void print_json(const cJSON *v) {
  if (v != NULL) {
    print_pretty(v, 0);
    putchar('\n');
  }
}

/* Calls 'method' with 'params' (taken) and prints its result. Returns an exit status. */
static int rpc_print(const cli_t *cli, const char *method, cJSON *params) {
  cJSON *r = NULL;
  if (rpc(cli, method, params, &r, NULL) != 0) {
    return EXIT_FAIL;
  }
  print_json(r);
  cJSON_Delete(r);
  return 0;
}

/* A params object holding only "scene". */
static cJSON *scene_params(const cli_t *cli) {
  cJSON *p = cJSON_CreateObject();
  cJSON_AddStringToObject(p, "scene", cli->cmd_scene != NULL ? cli->cmd_scene : cli->scene);
  return p;
}

/* Parses all of 's' as a number. Returns 1 on success. */
static int parse_double(const char *s, double *out) {
  char *end;
  errno = 0;
  double v = strtod(s, &end);
  if (s[0] == '\0' || *end != '\0' || errno != 0) {
    return 0;
  }
  *out = v;
  return 1;
}

static int parse_long(const char *s, long *out) {
  char *end;
  errno = 0;
  long v = strtol(s, &end, 10);
  if (s[0] == '\0' || *end != '\0' || errno != 0) {
    return 0;
  }
  *out = v;
  return 1;
}

/*
 * Command option scanner: when argv[*i] is 'name' (or 'alias', may be NULL), takes the next
 * word as its value. Returns 1 when matched and '*val' is set, -1 when the value is missing,
 * 0 when argv[*i] is another word. "--name=value" is accepted as well.
 */
static int take_opt(int argc, char **argv, int *i, const char *name, const char *alias,
                    const char **val) {
  const char *a = argv[*i];
  size_t n = strlen(name);
  if (strncmp(a, name, n) == 0 && a[n] == '=') {
    *val = a + n + 1;
    return 1;
  }
  if (strcmp(a, name) != 0 && (alias == NULL || strcmp(a, alias) != 0)) {
    return 0;
  }
  if (*i + 1 >= argc) {
    return -1;
  }
  *val = argv[++*i];
  return 1;
}

/* Splits "a,b,c" into a JSON array of strings. */
static cJSON *split_list(const char *s) {
  cJSON *arr = cJSON_CreateArray();
  while (*s != '\0') {
    const char *comma = strchr(s, ',');
    size_t n = comma != NULL ? (size_t)(comma - s) : strlen(s);
    char *word = strndup(s, n);
    if (word != NULL && n > 0) {
      cJSON_AddItemToArray(arr, cJSON_CreateString(word));
    }
    free(word);
    s += n;
    if (*s == ',') {
      s++;
    }
  }
  return arr;
}

/* Parses 's' as JSON, or NULL. */
static cJSON *parse_json(const char *s) {
  return cJSON_ParseWithOpts(s, NULL, 1);
}

/* Parses 'text', the JSON argument of 'what' ("set --patch"); when it is not JSON, reports
 * where the text stops being JSON and returns NULL. */
static cJSON *json_arg(const cli_t *cli, const char *what, const char *text) {
  const char *end = NULL;
  cJSON *v = cJSON_ParseWithOpts(text, &end, 1);
  if (v != NULL) {
    return v;
  }
  size_t at = end != NULL && end >= text ? (size_t)(end - text) : 0;
  diag_prefix(cli);
  if (at >= strlen(text)) {
    fprintf(stderr, "%s: invalid JSON: the text ends before the value does: %s\n", what, text);
  } else {
    fprintf(stderr, "%s: invalid JSON near byte %zu ('%c'): %s\n", what, at + 1, text[at], text);
  }
  return NULL;
}

/*
 * Options that render and watch share, added to 'p' as they are met. Returns 1 when argv[*i]
 * was one of them, 0 when not, EXIT_USAGE (negated) on a bad value.
 */
static int frame_opt(const cli_t *cli, int argc, char **argv, int *i, cJSON *p) {
  static const struct {
    const char *name, *alias, *key;
    int kind; /* 0 integer, 1 number, 2 string, 3 list, 4 JSON */
  } opts[] = {
      {"--width", "-W", "width", 0},       {"--height", "-H", "height", 0},
      {"--format", "-f", "format", 2},     {"--aov", NULL, "aov", 2},
      {"--layers", NULL, "layers", 3},     {"--camera", NULL, "camera", 4},
      {"--encoding", NULL, "encoding", 2}, {"--png-level", NULL, "png_level", 0},
      {"--quality", "-q", "quality", 0},   {"--fps", NULL, "fps", 1},
  };
  for (size_t k = 0; k < sizeof(opts) / sizeof(opts[0]); k++) {
    const char *v;
    int m = take_opt(argc, argv, i, opts[k].name, opts[k].alias, &v);
    if (m == 0) {
      continue;
    }
    if (m < 0) {
      return -usage_error(cli, "%s needs a value", opts[k].name);
    }
    long l;
    double d;
    cJSON *item = NULL;
    switch (opts[k].kind) {
    case 0:
      item = parse_long(v, &l) ? cJSON_CreateNumber((double)l) : NULL;
      break;
    case 1:
      item = parse_double(v, &d) ? cJSON_CreateNumber(d) : NULL;
      break;
    case 2:
      item = cJSON_CreateString(v);
      break;
    case 3:
      item = split_list(v);
      break;
    default:
      item = json_arg(cli, opts[k].name, v);
      if (item == NULL) {
        return -EXIT_USAGE;
      }
      break;
    }
    if (item == NULL) {
      return -usage_error(cli, "bad value for %s", opts[k].name);
    }
    cJSON_DeleteItemFromObjectCaseSensitive(p, opts[k].key);
    cJSON_AddItemToObject(p, opts[k].key, item);
    return 1;
  }
  return 0;
}

/* Without a format given: f32 when "aov" asks for a float image, else the format the file name
 * 'out' (or NULL) names by its extension (farm_format_of_name), else the server's default. */
static void default_format(cJSON *p, const char *out) {
  const cJSON *aov = cJSON_GetObjectItemCaseSensitive(p, "aov");
  int beauty = !cJSON_IsString(aov) || strcmp(aov->valuestring, "beauty") == 0;
  const char *named = out != NULL ? farm_format_of_name(out) : NULL;
  if (!cJSON_HasObjectItem(p, "format") && (!beauty || named != NULL)) {
    cJSON_AddStringToObject(p, "format", beauty ? named : "f32");
  }
}

/* Creates the directories above file 'path' that are missing ("out/a" for "out/a/f.png"). */
static void make_parents(const char *path) {
  char dir[4096];
  snprintf(dir, sizeof(dir), "%s", path);
  for (char *slash = strchr(dir + 1, '/'); slash != NULL; slash = strchr(slash + 1, '/')) {
    *slash = '\0';
    mkdir(dir, 0777); /* One that exists stays; one that cannot be made fails the fopen. */
    *slash = '/';
  }
}

/* Writes 'n' bytes to 'path' ("-" is stdout), creating missing directories above it. Returns 0
 * or EXIT_FAIL after reporting. */
static int write_file(const cli_t *cli, const char *path, const void *data, size_t n) {
  int to_stdout = strcmp(path, "-") == 0;
  if (!to_stdout) {
    make_parents(path);
  }
  FILE *f = to_stdout ? stdout : fopen(path, "wb");
  int ok = f != NULL && (n == 0 || fwrite(data, 1, n, f) == n);
  if (f != NULL && !to_stdout) {
    ok = (fclose(f) == 0) && ok;
  } else if (f != NULL) {
    ok = (fflush(f) == 0) && ok;
  }
  if (!ok) {
    diag_prefix(cli);
    fprintf(stderr, "cannot write %s: %s\n", path, strerror(errno));
    return EXIT_FAIL;
  }
  return 0;
}

/* get [PATH] */
static int cmd_get(const cli_t *cli, int argc, char **argv) {
  if (argc > 2) {
    return usage_error(cli, "get takes at most one PATH%s", NULL);
  }
  cJSON *p = scene_params(cli);
  if (argc == 2) {
    cJSON_AddStringToObject(p, "path", argv[1]);
  }
  return rpc_print(cli, "scene.get", p);
}

/* The value of an assignment: JSON when 's' parses as JSON, otherwise the string itself; NULL
 * (reported) when 's' starts like a JSON object, array or string but is not valid JSON. */
static cJSON *assigned_value(const cli_t *cli, const char *assignment, const char *s) {
  cJSON *v = parse_json(s);
  if (v != NULL || (s[0] != '{' && s[0] != '[' && s[0] != '"')) {
    return v != NULL ? v : cJSON_CreateString(s);
  }
  return json_arg(cli, assignment, s);
}

/* set PATH=VALUE... | set --patch JSON | set --ops JSON */
static int cmd_set(const cli_t *cli, int argc, char **argv) {
  if (argc < 2) {
    return usage_error(cli, "set needs PATH=VALUE, --patch JSON or --ops JSON%s", NULL);
  }
  if (strcmp(argv[1], "--patch") == 0 || strcmp(argv[1], "--ops") == 0) {
    int ops = strcmp(argv[1], "--ops") == 0;
    if (argc != 3) {
      return usage_error(cli, "set %s needs one JSON argument", argv[1]);
    }
    cJSON *arg = json_arg(cli, ops ? "set --ops" : "set --patch", argv[2]);
    if (arg == NULL) {
      return EXIT_USAGE;
    }
    cJSON *p = scene_params(cli);
    cJSON_AddItemToObject(p, ops ? "ops" : "patch", arg);
    return rpc_print(cli, "scene.set", p);
  }

  /* Every assignment is one change of one scene.set: applied in order, one version or none. */
  cJSON *changes = cJSON_CreateArray();
  for (int i = 1; i < argc; i++) {
    const char *eq = strchr(argv[i], '=');
    if (eq == NULL || eq == argv[i]) {
      cJSON_Delete(changes);
      return usage_error(cli, "expected PATH=VALUE, got '%s'", argv[i]);
    }
    char *path = strndup(argv[i], (size_t)(eq - argv[i]));
    int bad = path == NULL || path[strlen(path) - 1] == '.' || path[0] == '.' ||
              strstr(path, "..") != NULL;
    cJSON *value = bad ? NULL : assigned_value(cli, argv[i], eq + 1);
    if (value == NULL) {
      free(path);
      cJSON_Delete(changes);
      return bad ? usage_error(cli, "bad path in '%s'", argv[i]) : EXIT_USAGE;
    }
    cJSON *change = cJSON_CreateObject();
    cJSON_AddStringToObject(change, "path", path);
    cJSON_AddItemToObject(change, cJSON_IsObject(value) ? "patch" : "value", value);
    cJSON_AddItemToArray(changes, change);
    free(path);
  }
  cJSON *p = scene_params(cli);
  cJSON_AddItemToObject(p, "changes", changes);
  return rpc_print(cli, "scene.set", p);
}

/* The scene commands, each one method: NAME is params' "name" (the scene itself for create and
 * delete), FILE its "file"; the rest take the scene as --scene says. */
typedef enum { SCENE_ARG_NONE, SCENE_ARG_NAME, SCENE_ARG_FILE } scene_arg_t;

static const struct {
  const char *word, *method;
  scene_arg_t arg;
  int with_scene, takes_preset;
} scene_commands[] = {
    {"list", "scene.list", SCENE_ARG_NONE, 0, 0},
    {"presets", "scene.presets", SCENE_ARG_NONE, 0, 0},
    {"create", "scene.create", SCENE_ARG_NAME, 0, 1},
    {"delete", "scene.delete", SCENE_ARG_NAME, 0, 0},
    {"save", "scene.save", SCENE_ARG_FILE, 1, 0},
    {"load", "scene.load", SCENE_ARG_FILE, 1, 0},
    {"reset", NULL, SCENE_ARG_NONE, 1, 1},
};

/* The preset scene 'name' was created from, per scene.list (NULL: no such scene, reported). */
static char *scene_preset_of(const cli_t *cli, const char *name) {
  cJSON *r = NULL;
  if (rpc(cli, "scene.list", cJSON_CreateObject(), &r, NULL) != 0) {
    return NULL;
  }
  char *preset = NULL;
  const cJSON *e;
  cJSON_ArrayForEach(e, cJSON_GetObjectItemCaseSensitive(r, "scenes")) {
    const char *n = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(e, "name"));
    const char *p = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(e, "preset"));
    if (n != NULL && strcmp(n, name) == 0) {
      preset = strdup(p != NULL ? p : "");
    }
  }
  cJSON_Delete(r);
  if (preset == NULL) {
    diag_prefix(cli);
    fprintf(stderr, "not found: no scene named '%s'\n", name);
  }
  return preset;
}

/* Whether scene.presets lists 'preset'; reports when it does not (or the call fails). */
static int preset_known(const cli_t *cli, const char *preset) {
  cJSON *r = NULL;
  if (rpc(cli, "scene.presets", cJSON_CreateObject(), &r, NULL) != 0) {
    return 0;
  }
  int found = 0;
  const cJSON *e;
  cJSON_ArrayForEach(e, cJSON_GetObjectItemCaseSensitive(r, "presets")) {
    found |= cJSON_IsString(e) && strcmp(e->valuestring, preset) == 0;
  }
  cJSON_Delete(r);
  if (!found) {
    diag_prefix(cli);
    fprintf(stderr,
            "not found: '%s' is not a preset scene.create takes (volfx scene presets); "
            "give --preset NAME\n",
            preset);
  }
  return found;
}

/* scene reset [--preset P]: deletes the scene and creates it again under its name, from P or
 * the preset it was created from (defaults when none); its clock starts at frame 0. The preset
 * is checked first, so that a reset that cannot create the scene again leaves it alone. */
static int scene_reset(const cli_t *cli, const char *preset) {
  cJSON *p = scene_params(cli);
  const char *name = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(p, "scene"));
  char *from = preset != NULL ? strdup(preset) : scene_preset_of(cli, name);
  cJSON *r = NULL;
  int rc = from == NULL || (from[0] != '\0' && !preset_known(cli, from)) ? EXIT_FAIL : 0;
  if (rc == 0) {
    cJSON *d = cJSON_CreateObject();
    cJSON_AddStringToObject(d, "name", name);
    rc = rpc(cli, "scene.delete", d, &r, NULL);
    cJSON_Delete(r);
  }
  if (rc == 0) {
    cJSON *c = cJSON_CreateObject();
    cJSON_AddStringToObject(c, "name", name);
    if (from[0] != '\0') {
      cJSON_AddStringToObject(c, "preset", from);
    }
    rc = rpc_print(cli, "scene.create", c);
  }
  free(from);
  cJSON_Delete(p);
  return rc;
}

/* scene list | presets | create NAME [--preset P] | delete NAME | save FILE | load FILE |
 * reset [--preset P] */
static int cmd_scene(const cli_t *cli, int argc, char **argv) {
  size_t k = 0, n = sizeof(scene_commands) / sizeof(scene_commands[0]);
  while (argc >= 2 && k < n && strcmp(argv[1], scene_commands[k].word) != 0) {
    k++;
  }
  if (argc < 2 || k == n) {
    return usage_error(cli, "scene needs one of list, presets, create, delete, save, load, reset%s",
                       NULL);
  }
  const char *arg = NULL, *preset = NULL;
  for (int i = 2; i < argc; i++) {
    int m =
        scene_commands[k].takes_preset ? take_opt(argc, argv, &i, "--preset", NULL, &preset) : 0;
    if (m < 0) {
      return usage_error(cli, "--preset needs a NAME%s", NULL);
    }
    if (m == 0 && (arg != NULL || scene_commands[k].arg == SCENE_ARG_NONE)) {
      return usage_error(cli, "scene: unexpected '%s'", argv[i]);
    }
    if (m == 0) {
      arg = argv[i];
    }
  }
  if (scene_commands[k].arg != SCENE_ARG_NONE && arg == NULL) {
    return usage_error(cli,
                       scene_commands[k].arg == SCENE_ARG_NAME ? "scene %s needs a NAME"
                                                               : "scene %s needs a FILE",
                       argv[1]);
  }
  if (scene_commands[k].method == NULL) {
    return scene_reset(cli, preset);
  }
  cJSON *p = scene_commands[k].with_scene ? scene_params(cli) : cJSON_CreateObject();
  if (arg != NULL) {
    cJSON_AddStringToObject(p, scene_commands[k].arg == SCENE_ARG_NAME ? "name" : "file", arg);
  }
  if (preset != NULL) {
    cJSON_AddStringToObject(p, "preset", preset);
  }
  return rpc_print(cli, scene_commands[k].method, p);
}

/* step N [--dt S] */
static int cmd_step(const cli_t *cli, int argc, char **argv) {
  cJSON *p = scene_params(cli);
  int have_n = 0;
  for (int i = 1; i < argc; i++) {
    const char *v;
    long n;
    double dt;
    int m = take_opt(argc, argv, &i, "--dt", NULL, &v);
    if (m != 0) {
      if (m < 0 || !parse_double(v, &dt)) {
        cJSON_Delete(p);
        return usage_error(cli, "--dt needs a number of seconds%s", NULL);
      }
      cJSON_AddNumberToObject(p, "dt", dt);
    } else if (!have_n && parse_long(argv[i], &n)) {
      cJSON_AddNumberToObject(p, "steps", (double)n);
      have_n = 1;
    } else {
      cJSON_Delete(p);
      return usage_error(cli, "step: unexpected '%s'", argv[i]);
    }
  }
  return rpc_print(cli, "sim.step", p);
}

/* play [RATE] */
static int cmd_play(const cli_t *cli, int argc, char **argv) {
  double rate;
  if (argc > 2 || (argc == 2 && !parse_double(argv[1], &rate))) {
    return usage_error(cli, "play takes one optional RATE (steps per second)%s", NULL);
  }
  cJSON *p = scene_params(cli);
  if (argc == 2) {
    cJSON_AddNumberToObject(p, "rate", rate);
  }
  return rpc_print(cli, "sim.play", p);
}

/* Prints a number member of 'o' as " key VALUE" when present. */
static void print_member(FILE *out, const cJSON *o, const char *key) {
  const cJSON *v = cJSON_GetObjectItemCaseSensitive(o, key);
  if (cJSON_IsNumber(v)) {
    fprintf(out, " %s %g", key, v->valuedouble);
  }
}

/* render -o FILE [...] */
static int cmd_render(const cli_t *cli, int argc, char **argv) {
  cJSON *p = scene_params(cli);
  const char *out = NULL;
  for (int i = 1; i < argc; i++) {
    int m = take_opt(argc, argv, &i, "--output", "-o", &out);
    if (m < 0) {
      m = -usage_error(cli, "%s needs a value", argv[i]);
    } else if (m == 0) {
      m = frame_opt(cli, argc, argv, &i, p);
    }
    if (m <= 0) {
      cJSON_Delete(p);
      return m < 0 ? -m : usage_error(cli, "render: unexpected '%s'", argv[i]);
    }
  }
  if (out == NULL) {
    cJSON_Delete(p);
    return usage_error(cli, "render needs -o FILE%s", NULL);
  }
  default_format(p, out);

  cJSON *r = NULL;
  volfx_attachment_t att;
  if (rpc(cli, "render", p, &r, &att) != 0) {
    return EXIT_FAIL;
  }
  int rc = write_file(cli, out, att.data, att.len);
  if (rc == 0) {
    FILE *sum = strcmp(out, "-") == 0 ? stderr : stdout;
    const cJSON *fmt = cJSON_GetObjectItemCaseSensitive(r, "format");
    const cJSON *w = cJSON_GetObjectItemCaseSensitive(r, "width");
    const cJSON *h = cJSON_GetObjectItemCaseSensitive(r, "height");
    char *work = cJSON_PrintUnformatted(cJSON_GetObjectItemCaseSensitive(r, "work_ms"));
    fprintf(sum, "%s: %dx%d %s %zu bytes", out, cJSON_IsNumber(w) ? w->valueint : att.width,
            cJSON_IsNumber(h) ? h->valueint : att.height,
            cJSON_IsString(fmt) ? fmt->valuestring : att.format, att.len);
    print_member(sum, r, "frame");
    print_member(sum, r, "time");
    fprintf(sum, " work_ms %s\n", work != NULL ? work : "{}");
    free(work);
  }
  volfx_attachment_free(&att);
  cJSON_Delete(r);
  return rc;
}

/*
 * Expands 'pattern' for frame 'frame' into 'out': "%d" and "%0Nd"/"%Nd" become the number,
 * "%%" a percent sign; anything else is copied. Returns 0, or -1 when 'out' is too small.
 */
static int frame_path(const char *pattern, long long frame, char *out, size_t cap) {
  size_t o = 0;
  for (const char *s = pattern; *s != '\0'; s++) {
    char piece[64];
    size_t plen;
    if (s[0] == '%' && s[1] == '%') {
      piece[0] = '%';
      plen = 1;
      s++;
    } else if (s[0] == '%') {
      const char *q = s + 1;
      int zero = *q == '0';
      int width = 0;
      while (*q >= '0' && *q <= '9' && width < 32) {
        width = width * 10 + (*q++ - '0');
      }
      if (*q != 'd') {
        piece[0] = '%';
        plen = 1;
      } else {
        plen = (size_t)snprintf(piece, sizeof(piece), zero ? "%0*lld" : "%*lld", width, frame);
        s = q;
      }
    } else {
      piece[0] = *s;
      plen = 1;
    }
    if (o + plen + 1 > cap) {
      return -1;
    }
    memcpy(out + o, piece, plen);
    o += plen;
  }
  out[o] = '\0';
  return 0;
}

/* Installs (or with 'on' 0 removes) the SIGINT handler that stops `watch`. */
static void catch_sigint(int on) {
  struct sigaction sa;
  memset(&sa, 0, sizeof(sa));
  sa.sa_handler = on ? on_sigint : SIG_DFL;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, NULL); /* No SA_RESTART: a blocked poll() returns. */
}

/* watch [--fps F] [-W W] [-H H] [--format F] [--count N] [-o PATTERN] [--seq] [-v] */
static int cmd_watch(const cli_t *cli, int argc, char **argv) {
  cJSON *p = scene_params(cli);
  const char *pattern = NULL;
  long count = 0;
  int verbose = 0;
  int by_arrival = 0; /* --seq: name files by arrival count, not by the frame's number. */
  for (int i = 1; i < argc; i++) {
    const char *v;
    int m = take_opt(argc, argv, &i, "--output", "-o", &pattern);
    if (m == 0 && (m = take_opt(argc, argv, &i, "--count", "-n", &v)) > 0) {
      if (!parse_long(v, &count) || count < 0) {
        m = -usage_error(cli, "--count needs a whole number%s", NULL);
      }
    }
    if (m < 0 && m != -EXIT_USAGE) {
      m = -usage_error(cli, "%s needs a value", argv[i]);
    }
    if (m == 0 && (strcmp(argv[i], "-v") == 0 || strcmp(argv[i], "--verbose") == 0)) {
      verbose = 1;
      m = 1;
    }
    if (m == 0 && strcmp(argv[i], "--seq") == 0) {
      by_arrival = 1;
      m = 1;
    }
    if (m == 0) {
      m = frame_opt(cli, argc, argv, &i, p);
    }
    if (m <= 0) {
      cJSON_Delete(p);
      return m < 0 ? -m : usage_error(cli, "watch: unexpected '%s'", argv[i]);
    }
  }
  default_format(p, NULL);

  volfx_error_t e;
  int64_t id;
  int rc = volfx_subscribe(cli->conn, p, &id, &e);
  if (rc != 0) {
    return report(cli, rc, &e);
  }
  interrupted = 0;
  catch_sigint(1);

  long received = 0;
  long long last_frame = -1;
  int warned = 0; /* The note that files are written over was given. */
  double dropped = 0;
  int status = 0;
  int idle_ms = 0;
  while (!interrupted && (count == 0 || received < count)) {
    cJSON *fp = NULL;
    volfx_attachment_t att;
    /* Short waits so that a timeout and Ctrl-C are both noticed promptly. */
    rc = volfx_next_frame(cli->conn, 200, &fp, &att);
    if (rc == VOLFX_E_TIMEOUT || rc == VOLFX_E_INTR) {
      idle_ms += 200;
      if (cli->timeout_ms > 0 && idle_ms >= cli->timeout_ms) {
        diag_prefix(cli);
        fprintf(stderr, "no frame for %d ms\n", idle_ms);
        status = EXIT_FAIL;
        break;
      }
      continue;
    }
    if (rc != 0) {
      e.code = rc;
      snprintf(e.message, sizeof(e.message), "%s", volfx_strerror(rc));
      e.path[0] = '\0';
      status = report(cli, rc, &e);
      break;
    }
    idle_ms = 0;
    received++;
    const cJSON *jf = cJSON_GetObjectItemCaseSensitive(fp, "frame");
    const cJSON *jd = cJSON_GetObjectItemCaseSensitive(fp, "dropped");
    long long frame = cJSON_IsNumber(jf) ? (long long)jf->valuedouble : received;
    if (cJSON_IsNumber(jd)) {
      dropped = jd->valuedouble;
    }
    if (pattern != NULL && !by_arrival && received > 1 && frame <= last_frame && !warned) {
      diag_prefix(cli);
      fprintf(stderr,
              "frame %lld came again (a paused scene shows one frame number): its file is "
              "written over; --seq numbers the files by arrival\n",
              frame);
      warned = 1;
    }
    last_frame = frame;
    if (pattern != NULL) {
      char path[4096];
      if (frame_path(pattern, by_arrival ? received : frame, path, sizeof(path)) != 0) {
        status = usage_error(cli, "output pattern too long%s", NULL);
      } else {
        status = write_file(cli, path, att.data, att.len);
      }
    }
    if (verbose && status == 0) {
      printf("frame %lld: %zu bytes", frame, att.len);
      print_member(stdout, fp, "time");
      print_member(stdout, fp, "work_ms");
      print_member(stdout, fp, "dropped");
      putchar('\n');
      fflush(stdout);
    }
    volfx_attachment_free(&att);
    cJSON_Delete(fp);
    if (status != 0) {
      break;
    }
  }
  catch_sigint(0);

  cJSON *r = NULL;
  rc = volfx_unsubscribe(cli->conn, id, &r, &e);
  if (rc != 0) {
    report(cli, rc, &e);
    return EXIT_FAIL;
  }
  const cJSON *jd = cJSON_GetObjectItemCaseSensitive(r, "dropped");
  const cJSON *js = cJSON_GetObjectItemCaseSensitive(r, "sent");
  if (cJSON_IsNumber(jd)) {
    dropped = jd->valuedouble;
  }
  printf("watch: received %ld frames, dropped %.0f", received, dropped);
  if (cJSON_IsNumber(js)) {
    printf(", sent %.0f", js->valuedouble);
  }
  printf(" (subscription %lld%s)\n", (long long)id, interrupted ? ", interrupted" : "");
  cJSON_Delete(r);
  return status;
}

/* sequence FIRST LAST --dir DIR [--step N] [frame options] [-v] */
static int cmd_sequence(const cli_t *cli, int argc, char **argv) {
  long first, last, step = 1;
  if (argc < 3 || !parse_long(argv[1], &first) || !parse_long(argv[2], &last)) {
    return usage_error(cli, "sequence needs FIRST LAST (frame numbers)%s", NULL);
  }
  cJSON *p = scene_params(cli);
  const char *dir = NULL;
  int verbose = 0;
  for (int i = 3; i < argc; i++) {
    const char *v;
    int m = take_opt(argc, argv, &i, "--dir", "-d", &dir);
    if (m == 0 && (m = take_opt(argc, argv, &i, "--step", "-s", &v)) > 0 && !parse_long(v, &step)) {
      m = -usage_error(cli, "--step needs a whole number%s", NULL);
    }
    if (m < 0 && m != -EXIT_USAGE) {
      m = -usage_error(cli, "%s needs a value", argv[i]);
    }
    if (m == 0 && (strcmp(argv[i], "-v") == 0 || strcmp(argv[i], "--verbose") == 0)) {
      verbose = 1;
      m = 1;
    }
    if (m == 0) {
      m = frame_opt(cli, argc, argv, &i, p);
    }
    if (m <= 0) {
      cJSON_Delete(p);
      return m < 0 ? -m : usage_error(cli, "sequence: unexpected '%s'", argv[i]);
    }
  }
  if (dir == NULL) {
    cJSON_Delete(p);
    return usage_error(cli, "sequence needs --dir DIR%s", NULL);
  }
  cJSON_AddNumberToObject(p, "first", (double)first);
  cJSON_AddNumberToObject(p, "last", (double)last);
  cJSON_AddNumberToObject(p, "step", (double)step);
  cJSON_AddStringToObject(p, "dir", dir);
  default_format(p, NULL);
  cJSON *r = NULL;
  volfx_error_t e;
  int rc = volfx_call(cli->conn, "render.sequence", p, &r, NULL, &e);
  if (rc != 0) {
    report(cli, rc, &e);
    if (rc == PROTO_E_INVALID_PARAMS && strcmp(e.path, "first") == 0) {
      /* The live scene has played past FIRST: a private server renders any range. */
      fprintf(stderr,
              "volfx: to render frames %llu..%llu whatever the live scene's clock says, use "
              "`volfx batch SCENE -s %llu -e %llu -o 'DIR/frame_######.png'`\n",
              (unsigned long long)first, (unsigned long long)last, (unsigned long long)first,
              (unsigned long long)last);
    }
    return EXIT_FAIL;
  }
  double id = cJSON_GetNumberValue(cJSON_GetObjectItemCaseSensitive(r, "id"));
  cJSON_Delete(r);
  interrupted = 0;
  catch_sigint(1);
  int status = 0, cancelled = 0;
  for (;;) {
    if (interrupted && !cancelled) {
      cJSON *cp = cJSON_CreateObject();
      cJSON_AddNumberToObject(cp, "id", id);
      cJSON *cr = NULL;
      rpc(cli, "job.cancel", cp, &cr, NULL);
      cJSON_Delete(cr);
      cancelled = 1;
    }
    cJSON *msg = NULL;
    int rc = volfx_next_notification(cli->conn, "job.progress", 200, &msg, NULL);
    if (rc == VOLFX_E_TIMEOUT || rc == VOLFX_E_INTR) {
      continue;
    }
    if (rc != 0) {
      volfx_error_t e = {.code = rc};
      snprintf(e.message, sizeof(e.message), "%s", volfx_strerror(rc));
      status = report(cli, rc, &e);
      break;
    }
    const cJSON *jp = cJSON_GetObjectItemCaseSensitive(msg, "params");
    if (cJSON_GetNumberValue(cJSON_GetObjectItemCaseSensitive(jp, "id")) != id) {
      cJSON_Delete(msg);
      continue;
    }
    const char *state = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(jp, "state"));
    const char *file = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(jp, "last"));
    double done = cJSON_GetNumberValue(cJSON_GetObjectItemCaseSensitive(jp, "done"));
    double total = cJSON_GetNumberValue(cJSON_GetObjectItemCaseSensitive(jp, "total"));
    if (verbose && file != NULL && file[0] != '\0') {
      printf("%.0f/%.0f %s\n", done, total, file);
      fflush(stdout);
    }
    int ended = state == NULL || strcmp(state, "running") != 0;
    if (ended) {
      const char *why = cJSON_GetStringValue(cJSON_GetObjectItemCaseSensitive(jp, "error"));
      printf("sequence: job %.0f %s, %.0f of %.0f frames\n", id, state ? state : "?", done, total);
      if (why != NULL) {
        diag_prefix(cli);
        fprintf(stderr, "%s\n", why);
      }
      status = state != NULL && strcmp(state, "done") == 0 ? 0 : EXIT_FAIL;
    }
    cJSON_Delete(msg);
    if (ended) {
      break;
    }
  }
  catch_sigint(0);
  return status;
}

/* call METHOD [JSON_PARAMS] */
static int cmd_call(const cli_t *cli, int argc, char **argv) {
  if (argc < 2 || argc > 3) {
    return usage_error(cli, "call needs METHOD [JSON_PARAMS]%s", NULL);
  }
  cJSON *p = NULL;
  if (argc == 3 && (p = json_arg(cli, "call", argv[2])) == NULL) {
    return EXIT_USAGE;
  }
  return rpc_print(cli, argv[1], p);
}

/* Commands that are one call with fixed params. */
static int cmd_simple(const cli_t *cli, int argc, const char *method, int with_scene) {
  if (argc != 1) {
    return usage_error(cli, "%s takes no arguments", method);
  }
  return rpc_print(cli, method, with_scene ? scene_params(cli) : cJSON_CreateObject());
}

static int run_script(cli_t *cli, const char *file);

/*
 * Runs the command in argv[0..argc). "--scene NAME" anywhere among its words overrides the
 * default scene for this command. Returns an exit status.
 */
static int run_command(cli_t *cli, int argc, char **argv) {
  char *words[MAX_WORDS];
  int n = 0;
  cli->cmd_scene = NULL;
  for (int i = 0; i < argc && n < MAX_WORDS; i++) {
    const char *v;
    int m = i > 0 ? take_opt(argc, argv, &i, "--scene", NULL, &v) : 0;
    if (m < 0) {
      return usage_error(cli, "--scene needs a NAME%s", NULL);
    }
    if (m > 0) {
      cli->cmd_scene = v;
    } else {
      words[n++] = argv[i];
    }
  }
  if (n == 0) {
    return usage_error(cli, "no command%s", NULL);
  }
  const char *c = words[0];
  if (strcmp(c, "info") == 0) {
    return cmd_simple(cli, n, "server.info", 0);
  } else if (strcmp(c, "get") == 0) {
    return cmd_get(cli, n, words);
  } else if (strcmp(c, "set") == 0) {
    return cmd_set(cli, n, words);
  } else if (strcmp(c, "step") == 0) {
    return cmd_step(cli, n, words);
  } else if (strcmp(c, "play") == 0) {
    return cmd_play(cli, n, words);
  } else if (strcmp(c, "pause") == 0) {
    return cmd_simple(cli, n, "sim.pause", 1);
  } else if (strcmp(c, "render") == 0) {
    return cmd_render(cli, n, words);
  } else if (strcmp(c, "watch") == 0) {
    return cmd_watch(cli, n, words);
  } else if (strcmp(c, "sequence") == 0) {
    return cmd_sequence(cli, n, words);
  } else if (strcmp(c, "stats") == 0) {
    return cmd_simple(cli, n, "stats", 0);
  } else if (strcmp(c, "discover") == 0) {
    return cmd_simple(cli, n, "rpc.discover", 0);
  } else if (strcmp(c, "scenes") == 0) {
    return cmd_simple(cli, n, "scene.list", 0);
  } else if (strcmp(c, "scene") == 0) {
    return cmd_scene(cli, n, words);
  } else if (strcmp(c, "call") == 0) {
    return cmd_call(cli, n, words);
  } else if (strcmp(c, "shutdown") == 0) {
    return cmd_simple(cli, n, "server.shutdown", 0);
  } else if (strcmp(c, "script") == 0) {
    if (cli->script != NULL) {
      return usage_error(cli, "script cannot run inside a script%s", NULL);
    }
    if (n != 2) {
      return usage_error(cli, "script needs one FILE%s", NULL);
    }
    return run_script(cli, words[1]);
  } else if (strcmp(c, "help") == 0 || strcmp(c, "--help") == 0) {
    fputs(usage_text, stdout);
    return 0;
  }
  return usage_error(cli, "unknown command '%s'", c);
}

/*
 * Splits 'line' in place into words the way a shell would, without expansions: blanks
 * separate words, '...' is literal, "..." honours \" and \\, a backslash outside quotes
 * escapes the next character, and a word starting with # begins a comment. Returns the word
 * count or -1 (with '*why') on an unterminated quote or too many words.
 */
static int split_words(char *line, char **argv, int max, const char **why) {
  int argc = 0;
  char *r = line;
  char *w = line;
  for (;;) {
    while (*r == ' ' || *r == '\t' || *r == '\r' || *r == '\n') {
      r++;
    }
    if (*r == '\0' || *r == '#') {
      return argc;
    }
    if (argc == max) {
      *why = "too many words";
      return -1;
    }
    argv[argc++] = w;
    char quote = 0;
    while (*r != '\0') {
      char ch = *r;
      if (quote == 0 && (ch == ' ' || ch == '\t' || ch == '\r' || ch == '\n')) {
        break;
      }
      r++;
      if (quote == 0 && (ch == '\'' || ch == '"')) {
        quote = ch;
      } else if (quote != 0 && ch == quote) {
        quote = 0;
      } else if (ch == '\\' && quote == 0 && *r != '\0') {
        *w++ = *r++;
      } else if (ch == '\\' && quote == '"' && (*r == '"' || *r == '\\')) {
        *w++ = *r++;
      } else {
        *w++ = ch;
      }
    }
    if (quote != 0) {
      *why = "unterminated quote";
      return -1;
    }
    int more = *r != '\0';
    if (more) {
      r++;
    }
    *w++ = '\0';
    if (!more) {
      return argc;
    }
  }
}

/* script FILE: every command on this connection; stops at the first failing line. */
static int run_script(cli_t *cli, const char *file) {
  FILE *f = fopen(file, "r");
  if (f == NULL) {
    diag_prefix(cli);
    fprintf(stderr, "cannot open %s: %s\n", file, strerror(errno));
    return EXIT_FAIL;
  }
  char *line = NULL;
  size_t cap = 0;
  int status = 0;
  cli->script = file;
  cli->line = 0;
  while (status == 0 && getline(&line, &cap, f) >= 0) {
    cli->line++;
    line[strcspn(line, "\r\n")] = '\0';
    char *words[MAX_WORDS];
    const char *why = NULL;
    int n = split_words(line, words, MAX_WORDS, &why);
    if (n < 0) {
      status = usage_error(cli, "%s", why);
    } else if (n > 0) {
      status = run_command(cli, n, words);
      fflush(stdout);
    }
  }
  free(line);
  fclose(f);
  cli->script = NULL;
  return status;
}

/* Connects, authenticates when a token is known, runs the command and disconnects. */
int main(int argc, char **argv) {
  cli_t cli = {.scene = PROTO_DEFAULT_SCENE, .timeout_ms = DEFAULT_TIMEOUT_MS};
  const char *host = NULL;
  const char *unix_path = NULL;
  const char *token = getenv("VOLFX_TOKEN");
  long port = 0;
  int i = 1;
  for (; i < argc; i++) {
    const char *v;
    int m;
    double secs;
    if (strcmp(argv[i], "--help") == 0 || strcmp(argv[i], "-h") == 0) {
      fputs(usage_text, stdout);
      return 0;
    } else if ((m = take_opt(argc, argv, &i, "--host", NULL, &v)) != 0) {
      host = v;
    } else if ((m = take_opt(argc, argv, &i, "--port", "-p", &v)) != 0) {
      if (m > 0 && (!parse_long(v, &port) || port < 1 || port > 65535)) {
        return usage_error(&cli, "bad port '%s'", v);
      }
    } else if ((m = take_opt(argc, argv, &i, "--unix", NULL, &v)) != 0) {
      unix_path = v;
    } else if ((m = take_opt(argc, argv, &i, "--token", NULL, &v)) != 0) {
      token = v;
    } else if ((m = take_opt(argc, argv, &i, "--scene", NULL, &v)) != 0) {
      cli.scene = v;
    } else if ((m = take_opt(argc, argv, &i, "--timeout", NULL, &v)) != 0) {
      if (m > 0 && (!parse_double(v, &secs) || secs < 0 || secs > 86400)) {
        return usage_error(&cli, "bad timeout '%s'", v);
      }
      cli.timeout_ms = m > 0 ? (int)(secs * 1000) : 0;
    } else if (argv[i][0] == '-') {
      return usage_error(&cli, "unknown option '%s'", argv[i]);
    } else {
      break;
    }
    if (m < 0) {
      return usage_error(&cli, "%s needs a value", argv[i]);
    }
  }
  if (i >= argc) {
    fputs(usage_text, stderr);
    return EXIT_USAGE;
  }
  if (strcmp(argv[i], "help") == 0) {
    fputs(usage_text, stdout);
    return 0;
  }
  if (strcmp(argv[i], "batch") == 0) { /* These start a server of their own. */
    return cli_batch(argc - i, argv + i);
  } else if (strcmp(argv[i], "bake") == 0) {
    return cli_bake(argc - i, argv + i);
  }

  volfx_error_t e;
  int rc = unix_path != NULL ? volfx_connect_unix(&cli.conn, unix_path, cli.timeout_ms, &e)
                             : volfx_connect_tcp(&cli.conn, host, (int)port, cli.timeout_ms, &e);
  if (rc != 0) {
    return report(&cli, rc, &e);
  }
  int status = 0;
  if (token != NULL && token[0] != '\0' && (rc = volfx_auth(cli.conn, token, &e)) != 0) {
    status = report(&cli, rc, &e);
  } else {
    status = run_command(&cli, argc - i, argv + i);
  }
  volfx_close(cli.conn);
  return status;
}
