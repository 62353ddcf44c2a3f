"""Tolerances of an inspection: one for the whole part and one per region, each judged by the
share of points outside it.

A region is a named face set of the STEP nominal, a box or a sphere in part coordinates. A
tolerance file (TOML) reads::

    tolerance_mm = 0.5              # the whole part: -0.5 ... +0.5 (or lower_mm / upper_mm)
    allowed_out_share = 0.01        # pass while at most 1 % of the points are outside ...
    defect_area_mm2 = 25            # ... and no connected patch of them covers more than this

    [[region]]
    name = "licence plate"
    faces = ["plate", "plate_walls"] # STEP face names
    tolerance_mm = 0.3

    [[region]]
    name = "left corner"
    box = [[0, -700, 100], [400, -500, 250]]   # min and max corner (mm)
    lower_mm = -0.2
    upper_mm = 0.4

    [[region]]
    name = "hole"
    sphere = { centre = [100, 0, 0], radius = 25 }
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis import decision
from scancell.analysis.json_file import read_toml
from scancell.analysis.nominal import Nominal

DEFAULT_ALLOWED_OUT_SHARE = 0.01
#: a connected patch of out-of-tolerance points larger than this (mm²) is a defect that fails
#: its region whatever the share: 5 x 5 mm, where a scan 0.2-0.5 mm apart holds 100-600 points,
#: far more than noise puts together
DEFAULT_DEFECT_AREA_MM2 = 25.0
#: points of one patch lie within this many point spacings of each other
DEFECT_LINK_SPACINGS = 3.0
#: defects listed per region at most (the largest)
MAX_DEFECTS_LISTED = 20


class ToleranceError(ValueError):
    pass


@dataclass
class Tolerance:
    lower_mm: float
    upper_mm: float

    @classmethod
    def parse(cls, text: str) -> Tolerance:
        """``0.5`` (symmetric) or ``-0.3,+0.5`` (lower, upper)."""
        try:
            values = [float(v) for v in str(text).split(",")]
        except ValueError:
            raise ToleranceError(f"tolerance {text!r}: give T (mm) or LOWER,UPPER (mm)") from None
        if len(values) == 1:
            values = [-abs(values[0]), abs(values[0])]
        if len(values) != 2 or not values[0] < values[1] or not values[0] <= 0 <= values[1]:
            raise ToleranceError(f"tolerance {text!r}: LOWER must be <= 0 <= UPPER, LOWER < UPPER")
        return cls(*values)

    @classmethod
    def from_mapping(cls, m: dict[str, Any], where: str, default: Tolerance | None
                     ) -> Tolerance:
        if "tolerance_mm" in m:
            return cls.parse(str(m["tolerance_mm"]))
        if "lower_mm" in m or "upper_mm" in m:
            try:
                return cls.parse(f"{float(m['lower_mm'])},{float(m['upper_mm'])}")
            except KeyError as exc:
                raise ToleranceError(f"{where}: {exc.args[0]} missing beside the other "
                                     f"bound") from None
        if default is None:
            raise ToleranceError(f"{where}: no tolerance (tolerance_mm, or lower_mm and "
                                 f"upper_mm)")
        return default

    def to_json(self) -> dict[str, float]:
        return {"lower_mm": self.lower_mm, "upper_mm": self.upper_mm}


@dataclass
class Region:
    name: str
    kind: str  # faces | box | sphere
    tolerance: Tolerance
    faces: list[str] | None = None
    box: np.ndarray | None = None  # (2, 3) min, max
    centre: np.ndarray | None = None
    radius: float | None = None

    def contains(self, points_part: np.ndarray, face_of_point: np.ndarray,
                 nominal: Nominal) -> np.ndarray:
        if self.kind == "faces":
            return np.isin(face_of_point, nominal.faces_named(self.faces or []))
        if self.kind == "box":
            return np.all((points_part >= self.box[0]) & (points_part <= self.box[1]), axis=1)
        return np.linalg.norm(points_part - self.centre, axis=1) <= self.radius

    def describe(self) -> str:
        if self.kind == "faces":
            return "faces " + ", ".join(self.faces or [])
        if self.kind == "box":
            return f"box {self.box[0].tolist()} .. {self.box[1].tolist()}"
        return f"sphere r {self.radius} at {self.centre.tolist()}"


@dataclass
class ToleranceSpec:
    overall: Tolerance | None
    regions: list[Region]
    allowed_out_share: float = DEFAULT_ALLOWED_OUT_SHARE
    defect_area_mm2: float = DEFAULT_DEFECT_AREA_MM2


def _vector(v: Any, n: int, where: str) -> np.ndarray:
    try:
        a = np.asarray(v, float).reshape(n)
    except (ValueError, TypeError):
        raise ToleranceError(f"{where}: expected {n} numbers, got {v!r}") from None
    if not np.isfinite(a).all():
        raise ToleranceError(f"{where}: numbers must be finite, got {v!r}")
    return a


def parse_spec(m: dict[str, Any], where: str = "tolerances",
               overall: Tolerance | None = None) -> ToleranceSpec:
    """A tolerance spec from its mapping (see the module docstring); ``overall`` (e.g. from the
    command line) overrides the file's."""
    if "tolerance_mm" in m or "lower_mm" in m:
        overall = overall or Tolerance.from_mapping(m, where, None)
    share = float(m.get("allowed_out_share", DEFAULT_ALLOWED_OUT_SHARE))
    if not 0 <= share < 1:
        raise ToleranceError(f"{where}: allowed_out_share must be in [0, 1), got {share}")
    defect_area = float(m.get("defect_area_mm2", DEFAULT_DEFECT_AREA_MM2))
    if not defect_area > 0:
        raise ToleranceError(f"{where}: defect_area_mm2 must be > 0, got {defect_area}")
    regions = []
    for i, r in enumerate(m.get("region", [])):
        w = f"{where}: region {i + 1} ({r.get('name', '?')!r})"
        name = str(r.get("name") or f"region {i + 1}")
        tol = Tolerance.from_mapping(r, w, overall)
        kinds = [k for k in ("faces", "box", "sphere") if k in r]
        if len(kinds) != 1:
            raise ToleranceError(f"{w}: give exactly one of faces, box, sphere")
        if kinds[0] == "faces":
            faces = r["faces"] if isinstance(r["faces"], list) else [r["faces"]]
            regions.append(Region(name, "faces", tol, faces=[str(f) for f in faces]))
        elif kinds[0] == "box":
            box = _vector(r["box"], 6, f"{w} box").reshape(2, 3)
            if np.any(box[1] <= box[0]):
                raise ToleranceError(f"{w}: box max corner must exceed its min corner")
            regions.append(Region(name, "box", tol, box=box))
        else:
            s = r["sphere"]
            radius = float(s.get("radius", 0)) if isinstance(s, dict) else 0.0
            if radius <= 0:
                raise ToleranceError(f"{w}: sphere needs a radius > 0")
            regions.append(Region(name, "sphere", tol,
                                  centre=_vector(s.get("centre"), 3, f"{w} sphere centre"),
                                  radius=radius))
    return ToleranceSpec(overall, regions, share, defect_area)


