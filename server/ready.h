/*
 * Telling a parent process that volfxd is ready, without parsing its log: --port-file PATH
 * receives the bound port and host (written to a temporary file beside it and renamed, so a
 * reader never sees half of it), and --ready-fd N receives one line and is closed. Both are
 * checked before the slow start (the OpenCL device and kernels), so a port file in a place
 * volfxd cannot write is a start-up error at once. sd_notify's READY=1 is service.c's.
 */
#ifndef VOLFX_READY_H
#define VOLFX_READY_H

/*
 * Checks 'port_file' (NULL or "" for none) and 'ready_fd' (negative for none): creates the
 * temporary file beside 'port_file' and makes sure 'ready_fd' is open for writing. Returns 0,
 * or -1 after logging what was wrong, naming the path or descriptor and the cause.
 */
int ready_prepare(const char *port_file, int ready_fd);

/*
 * volfxd listens: writes "PORT\nHOST\n" into the port file ('host' NULL, port 0 and "unix:"
 * plus 'unix_path' when only a Unix socket listens) and "ready PORT HOST\n" to the ready
 * descriptor, then closes it. Returns 0, or -1 after logging why the port file could not be
 * published.
 */
int ready_publish(const char *host, int port, const char *unix_path);

/* volfxd stops: removes the port file it published (or its temporary file) and closes the
 * ready descriptor if it is still open, so a parent waiting on it sees end-of-file. */
void ready_finish(void);

#endif
