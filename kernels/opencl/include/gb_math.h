/* gb_math.h: precise or fast transcendental functions for the pixel maths (scene
 * output.fast_math, an accuracy knob).
 *
 * GB_FAST_MATH (a build-time define, set by gpu_blur.backends.opencl from the plan) selects
 * OpenCL's native_ functions in float builds: their accuracy and range are implementation-defined
 * (OpenCL C 1.2, 6.12.2; on NVIDIA GPUs the hardware's approximate exp2 / log2 / sin / cos).
 * native_ functions take float only, so a double build (GB_FP64) keeps the standard functions
 * whether or not GB_FAST_MATH is defined; GB_NATIVE_MATH says which one a build got.
 *
 * What uses them: gb_pow in the sRGB curves (gb_pixel.h) and the float Box-Muller of the Gaussian
 * normals (gb_random.h, gb_box_muller). Poisson counts never do: a count is an integer decision
 * whose rounding must repeat the reference's. Only functions change, never the arithmetic rules:
 * the passes are not built with -cl-fast-relaxed-math or -cl-unsafe-math-optimizations, which
 * would let the compiler reassociate the accumulate pass's compensated sums away.
 */
#ifndef GB_MATH_H
#define GB_MATH_H

#if defined(GB_FAST_MATH) && !defined(GB_FP64)
#define GB_NATIVE_MATH 1
/* powr is pow for x >= 0, the only inputs the callers pass. */
#define gb_pow(x, y) native_powr((x), (y))
#define gb_log(x) native_log(x)
#define gb_sqrt(x) native_sqrt(x)
#define gb_cos(x) native_cos(x)
#define gb_sin(x) native_sin(x)
#else
#define gb_pow(x, y) pow((x), (y))
#define gb_log(x) log(x)
#define gb_sqrt(x) sqrt(x)
#define gb_cos(x) cos(x)
#define gb_sin(x) sin(x)
#endif

#endif
