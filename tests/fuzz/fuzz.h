/*
 * What every libFuzzer target here shares: the entry point libFuzzer calls, and REQUIRE, which
 * checks a property that must hold whatever the input with abort(), so that the fuzzer reports
 * a broken one as a crash.
 */
#ifndef VOLFX_FUZZ_H
#define VOLFX_FUZZ_H

#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size);

#define REQUIRE(cond)                                                                              \
  do {                                                                                             \
    if (!(cond))                                                                                   \
      abort();                                                                                     \
  } while (0)

#endif
