/*
 * Internals of the render-farm commands `volfx batch` and `volfx bake` (cli_batch.c): the
 * private volfxd each of them runs (farm_server.c) and the files they write and read
 * (farm_files.c). Not part of libvolfx.
 */
#ifndef VOLFX_FARM_H
#define VOLFX_FARM_H

#include <limits.h>
#include <signal.h>
#include <stdint.h>
#include <sys/types.h>

#include "volfx.h"

#define EXIT_FAIL 1                   /* A frame, the bake or the server failed. */
#define EXIT_USAGE 2                  /* The command line was wrong; nothing was started. */
#define FARM_PATH_CAP (PATH_MAX + 64) /* Room for a path and a suffix or prefix. */

/* The state of one batch or bake run. */
typedef struct farm {
  const char *cmd;              /* "batch" or "bake": named in every message. */
  char where[48];               /* "frame N: " while working toward frame N, else "". */
  char why[1024];               /* What the last failed call said. */
  const char *presets;          /* --presets DIR for volfxd, or NULL. */
  const char *device;           /* --device D for volfxd, or NULL. */
  int verbose;                  /* -v: a line per frame or snapshot. */
  pid_t pid;                    /* The private volfxd; 0 when none runs. */
  volfx_conn_t *conn;           /* The connection to it, or NULL. */
  char tmp_data[FARM_PATH_CAP]; /* A data directory of our own, removed at the end, or "". */
  uint64_t *snaps;              /* Frames of the bake directory's snapshots, ascending. */
  size_t nsnaps;                /* How many. */
  char bake_base[NAME_MAX + 1]; /* The bake directory's name inside the data directory. */
  uint64_t frame;               /* The private scene's current frame. */
} farm_t;

/* ---- farm_server.c ---- */

/* SIGINT or SIGTERM once the CLI received it (after farm_catch_signals), else 0. */
extern volatile sig_atomic_t farm_stop_signal;

/* Prints "volfx CMD: [frame N: ]MESSAGE" to stderr and returns 'status'. */
__attribute__((format(printf, 3, 4))) int farm_say(const farm_t *f, int status, const char *fmt,
                                                   ...);
/* Formats a message into 'buf', cut to 'cap' bytes when longer. */
__attribute__((format(printf, 3, 4))) void farm_text(char *buf, size_t cap, const char *fmt, ...);
/* "SIGINT" or "SIGTERM". */
const char *farm_signal_name(int sig);
/* Catches SIGINT and SIGTERM: they set farm_stop_signal and are forwarded to the server. */
void farm_catch_signals(void);

/*
 * Starts the private volfxd with data directory 'data_dir' and main scene 'scene' (a preset
 * name or a scene file; "" for the plain default scene), connects and authenticates. Returns 0,
 * or EXIT_FAIL after saying why; farm_finish() cleans up either way.
 */
int farm_server_start(farm_t *f, const char *data_dir, const char *scene);
/* Stops the private server, when one runs, and removes the data directory of our own. */
void farm_server_stop(farm_t *f);
/*
 * Ends a run: stops the server, frees what 'f' holds and, after SIGINT or SIGTERM, dies of the
 * same signal. Otherwise returns 'status'.
 */
int farm_finish(farm_t *f, int status);

/*
 * One call to the private server, as volfx_call ('params' is taken). On failure 'f->why'
 * receives "METHOD: MESSAGE (path P)". Returns 0 or the call's code.
 */
int farm_call(farm_t *f, const char *method, cJSON *params, cJSON **result,
              volfx_attachment_t *att);
/* A params object naming the main scene, the only one the private server uses. */
cJSON *farm_main_params(void);
/* The number member 'name' of 'o', or 'dflt'. */
double farm_num(const cJSON *o, const char *name, double dflt);

/* ---- farm_files.c ---- */

/* Parses all of 's' as a whole number from 'min' to 'max'. Returns 1 on success. */
int farm_parse_u64(const char *s, uint64_t min, uint64_t max, uint64_t *out);
/* 1 when 'path' is a snapshot: a file whose first line is a JSON object with "volfx_snapshot". */
int farm_is_snapshot(const char *path);
/* Reads a whole file into a NUL-terminated string (free() it), or NULL with errno set. */
char *farm_read_text(const char *path);
/* The encoded frame format a file name's extension names ("png" for .png, "jpeg" for .jpg or
 * .jpeg, "webp" for .webp, in any case), or NULL. */
const char *farm_format_of_name(const char *name);
/*
 * Splits 'path' into its directory part (copied to 'dir', "." when there is none) and the name
 * after the last slash (returned, pointing into 'path').
 */
const char *farm_split_path(const char *path, char *dir, size_t cap);
/*
 * Creates directory 'path' and its missing parents (mkdir -p). On failure returns -1 with
 * errno set and 'bad' holding the directory that could not be made.
 */
int farm_make_dirs(const char *path, char *bad, size_t cap);
/*
 * Writes 'n' bytes to 'path' so that no reader ever sees part of them under that name: into a
 * new temporary file ".NAME.part.XXXXXX" beside it (after removing those a killed run left),
 * fsynced, renamed over 'path', and the directory fsynced; the directory is created first when
 * missing. The file gets 'mode'. Returns 0, or -1 with 'why' saying what failed.
 */
int farm_write_atomic(const char *path, const void *data, size_t n, mode_t mode, char *why,
                      size_t cap);
/*
 * 1 when 'n' bytes at 'data' are a whole frame: exactly 'raw_bytes' of a raw format, or (with
 * 'raw_bytes' 0) a PNG from its signature to its IEND chunk.
 */
int farm_bytes_whole(const unsigned char *data, size_t n, uint64_t raw_bytes);
/* farm_bytes_whole() for the file at 'path'; 0 when there is none. */
int farm_file_whole(const char *path, uint64_t raw_bytes);
/*
 * Expands 'pattern' for 'frame' into 'out': each run of '#' becomes the frame number padded
 * with zeros to the run's length (longer when the number needs more digits). Returns 0, or -1
 * when 'out' is too small.
 */
int farm_expand_pattern(const char *pattern, uint64_t frame, char *out, size_t cap);
/* Removes 'path' with everything under it. */
void farm_remove_tree(const char *path);

#endif