def load_spec(path: str | Path, overall: Tolerance | None = None) -> ToleranceSpec:
    return parse_spec(read_toml(path, ToleranceError), str(path), overall)


def judge(deviation: np.ndarray, tolerance: Tolerance, allowed_out_share: float,
          points: np.ndarray | None = None, spacing_mm: float | None = None,
          defect_area_mm2: float = DEFAULT_DEFECT_AREA_MM2, index: np.ndarray | None = None,
          sigma: np.ndarray | None = None, rule: str = decision.DEFAULT_RULE
          ) -> dict[str, Any]:
    """Statistics of ``deviation`` (mm) against ``tolerance`` and the verdict of ``rule``
    (:mod:`scancell.analysis.decision`): share below, above, proven inside and outside, the
    defects (with the points, part frame, mm, and their spacing: :func:`defects`; ``index``:
    the row of ``points`` of each deviation, None: row for row), ``verdict`` and ``pass``
    (true only when conformance is proven). ``sigma``: each deviation's 1-sigma uncertainty
    (mm; None: 0, nothing known). Sums in float64, whatever the deviations' type, without a
    float64 copy of them."""
    d = np.asarray(deviation)
    if d.size == 0:
        return {"points": 0, **tolerance.to_json(), "verdict": decision.NOT_MEASURED,
                "pass": None, "note": "no measured point in this region: not measured"}
    zone = decision.Zone(tolerance.lower_mm, tolerance.upper_mm)
    U = np.float32(0.0) if sigma is None else (decision.K * np.asarray(sigma)).astype(np.float32)
    inside, outside = decision.classify(d, U, zone, rule)
    below = float(np.mean(d < tolerance.lower_mm))
    above = float(np.mean(d > tolerance.upper_mm))
    found = (defects(points, d, tolerance, spacing_mm, defect_area_mm2, index, sigma, rule)
             if points is not None and spacing_mm else [])
    not_inside, proven_out = 1.0 - float(np.mean(inside)), float(np.mean(outside))
    verdict = decision.share_verdict(not_inside, proven_out, allowed_out_share,
                                     [f["verdict"] for f in found])
    u_typical = float(np.median(U)) if np.ndim(U) else float(U)
    u_mean = float(np.sqrt(np.mean(np.square(U, dtype=np.float64)))) if np.ndim(U) else float(U)
    out = {"points": int(d.size), **tolerance.to_json(),
           "mean_mm": float(np.mean(d, dtype=np.float64)),
           "std_mm": float(np.std(d, dtype=np.float64)), "min_mm": float(d.min()),
           "max_mm": float(d.max()),
           "below_share": below, "above_share": above, "out_share": below + above,
           "U_mm": round(u_typical, 5), "mean_U_mm": round(u_mean, 5),
           "proven_inside_share": 1.0 - not_inside, "proven_outside_share": proven_out,
           "defects": found[:MAX_DEFECTS_LISTED], "defect_count": len(found),
           "verdict": verdict, "pass": decision.as_pass(verdict)}
    why = decision.no_acceptance_zone(zone, u_typical, rule)
    if why:
        out["note"] = why
    return out


