/*
 * Fast reciprocal square root and division on float16 vectors, shared by the tone map
 * (tonemap.h) and the waves pass (waves.cl). The pragma lets LLVM use the CPU's reciprocal
 * estimates with one Newton step (vrsqrt14ps, vrcp14ps), which run beside the rest of the
 * maths, instead of vsqrtps and vdivps, which share one slow divider. It also lets LLVM assume
 * no infinities or NaNs, so it is kept to these helpers.
 */
#ifndef VOLFX_KERNELS_FASTMATH_H
#define VOLFX_KERNELS_FASTMATH_H

/* 1 / sqrt(x) to within a few ulp, for finite x > 0. */
static inline float16 fast_rsqrt(float16 x) {
#pragma float_control(precise, off)
  return 1.0f / sqrt(x);
}

/* a / b to within a few ulp, for finite a and finite b != 0. */
static inline float16 fast_div(float16 a, float16 b) {
#pragma float_control(precise, off)
  return a / b;
}

#endif
