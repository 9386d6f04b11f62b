/*
 * The OpenCL device behind the renderer (internal to render.c): picking a device, its context
 * and in-order queue, and the one program built from the .cl files of kernels/. Nothing here
 * logs; every failure comes back as -1 with a message.
 */
#ifndef VOLFX_CL_DEVICE_H
#define VOLFX_CL_DEVICE_H

#include <stddef.h>

#ifndef CL_TARGET_OPENCL_VERSION
#define CL_TARGET_OPENCL_VERSION 120
#endif
#include <CL/cl.h>

typedef struct cl_dev {
  cl_platform_id platform;
  cl_device_id device;
  cl_device_type type;
  cl_context context;
  cl_command_queue queue;
  cl_program program;
  char platform_name[128];
  char device_name[128];
  char binary_path[4200]; /* Where this program's binary is cached; "" when not cached. */
  int from_binary;        /* The program was loaded from 'binary_path'. */
} cl_dev_t;

/*
 * Opens the device named by 'which': NULL or "cpu" for the first CPU device of any platform,
 * "gpu" for the first GPU device, or a decimal index into all platforms' devices in order. A
 * NULL or empty 'which' takes the name from $VOLFX_DEVICE when that is set.
 * Points PoCL's kernel cache at $XDG_CACHE_HOME/volfx/pocl (or ~/.cache/volfx/pocl) first,
 * unless POCL_CACHE_DIR is set. Returns 0, or -1 with a message in 'err' and 'd' zeroed.
 */
int cl_dev_open(cl_dev_t *d, const char *which, char *err, size_t errlen);

/*
 * Builds the program from every kernel file, with quoted #includes of the other kernel files
 * expanded in place: the embedded copies, or the files of the same names in 'kernels_dir'
 * when it is not NULL. On a build failure 'err' holds the build log. A program binary saved by
 * cl_dev_save_binary for the same device, driver, options and source text is loaded instead
 * of compiling, from volfx-programs/ beside PoCL's cache (so clearing that cache clears both).
 */
int cl_dev_build(cl_dev_t *d, const char *kernels_dir, const char *options, char *err,
                 size_t errlen);

/*
 * Saves the built program's binary to 'binary_path' (written to a temporary file, then
 * renamed), unless it was loaded from there. Call it after every kernel has run: PoCL's binary
 * then holds the work-group functions compiled for the real local sizes, and a later start
 * loads it in milliseconds with nothing left to compile. Failure only costs speed.
 */
void cl_dev_save_binary(cl_dev_t *d);

/* Creates kernel 'name' of the built program; NULL with a message in 'err'. */
cl_kernel cl_dev_kernel(cl_dev_t *d, const char *name, char *err, size_t errlen);

/* Releases everything 'd' holds; safe on a zeroed or half-opened device. */
void cl_dev_close(cl_dev_t *d);

/* The name of an OpenCL status code ("CL_OUT_OF_RESOURCES"), or "CL_ERROR". */
const char *cl_dev_strerror(cl_int status);

#endif
