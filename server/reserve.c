/*
 * The free-space reserve of the data directory: statvfs before a write.
 */
#include "reserve.h"

#include <stdio.h>
#include <sys/statvfs.h>

int reserve_check(const char *dir, uint64_t bytes, uint64_t reserve, char *why, size_t whylen) {
  struct statvfs st;
  if (reserve == 0 || statvfs(dir, &st) != 0)
    return 0;
  /* f_bavail: what an unprivileged writer may still use, which is what the server is. */
  uint64_t avail = (uint64_t)st.f_bavail * (uint64_t)st.f_frsize;
  if (avail >= bytes && avail - bytes >= reserve)
    return 0;
  snprintf(why, whylen,
           "writing %llu bytes would leave %llu bytes free on the data directory's file system, "
           "under the reserve of %llu bytes (limits.data_reserve_bytes)",
           (unsigned long long)bytes, (unsigned long long)(avail > bytes ? avail - bytes : 0),
           (unsigned long long)reserve);
  return -1;
}
