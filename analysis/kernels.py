"""Fused per-pixel kernels (numba) for the scanner's hot path.

The numpy/OpenCV implementations in :mod:`scancell.analysis.phase` and
:mod:`scancell.analysis.stereo` are the reference and handle every configuration. They make
about ten full-image passes per frequency; on 2 x 5 Mpx that measured 0.5-0.75 s for the phase
alone (benchmarks/bench_decode_speed.py), against a 0.3 s budget for the whole decode. These
kernels do the same arithmetic in one pass per pixel, in parallel over rows, for the paper's
configuration (three frequencies, heterodyne, any number of steps) and for row matching.
tests/test_scanner.py checks they agree with the reference.
"""

from __future__ import annotations

import math

import numba
import numpy as np

# OpenMP first: the TBB found next to other wheels is too old for numba and only warns.
numba.config.THREADING_LAYER_PRIORITY = ["omp", "workqueue", "tbb"]

TWO_PI = 2.0 * math.pi

# Minimax odd polynomial of degree 17 for atan(t), t in [0, 1]: |error| < 6e-9 rad (fitted by
# Lawson's reweighted least squares on Chebyshev nodes). The phases of equal intensities, k·π/3,
# lie 3e-8 rad or more from a float32 rounding boundary: below that error the kernel rounds them
# as numpy's exact atan2 does, and the response histogram, whose bin edges they are, matches the
# reference's (tests/test_scanner.py). libm atan2 costs ~20 ns a call; three per pixel for
# 10 Mpx were a third of the budget.
_A = (0.99999988638, -0.33332597029, 0.19985906776, -0.14161229266, 0.10498946335,
      -0.07234857875, 0.03978122916, -0.01440136116, 0.00245672535)


_FM = {"contract", "arcp", "reassoc", "afn"}  # no "nnan": NaN marks invalid pixels


@numba.njit(inline="always", cache=True, fastmath=_FM)
def _atan2_0_2pi(y: float, x: float) -> float:
    """atan2 in [0, 2π) without branches: phases are random, so branches mispredict half the
    time (measured: the branchy version spent most of the kernel's time here)."""
    ax, ay = abs(x), abs(y)
    hi = max(ax, ay)
    lo = min(ax, ay)
    t = lo / (hi + 1e-30)
    t2 = t * t
    p = _A[8]
    p = p * t2 + _A[7]
    p = p * t2 + _A[6]
    p = p * t2 + _A[5]
    p = p * t2 + _A[4]
    p = p * t2 + _A[3]
    p = p * t2 + _A[2]
    p = p * t2 + _A[1]
    p = p * t2 + _A[0]
    a = p * t
    swap = 1.0 if ay > ax else 0.0
    a += swap * (0.5 * math.pi - 2.0 * a)
    neg_x = 1.0 if x < 0.0 else 0.0
    a += neg_x * (math.pi - 2.0 * a)
    neg_y = 1.0 if y < 0.0 else 0.0
    return a + neg_y * (TWO_PI - 2.0 * a)


INV_TWO_PI = 1.0 / TWO_PI


