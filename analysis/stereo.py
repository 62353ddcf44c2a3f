"""Stereo reconstruction from absolute phase: rectification, phase matching, triangulation.

Rectification keeps the whole common field of a converging rig: OpenCV's rectifying rotations
(``cv2.stereoRectify``) with our own projections, at the cameras' native focal length, each
camera's rectified image wide enough for its whole field and the rows every row both cameras
see. (``stereoRectify``'s own projections with ``alpha`` either crop a 25° converging rig's
overlap or shrink the focal length.)

Matching: along each rectified row the projector column seen by the right camera grows with x;
a left pixel's match is where the right row reaches the same column, interpolated between two
adjacent right pixels. Pixels next to a phase jump (a depth discontinuity or an occlusion edge)
are dropped before rectification, and interpolation never crosses a gap, so no point bridges two
surfaces. Output: points in MCS (the left camera's optical frame), mm.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from scancell.analysis.phase import PhaseMap
from scancell.analysis.stereo_calibration import StereoCalibration


@dataclass
class Rectification:
    R1: np.ndarray  # rectified-left <- left camera rotation
    R2: np.ndarray
    f: float  # px, both rectified cameras
    cx1: float
    cx2: float
    cy: float
    size1: tuple[int, int]  # (width, height)
    size2: tuple[int, int]
    baseline_mm: float
    maps1: tuple[np.ndarray, np.ndarray]
    maps2: tuple[np.ndarray, np.ndarray]


def _border(w: int, h: int, n: int = 64) -> np.ndarray:
    t = np.linspace(0, 1, n)
    xs, ys = t * (w - 1), t * (h - 1)
    return np.concatenate([np.stack([xs, np.zeros(n)], 1), np.stack([xs, np.full(n, h - 1.0)], 1),
                           np.stack([np.zeros(n), ys], 1), np.stack([np.full(n, w - 1.0), ys], 1)])


def rectify(calib: StereoCalibration) -> Rectification:
    """Rectifying maps for both cameras covering the whole common field (see module doc)."""
    w, h = calib.image_size
    R1, R2, *_ = cv2.stereoRectify(calib.K1, calib.D1, calib.K2, calib.D2, (w, h), calib.R,
                                   calib.T.reshape(3, 1), flags=0, alpha=-1)
    f = float(np.mean([calib.K1[0, 0], calib.K1[1, 1], calib.K2[0, 0], calib.K2[1, 1]]))
    P = np.array([[f, 0, 0], [0, f, 0], [0, 0, 1]], float)
    border = _border(w, h).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6)
    b1 = cv2.undistortPoints(border, calib.K1, calib.D1, R=R1, P=P, criteria=crit).reshape(-1, 2)
    b2 = cv2.undistortPoints(border, calib.K2, calib.D2, R=R2, P=P, criteria=crit).reshape(-1, 2)
    y0 = max(b1[:, 1].min(), b2[:, 1].min())
    y1 = min(b1[:, 1].max(), b2[:, 1].max())
    if y1 <= y0:
        raise ValueError("the two cameras share no rectified rows: is R, T right?")
    cy = -np.floor(y0)
    height = int(np.ceil(y1) - np.floor(y0)) + 1
    cx1, cx2 = -np.floor(b1[:, 0].min()), -np.floor(b2[:, 0].min())
    size1 = (int(np.ceil(b1[:, 0].max()) + cx1) + 1, height)
    size2 = (int(np.ceil(b2[:, 0].max()) + cx2) + 1, height)
    maps = []
    for K, D, R, cx, size in ((calib.K1, calib.D1, R1, cx1, size1), (calib.K2, calib.D2, R2, cx2, size2)):
        Pn = np.array([[f, 0, cx], [0, f, cy], [0, 0, 1]], float)
        maps.append(cv2.initUndistortRectifyMap(K, D, R, Pn, size, cv2.CV_32FC1))
    return Rectification(R1, R2, f, float(cx1), float(cx2), float(cy), size1, size2,
                         calib.baseline_mm, maps[0], maps[1])


@dataclass
class Cloud:
    """Points in MCS (mm) with per-point quality (fringe modulation, DN) and intensity (DN)."""

    points: np.ndarray  # (N, 3) float32
    quality: np.ndarray  # (N,) float32
    intensity: np.ndarray  # (N,) float32
    pixels: np.ndarray  # (N, 2) int32 rectified-left (x, y) of each point
    #: (N,) float32 1-sigma depth noise (mm, analysis.uncertainty); None if not computed
    uncertainty: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.points)


def typical_step(column: np.ndarray) -> float:
    """Median change of the projector column between horizontal neighbours (projector px)."""
    with np.errstate(invalid="ignore"):
        step = np.nanmedian(np.abs(np.diff(column[::4], axis=1)))
    return float(step) if np.isfinite(step) else 1.0


def mask_discontinuities(column: np.ndarray, max_step_px: float | np.ndarray,
                         max_bend_px: float | np.ndarray = 0.75, border_px: int = 3) -> np.ndarray:
    """``column`` with NaN next to any jump larger than ``max_step_px`` projector px between
    neighbouring camera pixels (depth edges, occlusions), where the column bends by more than
    ``max_bend_px`` (second difference: pixels that mix two surfaces through the lens blur),
    and on the image's outer ``border_px`` pixels (blur and vignetting). Either limit may be a
    per-pixel map (H x W, :mod:`scancell.analysis.decode_limits`); a pair of neighbours is held
    to the smaller of their limits, a bend to its centre pixel's."""
    c = column.copy()
    if border_px:
        c[:border_px] = c[-border_px:] = np.nan
        c[:, :border_px] = c[:, -border_px:] = np.nan
    bad = np.zeros(c.shape, bool)
    step = np.asarray(max_step_px, np.float32)
    bend = np.asarray(max_bend_px, np.float32)
    step_x = np.minimum(step[:, :-1], step[:, 1:]) if step.ndim == 2 else step
    step_y = np.minimum(step[:-1], step[1:]) if step.ndim == 2 else step
    bend_x = bend[:, 1:-1] if bend.ndim == 2 else bend
    bend_y = bend[1:-1] if bend.ndim == 2 else bend
    with np.errstate(invalid="ignore"):
        dx = np.abs(np.diff(column, axis=1)) > step_x
        dy = np.abs(np.diff(column, axis=0)) > step_y
    bad[:, :-1] |= dx
    bad[:, 1:] |= dx
    bad[:-1, :] |= dy
    bad[1:, :] |= dy
    with np.errstate(invalid="ignore"):
        bx = np.abs(column[:, :-2] - 2 * column[:, 1:-1] + column[:, 2:]) > bend_x
        by = np.abs(column[:-2] - 2 * column[1:-1] + column[2:]) > bend_y
    for shift in (0, 1, 2):
        bad[:, shift:shift + bx.shape[1]] |= bx
        bad[shift:shift + by.shape[0], :] |= by
    c[bad] = np.nan
    return c


