/*
 * The data directory (--data) and the files requests name under it. The directory is opened
 * once (datapath_init), and every file a request names is opened beneath that descriptor: by
 * openat2 with RESOLVE_BENEATH where the kernel has it, else one component at a time with
 * O_NOFOLLOW. No name, link or directory swapped in while a request waits can lead outside,
 * because nothing is checked before the open: the open is the check.
 *
 * Temporary files of atomic writes have names of one pattern (DATAPATH_TEMP_PREFIX and 16 hex
 * digits) that no request can name, so stale ones, left by a process killed while writing, can
 * be told apart and removed (datapath_sweep).
 */
#ifndef VOLFX_DATAPATH_H
#define VOLFX_DATAPATH_H

#include <stddef.h>
#include <sys/stat.h>

#define DATAPATH_TEMP_PREFIX ".volfx-tmp-"
/* Bytes of a temporary file's name, with its NUL. */
#define DATAPATH_TEMP_SIZE (sizeof DATAPATH_TEMP_PREFIX + 16)
/* A temporary file untouched for this long belongs to no running write. */
#define DATAPATH_TEMP_STALE_S 120

/*
 * Opens 'dir' as the data directory for every later open, replacing the one before (NULL or ""
 * leaves none), and removes stale temporary files in its tree. Call it at start-up, before any
 * request runs: the other functions read what it sets without a lock. Returns 0 or an errno.
 */
int datapath_init(const char *dir);

/* The data directory's descriptor, or -1 when there is none. */
int datapath_root(void);

/* Whether 'name' is one a request may give: relative, 1-255 bytes of letters, digits, '_', '-',
 * '.' and '/', no empty component and none starting with '.'. It looks at no file. */
int datapath_name_ok(const char *name);

/* The checks a request's file name gets on the loop thread: a data directory exists and
 * 'name' is well formed. Returns 0, or a protocol error code with a sentence in 'why'. */
int datapath_check(const char *name, char *why, size_t whylen);

/*
 * The name under the data directory of 'path': 'path' itself when it is relative, the part
 * after the data directory when it is an absolute path inside it (as datapath_resolve makes),
 * NULL otherwise.
 */
const char *datapath_relative(const char *path);

/*
 * Opens 'name' beneath the data directory with open(2) 'flags' (O_CLOEXEC is added). Links
 * inside the tree are followed where openat2 resolves them and stay inside it; absolute links,
 * links leading outside and /proc's magic links fail (EXDEV, ELOOP). Without openat2 no link is
 * followed (ELOOP, ENOTDIR). Returns the descriptor, or -1 with errno set. Any thread.
 */
int datapath_open(const char *name, int flags, mode_t mode);

/* Opens the directory that holds 'name' (O_RDONLY), pointing '*base' at the last component of
 * 'name'. Returns the descriptor, or -1 with errno set. */
int datapath_open_dir(const char *name, const char **base);

/*
 * Opens 'name' for reading only when it is a regular file of at most 'max' bytes: the open is
 * non-blocking (a FIFO cannot hold the thread), then fstat decides. Returns the descriptor in
 * blocking mode with its stat in '*st', or -1 with errno: EISDIR for a directory, ENODEV for
 * anything else that is not a regular file, EFBIG when larger than 'max'.
 */
int datapath_open_regular(const char *name, size_t max, struct stat *st);

/* The same checks on 'fd', opened O_NONBLOCK by the caller; clears O_NONBLOCK. 0 or -1. */
int datapath_fd_regular(int fd, size_t max, struct stat *st);

/* Reads at most 'size' bytes from 'fd' into a NUL-terminated buffer the caller frees, with the
 * count read in '*len'. NULL with errno set. */
char *datapath_fd_read(int fd, size_t size, size_t *len);

/* Reads the regular file 'name' (at most 'max' bytes) whole: datapath_open_regular, then
 * datapath_fd_read. NULL with errno set. */
char *datapath_read(const char *name, size_t max, size_t *len);

/* Makes directory 'name' and each missing one above it, beneath the data directory. Returns 0
 * or an errno (ENOTDIR when a component is a file). */
int datapath_mkdirs(const char *name);

/*
 * Describes errno 'err' of an open, read or write of the client's 'name' ('writing' when it was
 * a write; 'max' the size limit that EFBIG passed) in 'why', without revealing where the data
 * directory lives. Returns the protocol error code the request is answered with: -32004 for a
 * missing file or directory, -32003 for a full disk, -32602 for what the client named wrongly
 * (a file used as a directory, a directory, a link, not a regular file, too large, too long,
 * not permitted), -32603 for the rest.
 */
int datapath_error(int err, const char *name, int writing, size_t max, char *why, size_t whylen);

/* Writes a fresh random temporary file name (DATAPATH_TEMP_SIZE bytes) into 'out'. */
void datapath_temp_name(char *out);

/* Whether 'name' (one component) has the pattern of a temporary file. */
int datapath_is_temp(const char *name);

/*
 * Removes the temporary files in directory 'dirfd', and in its subdirectories 'depth' levels
 * down (neither hidden ones nor links are entered), untouched for DATAPATH_TEMP_STALE_S
 * seconds. Returns how many it removed.
 */
int datapath_sweep(int dirfd, int depth);

/* datapath_sweep of 'dirfd' alone, at most once a minute for each directory: for the
 * directory of a file about to be written. */
void datapath_sweep_beside(int dirfd);

/*
 * Older interface, for callers that still pass paths: checks 'name' as datapath_check does and
 * writes into 'out' the absolute path of 'name' under 'data_dir' (links resolved). With
 * 'must_exist' the file must exist, otherwise its directory must. Returns 0, or -1 with a
 * sentence in 'why'; 'notfound' (may be NULL) is set to 1 when only something is missing.
 * The path it gives is only good for the functions that open it beneath the data directory
 * again (datapath_relative): files_read, files_write_atomic, snapshot_out_write.
 */
int datapath_resolve(const char *data_dir, const char *name, int must_exist, char *out,
                     size_t outlen, char *why, size_t whylen, int *notfound);

#endif