@numba.njit(inline="always", cache=True)
def _unwrap(phi: float, ref: float, ratio: float) -> tuple[float, float]:
    o = (ref * ratio - phi) * INV_TWO_PI  # divisions cost ~20 cycles: multiply by inverses
    k = math.floor(o + 0.5)
    return phi + TWO_PI * k, abs(o - k)


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def wrapped3(images: np.ndarray, steps: int, dn_scale: float, sat_level: float,
             hist_min_mod: float, finest: int, phases: np.ndarray, modulation: np.ndarray,
             finest_modulation: np.ndarray, background: np.ndarray, saturated: np.ndarray,
             hist: np.ndarray) -> None:
    """First pass of the three-frequency decode of (3·steps, H, W) images: wrapped phases
    (3, H, W) in [0, 2π), the smallest modulation, the modulation of group ``finest`` and the
    background (DN), the saturation flag,
    and ``hist`` (blocks, 3, bins): the phases folded modulo 2π/steps of the pixels with at
    least ``hist_min_mod`` modulation and no saturation (see :mod:`scancell.analysis.phase_response`)."""
    h, w = images.shape[1:]
    nblk, _, bins = hist.shape
    sin_t = np.empty(steps)
    cos_t = np.empty(steps)
    for n in range(steps):
        sin_t[n] = math.sin(TWO_PI * n / steps)
        cos_t[n] = math.cos(TWO_PI * n / steps)
    mod_scale = 2.0 / steps * dn_scale
    bg_scale = dn_scale / (3 * steps)
    fold = bins * steps / TWO_PI
    period = TWO_PI / steps
    for blk in numba.prange(nblk):
        q = np.empty((3, w))
        a_sum = np.empty(w)
        sat = np.empty(w)
        s = np.empty(w)
        c = np.empty(w)
        for y in range(blk, h, nblk):
            a_sum[:] = 0.0
            sat[:] = 0.0
            for j in range(3):
                s[:] = 0.0
                c[:] = 0.0
                for n in range(steps):
                    sn, cn = sin_t[n], cos_t[n]
                    row = images[j * steps + n, y]
                    for x in range(w):
                        v = float(row[x])
                        s[x] += v * sn
                        c[x] += v * cn
                        a_sum[x] += v
                        sat[x] = max(sat[x], 1.0 if v >= sat_level else 0.0)
                for x in range(w):
                    phases[j, y, x] = _atan2_0_2pi(s[x], c[x])
                    q[j, x] = s[x] * s[x] + c[x] * c[x]
            for x in range(w):
                mod = math.sqrt(min(q[0, x], q[1, x], q[2, x])) * mod_scale
                modulation[y, x] = mod
                finest_modulation[y, x] = math.sqrt(q[finest, x]) * mod_scale
                background[y, x] = a_sum[x] * bg_scale
                saturated[y, x] = 1 if sat[x] > 0.0 else 0
                if mod >= hist_min_mod and sat[x] == 0.0:
                    for j in range(3):
                        p = phases[j, y, x]
                        b = int((p - period * math.floor(p / period)) * fold)
                        hist[blk, j, min(max(b, 0), bins - 1)] += 1


@numba.njit(inline="always", cache=True)
def _corrected(phi: float, table: np.ndarray, scale: float) -> float:
    """φ − e(φ mod 2π/N) by linear interpolation in ``table`` (bins + 1 edges), in [0, 2π)."""
    bins = table.size - 1
    u = phi * scale
    u -= bins * math.floor(u / bins)
    i = min(int(u), bins - 1)
    f = u - i
    out = phi - (table[i] * (1.0 - f) + table[i + 1] * f)
    if out < 0.0:
        out += TWO_PI
    elif out >= TWO_PI:
        out -= TWO_PI
    return out


#: the reason of a pixel that fails only the residual-is-noise test, until :func:`settle_suspects`
SUSPECT = 5


