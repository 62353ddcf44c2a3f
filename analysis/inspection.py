"""An inspection: a measured cloud against its nominal: alignment, signed deviation of every
point, tolerances per region, sections and the nominal surface left unmeasured.

Frames: the cloud arrives in its measuring frame (the tracker's, for a fused scan); everything
reported is in the part's frame, the nominal's, after the alignment ``T_part_from_measured``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scancell.analysis import alignment as al
from scancell.analysis import decision
from scancell.analysis.deviation import (
    CHUNK,
    ClosestPoints,
    Coverage,
    TileRunner,
    closest_points_moved,
    coverage,
    tiles_here,
)
from scancell.analysis.nominal import Nominal, check_scale, thinned
from scancell.analysis.tolerance import ToleranceSpec, judge, point_spacing_mm

ALIGNMENTS = ("asmeasured", "bestfit", "rps")


class InspectionError(ValueError):
    pass


@dataclass
class Section:
    """A cut of the nominal by the plane ``axis = offset`` (part frame)."""

    axis: str
    offset_mm: float
    segments: np.ndarray  # (S, 2, 3) the nominal's cut
    points: np.ndarray  # (K,) indices of measured points within half_width of the plane

    def to_json(self, deviation: np.ndarray) -> dict[str, Any]:
        d = deviation[self.points]
        out: dict[str, Any] = {"axis": self.axis, "offset_mm": self.offset_mm,
                               "points": int(d.size)}
        if d.size:
            out.update(mean_mm=float(d.mean()), min_mm=float(d.min()), max_mm=float(d.max()))
        return out


@dataclass
class InspectionSettings:
    align: str = "bestfit"
    #: T_part_from_measured: the fixture pose (asmeasured) or the start of bestfit / rps
    transform: np.ndarray | None = None
    rps: list[al.RpsPoint] | None = None
    tolerance: ToleranceSpec = field(default_factory=lambda: ToleranceSpec(None, []))
    #: points farther than this from the nominal are not part of it (fixtures, stray points)
    max_distance_mm: float = 5.0
    coverage_gap_mm: float = 2.0
    #: (axis, offset mm) per section; None: three across the part's longest axis and one
    #: through each of the three largest defects
    sections: list[tuple[str, float]] | None = None
    section_half_width_mm: float = 1.0
    trim_sigma: float = 3.0
    #: how conformance is decided (:mod:`scancell.analysis.decision`)
    decision_rule: str = decision.DEFAULT_RULE
    #: each point's 1-sigma (mm) where the cloud carries none; None: estimated from the
    #: cloud's own scatter (:func:`scancell.analysis.uncertainty.scatter_sigma`)
    default_sigma_mm: float | None = None


@dataclass
class Inspection:
    nominal: Nominal
    settings: InspectionSettings
    alignment: al.Alignment
    points: np.ndarray  # (N, 3) measured points in the part frame, input order
    closest: ClosestPoints
    in_range: np.ndarray  # (N,) bool: within max_distance of the nominal
    coverage: Coverage
    sections: list[Section]
    tolerances: dict[str, Any]
    seconds: dict[str, float]
    #: where the points' uncertainty came from (:func:`point_sigma`)
    uncertainty: dict[str, Any] = field(default_factory=dict)

    @property
    def deviation(self) -> np.ndarray:
        return self.closest.deviation

    def write_ply(self, path: str) -> None:
        """The measured points in the part frame, input order, with float properties
        ``deviation`` (mm), ``nx``/``ny``/``nz`` (the nominal's normal) and ``in_range``."""
        from scancell.analysis.cloud_io import write_ply_chunks

        normals = self.closest.triangle_normals.astype(np.float32)

        def chunks():  # CHUNK points at a time: no whole-cloud copy of the normals
            for s in range(0, len(self.points), CHUNK):
                part = slice(s, s + CHUNK)
                n = normals[self.closest.triangle[part]]
                yield self.points[part], {"deviation": self.deviation[part], "nx": n[:, 0],
                                          "ny": n[:, 1], "nz": n[:, 2],
                                          "in_range": self.in_range[part].astype(np.float32)}

        write_ply_chunks(path, len(self.points), ["deviation", "nx", "ny", "nz", "in_range"],
                         chunks(), comments=["frame: part (nominal), after alignment",
                                             "deviation: mm, + outside"])

    def face_names_of_points(self) -> np.ndarray:
        return self.nominal.face_of_triangle[self.closest.triangle]

    def statistics(self) -> dict[str, Any]:
        d = self.deviation[self.in_range]
        if not d.size:
            return {"points": 0}
        p = np.percentile(d, [1, 5, 50, 95, 99])
        return {"points": int(d.size), "points_out_of_range": int((~self.in_range).sum()),
                "max_distance_mm": self.settings.max_distance_mm,
                "mean_mm": float(d.mean()), "std_mm": float(d.std()),
                "rms_mm": float(np.sqrt(np.mean(d**2))), "min_mm": float(d.min()),
                "max_mm": float(d.max()), "p1_mm": p[0], "p5_mm": p[1], "median_mm": p[2],
                "p95_mm": p[3], "p99_mm": p[4]}

    def to_json(self) -> dict[str, Any]:
        c = self.coverage
        return {"nominal": self.nominal.describe(), "alignment": self.alignment.to_json(),
                "deviation": self.statistics(), "tolerances": self.tolerances,
                "coverage": {"nominal_covered_share": c.covered_share,
                             "gap_threshold_mm": c.threshold_mm, "samples": len(c.gap_mm),
                             "unmeasured_area_mm2": float(c.uncovered.mean()
                                                          * self.nominal.area_mm2)},
                "sections": [s.to_json(self.deviation) for s in self.sections],
                "uncertainty": self.uncertainty, "seconds": self.seconds}


def _align(nominal: Nominal, points: np.ndarray, s: InspectionSettings) -> al.Alignment:
    if s.align == "asmeasured":
        if s.transform is None:
            raise InspectionError("asmeasured alignment needs the fixture transform "
                                  "(T_part_from_measured)")
        return al.as_measured(nominal, points, s.transform)
    if s.align == "bestfit":
        return al.best_fit(nominal, points, s.transform, trim_sigma=s.trim_sigma)
    if s.align == "rps":
        if not s.rps:
            raise InspectionError("rps alignment needs reference points")
        return al.rps(nominal, points, s.rps, s.transform)
    raise InspectionError(f"alignment {s.align!r} unknown: use one of {', '.join(ALIGNMENTS)}")


def auto_sections(nominal: Nominal, count: int = 3) -> list[tuple[str, float]]:
    """``count`` planes across the nominal's longest axis, evenly inside its extent."""
    lo, hi = nominal.vertices.min(axis=0), nominal.vertices.max(axis=0)
    a = int(np.argmax(hi - lo))
    return [("xyz"[a], float(lo[a] + (hi[a] - lo[a]) * (i + 1) / (count + 1)))
            for i in range(count)]


def defect_sections(nominal: Nominal, tolerances: dict[str, Any], count: int = 3,
                    apart_mm: float = 5.0) -> list[tuple[str, float]]:
    """Planes across the nominal's longest axis through the centres of the ``count`` largest
    defects of ``tolerances`` (``judge_all``'s result), none nearer than ``apart_mm`` to
    another: the sections a reader wants beside the evenly spaced ones."""
    lo, hi = nominal.vertices.min(axis=0), nominal.vertices.max(axis=0)
    a = int(np.argmax(hi - lo))
    found = [d for r in [tolerances.get("overall"), *tolerances.get("regions", [])] if r
             for d in r.get("defects") or []]
    out: list[tuple[str, float]] = []
    for d in sorted(found, key=lambda d: -d["area_mm2"]):
        offset = float(d["centre_mm"][a])
        if len(out) < count and all(abs(offset - o) > apart_mm for _, o in out):
            out.append(("xyz"[a], offset))
    return out


def sections_with_defects(nominal: Nominal, tolerances: dict[str, Any],
                          apart_mm: float = 5.0) -> list[tuple[str, float]]:
    """The automatic sections: the evenly spaced ones, each replaced by the plane through a
    defect within ``apart_mm`` of it, and the defects' other planes; in order of offset."""
    through = defect_sections(nominal, tolerances, apart_mm=apart_mm)
    even = [(a, o) for a, o in auto_sections(nominal)
            if all(a != b or abs(o - q) > apart_mm for b, q in through)]
    return sorted(even + through, key=lambda p: ("xyz".index(p[0]), p[1]))


def cut(nominal: Nominal, axis: str, offset: float, points: np.ndarray, half_width: float
        ) -> Section:
    import trimesh

    if axis not in ("x", "y", "z"):
        raise InspectionError(f"section axis {axis!r}: use x, y or z")
    a = "xyz".index(axis)
    normal = np.eye(3)[a]
    mesh = trimesh.Trimesh(nominal.vertices, nominal.triangles, process=False)
    segments = trimesh.intersections.mesh_plane(mesh, normal, normal * offset)
    near = np.flatnonzero(np.abs(points[:, a] - offset) <= half_width)
    return Section(axis, float(offset), np.asarray(segments).reshape(-1, 2, 3), near)


def inspect_cloud(points_measured: np.ndarray, nominal: Nominal,
                  settings: InspectionSettings | None = None,
                  progress: Callable[[str], None] | None = None,
                  run_tiles: TileRunner = tiles_here, overwrite_input: bool = False,
                  sigma: np.ndarray | None = None) -> Inspection:
    """The whole inspection of ``points_measured`` (N, 3, measuring frame, mm); the deviation
    of every point tile by tile by ``run_tiles`` (here, or a cluster's). ``overwrite_input``:
    the caller is done with a float32 cloud, whose rows then become the part-frame points
    (a 50 M-point cloud: 0.6 GB less). ``sigma``: each point's 1-sigma uncertainty along the
    surface normal (mm; the fused model's ``uncertainty``), None where the cloud has none."""
    s = settings or InspectionSettings()
    say = progress or (lambda _msg: None)
    # the cloud as given (float32 from a PLY or the fusion): whole-cloud work goes CHUNK
    # points at a time, so a 50 M-point cloud is never copied whole
    pts = np.asarray(points_measured).reshape(-1, 3)
    if not np.issubdtype(pts.dtype, np.floating):
        pts = pts.astype(float)
    finite = sum(int(np.isfinite(pts[i:i + CHUNK]).all(axis=1).sum())
                 for i in range(0, len(pts), CHUNK))
    if finite < 10:
        raise InspectionError(f"the measured cloud has {finite} usable points")
    if finite < len(pts):
        raise InspectionError(f"{len(pts) - finite} measured points are not finite numbers")
    seconds: dict[str, float] = {}
    t = time.perf_counter()
    sigma, uncertainty = point_sigma(pts, sigma, s.default_sigma_mm)
    check_scale(nominal, pts if s.transform is None
                else al.apply(np.asarray(s.transform, float), thinned(pts)))
    say(f"aligning ({s.align}) {len(pts)} points to {len(nominal.triangles)} triangles")
    alignment = _align(nominal, pts, s)
    seconds["align"] = time.perf_counter() - t
    t = time.perf_counter()
    say("signed deviation of every point")
    reuse = (overwrite_input and pts.dtype == np.float32 and pts.flags.c_contiguous
             and pts.flags.writeable)
    part, cp, in_range = closest_points_moved(nominal, pts, alignment.T_part_from_measured,
                                              np.float32, s.max_distance_mm, run_tiles,
                                              out=pts if reuse else None)
    if in_range.mean() < 0.05:
        raise InspectionError(f"only {in_range.mean():.1%} of the points lie within "
                              f"{s.max_distance_mm} mm of the nominal after the {s.align} "
                              f"alignment: no overlap, nothing to report")
    seconds["deviation"] = time.perf_counter() - t
    t = time.perf_counter()
    say("tolerances, sections and unmeasured surface")
    tolerances = judge_all(nominal, part, cp, in_range, s.tolerance, sigma, s.decision_rule)
    # every k-th point, at most 1 M: their spacing stays far below the gap threshold
    cov = coverage(nominal, thinned(part) if in_range.all()
                   else part[thinned(np.flatnonzero(in_range))], s.coverage_gap_mm)
    planes = s.sections if s.sections is not None else sections_with_defects(nominal, tolerances)
    sections = [cut(nominal, a, o, part, s.section_half_width_mm) for a, o in planes]
    seconds["analysis"] = time.perf_counter() - t
    return Inspection(nominal, s, alignment, part, cp, in_range, cov, sections, tolerances,
                      {k: round(v, 3) for k, v in seconds.items()}, uncertainty)


def point_sigma(points: np.ndarray, sigma: np.ndarray | None, default_mm: float | None
                ) -> tuple[np.ndarray, dict[str, Any]]:
    """Each point's 1-sigma (mm, float32) and where it came from: the cloud's own (checked:
    no NaN, no negative), the stated default, or, with neither, the cloud's scatter about
    local planes (noise only). The verdicts are only as honest as these."""
    from scancell.analysis.uncertainty import check_point_sigma, scatter_sigma

    if sigma is not None:
        s = check_point_sigma(sigma, len(points), "the measured cloud's uncertainty")
        return s, {"source": "points", "median_sigma_mm": round(float(np.median(s)), 5)}
    if default_mm is not None:
        if not (np.isfinite(default_mm) and default_mm >= 0):
            raise InspectionError(f"the stated point uncertainty {default_mm!r} mm must be a "
                                  f"finite number >= 0")
        value, how = float(default_mm), "stated"
        note = (f"the cloud carries no per-point uncertainty: every point is taken at the "
                f"stated 1-sigma of {value:.4f} mm")
    else:
        value, how = scatter_sigma(points), "scatter"
        note = (f"the cloud carries no per-point uncertainty: every point is taken at "
                f"1-sigma {value:.4f} mm, its own scatter about local planes; that is noise "
                f"only (a station's pose and the calibration are not in it), so the verdicts "
                f"may claim too much")
    return (np.full(len(points), value, np.float32),
            {"source": how, "median_sigma_mm": round(value, 5), "note": note})


def judge_all(nominal: Nominal, part: np.ndarray, cp: ClosestPoints, in_range: np.ndarray,
              spec: ToleranceSpec, sigma: np.ndarray | None = None,
              rule: str = decision.DEFAULT_RULE) -> dict[str, Any]:
    """Every tolerance of ``spec`` judged on the points in range by ``rule``, with each
    point's 1-sigma ``sigma`` (mm, input order; None: no uncertainty known)."""
    out: dict[str, Any] = {"allowed_out_share": spec.allowed_out_share,
                           "defect_area_mm2": spec.defect_area_mm2, "overall": None,
                           "regions": [], "decision": decision.describe(rule)}
    d = cp.deviation
    used = None if in_range.all() else np.flatnonzero(in_range)  # None: every point, no copy
    spacing = point_spacing_mm(part, index=used) if (spec.overall or spec.regions) else 0.0
    out["point_spacing_mm"] = round(spacing, 4)
    if spec.overall is not None:
        out["overall"] = judge(d if used is None else d[used], spec.overall,
                               spec.allowed_out_share, part, spacing, spec.defect_area_mm2, used,
                               sigma if sigma is None or used is None else sigma[used], rule)
    faces = nominal.face_of_triangle[cp.triangle] if spec.regions else None  # 4 B a point
    for region in spec.regions:
        inside = np.flatnonzero(region.contains(part, faces, nominal) & in_range)
        out["regions"].append({"name": region.name, "kind": region.kind,
                               "where": region.describe(),
                               **judge(d[inside], region.tolerance, spec.allowed_out_share,
                                       part, spacing, spec.defect_area_mm2, inside,
                                       None if sigma is None else sigma[inside], rule)})
    judged = [r for r in [out["overall"], *out["regions"]] if r]
    out["verdict"] = decision.combine([r["verdict"] for r in judged]) if judged else None
    out["pass"] = decision.as_pass(out["verdict"]) if judged else None
    return out
