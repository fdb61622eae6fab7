/* gb_sum.h: the compensated running sum of the streamed passes (frames, poses, interpolated
 * frames).
 *
 * Neumaier's variant of Kahan summation: `sum` holds the running sum, `compensation` the
 * rounding errors of its additions, and sum + compensation the total, within
 * 2u |total| + O(n u^2) sum |terms| of the exact sum of the terms (u = 2^-24 in float, 2^-53 in
 * double; Higham, "Accuracy and Stability of Numerical Algorithms", 2nd ed., 4.3): about one
 * rounding of the total, for any number of terms in practice. Contraction is off and nothing
 * may be reassociated: do not build with -cl-fast-relaxed-math or
 * -cl-unsafe-math-optimizations.
 */
#ifndef GB_SUM_H
#define GB_SUM_H

#include "gb_common.h"

/* sum[i] += v, its rounding error added to compensation[i]. */
static inline void gb_sum_add(__global real *sum, __global real *compensation, size_t i, real v)
{
#pragma OPENCL FP_CONTRACT OFF
    real s = sum[i];
    real t = s + v;
    compensation[i] += fabs(s) >= fabs(v) ? (s - t) + v : (v - t) + s;
    sum[i] = t;
}

#endif
