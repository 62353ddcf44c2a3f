"""Where the hand-eye job asks for the calibration ball: positions spread over the scanner's
common field and depth range (scanner frame, mm)."""

from __future__ import annotations

import numpy as np


def ball_layout(n: int, depths_mm: list[float], spread_mm: tuple[float, float],
                baseline_mm: float = 300.0, crossing_mm: float = 676.0) -> np.ndarray:
    """``n`` ball centres in MCS (mm) spread over the common field and the depth range: the
    centre, the corners and the edge midpoints of a ``spread`` rectangle centred on the bisector
    of the two optical axes (which cross ``crossing_mm`` in front of the left camera; the right
    camera is ``baseline_mm`` along +x), each at the next depth in turn. Any three consecutive
    balls span a plane, so a job that loses a ball or two still has a usable geometry."""
    sx, sy = spread_mm
    pattern = [(0, 0), (1, 1), (-1, -1), (1, -1), (-1, 1), (1, 0), (-1, 0), (0, 1), (0, -1)]
    out = []
    for i in range(n):
        px, py = pattern[i % len(pattern)]
        d = depths_mm[(i + i // len(pattern)) % len(depths_mm)]
        out.append([baseline_mm / 2 * (1 - d / crossing_mm) + px * sx / 2, py * sy / 2, d])
    return np.asarray(out, float)
