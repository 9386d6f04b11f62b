/*
 * The check macro of the C unit tests: CHECK(cond, fmt, ...) counts the check and, when 'cond'
 * is false, prints the file, line, condition and a printf-formatted explanation, and counts a
 * failure. A test's main prints the counts and exits non-zero when 'failures' is not 0. Each
 * test is one translation unit, so the counters are static.
 */
#ifndef VOLFX_TEST_CHECK_H
#define VOLFX_TEST_CHECK_H

#include <stdio.h>

static int failures, checks;

#define CHECK(cond, ...)                                                                           \
  do {                                                                                             \
    checks++;                                                                                      \
    if (!(cond)) {                                                                                 \
      failures++;                                                                                  \
      fprintf(stderr, "%s:%d: CHECK(%s) failed: ", __FILE__, __LINE__, #cond);                     \
      fprintf(stderr, __VA_ARGS__);                                                                \
      fputc('\n', stderr);                                                                         \
    }                                                                                              \
  } while (0)

#endif
