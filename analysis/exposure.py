"""Choosing a station's exposures (HDR) from a preview: one dark and one full-white frame per
camera at the current exposure.

The fringes' modulation is about half the full-white signal above black, so a pixel whose
white is less than ``2 · min_modulation · margin`` DN above its black decodes poorly; a pixel
at saturation in white saturates in the fringes' bright phases. The base exposure is kept; a
longer one is added (×factor, up to ``max_factor``) while more than ``share`` of the lit pixels
are too dark, and a shorter one while more than ``share`` are saturated.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

SATURATION_DN = 254.5


def choose_exposures(previews: Sequence[tuple[np.ndarray, np.ndarray]], base_us: float,
                     min_modulation_dn: float = 8.0, margin: float = 2.0, share: float = 0.03,
                     factor: float = 4.0, max_factor: float = 16.0) -> list[float]:
    """Exposure times (µs, ascending) from (black, white) preview pairs of each camera."""
    blacks = [np.asarray(b, np.float32) for b, _ in previews]
    whites = [np.asarray(w, np.float32) for _, w in previews]
    lit = [(w - b) > 3.0 for b, w in zip(blacks, whites, strict=True)]
    n_lit = sum(int(m.sum()) for m in lit)
    if n_lit == 0:
        return [base_us]
    span = [(w - b)[m] for b, w, m in zip(blacks, whites, lit, strict=True)]
    bright = [w[m] for w, m in zip(whites, lit, strict=True)]
    need = 2.0 * min_modulation_dn * margin
    out = [base_us]
    f = 1.0
    while f * factor <= max_factor:
        dark = sum(int((s * f < need).sum()) for s in span) / n_lit
        if dark <= share:
            break
        f *= factor
        out.append(base_us * f)
    f = 1.0
    while f / factor >= 1.0 / max_factor:
        sat = sum(int((b * f >= SATURATION_DN).sum()) for b in bright) / n_lit
        if sat <= share:
            break
        f /= factor
        out.append(base_us * f)
    return sorted(out)