def _remap(img: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    return cv2.remap(img.astype(np.float32, copy=False), maps[0], maps[1], cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))


def match_rows(col_left: np.ndarray, col_right: np.ndarray, max_step_px: float
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every valid rectified-left pixel, the sub-pixel right x with the same projector
    column on the same row: (rows, left x, right x) of the matched pixels.

    Row by row: the right row's usable pixels (strictly increasing column) and one binary search
    for the row's left pixels; a match needs two horizontally adjacent right pixels around it.
    (One global search over ``row · 2^16 + column`` keys measured 2x slower: bench_decode_speed.)
    """
    right_ok = np.isfinite(col_right)
    left_ok = np.isfinite(col_left)
    out_r, out_xl, out_xr = [], [], []
    for r in np.flatnonzero(left_ok.any(axis=1) & (right_ok.sum(axis=1) >= 2)):
        xs = np.flatnonzero(right_ok[r])
        vals = col_right[r, xs]
        increasing = np.empty(len(vals), bool)
        increasing[0] = True
        np.greater(vals[1:], np.maximum.accumulate(vals)[:-1], out=increasing[1:])
        xs, vals = xs[increasing], vals[increasing]
        xl = np.flatnonzero(left_ok[r])
        q = col_left[r, xl]
        i1 = np.searchsorted(vals, q)
        good = (i1 > 0) & (i1 < len(vals))
        i1[~good] = 1
        i0 = i1 - 1
        step = vals[i1] - vals[i0]
        good &= (xs[i1] - xs[i0] == 1) & (step <= max_step_px)
        out_r.append(np.full(int(good.sum()), r, np.int64))
        out_xl.append(xl[good])
        out_xr.append(xs[i0[good]] + (q[good] - vals[i0[good]]) / step[good])
    if not out_r:
        empty = np.zeros(0, np.int64)
        return empty, empty, np.zeros(0)
    return np.concatenate(out_r), np.concatenate(out_xl), np.concatenate(out_xr).astype(np.float64)


def point_uncertainty(rect: Rectification, col_r: np.ndarray, sigma: tuple[np.ndarray, np.ndarray],
                      rows: np.ndarray, xl: np.ndarray, xr: np.ndarray) -> np.ndarray:
    """1-sigma depth noise (mm) of matched points from the cameras' column-noise maps
    ``sigma`` (unrectified, projector px) and the right row's column slope at the match."""
    from scancell.analysis.uncertainty import depth_sigma

    sig_l = _remap(sigma[0], rect.maps1)[rows, xl]
    sig_r_rect = _remap(sigma[1], rect.maps2)
    w2 = col_r.shape[1]
    i0 = np.clip(np.floor(xr).astype(np.int64), 0, w2 - 2)
    sig_r = sig_r_rect[rows, np.clip(np.rint(xr).astype(np.int64), 0, w2 - 1)]
    slope = col_r[rows, i0 + 1] - col_r[rows, i0]
    z = rect.f * rect.baseline_mm / ((xl - rect.cx1) - (xr - rect.cx2))
    out = depth_sigma(z, rect.f, rect.baseline_mm, sig_l, np.where(np.isfinite(sig_r), sig_r, sig_l),
                      slope)
    return np.where(np.isfinite(out), out, np.float32(np.nan)).astype(np.float32)


def reconstruct(calib: StereoCalibration, left: PhaseMap, right: PhaseMap,
                rect: Rectification | None = None, max_step_px: float | None = None,
                z_range_mm: tuple[float, float] = (50.0, 5000.0),
                timings: dict[str, float] | None = None, engine: str = "fast",
                sigma: tuple[np.ndarray, np.ndarray] | None = None,
                edge_limits: tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
                | None = None, border_px: int = 3, bend_px: float = 0.75) -> Cloud:
    """Triangulate matched phase into a cloud in MCS; ``timings`` receives the step times (s).
    ``engine="numpy"`` matches with the numpy reference instead of the numba kernel.
    ``sigma``: the left and right column-noise maps (analysis.uncertainty.column_sigma), for a
    per-point uncertainty. ``edge_limits``: per camera the (step, bend) limits of
    :func:`mask_discontinuities`, per pixel (analysis.decode_limits.discontinuity_limits);
    None: steps of ``max_step_px`` (default 3 x the typical step) and bends of ``bend_px``
    (the scanner's fixed limits, analysis.phase.DecodeSettings)."""
    clock = time.perf_counter
    t0 = clock()
    for side, pm in (("left", left), ("right", right)):
        calib.check_image_size(pm.column.shape[1], pm.column.shape[0], f"{side} phase maps")
    rect = rect or rectify(calib)
    if max_step_px is None:  # a few times the surface's own slope: depth edges jump far more
        max_step_px = 3.0 * typical_step(left.column)
    edges = edge_limits or ((max_step_px, bend_px), (max_step_px, bend_px))
    if engine == "fast":
        return _reconstruct_fast(left, right, rect, float(max_step_px), edges, z_range_mm,
                                 timings, t0, sigma, int(border_px))
    (step_l, bend_l), (step_r, bend_r) = edges
    col_l = _remap(mask_discontinuities(left.column, step_l, bend_l, border_px), rect.maps1)
    col_r = _remap(mask_discontinuities(right.column, step_r, bend_r, border_px), rect.maps2)
    t1 = clock()
    rows, xl, xr = match_rows(col_l, col_r, max_step_px)
    t2 = clock()
    d = (xl - rect.cx1) - (xr - rect.cx2)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = rect.f * rect.baseline_mm / d
    good = (d > 0) & (z > z_range_mm[0]) & (z < z_range_mm[1])
    rows, xl, xr, z = rows[good], xl[good], xr[good], z[good].astype(np.float32)
    inv_f = np.float32(1.0 / rect.f)
    p_rect = np.empty((len(z), 3), np.float32)
    p_rect[:, 0] = (xl - rect.cx1).astype(np.float32) * z * inv_f
    p_rect[:, 1] = (rows - rect.cy).astype(np.float32) * z * inv_f
    p_rect[:, 2] = z
    points = p_rect @ rect.R1.astype(np.float32)  # R1^T applied to each row vector
    flat_l = rows * rect.size1[0] + xl
    flat_r = rows * rect.size2[0] + np.clip(np.rint(xr).astype(np.int64), 0, rect.size2[0] - 1)
    mod_l = _remap(left.modulation, rect.maps1).ravel()[flat_l]
    mod_r = cv2.remap(right.modulation.astype(np.float32), rect.maps2[0], rect.maps2[1],
                      cv2.INTER_LINEAR).ravel()[flat_r]
    quality = np.minimum(mod_l, mod_r)
    intensity = _remap(left.background, rect.maps1).ravel()[flat_l]
    unc = point_uncertainty(rect, col_r, sigma, rows, xl, xr) if sigma is not None else None
    if timings is not None:
        timings.update(rectify=t1 - t0, match=t2 - t1, triangulate=clock() - t2)
    return Cloud(points, quality.astype(np.float32), intensity.astype(np.float32),
                 np.stack([xl, rows], 1).astype(np.int32), unc)


def _reconstruct_fast(left: PhaseMap, right: PhaseMap, rect: Rectification, max_step: float,
                      edges: tuple[tuple[Any, Any], tuple[Any, Any]],
                      z_range_mm: tuple[float, float], timings: dict[str, float] | None,
                      t0: float, sigma: tuple[np.ndarray, np.ndarray] | None,
                      border_px: int = 3) -> Cloud:
    """The same reconstruction with the numba kernels (scancell.analysis.kernels)."""
    from scancell.analysis import kernels as k

    clock = time.perf_counter
    masked = []
    for pm, maps, (step, bend) in ((left, rect.maps1, edges[0]), (right, rect.maps2, edges[1])):
        out = np.empty(pm.column.shape, np.float32)
        step_map = np.broadcast_to(np.asarray(step, np.float32), pm.column.shape)
        bend_map = np.broadcast_to(np.asarray(bend, np.float32), pm.column.shape)
        k.mask_discontinuities(pm.column, step_map, bend_map, border_px, out)
        masked.append(_remap(out, maps))
    col_l, col_r = masked
    t1 = clock()
    h = col_l.shape[0]
    x_right = np.empty(col_l.shape, np.float64)
    per_row = np.zeros(h, np.int64)
    fb = rect.f * rect.baseline_mm
    k.match_and_count(col_l, col_r, max_step, rect.cx1, rect.cx2, fb, float(z_range_mm[0]),
                      float(z_range_mm[1]), x_right, per_row)
    t2 = clock()
    offsets = np.zeros(h, np.int64)
    np.cumsum(per_row[:-1], out=offsets[1:])
    n = int(per_row.sum())
    points = np.empty((n, 3), np.float32)
    quality = np.empty(n, np.float32)
    intensity = np.empty(n, np.float32)
    pixels = np.empty((n, 2), np.int32)
    k.triangulate_compact(x_right, offsets, rect.cx1, rect.cx2, rect.cy, rect.f, fb, rect.R1,
                          rect.maps1[0], rect.maps1[1], rect.maps2[0], rect.maps2[1],
                          left.modulation, right.modulation, left.background, points, quality,
                          intensity, pixels)
    unc = None
    if sigma is not None:
        rows, xl = pixels[:, 1].astype(np.int64), pixels[:, 0].astype(np.int64)
        unc = point_uncertainty(rect, col_r, sigma, rows, xl, x_right[rows, xl])
    if timings is not None:
        timings.update(rectify=t1 - t0, match=t2 - t1, triangulate=clock() - t2)
    return Cloud(points, quality, intensity, pixels, unc)
