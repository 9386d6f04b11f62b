/*
 * Levelled logging to stderr, tagged by subsystem. The level is checked before anything is
 * formatted, so a debug line costs one comparison when debug logging is off.
 *
 * When stderr is connected to the systemd journal (JOURNAL_STREAM names stderr's device and
 * inode), each line starts with its syslog priority ("<3>" for an error, sd-daemon.h's SD_ERR)
 * and carries no timestamp, since the journal stamps lines itself; `journalctl -p err` then
 * finds the errors. Otherwise a line is "TIMESTAMP LEVEL [subsystem] message".
 */
#ifndef VOLFX_LOG_H
#define VOLFX_LOG_H

typedef enum { LOG_DEBUG, LOG_INFO, LOG_WARN, LOG_ERROR, LOG_QUIET } log_level_t;

/* The least level written. Read by every thread, written only by log_set_threshold. */
extern log_level_t log_threshold;

/* Parses "debug", "info", "warn", "error" or "quiet"; returns -1 for anything else. */
int log_level_parse(const char *s);

/* The name of 'level', as log_level_parse takes it. */
const char *log_level_name(log_level_t level);

/* Changes the threshold; safe while other threads log. */
void log_set_threshold(log_level_t level);

/* Looks at stderr and JOURNAL_STREAM to choose the line format; call once at start, before any
 * thread logs. Returns 1 when stderr is the journal. */
int log_init(void);

void log_write(log_level_t level, const char *subsystem, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));

#define LOG(level, subsystem, ...)                                                                 \
  do {                                                                                             \
    if ((level) >= (log_level_t)__atomic_load_n(&log_threshold, __ATOMIC_RELAXED))                 \
      log_write((level), (subsystem), __VA_ARGS__);                                                \
  } while (0)

#endif
