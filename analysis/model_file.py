"""The fused model on disk: written once from the voxel tiles, then read chunk by chunk.

A record per fused point: its world position (float64, mm), the 1-sigma of its voxel mean
(float32, mm; NaN when the stations carried no uncertainty) and, in simulation, its true
distance to the part (float32, mm; NaN without a truth). The file's records are read in chunks
with ``np.fromfile`` (not a memory map, whose pages would count in the process's resident
set), so publishing, the PLY and E57 files, the true-error figures and the mesh's sample each
hold one chunk of the model at a time, however large the part (issue 37).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

RECORD = np.dtype([("p", "<f8", 3), ("sigma", "<f4"), ("true_error", "<f4")])
#: records per chunk: 24 MB of records, ~100 MB with the arrays computed from them
CHUNK = 1_000_000


class ModelFileError(ValueError):
    """An empty model or an unreadable model file; names the file."""


@dataclass
class ModelFile:
    path: Path
    count: int
    lo: np.ndarray  # (3,) mm: the model's bounding box
    hi: np.ndarray
    #: every point has a 1-sigma (the stations carried uncertainty)
    weighted: bool
    #: every point has its true error (simulation)
    has_truth: bool

    @classmethod
    def write(cls, path: str | Path, parts: Iterable[tuple[np.ndarray, np.ndarray | None]]
              ) -> ModelFile:
        """Write ``parts``, each (points (M, 3) world mm, their 1-sigma (M,) mm or None), to
        ``path``."""
        p = Path(path)
        count, weighted = 0, True
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        with open(p, "wb") as f:
            for points, sigma in parts:
                for a in range(0, len(points), CHUNK):
                    pts = np.asarray(points[a:a + CHUNK], float)
                    rec = np.empty(len(pts), RECORD)
                    rec["p"] = pts
                    if sigma is None:
                        weighted = False
                        rec["sigma"] = np.nan
                    else:
                        rec["sigma"] = sigma[a:a + CHUNK]
                    rec["true_error"] = np.nan
                    rec.tofile(f)
                    count += len(pts)
                    lo, hi = np.minimum(lo, pts.min(axis=0)), np.maximum(hi, pts.max(axis=0))
        if not count:
            p.unlink(missing_ok=True)
            raise ModelFileError(f"{p}: the model has no points")
        return cls(p, count, lo, hi, weighted, False)

    def add_truth(self, truth: Callable[[np.ndarray], np.ndarray]) -> None:
        """Fill each point's true error, ``|truth(points)|`` (``truth``: world points (M, 3)
        mm -> signed distances to the true surface, mm), chunk by chunk in place."""
        with open(self.path, "r+b") as f:
            for a, rec in zip(range(0, self.count, CHUNK), self.chunks(), strict=True):
                rec["true_error"] = np.abs(truth(rec["p"]))
                f.seek(a * RECORD.itemsize)
                rec.tofile(f)
        self.has_truth = True

    def chunks(self, size: int | None = None) -> Iterator[np.ndarray]:
        """The records, ``size`` (default :data:`CHUNK`) at a time (structured arrays of
        :data:`RECORD`)."""
        size = size or CHUNK
        with open(self.path, "rb") as f:
            for a in range(0, self.count, size):
                rec = np.fromfile(f, RECORD, min(size, self.count - a))
                if len(rec) != min(size, self.count - a):
                    raise ModelFileError(f"{self.path}: ends after {a + len(rec)} of "
                                         f"{self.count} points")
                yield rec

    def sample(self, n: int) -> np.ndarray:
        """An even sample of about ``n`` points (every k-th record), (M, 3) mm."""
        k = max(1, -(-self.count // max(1, n)))
        step = max(k, CHUNK - CHUNK % k)  # chunks a multiple of k keep the stride even
        return np.concatenate([rec["p"][::k] for rec in self.chunks(step)])

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)
