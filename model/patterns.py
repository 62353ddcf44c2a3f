"""Fringe patterns of the scanner (fixed convention: files and other tools depend on it).

N-step, K-frequency vertical fringes. Image ``k = j*N + n`` shows

    I_n(x) = A + B * cos(2*pi*p_j*x / W - 2*pi*n / N)

with x the projector column (0 ... W-1, pixel centres), W the projector width and p_j the
number of periods across it. Default as the paper: 3 steps x 3 frequencies, periods 70, 64, 59
(heterodyne beats 70-64 = 6, 64-59 = 5, 6-5 = 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DEFAULT_PERIODS: tuple[float, ...] = (70.0, 64.0, 59.0)
DEFAULT_STEPS = 3
#: Columns of the scanner's DLP projector (W above): 1280 x 800, as TI's DLPC350 LightCrafter.
PROJECTOR_WIDTH = 1280
PROJECTOR_HEIGHT = 800


@dataclass(frozen=True)
class FringeSequence:
    periods: tuple[float, ...] = DEFAULT_PERIODS
    steps: int = DEFAULT_STEPS
    A: float = 0.5
    B: float = 0.5

    def __post_init__(self) -> None:
        if self.steps < 3:
            raise ValueError(f"phase shifting needs at least 3 steps, got {self.steps}")
        if not self.periods or any(p <= 0 for p in self.periods):
            raise ValueError(f"periods must be positive, got {self.periods}")
        if not (0 <= self.A - self.B and self.A + self.B <= 1):
            raise ValueError(f"A +- B must stay in [0, 1], got A={self.A} B={self.B}")

    @classmethod
    def from_spec(cls, spec: dict) -> FringeSequence:
        return cls(tuple(float(p) for p in spec.get("periods", DEFAULT_PERIODS)),
                   int(spec.get("steps", DEFAULT_STEPS)))

    def __len__(self) -> int:
        return self.steps * len(self.periods)

    def index(self, j: int, n: int) -> int:
        return j * self.steps + n

    def split(self, k: int) -> tuple[int, int]:
        """(frequency index j, step n) of image k."""
        if not 0 <= k < len(self):
            raise IndexError(f"pattern {k} outside a sequence of {len(self)}")
        return divmod(k, self.steps)

    def intensity(self, k: int, x: np.ndarray, width: int) -> np.ndarray:
        """Relative intensity (0..1) of pattern k at projector column(s) x (float, pixels)."""
        j, n = self.split(k)
        phase = 2 * np.pi * self.periods[j] * np.asarray(x) / width - 2 * np.pi * n / self.steps
        return self.A + self.B * np.cos(phase)

    def image(self, k: int, width: int, height: int) -> np.ndarray:
        """Pattern k as an 8-bit projector image (height x width)."""
        row = self.intensity(k, np.arange(width, dtype=float), width)
        return np.tile(np.round(row * 255).astype(np.uint8), (height, 1))
