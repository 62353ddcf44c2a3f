"""The fused model's voxel means, accumulated station by station on disk.

The model is resampled on a grid of ``voxel_mm`` voxels aligned to the world origin: each
occupied voxel's point is the inverse-variance weighted mean of the points in it (weighted by
their own noise), with that mean's 1-sigma: the noise of the mean, ``1 / √Σw``, and the error
its points share (a station's pose), which no mean removes: the weighted mean of their common
1-sigma, as if the stations' pose errors were one (they share the tracker's location, the
hand-eye and the scanner's scale), added in quadrature. Each station adds its partial sums per
voxel (Σw, Σw·x, Σw·y, Σw·z, Σw·σc) to the file of the tile of ``tile_voxels``³ voxels
they fall in; at the end each tile is summed and averaged alone. Memory holds one station's
points while it is added and one tile while it is read: not the model, not the job.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np

#: points summed into voxels at a time: the sort behind the voxel keys holds ~8 of its (N,)
#: int64 arrays at once (0.25 GB for a full-size station's 3.5 M points in one go)
ADD_CHUNK = 1_000_000

#: one voxel's partial sums from one station: its index inside the tile and the sums
RECORD = np.dtype([("k", np.uint16, 3), ("w", np.float64), ("wp", np.float64, 3),
                   ("wc", np.float64)])


class VoxelTiles:
    def __init__(self, folder: str | Path, voxel_mm: float, tile_voxels: int = 512) -> None:
        if voxel_mm <= 0:
            raise ValueError(f"voxel_mm must be positive, got {voxel_mm}")
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.voxel_mm = float(voxel_mm)
        self.tile_voxels = int(tile_voxels)
        self.points_added = 0

    def add(self, points: np.ndarray, sigma: np.ndarray | None = None,
            common: np.ndarray | None = None) -> None:
        """Add (N, 3) world points (mm) with their own noise's 1-sigma (mm; None, non-finite
        or ≤ 0: the median weight of the others, or 1) and the 1-sigma of the error they share
        with the rest of their station (mm, their pose's; None: 0), :data:`ADD_CHUNK` at a
        time (a voxel's sums may then come in more than one record; :meth:`means` adds them
        all)."""
        p = np.asarray(points).reshape(-1, 3)
        if not len(p):
            return
        fallback = 1.0
        if sigma is not None:
            s = np.asarray(sigma).ravel()
            ok = np.isfinite(s) & (s > 0)
            fallback = 1.0 / float(np.median(s[ok])) ** 2 if ok.any() else 1.0
        for a in range(0, len(p), ADD_CHUNK):
            self._add(np.asarray(p[a:a + ADD_CHUNK], float),
                      None if sigma is None else np.asarray(s[a:a + ADD_CHUNK], float), fallback,
                      None if common is None else np.asarray(common[a:a + ADD_CHUNK], float))
        self.points_added += len(p)

    def _add(self, p: np.ndarray, s: np.ndarray | None, fallback: float,
             common: np.ndarray | None) -> None:
        w = np.ones(len(p))
        if s is not None:
            ok = np.isfinite(s) & (s > 0)
            w = np.where(ok, 1.0 / np.maximum(s, 1e-6) ** 2, fallback)
        # one int64 key per point over the station's own voxel box: a 1-D unique, where
        # np.unique(axis=0) on (N, 3) voxels held ~0.25 GB more for a full-size station
        k0 = np.floor(p.min(axis=0) / self.voxel_mm).astype(np.int64)
        dims = np.floor(p.max(axis=0) / self.voxel_mm).astype(np.int64) - k0 + 1
        key = np.zeros(len(p), np.int64)
        for a in range(3):
            key *= dims[a]
            key += np.floor(p[:, a] / self.voxel_mm).astype(np.int64) - k0[a]
        keys, inverse = np.unique(key, return_inverse=True)
        del key
        voxels = np.empty((len(keys), 3), np.int64)
        for a in (2, 1, 0):
            keys, voxels[:, a] = np.divmod(keys, dims[a])
        voxels += k0
        sums = np.empty(len(voxels), RECORD)
        sums["w"] = np.bincount(inverse, weights=w, minlength=len(voxels))
        for i in range(3):
            sums["wp"][:, i] = np.bincount(inverse, weights=w * p[:, i], minlength=len(voxels))
        sums["wc"] = 0.0 if common is None else np.bincount(
            inverse, weights=w * np.nan_to_num(common), minlength=len(voxels))
        tile = np.floor_divide(voxels, self.tile_voxels)
        sums["k"] = voxels - tile * self.tile_voxels
        # the tile as one int64 over the station's few tiles, as the voxel key above:
        # np.unique(axis=0) sorted the (M, 3) rows as 24-byte records, 2 s a full-size station
        t0 = tile.min(axis=0)
        tdims = tile.max(axis=0) - t0 + 1
        which = ((tile[:, 0] - t0[0]) * tdims[1] + tile[:, 1] - t0[1]) * tdims[2] + tile[:, 2] - t0[2]
        order = np.argsort(which, kind="stable")
        which = which[order]
        starts = np.flatnonzero(np.r_[True, which[1:] != which[:-1]])
        for lo, hi in zip(starts, np.r_[starts[1:], len(order)], strict=True):
            t = tile[order[lo]]
            with open(self.folder / f"{t[0]}_{t[1]}_{t[2]}.bin", "ab") as f:
                sums[order[lo:hi]].tofile(f)

    def means(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Tile by tile: (the occupied voxels' weighted means (M, 3) mm, their 1-sigma (M,) mm)."""
        return tile_means([self.folder], self.tile_voxels)

    def model(self) -> tuple[np.ndarray, np.ndarray]:
        """Every tile's means together: (points (M, 3) mm, 1-sigma (M,) mm)."""
        parts = list(self.means())
        if not parts:
            return np.zeros((0, 3)), np.zeros(0)
        return np.concatenate([p for p, _ in parts]), np.concatenate([s for _, s in parts])

    def remove(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)


def tile_means(folders: list[Path], tile_voxels: int = 512
               ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """:meth:`VoxelTiles.means` over the tiles of several folders of the same grid (one a
    station, written on other machines): each tile's records read folder by folder in the
    given order, which in station order are the records, in their order, of one folder fed
    the same stations: the same means to the bit."""
    names = sorted({p.name for f in folders for p in Path(f).glob("*.bin")})
    tv = tile_voxels
    for name in names:
        rec = np.concatenate([np.fromfile(Path(f) / name, RECORD) for f in folders
                              if (Path(f) / name).exists()])
        key = (rec["k"][:, 0].astype(np.int64) * tv + rec["k"][:, 1]) * tv + rec["k"][:, 2]
        _, inverse = np.unique(key, return_inverse=True)
        n = int(inverse.max()) + 1
        wsum = np.bincount(inverse, weights=rec["w"], minlength=n)
        mean = np.column_stack([np.bincount(inverse, weights=rec["wp"][:, i], minlength=n)
                                for i in range(3)]) / wsum[:, None]
        common = np.bincount(inverse, weights=rec["wc"], minlength=n) / wsum
        yield mean, np.sqrt(1.0 / wsum + common * common)
