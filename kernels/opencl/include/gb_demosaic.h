/* gb_demosaic.h: Bayer demosaicing of one pixel (Malvar-He-Cutler 2004 and bilinear) as device
 * functions; no kernels. Same maths, taps and summation order as gpu_blur.reference.demosaic.
 *
 * Both functions take a RAW buffer view (gb_common.h): `raw` holds global pixels
 * [x0, x0 + w) x [y0, y0 + h) row-major with width w, and must contain every global pixel the
 * stencil of (gx, gy) reads after the border rule: the pixels within HALO (2 for Malvar, 1 for
 * bilinear) of (gx, gy), clipped to the image [0, full_w) x [0, full_h). The host guarantees it.
 *
 * Border rule, in GLOBAL coordinates (the full image's edges, never a tile's):
 *   zero_border == 0  "reflect": a tap at global i reads gb_reflect101(i, n) (mirror without
 *                     repeating the edge sample, period 2 (n - 1), keeps the Bayer phase; for
 *                     n = 2 it alternates x0 x1 x0 x1 as the reference's repeated mirroring);
 *   zero_border != 0  "zero": taps outside the image read 0 (and are never loaded).
 * `cfa` packs the channel of each cell site as gb_cfa_channel reads it, for the full image's
 * pattern (its (0, 0) at global (0, 0)). The output rgb[0..2] = R, G, B is not clipped.
 */
#ifndef GB_DEMOSAIC_H
#define GB_DEMOSAIC_H

#include "gb_common.h"

/* Malvar, He, Cutler, "High-quality linear interpolation for demosaicing of Bayer-patterned color
 * images", ICASSP 2004, Fig. 2: the four 5 x 5 filters times 8 (each sums to 8), row-major,
 * rows dy = -2 .. 2 (top to bottom), columns dx = -2 .. 2 (left to right). Weight = entry / 8.
 * The entries are gpu_blur.reference.demosaic's filters times 8 (gb_constants.h). */

/* G at R sites and at B sites. */
__constant real GB_MALVAR2004_G_AT_RB[25] = GB_MALVAR2004_G_AT_RB_X8;

/* R at a G site whose row holds R (B at a G site whose row holds B): same colour left and right. */
__constant real GB_MALVAR2004_RB_AT_G_ROW[25] = GB_MALVAR2004_RB_AT_G_ROW_X8;

/* R at a G site whose column holds R (B likewise): the transpose, same colour above and below. */
__constant real GB_MALVAR2004_RB_AT_G_COLUMN[25] = GB_MALVAR2004_RB_AT_G_COLUMN_X8;

/* R at B sites and B at R sites. */
__constant real GB_MALVAR2004_RB_AT_BR[25] = GB_MALVAR2004_RB_AT_BR_X8;

/* Bilinear, times 4, rows dy = -1 .. 1, columns dx = -1 .. 1; applied to the plane of one
 * channel (zeros at the other channels' sites). Weight = entry / 4. */

/* G: mean of the 4 axial neighbours. */
__constant real GB_BILINEAR_G[9] = GB_BILINEAR_G_X4;

/* R or B: mean of the 2 neighbours at G sites, of the 4 diagonal neighbours at B or R sites. */
__constant real GB_BILINEAR_RB[9] = GB_BILINEAR_RB_X4;

/* Stencil coordinates along one axis: global position g + k - reach (k = 0 .. 2 reach) under the
 * border rule, as an index relative to the view's origin `o` (a column, or a row to be scaled by
 * the width), and whether it lies inside the image (always 1 under reflect). */
static inline void gb_stencil_axis(long g, long n, long o, int zero_border, int reach, long idx[5],
                                   int inside[5])
{
    for (int k = 0; k <= 2 * reach; ++k) {
        long i = g + k - reach;
        int in_image = i >= 0 && i < n;
        if (!in_image && !zero_border) {
            i = gb_reflect101(i, n);
            in_image = 1;
        }
        inside[k] = in_image;
        idx[k] = in_image ? i - o : 0;
    }
}

/* One sample of the stencil: row k, column l (0 = the top/left tap); 0 outside the image. */
static inline real gb_stencil_sample(__global const real *raw, long w, const long row[5],
                                     const int row_in[5], const long col[5], const int col_in[5],
                                     int k, int l)
{
    return (row_in[k] && col_in[l]) ? raw[row[k] * w + col[l]] : GB_REAL(0.0);
}

