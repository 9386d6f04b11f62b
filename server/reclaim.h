/*
 * Big blocks freed on a thread of their own. Returning tens of megabytes to the system (a 256³
 * density, 2^20 particles) unmaps them page by page: about 4 ms for 64 MB here. The last
 * reference to such a block is often dropped on the loop thread (a scene.set replacing a cloud,
 * a scene.delete), which must not stall for it (SPEC §3), so those blocks go to the reclaimer.
 */
#ifndef VOLFX_RECLAIM_H
#define VOLFX_RECLAIM_H

#include <stddef.h>

/* Blocks smaller than this are freed by the caller at once: a few pages cost less than the
 * hand-over. */
#define RECLAIM_MIN_BYTES ((size_t)1 << 20)

/* Starts the reclaimer's thread. Returns 0, or -1 when it could not be started, in which case
 * reclaim_free frees on the caller as before. */
int reclaim_start(void);

/* Frees whatever is still queued, then stops the thread. Blocks freed afterwards are freed on
 * the caller. */
void reclaim_stop(void);

/* Frees 'block' (of 'bytes'; NULL is fine): on the reclaimer's thread when it runs and the
 * block is big, else at once. Safe from any thread. */
void reclaim_free(void *block, size_t bytes);

/* Blocks handed to the reclaimer since it started, freed or not (for tests and stats). */
size_t reclaim_handed(void);

#endif
