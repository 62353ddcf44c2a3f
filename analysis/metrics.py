"""The seed paper's metric tool for overlapping clouds (Section 3.2).

For clouds PC1, PC2 (same frame, mm): mean point spacing dm of PC1; neighbourhood radius
r = k·dm (k = 6); at each point C1 of PC1 the least-squares plane of its r-neighbourhood gives
the normal n1; C2 is the nearest point of PC2 and n2 its normal (same construction in PC2).
Translation error d = |C1C2|·|cos∠(n1, C1C2)| (the distance from C2 to C1's tangent plane);
rotation error = the angle between the two normals. Only points of PC1 whose nearest PC2 point
lies within r count as overlap.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scancell.analysis.grid_kernels import CellGrid, grid_nearest, grid_normals, in_box
from scipy.spatial import cKDTree


class MetricsError(ValueError):
    """Empty, non-finite or non-overlapping clouds; the message says which."""


def mean_spacing(points: np.ndarray, sample: int = 20000, seed: int = 0) -> float:
    """Mean distance (mm) of a point to its nearest neighbour in the same cloud."""
    p = np.asarray(points, float)
    if len(p) < 2:
        raise MetricsError(f"a cloud of {len(p)} point(s) has no spacing")
    rng = np.random.default_rng(seed)
    idx = rng.choice(len(p), size=min(sample, len(p)), replace=False)
    d, _ = cKDTree(p).query(p[idx], k=2, workers=-1)
    return float(np.mean(d[:, 1]))


def normals(points: np.ndarray, radius: float, grid: CellGrid | None = None) -> np.ndarray:
    """Unit normals of the least-squares plane of each point's ``radius`` neighbourhood (all
    points within r; r = 6 x the spacing holds ~28 on a surface). Fewer than 3: +z.

    On a grid of cells of size r (:mod:`scancell.analysis.grid_kernels`). Measured in
    bench_metrics on 1 M points: Open3D's ``estimate_normals`` 12.7 s, a scipy k-d tree query
    plus a covariance kernel 5 s; the grid takes well under a second.
    """
    p = np.ascontiguousarray(points, dtype=np.float64)
    g = grid or CellGrid(p, radius)
    out = np.empty_like(p)
    count = np.empty(len(p), np.int32)
    grid_normals(g.sorted, g.order, g.cell_keys, g.cell_start, g.cell_end, g.dims, float(radius),
                 out, count)
    return out


def nearest_within(grid: CellGrid, query: np.ndarray, radius: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """For every query point the nearest grid point within ``radius``: (distance, index into the
    grid's points in their original order); inf and -1 where there is none."""
    q = np.ascontiguousarray(query, dtype=np.float64)
    idx = np.empty(len(q), np.int64)
    dist = np.empty(len(q), np.float64)
    grid_nearest(q, grid.sorted, grid.cell_keys, grid.cell_start, grid.cell_end, grid.origin,
                 grid.cell, grid.dims, float(radius), idx, dist)
    return dist, np.where(idx >= 0, grid.order[np.maximum(idx, 0)], -1)


@dataclass
class PairMetrics:
    a: str
    b: str
    n: int  # points of A in overlap with B
    translation_mm: np.ndarray = field(repr=False)
    rotation_deg: np.ndarray = field(repr=False)
    #: per overlap point sqrt(σ_A² + σ_B²) of the two points compared (mm); None if unknown
    sigma_mm: np.ndarray | None = field(default=None, repr=False)

    def summary(self) -> dict[str, float | int | str]:
        return {"a": self.a, "b": self.b, "n": self.n,
                "translation_mean_mm": float(self.translation_mm.mean()) if self.n else None,
                "rotation_mean_deg": float(self.rotation_deg.mean()) if self.n else None}


def _check(name: str, pts: np.ndarray) -> np.ndarray:
    p = np.asarray(pts, float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise MetricsError(f"{name}: empty cloud or not (N, 3) points")
    bad = ~np.all(np.isfinite(p), axis=1)
    if bad.any():
        raise MetricsError(f"{name}: {int(bad.sum())} points are NaN or infinite (first at index "
                           f"{int(np.flatnonzero(bad)[0])})")
    return p


def _pair(a: np.ndarray, b: np.ndarray, radius: float, names: tuple[str, str], na: np.ndarray,
          nb: np.ndarray, grid_b: CellGrid, ua: np.ndarray | None = None,
          ub: np.ndarray | None = None) -> PairMetrics:
    # only A's points within r of B's grid can overlap it: most station pairs share none
    near = in_box(a, *grid_b.bounds(radius))
    dist, j = nearest_within(grid_b, a[near], radius)
    hit = np.isfinite(dist)
    if not hit.any():
        return PairMetrics(*names, 0, np.zeros(0), np.zeros(0))
    overlap, j = near[hit], j[hit]
    sigma = np.hypot(ua[overlap], ub[j]) if ua is not None and ub is not None else None
    c1, n1 = a[overlap], na[overlap]
    c2, n2 = b[j], nb[j]
    v = c2 - c1
    d = np.abs(np.einsum("ij,ij->i", v, n1))  # |C1C2|·|cos∠(n1, C1C2)|
    cos = np.clip(np.abs(np.einsum("ij,ij->i", n1, n2)), 0.0, 1.0)  # normals' sign is arbitrary
    return PairMetrics(*names, len(overlap), d, np.degrees(np.arccos(cos)), sigma)


@dataclass
class MetricsReport:
    radius_mm: float
    spacing_mm: float
    pairs: list[PairMetrics]

    def values(self) -> tuple[np.ndarray, np.ndarray]:
        d = np.concatenate([p.translation_mm for p in self.pairs]) if self.pairs else np.zeros(0)
        r = np.concatenate([p.rotation_deg for p in self.pairs]) if self.pairs else np.zeros(0)
        return d, r

    def sigmas(self) -> np.ndarray | None:
        """sqrt(σ_A² + σ_B²) of every overlap point, if every pair has it."""
        if not self.pairs or any(p.sigma_mm is None for p in self.pairs if p.n):
            return None
        return np.concatenate([p.sigma_mm for p in self.pairs if p.n])

    def to_json(self) -> dict:
        d, r = self.values()
        if len(d) == 0:
            raise MetricsError("no overlap between any pair of clouds")
        translation = {"max": float(d.max()), "min": float(d.min()), "mean": float(d.mean()),
                       "std": float(d.std()), "p_lt_0_6": float(np.mean(d < 0.6)),
                       "p_lt_1_0": float(np.mean(d < 1.0))}
        s = self.sigmas()
        if s is not None and len(s) == len(d):
            ok = np.isfinite(s) & (s > 0)
            if ok.any():
                w = 1.0 / s[ok] ** 2
                # inverse-variance weighted mean; and the errors in units of their own noise
                # (a median near 0.67 means the overlap errors are the scanner's noise alone)
                translation["weighted_mean"] = float(np.sum(w * d[ok]) / np.sum(w))
                translation["normalised_median"] = float(np.median(d[ok] / s[ok]))
                translation["expected_mean"] = float(np.mean(s[ok]) * np.sqrt(2 / np.pi))
        return {
            "translation_mm": translation,
            "rotation_deg": {"max": float(r.max()), "min": float(r.min()), "mean": float(r.mean()),
                             "std": float(r.std()), "p_lt_10": float(np.mean(r < 10.0))},
            "pairs": [p.summary() for p in self.pairs],
            "radius_mm": self.radius_mm, "spacing_mm": self.spacing_mm,
        }


class OverlapComparer:
    """The metric tool one cloud at a time, as a fuse worker receives stations: each cloud
    added is compared with every cloud added before it (the ordered pair (earlier, new)), so
    a job's pairs are done while it measures. The neighbourhood radius is ``radius_factor``
    x the mean spacing of the first cloud. Only a cloud's points, normals and uncertainty are
    kept; its grid serves the pairs of its own ``add``."""

    def __init__(self, radius_factor: float = 6.0) -> None:
        self.radius_factor = radius_factor
        self.spacing_mm: float | None = None
        self.radius_mm: float | None = None
        self.pairs: list[PairMetrics] = []
        self._clouds: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]] = {}
        self._boxes: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # name -> its cells' box

    @property
    def names(self) -> list[str]:
        return list(self._clouds)

    def add(self, name: str, points: np.ndarray, uncertainty: np.ndarray | None = None) -> None:
        """Compare cloud ``name`` (N, 3, mm, the others' frame) with every cloud before it.
        ``uncertainty``: per-point 1-sigma (mm), or None."""
        if name in self._clouds:
            raise MetricsError(f"{name}: added twice")
        p = _check(name, points)
        if self.radius_mm is None:
            self.spacing_mm = mean_spacing(p)
            self.radius_mm = self.radius_factor * self.spacing_mm
        r = self.radius_mm
        grid = CellGrid(p, r)
        nrm = normals(p, r, grid)
        box = grid.bounds(r)
        for a, (pa, na, ua) in self._clouds.items():
            lo, hi = self._boxes[a]
            if np.any(lo > box[1]) or np.any(hi < box[0]):  # too far apart to overlap
                self.pairs.append(PairMetrics(a, name, 0, np.zeros(0), np.zeros(0)))
                continue
            self.pairs.append(_pair(pa, p, r, (a, name), na, nrm, grid, ua, uncertainty))
        self._clouds[name] = (p, nrm, uncertainty)
        self._boxes[name] = grid.bounds()

    def report(self) -> MetricsReport:
        """Every pair so far, in the order the clouds were added; raises MetricsError with
        fewer than two clouds or none overlapping."""
        names = self.names
        if len(names) < 2:
            raise MetricsError(f"need at least two clouds, got {len(names)}")
        if not any(p.n for p in self.pairs):
            raise MetricsError(f"no overlap: no point of one cloud is within r = "
                               f"{self.radius_mm:.3f} mm ({self.radius_factor:g} x the mean "
                               f"spacing {self.spacing_mm:.3f} mm) of another cloud "
                               f"({', '.join(names)}); same frame and units?")
        order = {n: i for i, n in enumerate(names)}
        pairs = sorted(self.pairs, key=lambda m: (order[m.a], order[m.b]))
        return MetricsReport(self.radius_mm, self.spacing_mm, pairs)