@numba.njit(parallel=True, cache=True, fastmath=_FM)
def unwrap3_heterodyne(phases: np.ndarray, modulation: np.ndarray, saturated: np.ndarray,
                       tables: np.ndarray, steps: int, p1: float, p2: float, p3: float,
                       width: float, min_mod: float, tol: float,
                       background: np.ndarray, noise_floor: float, noise_gain: float,
                       noise_ref: float, noise_lowest: float, noise_highest: float,
                       threshold_on_snr: bool, margin_max: float,
                       units: np.ndarray, alias_orders: np.ndarray, systematic: np.ndarray,
                       z: float, ln_inv_alpha: float,
                       column: np.ndarray, reason: np.ndarray, counts: np.ndarray) -> None:
    """Second pass: remove the phase error ``tables`` (3, bins + 1; zeros for none) from the
    wrapped phases, unwrap by the heterodyne tree and check the frequencies agree.

    The five order decisions (beats 1 and 2 by the top, then p1, p2, p3) are held to
    ``margin_max`` fringes, or with ``margin_max`` < 0 to the per-pixel limits of
    :func:`scancell.analysis.decode_limits.order_limits` (``units``: σ_o · B of each decision;
    ``alias_orders``: how many independent errors an error the agreement check cannot see
    needs, 0 for none; ``systematic``: the residual's spread that noise does not explain,
    fringes). Every noise is σ_I / B, with σ_I² = ``noise_floor`` + ``noise_gain`` · A at the
    pixel's ``background`` A (DN, held within ``noise_lowest`` … ``noise_highest``, the levels
    the law was measured over) and the units quoted at σ_I = ``noise_ref``; with
    ``threshold_on_snr`` the modulation is compared with ``min_mod`` as if at ``noise_ref``.

    reason: 0 valid, 1 low modulation, 2 saturated, 3 order inconsistent, 4 outside projector;
    counts (H, 5): pixels of each reason per row.
    """
    h, w = modulation.shape
    b1, b2 = p1 - p2, p2 - p3
    top = b1 - b2
    r_b1, r_b2 = b1 / top, b2 / top
    r1, r2, r3 = p1 / b1, p2 / b2, p3 / b2
    inv_wsum = 1.0 / (p1 * p1 + p2 * p2 + p3 * p3)
    s1 = tol / max(tol, 0.1 * width / p1)
    s2 = tol / max(tol, 0.1 * width / p2)
    s3 = tol / max(tol, 0.1 * width / p3)
    c1 = width / (TWO_PI * p1)
    c2 = width / (TWO_PI * p2)
    c3 = width / (TWO_PI * p3)
    scale = (tables.shape[1] - 1) * steps / TWO_PI
    correct = False
    for j in range(3):
        for i in range(tables.shape[1]):
            if tables[j, i] != 0.0:
                correct = True
    for y in numba.prange(h):
        for x in range(w):
            ph0, ph1, ph2 = phases[0, y, x], phases[1, y, x], phases[2, y, x]
            if correct:
                ph0 = _corrected(ph0, tables[0], scale)
                ph1 = _corrected(ph1, tables[1], scale)
                ph2 = _corrected(ph2, tables[2], scale)
            mod = modulation[y, x]
            if noise_gain > 0.0:  # the modulation at which σ_ref gives this pixel's SNR
                level = min(max(background[y, x], noise_lowest), noise_highest)
                eff = mod * noise_ref / math.sqrt(noise_floor + noise_gain * level)
            else:
                eff = mod
            w12 = ph0 - ph1
            w12 += TWO_PI if w12 < 0.0 else 0.0
            w23 = ph1 - ph2
            w23 += TWO_PI if w23 < 0.0 else 0.0
            wt = w12 - w23
            wt += TWO_PI if wt < 0.0 else 0.0
            a12, m1 = _unwrap(w12, wt, r_b1)
            a23, m2 = _unwrap(w23, wt, r_b2)
            a1, m3 = _unwrap(ph0, a12, r1)
            a2, m4 = _unwrap(ph1, a23, r2)
            a3, m5 = _unwrap(ph2, a23, r3)
            noise_bad = False
            if margin_max >= 0.0:
                order_bad = max(m1, m2, m3, m4, m5) > margin_max
            else:
                inv_b = 1.0 / eff if eff > 0.0 else 1e30
                order_bad = False
                for d, m in enumerate((m1, m2, m3, m4, m5)):
                    sd = units[d] * inv_b
                    var = sd * sd + systematic[d] * systematic[d]
                    noise_bad = noise_bad or m > z * math.sqrt(var)
                    if alias_orders[d] > 0.0:
                        order_bad = order_bad or m > 0.5 - var * ln_inv_alpha / alias_orders[d]
            e1 = a1 * c1
            e2 = a2 * c2
            e3 = a3 * c3
            col = (p1 * p1 * e1 + p2 * p2 * e2 + p3 * p3 * e3) * inv_wsum
            spread = max(abs(e1 - col) * s1, abs(e2 - col) * s2, abs(e3 - col) * s3)
            code = 0
            code = 4 if (col < -0.5 or col > width - 0.5) else code
            code = SUSPECT if (code == 0 and noise_bad) else code
            code = 3 if (spread > tol or order_bad) else code
            code = 1 if (eff if threshold_on_snr else mod) < min_mod else code
            code = 2 if saturated[y, x] != 0 else code  # over low: a clipped fringe is weak
            reason[y, x] = code
            counts[y, min(code, 3)] += 1
            column[y, x] = col if (code == 0 or code == SUSPECT) else np.nan


