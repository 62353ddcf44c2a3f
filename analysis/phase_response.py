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

from dataclasses import dataclass, field
from functools import lru_cache

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
        t = self.tables[j]
        bins = t.size - 1
        u = np.mod(phi, self.period) * (bins / self.period)
        return np.interp(u, np.arange(bins + 1), t)

    def apply(self, j: int, phi: np.ndarray) -> np.ndarray:
        """Corrected wrapped phase of frequency j, in [0, 2π), float32."""
        if not self.applied:
            return phi
        out = np.mod(phi - self.error_at(j, phi), 2 * np.pi).astype(np.float32)
        out[out >= np.float32(2 * np.pi)] = 0.0  # float32 rounding of a value just below 2π
        return out

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


@lru_cache(maxsize=16)
def _gamma_curves(steps: int, A: float, B: float) -> tuple[np.ndarray, np.ndarray]:
    """Folded phase errors e(u) (rad, ``_GRID`` points over 2π/N, as functions of the measured
    phase like the tables) of ``(A + B cos)^γ`` fringes for a grid of γ: the references
    :func:`equivalent_gamma` compares with."""
    gammas = np.geomspace(0.25, 5.0, 200)
    phi = np.linspace(0, 2 * np.pi, 8192, endpoint=False)
    shifts = 2 * np.pi * np.arange(steps) / steps
    period = 2 * np.pi / steps
    u = (np.arange(_GRID) + 0.5) * (period / _GRID)
    curves = []
    for g in gammas:
        images = [np.clip(A + B * np.cos(phi - d), 0, None) ** g for d in shifts]
        s = sum(i * np.sin(d) for i, d in zip(images, shifts, strict=True))
        c = sum(i * np.cos(d) for i, d in zip(images, shifts, strict=True))
        measured = np.mod(np.arctan2(s, c), 2 * np.pi)
        e = np.angle(np.exp(1j * (measured - phi)))
        folded = np.mod(measured, period)
        order = np.argsort(folded)
        curves.append(np.interp(u, folded[order], e[order], period=period))
    return gammas, np.asarray(curves)


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
            f"{done}; calibrate the projector response (scancell calibrate projector)")