def compare_clouds(clouds: dict[str, np.ndarray], radius_factor: float = 6.0,
                   uncertainty: dict[str, np.ndarray] | None = None) -> MetricsReport:
    """Every ordered pair (A, B), A before B in the given order, that overlaps. With
    ``uncertainty`` (per-point 1-sigma, mm, for every cloud) the report adds the
    inverse-variance weighted mean of the translation error."""
    if len(clouds) < 2:
        raise MetricsError(f"need at least two clouds, got {len(clouds)}")
    pts = {name: _check(name, p) for name, p in clouds.items()}
    comparer = OverlapComparer(radius_factor)
    for name, p in pts.items():
        comparer.add(name, p, uncertainty.get(name) if uncertainty else None)
    return comparer.report()


def histograms(report: MetricsReport, folder: str) -> list[str]:
    """PNG histograms of the translation and rotation errors, as the paper's Figure 11."""
    import matplotlib

    matplotlib.use("Agg")
    from pathlib import Path

    import matplotlib.pyplot as plt

    d, r = report.values()
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for values, name, unit, marks in ((d, "translation_error", "mm", (0.6, 1.0)),
                                      (r, "rotation_error", "deg", (10.0,))):
        fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
        ax.hist(values, bins=60, color="#3b6ea8")
        for m, style in zip(marks, ("--", ":"), strict=False):
            ax.axvline(m, color="#c0392b", ls=style, lw=1,
                       label=f"{np.mean(values < m):.2%} of points < {m:g} {unit}")
        ax.legend(fontsize=8, loc="upper right")
        ax.set_xlabel(f"{name.replace('_', ' ')} ({unit})")
        ax.set_ylabel("points")
        ax.set_title(f"{name.replace('_', ' ')}: mean {values.mean():.4f} {unit}, "
                     f"std {values.std():.4f}, n = {len(values)}", fontsize=9)
        fig.tight_layout()
        path = out / f"{name}.png"
        fig.savefig(path)
        plt.close(fig)
        files.append(str(path))
    return files
