"""The temporal noise of one simulated camera frame: standard normal, one value per pixel.

At 2448 x 2048 numpy's generator takes ~40 ms of one core per frame, a third of a station's
rendering once the images' geometry is cached, and there is no faster exact normal generator
at hand: a counter-based Box-Muller kernel in numba took 70 ms per frame on one core. The rows
are drawn in two halves in two threads instead (numpy's generators release the GIL while they
fill), each half from its own generator, seeded by the frame's seed and the half: the same seed
gives the same noise whichever thread runs first.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

#: below this many pixels one thread draws the whole frame (the threads' hand-over costs more)
THREADED_FROM_PX = 1 << 20

_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def _executor() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(2, thread_name_prefix="sensor-noise")
        return _pool


def frame_noise(shape: tuple[int, int], seed: list[int]) -> np.ndarray:
    """Standard normal float32 noise of shape (H, W) from ``seed`` (a list of ints)."""
    out = np.empty(shape, np.float32)
    split = shape[0] // 2

    def fill(half: int) -> None:
        rows = out[:split] if half == 0 else out[split:]
        np.random.default_rng([*seed, half]).standard_normal(dtype=np.float32, out=rows)

    if out.size < THREADED_FROM_PX:
        fill(0)
        fill(1)
    else:
        list(_executor().map(fill, (0, 1)))
    return out
