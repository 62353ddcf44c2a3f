"""The seed paper's metric tool for overlapping clouds (Section 3.2).

For clouds PC1, PC2 (same frame, mm): mean point spacing dm of PC1; neighbourhood radius
r = k·dm (k = 6); at each point C1 of PC1 the least-squares plane of its r-neighbourhood gives
the normal n1; C2 is the nearest point of PC2 and n2 its normal (same construction in PC2).
Translation error d = |C1C2|·|cos∠(n1, C1C2)| (the distance from C2 to C1's tangent plane);
rotation error = the angle between the two normals. Only points of PC1 whose nearest PC2 point
lies within r count as overlap.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scancell.analysis.grid_kernels import (
    CellGrid,
    float_type,
    grid_nearest,
    grid_normals,
    grid_normals_of,
    in_box,
)
from scancell.analysis.station_store import StationStore, WorldFromMcs
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
    points within r). Fewer than 3: +z. At r = 6 x :func:`mean_spacing` a neighbourhood holds
    ~28 points where they lie at random (nearest neighbour ~0.5 / √density), but π·6² ≈ 113 on
    a scanner's pixel grid (nearest neighbour = the pitch: the car body's stations, 84-101 by
    median): there the normals are most of a fuse worker's time.

    On a grid of cells of size r (:mod:`scancell.analysis.grid_kernels`). Measured in
    bench_metrics on 1 M points: Open3D's ``estimate_normals`` 12.7 s, a scipy k-d tree query
    plus a covariance kernel 5 s; the grid takes well under a second.
    """
    p = np.ascontiguousarray(points, dtype=float_type(points))
    g = grid or CellGrid(p, radius)
    out = np.empty_like(p)
    count = np.empty(len(p), np.int32)
    grid_normals(g.sorted, g.order, g.cell_keys, g.cell_start, g.cell_end, g.dims, float(radius),
                 out, count)
    return out


class NormalsOnDemand:
    """The :func:`normals` of ``points`` (those ``grid`` holds, in their own order), each
    worked out the first time it is asked for (``[idx]``) and kept: the overlap metric needs
    a new station's normals only where an earlier station's points meet it, and at the
    points it keeps for the stations after it. Each one has the bits :func:`normals` gives
    it."""

    def __init__(self, points: np.ndarray, grid: CellGrid, radius: float) -> None:
        self.points, self.grid, self.radius = points, grid, float(radius)
        n = len(points)
        self.values = np.zeros((n, 3), grid.sorted.dtype)
        self.done = np.zeros(n, bool)

    def __getitem__(self, idx: np.ndarray) -> np.ndarray:
        idx = np.asarray(idx, np.int64)
        # the rows still to do, each once and in order, by a mask: np.unique hashed a station's
        # ~1 M kept rows for 1.5 s
        need = np.zeros(len(self.done), bool)
        need[idx] = True
        need &= ~self.done
        todo = np.flatnonzero(need)
        if len(todo):
            g = self.grid
            out = np.empty((len(todo), 3), g.sorted.dtype)
            grid_normals_of(np.ascontiguousarray(self.points[todo], g.sorted.dtype), g.sorted,
                            g.cell_keys, g.cell_start, g.cell_end, g.origin, g.cell, g.dims,
                            self.radius, out)
            self.values[todo] = out
            self.done[todo] = True
        return self.values[idx]