#: a defect's height is the median deviation of the points within this radius of its
#: extreme, in point spacings: about π · 3.1² ≈ 30 points, whose median has 1.25 / √30 ≈ 0.23
#: of one point's noise
DEFECT_FIT_SPACINGS = 3.1
#: patch points whose neighbourhood is fitted, at most (spread evenly over the patch)
DEFECT_FIT_PROBES = 2000


def defects(points: np.ndarray, deviation: np.ndarray, tolerance: Tolerance, spacing_mm: float,
            min_area_mm2: float, index: np.ndarray | None = None,
            sigma: np.ndarray | None = None, rule: str = decision.DEFAULT_RULE
            ) -> list[dict[str, Any]]:
    """The connected patches of out-of-tolerance points (each side apart) larger than
    ``min_area_mm2``, largest first: where (centroid, mm), how large (area ≈ points x
    spacing², mm²), the extreme deviation (mm), and the robust height from a local fit
    (:func:`defect_height`) with its U and the rule's verdict on it. Patches are Open3D's
    DBSCAN of the out-of-tolerance points, linked within DEFECT_LINK_SPACINGS spacings."""
    import open3d as o3d

    out = []
    per_point = spacing_mm ** 2
    zone = decision.Zone(tolerance.lower_mm, tolerance.upper_mm)
    for side, mask in (("above", deviation > tolerance.upper_mm),
                       ("below", deviation < tolerance.lower_mm)):
        n = int(mask.sum())
        if n * per_point <= min_area_mm2:
            continue
        rows = mask if index is None else index[mask]
        pts, dev = np.asarray(points[rows], float), np.asarray(deviation[mask], float)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        labels = np.asarray(cloud.cluster_dbscan(DEFECT_LINK_SPACINGS * spacing_mm, 3))
        for label in np.unique(labels[labels >= 0]):
            member = labels == label
            area = float(member.sum() * per_point)
            if area <= min_area_mm2:
                continue
            extreme = dev[member][np.argmax(np.abs(dev[member]))]
            lo, hi = pts[member].min(axis=0), pts[member].max(axis=0)
            height, u = defect_height(points, deviation, index, sigma, pts[member], side,
                                      spacing_mm)
            out.append({"side": side, "centre_mm": [round(float(v), 3) for v in pts[member].mean(axis=0)],
                        "size_mm": [round(float(v), 3) for v in hi - lo],
                        "area_mm2": round(area, 1), "points": int(member.sum()),
                        "extreme_mm": round(float(extreme), 4),
                        "height_mm": round(height, 4), "U_mm": round(u, 4),
                        "verdict": decision.decide(height, u, zone, rule)})
    return sorted(out, key=lambda x: -x["area_mm2"])


