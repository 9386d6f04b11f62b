/*
 * The free-space reserve of the data directory (limits.data_reserve_bytes): files written under
 * --data (render.sequence frames, sim.bake snapshots, scene.save) must leave that much free on
 * its file system, so that one client's files cannot fill the disk that logs, the system and
 * other clients' saves share.
 */
#ifndef VOLFX_RESERVE_H
#define VOLFX_RESERVE_H

#include <stddef.h>
#include <stdint.h>

/*
 * Whether writing 'bytes' more into directory 'dir' leaves at least 'reserve' bytes free for
 * unprivileged users on its file system (statvfs). Returns 0 when it does (or when the file
 * system cannot be asked: the write itself then says what is wrong), or -1 with a sentence in
 * 'why' that names the reserve. Blocks on the file system: call it off the loop thread.
 */
int reserve_check(const char *dir, uint64_t bytes, uint64_t reserve, char *why, size_t whylen);

#endif