@numba.njit(parallel=True, cache=True)
def settle_suspects(reason: np.ndarray, column: np.ndarray, counts: np.ndarray) -> None:
    """Each SUSPECT pixel of :func:`unwrap3_heterodyne` (counted there as order inconsistent):
    valid (0) when its 8 neighbours are valid, else order inconsistent (3) and its column NaN
    (:func:`scancell.analysis.decode_limits.lone_pixels`)."""
    h, w = reason.shape
    lone = np.zeros((h, w), np.bool_)
    for y in numba.prange(1, h - 1):
        for x in range(1, w - 1):
            if reason[y, x] == SUSPECT:
                ok = True
                for dy in range(-1, 2):
                    for dx in range(-1, 2):
                        if (dy != 0 or dx != 0) and reason[y + dy, x + dx] != 0:
                            ok = False
                lone[y, x] = ok
    for y in numba.prange(h):
        for x in range(w):
            if reason[y, x] == SUSPECT:
                if lone[y, x]:
                    reason[y, x] = 0
                    counts[y, 3] -= 1
                    counts[y, 0] += 1
                else:
                    reason[y, x] = 3
                    column[y, x] = np.nan


@numba.njit(parallel=True, cache=True)
def mask_discontinuities(column: np.ndarray, max_step: np.ndarray, max_bend: np.ndarray,
                         border: int, out: np.ndarray) -> None:
    """Same rule as :func:`scancell.analysis.stereo.mask_discontinuities`, in one pass: NaN on
    the border, next to a step larger than the smaller of the two pixels' ``max_step``, or
    within one pixel of a second difference larger than its centre's ``max_bend`` (both H x W;
    NaN neighbours never trigger either test)."""
    h, w = column.shape
    for y in numba.prange(h):
        for x in range(w):
            v = column[y, x]
            bad = y < border or y >= h - border or x < border or x >= w - border
            for dy, dx in ((0, -1), (0, 1), (-1, 0), (1, 0)):
                yn, xn = y + dy, x + dx
                if 0 <= yn < h and 0 <= xn < w and abs(column[yn, xn] - v) > min(
                        max_step[y, x], max_step[yn, xn]):
                    bad = True
            for dy, dx in ((0, 1), (1, 0)):
                for m in (-1, 0, 1):
                    yc, xc = y + dy * m, x + dx * m
                    ya, xa, yb, xb = yc - dy, xc - dx, yc + dy, xc + dx
                    if 0 <= ya and 0 <= xa and yb < h and xb < w:
                        bend = column[ya, xa] - 2.0 * column[yc, xc] + column[yb, xb]
                        if abs(bend) > max_bend[yc, xc]:
                            bad = True
            out[y, x] = np.nan if bad else v


@numba.njit(inline="always", cache=True)
def _bilinear(img: np.ndarray, x: float, y: float) -> float:
    h, w = img.shape
    if not (x >= 0.0 and y >= 0.0 and x <= w - 1.0 and y <= h - 1.0):
        return np.nan
    x0 = min(int(x), w - 2)
    y0 = min(int(y), h - 2)
    fx, fy = x - x0, y - y0
    return ((img[y0, x0] * (1 - fx) + img[y0, x0 + 1] * fx) * (1 - fy)
            + (img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x0 + 1] * fx) * fy)


