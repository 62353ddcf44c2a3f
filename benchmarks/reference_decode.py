"""Plain-numpy reference of the scanner's decode, for bench_decode_speed.py.

The same steps and the same maths as scancell.analysis (phase, heterodyne unwrapping with the
consistency check, rectification by bilinear interpolation, phase matching along rows,
triangulation), written the straightforward way: float64 numpy, np.mod/np.arctan2, numpy
bilinear interpolation instead of cv2.remap, one np.searchsorted per row.
"""

from __future__ import annotations

import numpy as np


def wrapped_phase(images: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = len(images)
    stack = np.stack([im.astype(np.float64) for im in images])
    d = 2 * np.pi * np.arange(n) / n
    s = np.tensordot(np.sin(d), stack, 1)
    c = np.tensordot(np.cos(d), stack, 1)
    return np.mod(np.arctan2(s, c), 2 * np.pi), 2 / n * np.hypot(s, c), stack.mean(0)


def decode(images: list[np.ndarray], periods=(70.0, 64.0, 59.0), steps: int = 3,
           width: int = 1280, min_mod: float = 8.0, tol: float = 1.0, margin_max: float = 0.3
           ) -> np.ndarray:
    phases, mods = [], []
    sat = np.zeros(images[0].shape, bool)
    for j in range(len(periods)):
        phi, b, _ = wrapped_phase(images[j * steps:(j + 1) * steps])
        phases.append(phi)
        mods.append(b)
        for im in images[j * steps:(j + 1) * steps]:
            sat |= im >= 254.5
    two_pi = 2 * np.pi
    p1, p2, p3 = periods
    b12 = np.mod(phases[0] - phases[1], two_pi)
    b23 = np.mod(phases[1] - phases[2], two_pi)
    top = np.mod(b12 - b23, two_pi)
    margin = np.zeros_like(top)

    def unwrap(phi, ref, ratio):
        o = (ref * ratio - phi) / two_pi
        k = np.round(o)
        np.maximum(margin, np.abs(o - k), out=margin)
        return phi + two_pi * k

    a12 = unwrap(b12, top, p1 - p2)
    a23 = unwrap(b23, top, p2 - p3)
    a1 = unwrap(phases[0], a12, p1 / (p1 - p2))
    a2 = unwrap(phases[1], a23, p2 / (p2 - p3))
    a3 = unwrap(phases[2], a23, p3 / (p2 - p3))
    est = [a * width / (two_pi * p) for a, p in zip((a1, a2, a3), periods, strict=True)]
    w = np.array(periods) ** 2
    col = (w[0] * est[0] + w[1] * est[1] + w[2] * est[2]) / w.sum()
    spread = np.zeros_like(col)
    for e, p in zip(est, periods, strict=True):
        t = max(tol, 0.1 * width / p)
        spread = np.maximum(spread, np.abs(e - col) * tol / t)
    bad = (np.minimum.reduce(mods) < min_mod) | sat | (spread > tol) | (margin > margin_max)
    col[bad] = np.nan
    return col


def remap(img: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    h, w = img.shape
    x0, y0 = np.floor(mx).astype(np.int64), np.floor(my).astype(np.int64)
    fx, fy = mx - x0, my - y0
    inside = (x0 >= 0) & (y0 >= 0) & (x0 < w - 1) & (y0 < h - 1)
    x0c, y0c = np.clip(x0, 0, w - 2), np.clip(y0, 0, h - 2)
    v = (img[y0c, x0c] * (1 - fx) * (1 - fy) + img[y0c, x0c + 1] * fx * (1 - fy)
         + img[y0c + 1, x0c] * (1 - fx) * fy + img[y0c + 1, x0c + 1] * fx * fy)
    v[~inside] = np.nan
    return v


def match(col_l: np.ndarray, col_r: np.ndarray, max_step: float):
    rows, xls, xrs = [], [], []
    for r in range(col_l.shape[0]):
        right = col_r[r]
        ok = np.isfinite(right)
        xs = np.flatnonzero(ok)
        vals = right[ok]
        if len(vals) < 2:
            continue
        mono = np.concatenate([[True], vals[1:] > np.maximum.accumulate(vals)[:-1]])
        xs, vals = xs[mono], vals[mono]
        left = col_l[r]
        xl = np.flatnonzero(np.isfinite(left))
        q = left[xl]
        i1 = np.searchsorted(vals, q)
        good = (i1 > 0) & (i1 < len(vals))
        i1 = np.where(good, i1, 1)
        i0 = i1 - 1
        step = vals[i1] - vals[i0]
        good &= (xs[i1] - xs[i0] == 1) & (step <= max_step)
        t = (q - vals[i0]) / np.where(step > 0, step, 1)
        rows.append(np.full(good.sum(), r))
        xls.append(xl[good])
        xrs.append((xs[i0] + t)[good])
    return np.concatenate(rows), np.concatenate(xls), np.concatenate(xrs)


def triangulate(rows, xl, xr, rect) -> np.ndarray:
    d = (xl - rect.cx1) - (xr - rect.cx2)
    z = rect.f * rect.baseline_mm / d
    p = np.stack([(xl - rect.cx1) * z / rect.f, (rows - rect.cy) * z / rect.f, z], 1)
    good = d > 0
    return (p[good] @ rect.R1)
