/* gb_common.h: the scalar type, pixel addressing and border rules shared by every pass.
 *
 * Build-time defines (set by gpu_blur.backends.opencl, one place):
 *   GB_FP64          compute in double (cl_khr_fp64) instead of float
 *   GB_HAS_FP64      the device has cl_khr_fp64 (samplers may use double inside)
 *   GB_STAGE_<NAME>  a stage of the plan is compiled in (see gpu_blur.plan)
 *   GB_SOURCE_BITS   how input frames are stored: 8 (uchar codes), 16 (ushort codes) or 0
 *                    (real sRGB values in [0, 1]; the default)
 *
 * Images live in row-major buffers that cover a region of the full image: a buffer "view"
 * is (x0, y0) = global coordinates of its first pixel, (w, h) = its size, and the full image's
 * (full_w, full_h). Kernels address pixels by GLOBAL coordinates, so a tile with its halo gives
 * the same values as one whole-image launch.
 */
#ifndef GB_COMMON_H
#define GB_COMMON_H

#if defined(GB_FP64) || defined(GB_HAS_FP64)
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
#endif

#ifdef GB_FP64
typedef double real;
#define GB_REAL(x) (x)
#else
typedef float real;
#define GB_REAL(x) (x##f)
#endif

/* Input frames travel to the device as stored (an 8-bit frame is a quarter of its float copy)
 * and become values in [0, 1] in the kernel: code / (2^bits - 1), a correctly rounded division,
 * so a value equals the host's float64 code / 255 rounded to real (checked for every 8- and
 * 16-bit code), as gpu_blur.imageio.to_unit. */
#ifndef GB_SOURCE_BITS
#define GB_SOURCE_BITS 0
#endif
#if GB_SOURCE_BITS == 8
typedef uchar gb_source;
#define gb_source_value(v) ((real)(v) / GB_REAL(255.0))
#elif GB_SOURCE_BITS == 16
typedef ushort gb_source;
#define gb_source_value(v) ((real)(v) / GB_REAL(65535.0))
#else
typedef real gb_source;
#define gb_source_value(v) (v)
#endif

/* Pixel positions of warps (camera poses, optical flow): double where the device has it, so
 * sub-pixel positions far from the origin keep the reference's float64 precision. */
#ifdef GB_HAS_FP64
typedef double gb_pos;
#else
typedef float gb_pos;
#endif

/* Mirror index i into [0, n) without repeating the edge sample (numpy "reflect", OpenCV
 * BORDER_REFLECT_101): period 2 (n - 1); keeps the Bayer phase. n == 1 gives 0. */
inline long gb_reflect101(long i, long n)
{
    if (n == 1) return 0;
    long period = 2 * (n - 1);
    long m = i % period;
    if (m < 0) m += period;
    return m < n ? m : period - m;
}

/* Offset of global pixel (gx, gy) in a buffer view whose first pixel is (x0, y0), width w. */
inline long gb_offset(long gx, long gy, long x0, long y0, long w)
{
    return (gy - y0) * w + (gx - x0);
}

/* Bayer colour (0 = R, 1 = G, 2 = B) at global (gx, gy): `cfa` packs the channels at the
 * cell offsets (0,0), (0,1), (1,0), (1,1) in bits 0-1, 2-3, 4-5, 6-7. */
inline int gb_cfa_channel(int cfa, long gx, long gy)
{
    int site = (int)(((gy & 1) << 1) | (gx & 1));
    return (cfa >> (2 * site)) & 3;
}

#endif
