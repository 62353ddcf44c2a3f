"""The temporal noise of one simulated camera frame: standard normal, one value per pixel.

At 2448 x 2048 numpy's generator takes ~40 ms of one core per frame, a third of a station's
rendering once the images' geometry is cached, and there is no faster exact normal generator
at hand: a counter-based Box-Muller kernel in numba took 70 ms per frame on one core. The rows
are drawn in two halves in two threads instead (numpy's generators release the GIL while they
fill), each half from its own generator, seeded by the frame's seed and the half: the same seed
gives the same noise whichever thread runs first.
"""

from __future__ import annotations

import contextlib
import queue
import threading
import time
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor

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


class NoiseBank:
    """Frames' noise drawn ahead on a background thread while the simulator idles (the arm
    moving, the tracker measuring): frame f's noise is :func:`frame_noise` of ``[*seed, f]``
    whoever draws it, so the images are the same as drawn on demand, and a scan's frames then
    cost only their irradiance and the sensor model. The thread draws only after the renderer
    has been idle for ``IDLE_S`` (it never competes with a scan), and keeps up to ``ahead``
    frames (20 MB each at 2448 x 2048); frames under ``THREADED_FROM_PX`` are drawn on demand.
    The default, 9, is one camera's 3 x 3 patterns (180 MB at full size), held through the
    geometry and shading of the next pose, the daemon's peak; the other frames draw their noise
    as they render (~20 ms a frame on two threads). 40 frames ahead held 0.8 GB of the daemon's
    memory, 18 held 344 MB of its 3.1 GB peak in the demo (issue 37)."""

    #: the renderer idle this long (s): the scan has ended, the next has not begun
    IDLE_S = 0.2

    def __init__(self, seed: list[int], ahead: int = 9) -> None:
        self.seed = list(seed)
        self.ahead = ahead
        self._drawn: dict[tuple[tuple[int, int], int], Future[np.ndarray]] = {}
        self._lock = threading.Lock()
        self._queue: queue.SimpleQueue[tuple[tuple[int, int], int, Future[np.ndarray]]] = (
            queue.SimpleQueue())
        self._thread: threading.Thread | None = None
        self._rendering = 0
        self._idle_since = time.monotonic()

    @contextlib.contextmanager
    def rendering(self) -> Iterator[None]:
        """Around the renderer's work: the thread waits until it has been idle for a while."""
        with self._lock:
            self._rendering += 1
        try:
            yield
        finally:
            with self._lock:
                self._rendering -= 1
                self._idle_since = time.monotonic()

    def take(self, shape: tuple[int, int], frame: int) -> np.ndarray:
        """Frame ``frame``'s noise; the frames after it are drawn ahead."""
        if shape[0] * shape[1] < THREADED_FROM_PX:
            return frame_noise(shape, [*self.seed, frame])
        with self._lock:
            ahead = self._drawn.pop((shape, frame), None)
            for key in [k for k in self._drawn if k[0] != shape or k[1] < frame]:
                self._drawn.pop(key).cancel()
            for f in range(frame + 1, frame + 1 + self.ahead):
                if (shape, f) not in self._drawn:
                    self._drawn[(shape, f)] = fut = Future()
                    self._queue.put((shape, f, fut))
            if self._thread is None:
                self._thread = threading.Thread(target=self._draw, daemon=True,
                                                name="sensor-noise-ahead")
                self._thread.start()
        if ahead is not None and not ahead.cancel():  # drawn or being drawn: wait for it
            try:
                return ahead.result()
            except Exception:  # it failed there (memory): drawn here instead
                pass
        return frame_noise(shape, [*self.seed, frame])

    def _busy(self) -> bool:
        with self._lock:
            return self._rendering > 0 or time.monotonic() - self._idle_since < self.IDLE_S

    def _draw(self) -> None:
        while True:
            shape, frame, fut = self._queue.get()
            while not fut.cancelled() and self._busy():
                time.sleep(0.05)
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(frame_noise(shape, [*self.seed, frame]))
                except Exception as exc:  # e.g. memory: take() then draws it itself
                    fut.set_exception(exc)
