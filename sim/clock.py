"""The simulated cell's clock: seconds of simulated time, advanced by what the cell does.

A move advances it by its travel time, a tracker shot by its averaging time, a projected pattern
by its period. Nothing reads the wall clock, so a seeded run sees the same times, and every
time-dependent effect (vibration, drift, warm-up) is repeatable.
"""

from __future__ import annotations

import threading


class SimClock:
    def __init__(self, start_s: float = 0.0) -> None:
        self._t = float(start_s)
        self._lock = threading.Lock()

    def now(self) -> float:
        """Simulated seconds since the cell was set up."""
        with self._lock:
            return self._t

    def advance(self, dt_s: float) -> float:
        """Let ``dt_s`` seconds pass; returns the new time."""
        if dt_s < 0:
            raise ValueError(f"the simulated clock cannot go back ({dt_s} s)")
        with self._lock:
            self._t += float(dt_s)
            return self._t

    def now_ns(self) -> int:
        return round(self.now() * 1e9)
