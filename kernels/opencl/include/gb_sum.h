/* gb_sum.h: the compensated running sums of pass 1 (frames, poses, interpolated frames).
 *
 * Streamed sums are compensated (Neumaier's variant of Kahan summation): `sum` holds the running
 * sum, `compensation` the rounding errors of its additions, and sum + compensation the total,
 * within 2u |total| + O(n u^2) sum |terms| of the exact sum of the terms (u = 2^-24 in float,
 * 2^-53 in double; Higham, "Accuracy and Stability of Numerical Algorithms", 2nd ed., 4.3):
 * about one rounding of the total, for any number of terms in practice. A plain float sum
 * drifts by up to (n - 1) u of it: measured 1.5e-5 on the mean of 1,000 equal frames, 5.5e-6
 * over a 1,000-pose camera path. The float64 reference keeps its plain float64 sum (its own
 * error is below (n - 1) 2^-53 relative, 1.1e-13 at 1,000 frames). Contraction is off and
 * nothing may be reassociated: do not build with -cl-fast-relaxed-math or
 * -cl-unsafe-math-optimizations.
 *
 * Exact for 8-bit frames (float builds). Their linear values are whole multiples of
 * q = 2^-35 (GB_EXACT_UNIT, gpu_blur.kernel_constants) in [0, 1]. Summing n <= 128 of them
 * (EXACT_FRAMES_MAX), every running sum, term and rounding error e_k = s + v - t (exact:
 * Fast2Sum) is a multiple of q; the sums stay <= 128, so |e_k| <= half a float spacing in
 * [64, 128), 2^-18, and every partial sum of errors is a multiple of q of size <= 128 * 2^-18
 * = 2^24 q: a float, so `compensation` holds the errors' sum exactly and sum + compensation
 * rounds the exact total once. gb_blur_average_exact (accumulate.cl) sums the same values as
 * integer counts of q and rounds that total once: the same bits, with one integer add a
 * frame (tests/backends/test_hard_cases.py compares both on the cases nearest the rounding).
 */
#ifndef GB_SUM_H
#define GB_SUM_H

#include "gb_common.h"

/* sum[i] += v, its rounding error added to compensation[i]. */
static inline void gb_add_compensated(__global real *sum, __global real *compensation, size_t i,
                                      real v)
{
#pragma OPENCL FP_CONTRACT OFF
    real s = sum[i];
    real t = s + v;
    compensation[i] += fabs(s) >= fabs(v) ? (s - t) + v : (v - t) + s;
    sum[i] = t;
}

#endif
