/*
 * Big blocks freed on a thread of their own, and kept a moment for reuse. Returning tens of
 * megabytes to the system (a 256³ density, 2^20 particles) unmaps them page by page: about 4 ms
 * for 64 MB here. The last reference to such a block is often dropped on the loop thread (a
 * scene.set replacing a cloud, a scene.delete), which must not stall for it (SPEC §3), so those
 * blocks go to the reclaimer. And a cloud's step allocates its grids anew every step (three of
 * 8 MB at 128³): fresh pages from the system cost a fault and a zeroing each, a third of the
 * step, so a block of the same size dropped within the last second is handed back instead.
 */
#ifndef VOLFX_RECLAIM_H
#define VOLFX_RECLAIM_H

#include <stddef.h>

/* Blocks smaller than this are freed by the caller at once: a few pages cost less than the
 * hand-over. */
#define RECLAIM_MIN_BYTES ((size_t)1 << 20)

/* The blocks kept for reuse: the newest, up to this many, this many bytes in all, and this
 * long after they were dropped; the rest are freed. */
#define RECLAIM_KEEP_BLOCKS 8
#define RECLAIM_KEEP_BYTES ((size_t)320 << 20)
#define RECLAIM_KEEP_MS 1000

/* Starts the reclaimer's thread. Returns 0, or -1 when it could not be started, in which case
 * reclaim_free frees on the caller as before. */
int reclaim_start(void);

/* Frees whatever is still kept, then stops the thread. Blocks freed afterwards are freed on
 * the caller. */
void reclaim_stop(void);

/* Frees 'block' (NULL is fine) of 'bytes', the size it was allocated with, since it may be
 * handed back for that size: kept, then freed on the reclaimer's thread when it runs and the
 * block is big, else at once. Safe from any thread. */
void reclaim_free(void *block, size_t bytes);

/* 'bytes' of uninitialised memory, like malloc: a kept block of exactly that size when there is
 * one, the most recently dropped. Free it with free or reclaim_free. Safe from any thread. */
void *reclaim_alloc(size_t bytes);

/* Blocks handed to the reclaimer since it started, freed or not, and those of them taken back
 * by reclaim_alloc (for tests and stats). */
size_t reclaim_handed(void);
size_t reclaim_reused(void);
/* Bytes of the blocks kept for reuse now (stats). */
size_t reclaim_kept_bytes(void);

#endif