@numba.njit(parallel=True, cache=True)
def match_and_count(col_left: np.ndarray, col_right: np.ndarray, max_step: float, cx1: float,
                    cx2: float, fb: float, z_min: float, z_max: float, x_right: np.ndarray,
                    per_row: np.ndarray) -> None:
    """For each rectified-left pixel, the right x with the same projector column on the same
    row (NaN if none), as :func:`scancell.analysis.stereo.match_rows`: the right row's strictly
    increasing pixels, a binary search, two adjacent pixels around the match; then the
    disparity and depth-range checks. per_row counts each row's matches (for compaction)."""
    h, w1 = col_left.shape
    w2 = col_right.shape[1]
    for y in numba.prange(h):
        xs = np.empty(w2, np.int64)
        vals = np.empty(w2, np.float64)
        m = 0
        best = -np.inf
        for x in range(w2):
            v = col_right[y, x]
            if v == v and v > best:
                xs[m] = x
                vals[m] = v
                m += 1
                best = v
        count = 0
        for x in range(w1):
            q = col_left[y, x]
            x_right[y, x] = np.nan
            if not (q == q) or m < 2:
                continue
            lo, hi = 0, m
            while lo < hi:
                mid = (lo + hi) // 2
                if vals[mid] < q:
                    lo = mid + 1
                else:
                    hi = mid
            if lo == 0 or lo == m:
                continue
            i0 = lo - 1
            step = vals[lo] - vals[i0]
            if xs[lo] - xs[i0] != 1 or step > max_step:
                continue
            xr = xs[i0] + (q - vals[i0]) / step
            d = (x - cx1) - (xr - cx2)
            if d <= 0.0:
                continue
            z = fb / d
            if z <= z_min or z >= z_max:
                continue
            x_right[y, x] = xr
            count += 1
        per_row[y] = count


@numba.njit(parallel=True, cache=True)
def triangulate_compact(x_right: np.ndarray, offsets: np.ndarray, cx1: float, cx2: float,
                        cy: float, f: float, fb: float, r1: np.ndarray, map1x: np.ndarray,
                        map1y: np.ndarray, map2x: np.ndarray, map2y: np.ndarray,
                        mod_l: np.ndarray, mod_r: np.ndarray, bg_l: np.ndarray,
                        points: np.ndarray, quality: np.ndarray, intensity: np.ndarray,
                        pixels: np.ndarray) -> None:
    """Points in MCS (R1ᵀ · rectified-left point) for every matched pixel, written at
    ``offsets[row]`` onwards; quality = min modulation of both cameras at the point's source
    pixels, intensity = left background, both sampled in the unrectified images."""
    h, w1 = x_right.shape
    w2 = map2x.shape[1]
    for y in numba.prange(h):
        k = offsets[y]
        for x in range(w1):
            xr = x_right[y, x]
            if not (xr == xr):
                continue
            z = fb / ((x - cx1) - (xr - cx2))
            px = (x - cx1) * z / f
            py = (y - cy) * z / f
            for i in range(3):
                points[k, i] = r1[0, i] * px + r1[1, i] * py + r1[2, i] * z
            sx, sy = map1x[y, x], map1y[y, x]
            xi = min(max(int(xr + 0.5), 0), w2 - 1)
            ml = _bilinear(mod_l, sx, sy)
            mr = _bilinear(mod_r, map2x[y, xi], map2y[y, xi])
            quality[k] = min(ml, mr) if mr == mr else ml
            intensity[k] = _bilinear(bg_l, sx, sy)
            pixels[k, 0] = x
            pixels[k, 1] = y
            k += 1
