/* Levelled logging to stderr: one line per message, with a timestamp (or, for the journal, a
 * syslog priority) and subsystem tag. */
#include "log.h"

#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

log_level_t log_threshold = LOG_INFO;

static const char *const level_names[] = {"debug", "info", "warn", "error", "quiet"};

/* Syslog priorities of the levels, as sd-daemon.h's SD_DEBUG, SD_INFO, SD_WARNING and SD_ERR
 * spell them (written out here so that the format needs no libsystemd). */
static const char *const journal_prefix[] = {"<7>", "<6>", "<4>", "<3>", "<3>"};

static int to_journal; /* Set by log_init when stderr is the journal's stream. */

int log_level_parse(const char *s) {
  for (int i = 0; i <= LOG_QUIET; i++)
    if (strcmp(s, level_names[i]) == 0)
      return i;
  return -1;
}

const char *log_level_name(log_level_t level) {
  return level >= LOG_DEBUG && level <= LOG_QUIET ? level_names[level] : "?";
}

void log_set_threshold(log_level_t level) {
  __atomic_store_n(&log_threshold, level, __ATOMIC_RELAXED);
}

int log_init(void) {
  /* systemd sets JOURNAL_STREAM to "DEVICE:INODE" of the stream it connected stdout and stderr
   * to. A child that inherited the variable but not the stream (stderr redirected to a file)
   * sees another device or inode and keeps the plain format. */
  const char *js = getenv("JOURNAL_STREAM");
  struct stat st;
  unsigned long long dev, ino;
  char tail;
  to_journal = js && sscanf(js, "%llu:%llu%c", &dev, &ino, &tail) == 2 &&
               fstat(STDERR_FILENO, &st) == 0 && (unsigned long long)st.st_dev == dev &&
               (unsigned long long)st.st_ino == ino;
  return to_journal;
}

void log_write(log_level_t level, const char *subsystem, const char *fmt, ...) {
  char msg[1024];
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(msg, sizeof msg, fmt, ap);
  va_end(ap);
  if (level < LOG_DEBUG || level > LOG_QUIET)
    level = LOG_ERROR;

  /* One fprintf per line keeps lines from different threads whole. */
  if (to_journal) {
    /* The journal takes each line of a message (an OpenCL build log has many) as its own
     * entry, so every line gets the priority. */
    char out[2 * sizeof msg];
    const char *pre = journal_prefix[level];
    int n = snprintf(out, sizeof out, "%s%-5s [%s] ", pre, level_names[level], subsystem);
    for (const char *p = msg; *p && n < (int)sizeof out - 8; p++) {
      out[n++] = *p;
      if (*p == '\n' && p[1])
        n += snprintf(out + n, sizeof out - (size_t)n, "%s", pre);
    }
    if (n > (int)sizeof out - 2)
      n = (int)sizeof out - 2;
    out[n++] = '\n';
    fwrite(out, 1, (size_t)n, stderr);
    return;
  }
  struct timespec ts;
  struct tm tm;
  clock_gettime(CLOCK_REALTIME, &ts);
  gmtime_r(&ts.tv_sec, &tm);
  fprintf(stderr, "%04d-%02d-%02dT%02d:%02d:%02d.%03ldZ %-5s [%s] %s\n", tm.tm_year + 1900,
          tm.tm_mon + 1, tm.tm_mday, tm.tm_hour, tm.tm_min, tm.tm_sec, ts.tv_nsec / 1000000,
          level_names[level], subsystem, msg);
}