/* Correlation with a 5 x 5 Malvar filter: the nonzero taps in row-major order, each adding
 * (entry / 8) * sample to a sum that starts at 0, as the reference's _correlate. */
static inline real gb_malvar2004_filter(__global const real *raw, long w, const long row[5],
                                        const int row_in[5], const long col[5],
                                        const int col_in[5], __constant real *taps)
{
    real sum = GB_REAL(0.0);
    for (int k = 0; k < 5; ++k) {
        for (int l = 0; l < 5; ++l) {
            real entry = taps[5 * k + l];
            if (entry != GB_REAL(0.0)) {
                real weight = entry * GB_MALVAR2004_TAP_WEIGHT; /* 1/8, exact: entries are k/2 */
                sum += weight * gb_stencil_sample(raw, w, row, row_in, col, col_in, k, l);
            }
        }
    }
    return sum;
}

/* Malvar-He-Cutler demosaicing of the pixel at global (gx, gy) (demosaic.demosaic_malvar2004):
 * the site keeps its RAW value for its own channel; at a G site, the colour of the row (the one
 * at (gx + 1, gy)) comes from the ROW filter and the other from the COLUMN filter; at an R or B
 * site, G from G_AT_RB and the opposite colour from RB_AT_BR. */
static inline void gb_demosaic_malvar2004(__global const real *raw, long x0, long y0, long w,
                                          long full_w, long full_h, long gx, long gy, int cfa,
                                          int zero_border, real rgb[3])
{
    long row[5], col[5];
    int row_in[5], col_in[5];
    gb_stencil_axis(gy, full_h, y0, zero_border, 2, row, row_in);
    gb_stencil_axis(gx, full_w, x0, zero_border, 2, col, col_in);
    int own = gb_cfa_channel(cfa, gx, gy);
    rgb[own] = raw[gb_offset(gx, gy, x0, y0, w)];
    if (own == 1) {
        int in_row = gb_cfa_channel(cfa, gx + 1, gy); /* R or B: shares this row */
        rgb[in_row] = gb_malvar2004_filter(raw, w, row, row_in, col, col_in,
                                           GB_MALVAR2004_RB_AT_G_ROW);
        rgb[2 - in_row] = gb_malvar2004_filter(raw, w, row, row_in, col, col_in,
                                               GB_MALVAR2004_RB_AT_G_COLUMN);
    } else {
        rgb[1] = gb_malvar2004_filter(raw, w, row, row_in, col, col_in, GB_MALVAR2004_G_AT_RB);
        rgb[2 - own] = gb_malvar2004_filter(raw, w, row, row_in, col, col_in,
                                            GB_MALVAR2004_RB_AT_BR);
    }
}

/* Bilinear demosaicing of the pixel at global (gx, gy) (demosaic.demosaic_bilinear): the site
 * keeps its RAW value for its own channel; each missing channel is the correlation of that
 * channel's plane with GB_BILINEAR_G or GB_BILINEAR_RB, taps in row-major order (taps on other
 * channels' sites add nothing and are skipped). Reflect keeps the Bayer phase, so a tap's
 * channel is that of its unreflected global position. */
static inline void gb_demosaic_bilinear(__global const real *raw, long x0, long y0, long w,
                                        long full_w, long full_h, long gx, long gy, int cfa,
                                        int zero_border, real rgb[3])
{
    long row[5], col[5];
    int row_in[5], col_in[5];
    gb_stencil_axis(gy, full_h, y0, zero_border, 1, row, row_in);
    gb_stencil_axis(gx, full_w, x0, zero_border, 1, col, col_in);
    int own = gb_cfa_channel(cfa, gx, gy);
    for (int c = 0; c < 3; ++c) {
        if (c == own) {
            rgb[c] = raw[gb_offset(gx, gy, x0, y0, w)];
            continue;
        }
        __constant real *taps = c == 1 ? GB_BILINEAR_G : GB_BILINEAR_RB;
        real sum = GB_REAL(0.0);
        for (int k = 0; k < 3; ++k) {
            for (int l = 0; l < 3; ++l) {
                real entry = taps[3 * k + l];
                if (entry != GB_REAL(0.0) && gb_cfa_channel(cfa, gx + l - 1, gy + k - 1) == c) {
                    real weight = entry * GB_BILINEAR_TAP_WEIGHT; /* 1/4, exact */
                    sum += weight * gb_stencil_sample(raw, w, row, row_in, col, col_in, k, l);
                }
            }
        }
        rgb[c] = sum;
    }
}

#endif
