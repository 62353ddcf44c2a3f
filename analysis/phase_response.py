"""Passive compensation of a nonlinear fringe response, from the fringe images alone.

A projector (or camera) whose light output is not linear in the pattern value turns each
sinusoidal fringe into a distorted periodic profile. N-step phase shifting then measures
``φ' = φ + e(φ)``, where the error ``e`` is periodic in the phase with period 2π/N (the
harmonics N ± 1, 2N ± 1, … of the profile alias onto the fundamental) and odd for any
pointwise response. The error is the same at every pixel: ambient light and albedo change only
the profile's offset and scale, which phase shifting removes.

Estimate: over a scene that shows many fringes, the true phase is close to uniformly
distributed, so the distribution of the measured phase folded modulo 2π/N is the error's
fingerprint: its cumulative distribution maps measured to true phase (histogram equalisation
of the folded phase; folding also removes the scene's own, fringe-periodic, non-uniformity).
The constant left free by the cumulative sum is fixed by the error's zero mean (oddness).

Detection: the first harmonic of the measured error is matched against that of a pure power
law ``I = (A + B cos)^γ`` on the same pattern, which gives an equivalent gamma.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

#: bins of the folded phase (over 2π/N): 1 M pixels leave ~1000 per bin
BINS = 1024
#: fewer valid pixels per frequency than this and the histogram says too little
MIN_PIXELS = 4000
#: an estimated error below this (peak to peak, rad; 0.02 rad moves a 20 px fringe by 0.06 px) is
#: left alone: the estimate's own noise on small scenes is of that order
APPLY_ABOVE_PP_RAD = 0.02
#: equivalent gammas outside this are reported as "far from linear"
LINEAR_GAMMA_RANGE = (0.9, 1.1)


@dataclass
class PhaseCorrection:
    """Per-frequency error tables ``e(u)`` (rad) at ``u = i · (2π/N) / bins``, i = 0 … bins
    (the last equals the first); ``apply`` subtracts them from wrapped phases."""

    steps: int
    tables: np.ndarray  # (K, bins + 1) float64, rad
    applied: bool
    pixels: list[int] = field(default_factory=list)

    @property
    def period(self) -> float:
        return 2 * np.pi / self.steps

    def error_at(self, j: int, phi: np.ndarray) -> np.ndarray:
        """e(φ') of frequency j for wrapped phases φ' (rad)."""
        return table_error(self.tables[j], phi, self.steps)

    def apply(self, j: int, phi: np.ndarray) -> np.ndarray:
        """Corrected wrapped phase of frequency j, in [0, 2π), float32."""
        if not self.applied:
            return phi
        return subtract_error(self.tables[j], phi, self.steps)

    def peak_to_peak_rad(self) -> list[float]:
        return [float(np.ptp(t)) for t in self.tables]

    def report(self, A: float = 0.5, B: float = 0.5) -> dict:
        """What decode states about the response it found (JSON-ready)."""
        pp = self.peak_to_peak_rad()
        rms = [float(np.sqrt(np.mean(t[:-1] ** 2))) for t in self.tables]
        gamma = equivalent_gamma(self.tables, self.steps, A, B)
        lo, hi = LINEAR_GAMMA_RANGE
        return {"equivalent_gamma": round(gamma, 3) if np.isfinite(gamma) else None,
                "phase_error_pp_rad": [round(v, 4) for v in pp],
                "phase_error_rms_rad": [round(v, 4) for v in rms],
                "compensated": bool(self.applied),
                "pixels": list(self.pixels),
                "linear": bool(np.isfinite(gamma) and lo <= gamma <= hi)}


#: cv2.remap takes images of fewer than 32767 columns: long 1-D inputs are folded into rows
_REMAP_COLUMNS = 4096


def table_error(table: np.ndarray, phi: np.ndarray, steps: int) -> np.ndarray:
    """An error table's value (rad, float32) at wrapped phases ``phi`` in [0, 2π), linearly
    interpolated between its bins. The table, periodic in 2π/N, is laid out N times over the
    whole 2π so the phase indexes it without a modulo, and cv2.remap interpolates (np.interp
    took 55 ms a frame of 1.3 Mpx, this 4 ms; remap's weights come in 1/32 of a bin, which
    leaves ≤ 1.1e-4 rad against np.interp, a hundredth of a good pixel's phase noise)."""
    bins = table.size - 1
    full = np.concatenate([np.tile(np.asarray(table[:-1], np.float32), steps),
                           np.asarray(table[:1], np.float32)])[None, :]
    phi = np.asarray(phi, np.float32)
    flat = phi.ndim != 2 or phi.shape[1] >= 32767
    if flat:
        n = phi.size
        rows = max(1, -(-n // _REMAP_COLUMNS))
        padded = np.zeros(rows * _REMAP_COLUMNS, np.float32)
        padded[:n] = phi.reshape(-1)
        src = padded.reshape(rows, _REMAP_COLUMNS)
    else:
        src = phi
    u = src * np.float32(steps * bins / (2 * np.pi))
    err = cv2.remap(full, u, np.zeros_like(u), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return err.reshape(-1)[:phi.size].reshape(phi.shape) if flat else err


def subtract_error(table: np.ndarray, phi: np.ndarray, steps: int) -> np.ndarray:
    """``phi`` (in [0, 2π)) less the table's error, wrapped into [0, 2π), float32."""
    two_pi = np.float32(2 * np.pi)
    out = np.asarray(phi, np.float32) - table_error(table, phi, steps)
    out += two_pi * (out < 0)
    out -= two_pi * (out >= two_pi)
    return out


def folded_histogram(phi: np.ndarray, usable: np.ndarray, steps: int, bins: int = BINS
                     ) -> np.ndarray:
    """Counts (bins,) of wrapped phases (rad) folded modulo 2π/steps, over ``usable`` pixels."""
    period = 2 * np.pi / steps
    u = np.mod(phi[usable].astype(np.float64), period) * (bins / period)
    return np.bincount(np.minimum(u.astype(np.int64), bins - 1), minlength=bins)


def error_table(counts: np.ndarray, steps: int) -> np.ndarray:
    """The error e(u) (rad, bins + 1 values at the bin edges) whose removal makes the folded
    phase uniform; zero-mean."""
    period = 2 * np.pi / steps
    bins = counts.size
    cdf = np.concatenate([[0.0], np.cumsum(counts, dtype=np.float64)]) / max(counts.sum(), 1)
    u = np.arange(bins + 1) * (period / bins)
    e = u - period * cdf
    e -= np.mean(0.5 * (e[:-1] + e[1:]))  # zero mean over u
    e[-1] = e[0]
    return e


def estimate_correction(histograms: np.ndarray, steps: int) -> PhaseCorrection:
    """Correction from per-frequency folded histograms (K, bins); frequencies with too few
    pixels get none, and nothing is applied if the error is at the noise floor."""
    tables = np.zeros((histograms.shape[0], histograms.shape[1] + 1))
    pixels = [int(h.sum()) for h in histograms]
    for j, h in enumerate(histograms):
        if pixels[j] >= MIN_PIXELS:
            tables[j] = error_table(h, steps)
    applied = bool(min(pixels) >= MIN_PIXELS
                   and max(np.ptp(t) for t in tables) > APPLY_ABOVE_PP_RAD)
    return PhaseCorrection(steps, tables, applied, pixels)


_GRID = 256
_GAMMA_LOCK = threading.Lock()


@lru_cache(maxsize=16)
def _gamma_curves(steps: int, A: float, B: float) -> tuple[np.ndarray, np.ndarray]:
    """Folded phase errors e(u) (rad, ``_GRID`` points over 2π/N, as functions of the measured
    phase like the tables) of ``(A + B cos)^γ`` fringes for a grid of γ: the references
    :func:`equivalent_gamma` compares with."""
    gammas = np.geomspace(0.25, 5.0, 200)
    # 1024 phases leave 340 samples a folded period for the 256-point grid (the curves move by
    # 3e-6 rad against 8192 phases); all γ at once (a loop over γ on 8192 phases cost 0.15 s
    # of every decode process)
    phi = np.linspace(0, 2 * np.pi, 1024, endpoint=False)
    shifts = 2 * np.pi * np.arange(steps) / steps
    period = 2 * np.pi / steps
    u = (np.arange(_GRID) + 0.5) * (period / _GRID)
    base = np.clip(A + B * np.cos(phi[None, :] - shifts[:, None]), 0, None)  # (N, phases)
    images = base[None] ** gammas[:, None, None]  # (γ, N, phases)
    s = np.einsum("gnp,n->gp", images, np.sin(shifts))
    c = np.einsum("gnp,n->gp", images, np.cos(shifts))
    measured = np.mod(np.arctan2(s, c), 2 * np.pi)
    e = np.angle(np.exp(1j * (measured - phi[None, :])))
    folded = np.mod(measured, period)
    order = np.argsort(folded, axis=1)
    f_sorted = np.take_along_axis(folded, order, 1)
    e_sorted = np.take_along_axis(e, order, 1)
    curves = np.stack([np.interp(u, f_sorted[i], e_sorted[i], period=period)
                       for i in range(len(gammas))])
    return gammas, curves


def equivalent_gamma(tables: np.ndarray, steps: int, A: float = 0.5, B: float = 0.5) -> float:
    """The power-law exponent whose fringes show the phase error closest (least squares) to
    ``tables``, averaged over the frequencies with data; NaN if none has data."""
    used = [t for t in tables if np.ptp(t) > 0]
    if not used:
        return float("nan")
    bins = tables.shape[1] - 1
    measured = np.mean(used, axis=0)
    u = (np.arange(_GRID) + 0.5) * (bins / _GRID)
    e = np.interp(u, np.arange(bins + 1), measured)
    with _GAMMA_LOCK:  # the two cameras' decodes ask at once: build the curves once
        gammas, curves = _gamma_curves(steps, float(A), float(B))
    cost = np.sum((curves - e) ** 2, axis=1)
    i = int(np.argmin(cost))
    if 0 < i < len(gammas) - 1:  # parabola through the three best (in log γ)
        c0, c1, c2 = cost[i - 1:i + 2]
        den = c0 - 2 * c1 + c2
        step = 0.5 * (c0 - c2) / den if den > 0 else 0.0
        lg = np.log(gammas)
        return float(np.exp(lg[i] + np.clip(step, -1, 1) * (lg[i + 1] - lg[i])))
    return float(gammas[i])


def response_warning(camera: str, report: dict) -> str:
    """One line on a far-from-linear response found by decode (``report``: PhaseCorrection.report)."""
    gamma = report.get("equivalent_gamma")
    pp = max(report.get("phase_error_pp_rad") or [0.0])
    done = ("removed from the fringes (passive)" if report.get("compensated")
            else "NOT removed")
    return (f"{camera} camera: fringe response far from linear (equivalent gamma "
            f"{gamma if gamma is not None else '?'}, phase error {pp:.3f} rad peak to peak), "
            f"{done}; to pre-compensate the fringes instead, calibrate the projector response "
            f"(scancell calibrate projector) on a projector that can play them (the daemon's "
            f"log says why these were not)")
