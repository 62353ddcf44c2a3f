"""The inspection's deviation over a Dask cluster: one task per tile of the measured cloud.

``scancell inspect --scheduler`` aligns the cloud here (the alignment iterates on at most 1 M
points), then sends the cloud's tiles (:data:`scancell.analysis.deviation.CHUNK` points each,
moved to the part frame on the worker) to the cluster: each worker finds its tile's closest
points on the nominal, which it loads once from the same path (a STEP's tessellation comes from
the cache, ``scancell.analysis.tessellation_cache``). The answers are put together here, bit for
bit what the inspection computes alone (each point's answer depends on that point only); the
tolerances, coverage and sections follow here.

At most two tiles per worker are in flight, so the cloud is never copied whole to the cluster.
The nominal must be at the same path on the workers' hosts (one machine, or shared storage); a
worker that finds a different file there fails the inspection with its name.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.deviation import Tile, TileRunner, closest_tile
from scancell.analysis.nominal import Nominal, load_nominal

#: tiles in flight per worker: one computing, one on its way
IN_FLIGHT_PER_WORKER = 2


class ClusterInspectionError(RuntimeError):
    """A tile could not be computed on the cluster (the worker and why)."""


@lru_cache(maxsize=2)
def _nominal(source: str, stamp: tuple[int, int], unit: str | None, chordal_mm: float | None
             ) -> Nominal:
    if chordal_mm is None:  # a mesh, in the unit given
        return load_nominal(source, unit)
    return load_nominal(source, None, chordal_mm)  # a STEP states its own unit


def deviation_tile(source: str, unit: str | None, chordal_mm: float | None, triangles: int,
                   points: np.ndarray, T: np.ndarray | None, dtype: str,
                   within_mm: float | None) -> Tile:
    """On a worker: :func:`closest_tile` of ``points`` against the nominal at ``source``
    (loaded once per worker process and file version); refused when that file's tessellation
    has not ``triangles`` triangles (another file at the same path)."""
    st = os.stat(source)
    nominal = _nominal(source, (st.st_mtime_ns, st.st_size), unit, chordal_mm)
    if len(nominal.triangles) != triangles:
        raise ClusterInspectionError(
            f"{source}: {len(nominal.triangles)} triangles on this worker, {triangles} where the "
            f"inspection runs: not the same nominal")
    return closest_tile(nominal, points, T, np.dtype(dtype).type, within_mm)


def cluster_tiles(client: Any) -> TileRunner:
    """A :data:`TileRunner` that computes the tiles on ``client``'s cluster."""

    def run(nominal: Nominal, points: np.ndarray, tiles: list[slice], T: np.ndarray | None,
            dtype: type, within_mm: float | None):
        from distributed import as_completed

        if not Path(nominal.source).is_file():
            raise ClusterInspectionError(f"the nominal {nominal.source!r} is not a file the "
                                         f"cluster's workers can load")
        args = (str(Path(nominal.source).resolve()), nominal.unit, nominal.chordal_tolerance_mm,
                len(nominal.triangles))
        workers = max(1, len(client.scheduler_info()["workers"]))
        pending = iter(tiles)
        futures: dict[Any, slice] = {}

        def submit() -> Any | None:
            tile = next(pending, None)
            if tile is None:
                return None
            fut = client.submit(deviation_tile, *args, np.ascontiguousarray(points[tile]), T,
                                np.dtype(dtype).name, within_mm, pure=False)
            futures[fut] = tile
            return fut

        queue = as_completed([f for f in (submit() for _ in range(IN_FLIGHT_PER_WORKER * workers))
                              if f is not None])
        for fut in queue:
            tile = futures.pop(fut)
            try:
                answer = fut.result()
            except ClusterInspectionError:
                raise
            except Exception as exc:  # KilledWorker after too many deaths, a worker-side error
                raise ClusterInspectionError(f"points {tile.start}-{tile.stop - 1}: "
                                             f"{type(exc).__name__}: {exc}") from None
            fut.release()
            nxt = submit()
            if nxt is not None:
                queue.add(nxt)
            yield tile, answer

    return run