def local_plane_distance(points: np.ndarray, reference: np.ndarray, reach_mm: float,
                         min_points: int = 6, k: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Each point's distance (mm) to the least-squares plane of the reference's points within
    ``reach_mm`` of it (its ``k`` nearest at most), as CloudCompare's cloud-to-cloud distance
    with a local plane model does: a sparse reference (stripe edges, a scan line's points) is
    a surface there, not a set of points to be near. Points with fewer than ``min_points``
    reference points in reach are unsupported: distance NaN, and False in the second array."""
    d, idx = cKDTree(reference).query(points, k=k, distance_upper_bound=reach_mm, workers=2)
    near = np.isfinite(d)
    supported = near.sum(axis=1) >= min_points
    out = np.full(len(points), np.nan)
    w = near[supported][..., None]
    nb = reference[np.where(near[supported], idx[supported], 0)]
    centre = (nb * w).sum(axis=1) / w.sum(axis=1)
    x = (nb - centre[:, None]) * w
    normal = np.linalg.eigh(np.einsum("nki,nkj->nij", x, x))[1][:, :, 0]
    out[supported] = np.abs(np.einsum("ni,ni->n", points[supported] - centre, normal))
    return out, supported


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


class Distribution:
    """A streaming summary of non-negative values: count, sum, sum of squares, extremes, the
    share below each of ``marks``, and a fixed-bin histogram (``bins`` bins over [0, ``top``),
    the last one holding everything beyond) for the pictures and the median. A job's overlap
    errors are summed station by station without keeping them (issue 37: a whole car body has
    ~10^9 of them)."""

    def __init__(self, top: float, bins: int, marks: tuple[float, ...] = ()) -> None:
        self.top, self.bins, self.marks = float(top), int(bins), tuple(marks)
        self.n = 0
        #: each add's sum and sum of squares, added up exactly (math.fsum) when asked: the
        #: figures do not depend on the order the pairs came in (live, as stations arrive, or
        #: reprocessed from a recording)
        self._sums: list[float] = []
        self._squares: list[float] = []
        self.lo, self.hi = float("inf"), float("-inf")
        self.below = [0] * len(self.marks)
        self.counts = np.zeros(self.bins, np.int64)

    def add(self, values: np.ndarray) -> None:
        v = np.asarray(values, float).ravel()
        if not len(v):
            return
        self.n += len(v)
        self._sums.append(float(v.sum()))
        # not np.dot: BLAS sums in an order that depends on its threads (a Dask worker has one)
        self._squares.append(float(np.sum(v * v)))
        self.lo, self.hi = min(self.lo, float(v.min())), max(self.hi, float(v.max()))
        for i, m in enumerate(self.marks):
            self.below[i] += int(np.count_nonzero(v < m))
        k = np.minimum((v * (self.bins / self.top)).astype(np.int64), self.bins - 1)
        self.counts += np.bincount(k, minlength=self.bins)

    def merge(self, other: Distribution) -> None:
        """Add ``other``'s values (the same bins and marks)."""
        if (other.top, other.bins, other.marks) != (self.top, self.bins, self.marks):
            raise ValueError("distributions of different bins cannot be merged")
        self.n += other.n
        self._sums += other._sums
        self._squares += other._squares
        self.lo, self.hi = min(self.lo, other.lo), max(self.hi, other.hi)
        self.below = [x + y for x, y in zip(self.below, other.below, strict=True)]
        self.counts += other.counts

    @property
    def total(self) -> float:
        return math.fsum(self._sums)

    @property
    def squares(self) -> float:
        return math.fsum(self._squares)

    @property
    def mean(self) -> float:
        return self.total / self.n

    @property
    def std(self) -> float:
        return float(np.sqrt(max(self.squares / self.n - self.mean ** 2, 0.0)))

    def share_below(self, mark: float) -> float:
        return self.below[self.marks.index(mark)] / self.n

    def median(self) -> float:
        """Within half a bin (top / bins / 2)."""
        return self.quantile(0.5)

    def quantile(self, q: float) -> float:
        """The value below which a share ``q`` of the values lie, within half a bin (at most
        ``top``: the last bin holds everything beyond)."""
        k = int(np.searchsorted(np.cumsum(self.counts), q * self.n))
        return min(k + 0.5, self.bins) * self.top / self.bins

    def histogram(self, bins: int = 60, upto: float | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """(counts, edges) from 0 to the bin holding the largest value (or ``upto``), in about
        ``bins`` bins."""
        last = int(np.flatnonzero(self.counts).max()) + 1 if self.n else 1
        if upto is not None:
            last = max(1, min(self.bins, int(np.ceil(upto * self.bins / self.top))))
        group = max(1, int(np.ceil(last / bins)))
        c = np.add.reduceat(self.counts[:last], np.arange(0, last, group))
        return c, np.arange(len(c) + 1) * group * self.top / self.bins


#: the overlap errors' distributions (top, bins, marks): translation (mm), rotation (deg),
#: translation over its own noise; bins of 1 µm, 0.01 deg and 0.005 (medians within half that)
TRANSLATION_BINS = (5.0, 5000, (0.6, 1.0))
ROTATION_BINS = (90.0, 9000, (10.0,))
NORMALISED_BINS = (20.0, 4000, ())


@dataclass
class PairMetrics:
    """One ordered pair's overlap: how many of A's points overlap B, and their mean errors."""

    a: str
    b: str
    n: int  # points of A in overlap with B
    translation_mean_mm: float | None = None
    rotation_mean_deg: float | None = None

    def summary(self) -> dict[str, float | int | str | None]:
        return {"a": self.a, "b": self.b, "n": self.n,
                "translation_mean_mm": self.translation_mean_mm,
                "rotation_mean_deg": self.rotation_mean_deg}


def _check(name: str, pts: np.ndarray) -> np.ndarray:
    """The points as (N, 3) float64, or float32 as given (a station's world points in the fuse
    worker, as its store keeps them: half the memory of a full-size station's grid and
    normals)."""
    p = np.asarray(pts, float_type(pts))
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise MetricsError(f"{name}: empty cloud or not (N, 3) points")
    bad = ~np.all(np.isfinite(p), axis=1)
    if bad.any():
        raise MetricsError(f"{name}: {int(bad.sum())} points are NaN or infinite (first at index "
                           f"{int(np.flatnonzero(bad)[0])})")
    return p


@dataclass
class OverlapValues:
    """A job's overlap errors, summed pair by pair (:class:`Distribution`), and their noise.
    Its sums are kept as partial sums added up exactly (math.fsum) when asked, like
    :class:`Distribution`'s: summed in any order or on any machine (:meth:`merge`), the
    figures are the same to the bit."""

    translation: Distribution = field(default_factory=lambda: Distribution(*TRANSLATION_BINS))
    rotation: Distribution = field(default_factory=lambda: Distribution(*ROTATION_BINS))
    normalised: Distribution = field(default_factory=lambda: Distribution(*NORMALISED_BINS))
    #: over the points with a known noise s = sqrt(σ_A² + σ_B²): the partial sums of d/s²,
    #: 1/s² and s, and their count
    weighted_sums: list[float] = field(default_factory=list)
    weights: list[float] = field(default_factory=list)
    sigma_sums: list[float] = field(default_factory=list)
    sigma_n: int = 0
    #: every overlap point had a known, positive noise
    all_sigma: bool = True

    @property
    def weighted_sum(self) -> float:
        return math.fsum(self.weighted_sums)

    @property
    def weight(self) -> float:
        return math.fsum(self.weights)

    @property
    def sigma_sum(self) -> float:
        return math.fsum(self.sigma_sums)

    def add(self, d: np.ndarray, rot: np.ndarray, sigma: np.ndarray | None) -> None:
        self.translation.add(d)
        self.rotation.add(rot)
        if sigma is None:
            self.all_sigma = self.all_sigma and not len(d)
            return
        ok = np.isfinite(sigma) & (sigma > 0)
        self.all_sigma = self.all_sigma and bool(ok.all())
        if ok.any():
            w = 1.0 / sigma[ok] ** 2
            self.weighted_sums.append(float(np.sum(w * d[ok])))
            self.weights.append(float(np.sum(w)))
            self.sigma_sums.append(float(np.sum(sigma[ok])))
            self.sigma_n += int(ok.sum())
            self.normalised.add(d[ok] / sigma[ok])

    def merge(self, other: OverlapValues) -> None:
        """Add ``other``'s values (another machine's pairs of the same job)."""
        for mine, theirs in ((self.translation, other.translation),
                             (self.rotation, other.rotation),
                             (self.normalised, other.normalised)):
            mine.merge(theirs)
        self.weighted_sums += other.weighted_sums
        self.weights += other.weights
        self.sigma_sums += other.sigma_sums
        self.sigma_n += other.sigma_n
        self.all_sigma = self.all_sigma and other.all_sigma


#: points of A compared with B at a time: a pair's temporaries stay ~0.1 GB however many of a
#: full-size station's 3.5 M points overlap
PAIR_CHUNK = 500_000


def _pair(a: np.ndarray, b: np.ndarray, radius: float, names: tuple[str, str], na: np.ndarray,
          nb: np.ndarray | NormalsOnDemand, grid_b: CellGrid, values: OverlapValues,
          ua: np.ndarray | None = None, ub: np.ndarray | None = None) -> PairMetrics:
    # only A's points within r of B's grid can overlap it: most station pairs share none
    near = in_box(a, *grid_b.bounds(radius))
    n, d_sum, rot_sum = 0, 0.0, 0.0
    for start in range(0, len(near), PAIR_CHUNK):
        part = near[start:start + PAIR_CHUNK]
        dist, j = nearest_within(grid_b, a[part], radius)
        hit = np.isfinite(dist)
        if not hit.any():
            continue
        overlap, j = part[hit], j[hit]
        sigma = np.hypot(ua[overlap], ub[j]) if ua is not None and ub is not None else None
        c1, n1 = a[overlap], na[overlap]
        c2, n2 = b[j], nb[j]
        v = c2 - c1
        d = np.abs(np.einsum("ij,ij->i", v, n1))  # |C1C2|·|cos∠(n1, C1C2)|
        cos = np.clip(np.abs(np.einsum("ij,ij->i", n1, n2)), 0.0, 1.0)  # normals' sign: arbitrary
        rot = np.degrees(np.arccos(cos))
        values.add(d, rot, sigma)
        n, d_sum, rot_sum = n + len(overlap), d_sum + float(d.sum()), rot_sum + float(rot.sum())
    if not n:
        return PairMetrics(*names, 0)
    return PairMetrics(*names, n, d_sum / n, rot_sum / n)


def pairs_with_earlier(name: str, points: np.ndarray, normals_: np.ndarray | NormalsOnDemand,
                       grid: CellGrid, uncertainty: np.ndarray | None,
                       earlier: list[tuple[str, tuple[np.ndarray, np.ndarray]]],
                       load: Callable[[str, np.ndarray, np.ndarray],
                                      tuple[np.ndarray, np.ndarray, np.ndarray | None]],
                       radius: float, values: OverlapValues) -> list[PairMetrics]:
    """Cloud ``name`` (its points, normals, grid of cell ``radius``) against each earlier cloud
    (its name and its cells' box), in that order: the pairs (earlier, name), their errors
    summed into ``values``. ``load(a, lo, hi)`` gives cloud a's points, normals and 1-sigma
    inside the box; a cloud whose box lies farther than ``radius`` is not read."""
    box = grid.bounds(radius)
    out = []
    for a, (lo, hi) in earlier:
        if np.any(lo > box[1]) or np.any(hi < box[0]):  # too far apart to overlap
            out.append(PairMetrics(a, name, 0))
            continue
        pa, na, ua = load(a, *box)
        out.append(_pair(pa, points, radius, (a, name), na, normals_, grid, values, ua,
                         uncertainty))
    return out


@dataclass
class MetricsReport:
    radius_mm: float
    spacing_mm: float
    pairs: list[PairMetrics]
    values: OverlapValues

    def to_json(self) -> dict:
        t, r, v = self.values.translation, self.values.rotation, self.values
        if t.n == 0:
            raise MetricsError("no overlap between any pair of clouds")
        translation = {"max": t.hi, "min": t.lo, "mean": t.mean, "std": t.std,
                       "p_lt_0_6": t.share_below(0.6), "p_lt_1_0": t.share_below(1.0)}
        if v.all_sigma and v.sigma_n:
            # inverse-variance weighted mean; and the errors in units of their own noise
            # (a median near 0.67 means the overlap errors are the scanner's noise alone)
            translation["weighted_mean"] = v.weighted_sum / v.weight
            translation["normalised_median"] = v.normalised.median()
            translation["expected_mean"] = v.sigma_sum / v.sigma_n * float(np.sqrt(2 / np.pi))
        return {
            "translation_mm": translation,
            "rotation_deg": {"max": r.hi, "min": r.lo, "mean": r.mean, "std": r.std,
                             "p_lt_10": r.share_below(10.0)},
            "pairs": [p.summary() for p in self.pairs],
            "radius_mm": self.radius_mm, "spacing_mm": self.spacing_mm,
        }


def kept_cloud(points: np.ndarray, normals_: NormalsOnDemand, uncertainty: np.ndarray | None,
               every: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(points, normals, 1-sigma or None) of the rows of a cloud that are the overlap metric's
    C1 against the clouds after it: every ``every``-th, from the first."""
    kept = np.arange(0, len(points), every)
    return (points[kept], normals_[kept],
            None if uncertainty is None else np.asarray(uncertainty)[kept])


class OverlapComparer:
    """The metric tool one cloud at a time, as a fuse worker receives stations: each cloud
    added is compared with every cloud added before it (the ordered pair (earlier, new)), so
    a job's pairs are done while it measures. The neighbourhood radius is ``radius_factor``
    x the mean spacing of the first cloud. The errors are summed as they come
    (:class:`OverlapValues`). A cloud's points, normals and uncertainty are kept for the pairs
    of the clouds after it: in memory, or with ``store`` on disk (a whole car body's stations
    do not fit in memory), where a new cloud reads back only the part of each earlier one
    within its own box.

    ``every``: a cloud keeps only every ``every``-th point (:func:`kept_cloud`) for the clouds
    after it, so those are its C1 against them; its nearest points C2 are still sought among
    all the points of each later cloud, whose normals are worked out only there
    (:class:`NormalsOnDemand`). 1 (the default) is the paper's tool, which traverses every
    point; a fuse worker's ~10^8 overlap points a job need not all be traversed to give
    their mean.
    """

    def __init__(self, radius_factor: float = 6.0,
                 store: StationStore | WorldFromMcs | None = None, every: int = 1) -> None:
        if every < 1 or (isinstance(store, WorldFromMcs) and store.every != every):
            raise ValueError(f"every must be >= 1 and the store's own, got {every}")
        self.radius_factor = radius_factor
        self.every = int(every)
        self.spacing_mm: float | None = None
        self.radius_mm: float | None = None
        self.pairs: list[PairMetrics] = []
        self.values = OverlapValues()
        self.store = store
        self._clouds: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray | None]] = {}
        self._boxes: dict[str, tuple[np.ndarray, np.ndarray]] = {}  # name -> its cells' box

    @property
    def names(self) -> list[str]:
        return list(self._boxes)

    def add(self, name: str, points: np.ndarray, uncertainty: np.ndarray | None = None) -> None:
        """Compare cloud ``name`` (N, 3, mm, the others' frame) with every cloud before it.
        ``uncertainty``: per-point 1-sigma (mm), or None."""
        if name in self._boxes:
            raise MetricsError(f"{name}: added twice")
        p = _check(name, points)
        if self.radius_mm is None:
            self.spacing_mm = mean_spacing(p)
            self.radius_mm = self.radius_factor * self.spacing_mm
        r = self.radius_mm
        grid = CellGrid(p, r)
        nrm = NormalsOnDemand(p, grid, r)
        self.pairs += pairs_with_earlier(
            name, p, nrm, grid, uncertainty, [(a, self._boxes[a]) for a in self.names],
            self.store.load if self.store is not None else lambda a, lo, hi: self._clouds[a],
            r, self.values)
        kept = kept_cloud(p, nrm, uncertainty, self.every)
        if self.store is not None:
            self.store.put(name, *kept)
        else:
            self._clouds[name] = kept
        self._boxes[name] = grid.bounds()

    def report(self) -> MetricsReport:
        """Every pair so far, in the order the clouds were added; raises MetricsError with
        fewer than two clouds or none overlapping."""
        return overlap_report(self.names, self.pairs, self.values, self.radius_mm,
                              self.spacing_mm, self.radius_factor)


def overlap_report(names: list[str], pairs: list[PairMetrics], values: OverlapValues,
                   radius_mm: float, spacing_mm: float, radius_factor: float) -> MetricsReport:
    """The report of clouds ``names`` (in the order they were added) from their ``pairs``, in
    that order; raises MetricsError with fewer than two clouds or none overlapping."""
    if len(names) < 2:
        raise MetricsError(f"need at least two clouds, got {len(names)}")
    if not any(p.n for p in pairs):
        raise MetricsError(f"no overlap: no point of one cloud is within r = "
                           f"{radius_mm:.3f} mm ({radius_factor:g} x the mean "
                           f"spacing {spacing_mm:.3f} mm) of another cloud "
                           f"({', '.join(names)}); same frame and units?")
    order = {n: i for i, n in enumerate(names)}
    pairs = sorted(pairs, key=lambda m: (order[m.a], order[m.b]))
    return MetricsReport(radius_mm, spacing_mm, pairs, values)


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

    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for dist, name, unit in ((report.values.translation, "translation_error", "mm"),
                             (report.values.rotation, "rotation_error", "deg")):
        counts, edges = dist.histogram(60)
        fig, ax = plt.subplots(figsize=(6, 4), dpi=120)
        ax.stairs(counts, edges, fill=True, color="#3b6ea8")
        for m, style in zip(dist.marks, ("--", ":"), strict=False):
            ax.axvline(m, color="#c0392b", ls=style, lw=1,
                       label=f"{dist.share_below(m):.2%} of points < {m:g} {unit}")
        ax.legend(fontsize=8, loc="upper right")
        ax.set_xlabel(f"{name.replace('_', ' ')} ({unit})")
        ax.set_ylabel("points")
        ax.set_title(f"{name.replace('_', ' ')}: mean {dist.mean:.4f} {unit}, "
                     f"std {dist.std:.4f}, n = {dist.n}", fontsize=9)
        fig.tight_layout()
        path = out / f"{name}.png"
        fig.savefig(path)
        plt.close(fig)
        files.append(str(path))
    return files
