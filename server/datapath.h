/*
 * Files named in requests live only under the data directory (--data). This module turns a
 * client's relative name into an absolute path inside it, refusing absolute names, ".."
 * components, odd characters and symbolic links that lead outside.
 */
#ifndef VOLFX_DATAPATH_H
#define VOLFX_DATAPATH_H

#include <stddef.h>

/* Whether 'name' is one datapath_resolve may accept: relative, letters, digits, '_', '-', '.',
 * '/', no empty component and none starting with '.'. It looks at no file. */
int datapath_name_ok(const char *name);

/*
 * Resolves 'name' under 'data_dir' into 'out' ('outlen' bytes). With 'must_exist' the file
 * itself must exist (and is resolved through links); otherwise only its directory must exist.
 * Returns 0, or -1 with a sentence in 'why' that names the file but not the data directory.
 * 'notfound' (may be NULL) is set to 1 when the only problem is that something is missing.
 */
int datapath_resolve(const char *data_dir, const char *name, int must_exist, char *out,
                     size_t outlen, char *why, size_t whylen, int *notfound);

#endif
