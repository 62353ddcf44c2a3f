"""Stations on disk: a job's clouds kept out of memory while it measures.

Each station's world points (float32, mm), unit normals (float32) and per-point 1-sigma
(float32, mm) go to ``.npy`` files in a folder; memory keeps only each station's bounding box
and point count. A station is read back whole or only the part inside a box, through a memory
map that is closed straight after (its pages leave the process's resident set with it).

float32 holds a world coordinate of up to 8 m to 0.5 µm: far below the scanner's noise
(~0.02 mm). Normals stay float32 too: float16 rounds a component near 1 by 0.0005, which moved
the overlap's mean rotation error (~0.05°) by half of itself.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class StoredStation:
    index: int
    count: int
    lo: np.ndarray  # (3,) mm: the points' bounding box
    hi: np.ndarray
    normals: bool
    uncertainty: bool


class StationStore:
    """A folder of station clouds (created if missing; :meth:`remove` deletes it)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.stations: dict[str, StoredStation] = {}

    def _path(self, name: str, field: str) -> Path:
        return self.folder / f"{self.stations[name].index:05d}.{field}.npy"

    def put(self, name: str, points: np.ndarray, normals: np.ndarray | None = None,
            uncertainty: np.ndarray | None = None) -> StoredStation:
        """Write station ``name`` (replacing one of that name); raises OSError on a full disk."""
        pts = np.asarray(points, np.float32).reshape(-1, 3)
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

    def load(self, name: str, lo: np.ndarray | None = None, hi: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(points (N, 3), normals or None, 1-sigma or None) of station ``name``, float32 as
        stored: all of them, or those inside the box [lo, hi]."""
        st = self.stations[name]
        pts = np.load(self._path(name, "points"), mmap_mode="r")
        if lo is None:
            idx = slice(None)
        else:
            inside = np.ones(len(pts), bool)
            for k in range(3):
                col = pts[:, k]
                inside &= (col >= lo[k]) & (col <= hi[k])
            idx = np.flatnonzero(inside)
        out_pts = np.asarray(pts[idx])
        del pts
        out = [out_pts]
        for field, present in (("normals", st.normals), ("uncertainty", st.uncertainty)):
            if not present:
                out.append(None)
                continue
            arr = np.load(self._path(name, field), mmap_mode="r")
            out.append(np.asarray(arr[idx]))
            del arr
        return out[0], out[1], out[2]

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
        self.stations.clear()
