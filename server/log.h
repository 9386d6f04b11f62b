/*
 * Levelled logging to stderr, tagged by subsystem. The level is checked before anything is
 * formatted, so a debug line costs one comparison when debug logging is off.
 */
#ifndef VOLFX_LOG_H
#define VOLFX_LOG_H

typedef enum { LOG_DEBUG, LOG_INFO, LOG_WARN, LOG_ERROR, LOG_QUIET } log_level_t;

extern log_level_t log_threshold;

/* Parses "debug", "info", "warn", "error" or "quiet"; returns -1 for anything else. */
int log_level_parse(const char *s);

void log_write(log_level_t level, const char *subsystem, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));

#define LOG(level, subsystem, ...)                                                                 \
  do {                                                                                             \
    if ((level) >= log_threshold)                                                                  \
      log_write((level), (subsystem), __VA_ARGS__);                                                \
  } while (0)

#endif