def defect_height(points: np.ndarray, deviation: np.ndarray, index: np.ndarray | None,
                  sigma: np.ndarray | None, patch: np.ndarray, side: str, spacing_mm: float
                  ) -> tuple[float, float]:
    """A defect's robust height (mm) and its expanded uncertainty U (mm, k = 2).

    The height is a local fit of order zero: at each of up to DEFECT_FIT_PROBES points of the
    patch (part frame, mm), the median deviation of every judged point within
    DEFECT_FIT_SPACINGS spacings; the most extreme of these on the patch's side. One noisy
    point moves a median of ~30 by nothing. Its U: the median's noise, 1.253 s / √n with s
    the neighbours' robust scatter (1.4826 MAD), and the share of the points' stated
    variance the scatter does not show (mean σ² − s², the error common to the neighbours: the
    stations' poses), which no average removes."""
    from scipy.spatial import cKDTree

    radius = DEFECT_FIT_SPACINGS * spacing_mm
    lo, hi = patch.min(axis=0) - radius, patch.max(axis=0) + radius
    rows = np.arange(len(deviation)) if index is None else np.asarray(index)
    near = np.ones(len(rows), bool)
    for a in range(3):  # the judged points around the patch, axis by axis (no big copies)
        near &= (points[rows, a] >= lo[a]) & (points[rows, a] <= hi[a])
    local = np.flatnonzero(near)
    tree = cKDTree(np.asarray(points[rows[local]], float))
    probes = patch[:: max(1, len(patch) // DEFECT_FIT_PROBES)]
    hoods = [h for h in tree.query_ball_point(probes, radius) if h]
    medians = np.array([np.median(np.asarray(deviation[local[h]], float)) for h in hoods])
    k = int(np.argmax(medians) if side == "above" else np.argmin(medians))
    dev = np.asarray(deviation[local[hoods[k]]], float)
    s = 1.4826 * float(np.median(np.abs(dev - medians[k])))
    common = 0.0
    if sigma is not None:
        common = max(0.0, float(np.mean(np.square(np.asarray(sigma[local[hoods[k]]], float))))
                     - s * s)
    return float(medians[k]), decision.K * float(np.sqrt((1.253 * s) ** 2 / len(dev) + common))


#: points per k-d tree of :func:`point_spacing_mm` (a tree and its float64 copy: ~60 MB a million)
SPACING_CHUNK = 4_000_000
#: points of the subsample whose k-d tree gives every probe its first bound on r₈
SPACING_BOUND_SAMPLE = 1_000_000


def point_spacing_mm(points: np.ndarray, sample: int = 20_000, seed: int = 0,
                     index: np.ndarray | None = None) -> float:
    """The cloud's spacing (mm): the square root of the surface area each point stands for,
    from the local density at a subsample, π r₈² / 8 with r₈ the distance to the 8th nearest
    neighbour (right for a scanner's grid, π/4 of its pitch², and for random samples, whose
    nearest-neighbour distance would understate it 2x). ``index``: the rows of ``points`` that
    form the cloud (None: all).

    A cloud of more than SPACING_CHUNK points is searched a chunk at a time, a k-d tree each,
    and the neighbours merged: the same r₈ as one tree over all, in bounded memory. Each search
    is bounded by the probe's r₈ so far. Unbounded, a probe searching a chunk it is not part of
    visits every leaf whose points lie about as far away as its nearest: all of them for a probe
    near the centre of a curved panel's chunk (20 such probes took 3.5 s against one 4 M-point
    hemisphere, 1 ms bounded). The first bound is the 9th distance in a subsample's tree, never
    below the cloud's own (the subsample's nine nearest are nine of the cloud's points)."""
    from scipy.spatial import cKDTree

    n = len(points) if index is None else len(index)
    if n < 9:
        return 0.0

    def take(rows: slice | np.ndarray) -> np.ndarray:
        return np.asarray(points[rows] if index is None else points[index[rows]], float)

    rng = np.random.default_rng(seed)
    probe = take(rng.choice(n, min(sample, n), replace=False))
    best = np.full((len(probe), 9), np.inf)
    bound = np.full(len(probe), np.inf)
    if n > SPACING_CHUNK:
        rows = np.sort(rng.choice(n, min(SPACING_BOUND_SAMPLE, n), replace=False))
        bound = cKDTree(take(rows)).query(probe, k=9, workers=-1)[0][:, 8]
    for s in range(0, n, SPACING_CHUNK):
        chunk = take(slice(s, s + SPACING_CHUNK))
        best = _merge_nearest(best, np.minimum(bound, best[:, 8]), cKDTree(chunk), probe,
                              chunk.min(axis=0), chunk.max(axis=0))
    r8 = best[:, 8]
    return float(np.sqrt(np.pi * np.median(r8 ** 2) / 8))


def _merge_nearest(best: np.ndarray, bound: np.ndarray, tree: Any, probe: np.ndarray,
                   lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``best`` (probes x k distances, ascending) merged in place with ``tree``'s points
    spanning the box ``lo``-``hi``. ``bound``: no probe's k-th nearest lies farther (inf: not
    known). Only probes whose bound reaches the box search it, in groups of bounds within 2x of
    each other, each group bounded by its largest: no probe then searches much past its own
    bound."""
    k = best.shape[1]
    gap = np.linalg.norm(np.maximum(0.0, np.maximum(lo - probe, probe - hi)), axis=1)
    reach = np.flatnonzero(gap <= bound)
    finite = np.isfinite(bound[reach])
    group = np.where(finite, np.ceil(np.log2(np.maximum(bound[reach], 1e-300))), np.inf)
    for g in np.unique(group):
        rows = reach[group == g]
        # a hair over the bound: a neighbour exactly at it still counts
        limit = np.inf if not np.isfinite(g) else float(bound[rows].max()) * (1 + 1e-9) + 1e-12
        d = tree.query(probe[rows], k=min(k, tree.n), workers=-1,
                       distance_upper_bound=limit)[0].reshape(len(rows), -1)
        best[rows] = np.sort(np.concatenate([best[rows], d], axis=1), axis=1)[:, :k]
    return best
