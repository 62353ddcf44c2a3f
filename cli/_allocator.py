"""Keep freed memory in the process (glibc): the long-running services allocate and free
arrays of tens of MB per frame or cloud (a 2448 x 2048 float32 image is 20 MB). glibc returns
such blocks to the kernel on free (mmap/munmap, heap trimming), so every frame faults its pages
in again: rendering a full-size station spent 5.9 s in the kernel, 1.8 s with the thresholds
below, and 19.9 s against 16.6 s in all (measured in-process, 3 poses x 2 cameras x 2
exposures x 9 patterns). Linux with glibc only; elsewhere nothing changes.

One malloc arena per core the process may run on, not glibc's eight per core: a frame is freed
into the arena of the thread that allocated it, and memory freed in one arena is no use to a
thread of another, so a service of a dozen threads (its event loop's executor, the simulator's,
the noise and decode threads, zenoh's) kept up to ~1 GB of freed blocks beside its live heap
(the daemon in the demo: heap 1.7 GB at 2.98 GB resident, memray). With two arenas on this
2-core machine the daemon alone over six full-size auto-HDR stations peaked at 2 192 MB, not
2 388, its scans as fast within 2 % (benchmarks/RESULTS.md, session 43).

What is kept is given back once the process is idle (:func:`give_back_when_idle`): a service
between jobs, or a worker waiting for the next station, holds its live data only."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
import sys
import threading
import time
from collections.abc import Callable

#: mallopt parameters (malloc.h)
M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD, M_ARENA_MAX = -1, -2, -3, -8
MMAP_THRESHOLD_BYTES = 256 << 20  # blocks below it come from the heap, and go back to it
TRIM_THRESHOLD_BYTES = 1 << 30  # free memory at the heap's top kept up to this much
TOP_PAD_BYTES = 256 << 20  # the heap grows in steps of this much


#: a process is idle once it has used less than this share of one core ...
IDLE_CPU_SHARE = 0.05
#: ... for this long: longer than the gaps inside a station's work (a frame, a decode step),
#: shorter than the robot's move between stations
IDLE_S = 2.0
POLL_S = 0.5


@functools.cache
def _libc():
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def cores() -> int:
    """The cores this process may run on (its CPU affinity, else the machine's)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def keep_freed_memory() -> bool:
    """Set the allocator's thresholds and its arenas (one per core) for this process; whether
    it could."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = _libc().mallopt
    except AttributeError:  # no libc, or not glibc (musl has no mallopt)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return all(mallopt(p, v) == 1 for p, v in ((M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES),
                                                (M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES),
                                                (M_TOP_PAD, TOP_PAD_BYTES),
                                                (M_ARENA_MAX, cores())))


def trim_heap() -> bool:
    """Give the heap's free pages back to the kernel (glibc ``malloc_trim(0)``); whether any
    were."""
    try:
        malloc_trim = _libc().malloc_trim
    except AttributeError:
        return False
    malloc_trim.argtypes, malloc_trim.restype = [ctypes.c_size_t], ctypes.c_int
    return bool(malloc_trim(0))


class IdleTrim:
    """Trims the heap once each time the process falls idle: less than ``cpu_share`` of a core
    (all threads) for ``quiet_s``. :meth:`step` is called every ``poll_s`` with the process's
    CPU seconds and the clock."""

    def __init__(self, trim: Callable[[], object] = trim_heap, quiet_s: float = IDLE_S,
                 cpu_share: float = IDLE_CPU_SHARE) -> None:
        self.trim = trim
        self.quiet_s = quiet_s
        self.cpu_share = cpu_share
        self.trims = 0
        self._last: tuple[float, float] | None = None
        self._quiet_since: float | None = None
        self._trimmed = False

    def step(self, cpu_s: float, now_s: float) -> None:
        last, self._last = self._last, (cpu_s, now_s)
        if last is None or now_s <= last[1]:
            return
        if (cpu_s - last[0]) / (now_s - last[1]) >= self.cpu_share:
            self._quiet_since, self._trimmed = None, False
            return
        if self._quiet_since is None:
            self._quiet_since = last[1]
        if not self._trimmed and now_s - self._quiet_since >= self.quiet_s:
            self.trim()
            self.trims += 1
            self._trimmed = True
            self._last = None  # the next window holds the trim's own CPU: not a sign of work


def give_back_when_idle(poll_s: float = POLL_S) -> threading.Thread | None:
    """Start a daemon thread that trims the heap whenever the process falls idle (after
    :func:`keep_freed_memory`); None where the allocator has no ``malloc_trim``."""
    libc = _libc()
    if not sys.platform.startswith("linux") or libc is None or not hasattr(libc, "malloc_trim"):
        return None
    idle = IdleTrim()

    def run() -> None:
        while True:
            time.sleep(poll_s)
            idle.step(time.process_time(), time.monotonic())

    thread = threading.Thread(target=run, name="idle-trim", daemon=True)
    thread.start()
    return thread
