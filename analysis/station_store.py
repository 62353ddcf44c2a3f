"""Stations on disk: a job's clouds kept out of memory while it measures.

Each station's points (float32, mm), unit normals (float32) and per-point 1-sigma
(float32, mm) go to ``.npy`` files in a folder; memory keeps only each station's bounding box
and point count. A station is read back whole (through a memory map) or only the part inside a
box, read :data:`READ_CHUNK` rows at a time with plain reads, so the process holds one chunk of
the file and the rows kept rather than every mapped page it has touched. A
job's world points are not a second copy: :class:`WorldFromMcs` moves its MCS points by each
station's pose as they are read, and keeps only their normals.

float32 holds a world coordinate of up to 8 m to 0.5 µm: far below the scanner's noise
(~0.02 mm). Normals stay float32 too: float16 rounds a component near 1 by 0.0005, which moved
the overlap's mean rotation error (~0.05°) by half of itself.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
from scancell.analysis.grid_kernels import in_box


@dataclass(frozen=True)
class StoredStation:
    index: int
    count: int
    lo: np.ndarray  # (3,) mm: the points' bounding box
    hi: np.ndarray
    normals: bool
    uncertainty: bool


#: rows of a ``.npy`` file read at a time by :func:`npy_chunks` (12 MB of float32 points)
READ_CHUNK = 1 << 20


def _npy_header(f: BinaryIO, path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """The (shape, dtype) of the C-ordered ``.npy`` array whose file ``f`` is at its start; the
    file is left at the first byte of data. Raises ValueError on anything else."""
    fmt = np.lib.format
    version = fmt.read_magic(f)
    if version not in ((1, 0), (2, 0)):
        raise ValueError(f"{path}: .npy format version {version} is not read here")
    header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
    shape, fortran, dtype = header(f)
    if fortran or not shape:
        raise ValueError(f"{path}: a Fortran-ordered or 0-d array, not a station field")
    return shape, dtype


def npy_chunks(path: Path, chunk: int = READ_CHUNK) -> Iterator[tuple[int, np.ndarray]]:
    """(index of the first row, rows) of the ``.npy`` array at ``path``, ``chunk`` rows at a
    time, read with plain reads. Raises ValueError on a file that is not a C-ordered ``.npy``
    or ends early."""
    with open(path, "rb") as f:
        shape, dtype = _npy_header(f, path)
        row_items = int(np.prod(shape[1:], dtype=np.int64))
        for first in range(0, shape[0], chunk):
            n = min(chunk, shape[0] - first)
            rows = np.fromfile(f, dtype, n * row_items)
            if len(rows) != n * row_items:
                raise ValueError(f"{path}: ends within rows {first}..{first + n} of {shape[0]}")
            yield first, rows.reshape((n, *shape[1:]))


def read_rows(path: Path, idx: np.ndarray | slice, chunk: int = READ_CHUNK) -> np.ndarray:
    """The rows ``idx`` (ascending indices, or ``slice(None)`` for all) of the ``.npy`` array at
    ``path``: all of them through a memory map, a subset chunk by chunk (:func:`npy_chunks`).
    Raises IndexError on an index outside the array."""
    if isinstance(idx, slice):
        return np.asarray(np.load(path, mmap_mode="r")[idx])
    idx = np.asarray(idx, np.int64)
    with open(path, "rb") as f:
        shape, dtype = _npy_header(f, path)
    if len(idx) and (idx[0] < 0 or idx[-1] >= shape[0]):
        raise IndexError(f"{path}: rows {idx[0]}..{idx[-1]} asked of {shape[0]}")
    out = np.empty((len(idx), *shape[1:]), dtype)
    if len(idx):
        for first, rows in npy_chunks(path, chunk):
            a, b = np.searchsorted(idx, (first, first + len(rows)))
            out[a:b] = rows[idx[a:b] - first]
    return out


class StationStore:
    """A folder of station clouds (created if missing; :meth:`remove` deletes it)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.stations: dict[str, StoredStation] = {}

    def _path(self, name: str, field: str) -> Path:
        return self.folder / f"{self.stations[name].index:05d}.{field}.npy"

    def put(self, name: str, points: np.ndarray, normals: np.ndarray | None = None,
            uncertainty: np.ndarray | None = None, index: int | None = None) -> StoredStation:
        """Write station ``name`` (replacing one of that name) as file number ``index`` (by
        default its place in this store); raises OSError on a full disk, ValueError when the
        normals or 1-sigma are not one a point."""
        pts = np.asarray(points, np.float32).reshape(-1, 3)
        for field, arr in (("normals", normals), ("1-sigma", uncertainty)):
            if arr is not None and len(arr) != len(pts):
                raise ValueError(f"station {name}: {len(arr)} {field} for {len(pts)} points")
        if index is None:
            index = self.stations[name].index if name in self.stations else len(self.stations)
        st = StoredStation(index, len(pts), pts.min(axis=0) if len(pts) else np.zeros(3, np.float32),
                           pts.max(axis=0) if len(pts) else np.zeros(3, np.float32),
                           normals is not None, uncertainty is not None)
        self.stations[name] = st
        np.save(self._path(name, "points"), pts)
        if normals is not None:
            np.save(self._path(name, "normals"), np.asarray(normals, np.float32))
        if uncertainty is not None:
            np.save(self._path(name, "uncertainty"), np.asarray(uncertainty, np.float32))
        return st

    def adopt(self, name: str, stored: StoredStation) -> None:
        """Know station ``name`` as another process wrote it into this folder."""
        self.stations[name] = stored

    def inside(self, name: str, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """The indices (ascending) of station ``name``'s points inside the box [lo, hi] (mm)."""
        lo64, hi64 = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        found = [first + in_box(rows, lo64, hi64)
                 for first, rows in npy_chunks(self._path(name, "points"))]
        return np.concatenate(found) if found else np.empty(0, np.int64)

    def load(self, name: str, lo: np.ndarray | None = None, hi: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(points (N, 3), normals or None, 1-sigma or None) of station ``name``, float32 as
        stored: all of them, or those inside the box [lo, hi]."""
        return self.select(name, slice(None) if lo is None else self.inside(name, lo, hi))

    def select(self, name: str, idx: np.ndarray | slice
               ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(points, normals or None, 1-sigma or None) of station ``name`` at ``idx``."""
        st = self.stations[name]
        out: list[np.ndarray | None] = []
        for field, present in (("points", True), ("normals", st.normals),
                               ("uncertainty", st.uncertainty)):
            if not present:
                out.append(None)
                continue
            out.append(read_rows(self._path(name, field), idx))
        return out[0], out[1], out[2]

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
        self.stations.clear()


#: points moved at a time by :func:`move_points` into its float32 result
MOVE_CHUNK = 1 << 20


def move_points(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(N, 3) points (mm) moved by the rigid 4 x 4 ``T``, as float32 (0.25 µm steps at 3 m).

    Each coordinate is ``x·T[i,0] + y·T[i,1] + z·T[i,2] + T[i,3]`` in float64, in that order,
    rounded once: element by element, not a BLAS product (whose kernels may sum a row
    differently with the batch's size), so any subset of a cloud moved alone gets the same
    bits as when it was moved with the whole cloud (:class:`WorldFromMcs` relies on it)."""
    T = np.asarray(T, np.float64)
    out = np.empty((len(points), 3), np.float32)
    for lo in range(0, len(points), MOVE_CHUNK):
        p = np.asarray(points[lo:lo + MOVE_CHUNK], np.float64)
        for i in range(3):
            out[lo:lo + MOVE_CHUNK, i] = (p[:, 0] * T[i, 0] + p[:, 1] * T[i, 1]
                                          + p[:, 2] * T[i, 2] + T[i, 3])
    return out


#: the margin (mm) by which a world box is widened once moved into a station's MCS: more than
#: float32's rounding of a world coordinate (≤ 0.25 µm within 8 m), so no point is missed
BOX_MARGIN_MM = 1e-3


class WorldFromMcs:
    """A job's stations in world for the overlap metric, derived from their clouds in the
    MCS store: only the world normals are written here (12 bytes a point); the points and
    their 1-sigma are read from ``mcs`` and moved by each station's pose (:meth:`place`), to
    the same float32 bits as the world points first given (:func:`move_points`). It saves
    the 16 bytes a point that a second copy of the points and 1-sigma cost on disk.

    ``every``: the overlap keeps every ``every``-th point of a station
    (:func:`~scancell.analysis.metrics.kept_cloud`): ``put`` takes and ``load`` gives those.

    The interface of :class:`StationStore` that
    :class:`~scancell.analysis.metrics.OverlapComparer` uses: ``put`` and ``load``."""

    def __init__(self, mcs: StationStore, folder: str | Path, every: int = 1) -> None:
        self.mcs = mcs
        self.every = int(every)
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.poses: dict[str, np.ndarray] = {}

    def place(self, name: str, T_world_from_mcs: np.ndarray) -> None:
        """Station ``name``'s pose: its MCS points through it are its world points (mm)."""
        self.poses[name] = np.asarray(T_world_from_mcs, np.float64).copy()

    def put(self, name: str, points: np.ndarray, normals: np.ndarray | None = None,
            uncertainty: np.ndarray | None = None) -> None:
        """Keep station ``name``'s world normals; ``points`` must be its MCS cloud's kept rows
        (every ``every``-th) moved by its pose (their count is checked; raises ValueError),
        ``uncertainty`` the 1-sigma stored with it (not written again). Raises OSError on a
        full disk."""
        if name not in self.poses or name not in self.mcs.stations:
            raise ValueError(f"station {name}: no pose placed or no MCS cloud stored")
        count = len(range(0, self.mcs.stations[name].count, self.every))
        if len(points) != count or normals is None or len(normals) != count:
            raise ValueError(f"station {name}: {len(points)} world points and "
                             f"{0 if normals is None else len(normals)} normals for the "
                             f"{count} kept of its MCS cloud (every {self.every})")
        np.save(self._normals(name), np.asarray(normals, np.float32))

    def load(self, name: str, lo: np.ndarray | None = None, hi: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """(world points (N, 3) float32, normals, 1-sigma or None) of station ``name``'s kept
        points: all of them, or those inside the world box [lo, hi] (mm), in their order."""
        T = self.poses[name]
        if lo is None:
            idx: np.ndarray | slice = slice(None, None, self.every)
        else:
            corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                                for z in (lo[2], hi[2])], np.float64)
            back = np.linalg.inv(T)
            c = corners @ back[:3, :3].T + back[:3, 3]
            idx = self.mcs.inside(name, c.min(axis=0) - BOX_MARGIN_MM,
                                  c.max(axis=0) + BOX_MARGIN_MM)
            idx = idx[idx % self.every == 0]
        pts, _, unc = self.mcs.select(name, idx)
        world = move_points(pts, T)
        del pts
        if lo is not None:
            keep = in_box(world, np.asarray(lo, np.float64), np.asarray(hi, np.float64))
            idx, world = idx[keep], world[keep]
            unc = None if unc is None else unc[keep]
        return world, read_rows(self._normals(name), idx // self.every if lo is not None
                                else slice(None)), unc

    def full(self, name: str) -> tuple[np.ndarray, np.ndarray | None]:
        """(every world point (N, 3) float32, 1-sigma or None) of station ``name``, kept or
        not: the later station of a pair seeks its nearest points among all of them."""
        pts, _, unc = self.mcs.select(name, slice(None))
        return move_points(pts, self.poses[name]), unc

    def _normals(self, name: str) -> Path:
        return self.folder / f"{self.mcs.stations[name].index:05d}.normals.npy"
