"""Acceptance test of an optical 3D scanner after VDI/VDE 2634 Part 2 (single view) and Part 3
(multiple views): the quality parameters from the clouds of calibrated artefacts.

Our reading of the guideline (2012 editions), with where it is uncertain:
- **Measuring volume.** A box in the scanner frame (MCS), centred on the scanner's axis at its
  working distance; L0 is its space diagonal.
- **Probing error, form PF and size PS** on a sphere of diameter 0.1–0.2 L0: a least-squares
  sphere with free radius through the sphere's points; PF is the range of the radial
  residuals, PS the fitted diameter minus the calibrated one. The guideline lets up to 0.3 %
  of the points go as outliers: we drop the 0.3 % with the largest |residual|. We take the
  sphere at 10 positions spread over the volume (centre, corners); how many positions the
  guideline asks for PF/PS we read as "several" (uncertain).
- **Sphere-spacing error SD** on a ball bar (dumbbell) as long as the volume allows (we read
  the guideline's minimum as about 0.3 L0; uncertain), in 7 positions: the
  4 space diagonals and 3 face diagonals of the volume (the guideline's figure shows
  diagonals and positions parallel to the sides; which 3 besides the space diagonals is our
  choice). SD is the distance of the two least-squares centres minus the calibrated one.
- **Flatness F** on a plane of length >= 0.5 L0, in 6 positions (frontal at three depths and
  tilted about both axes: our choice of the 6): the range of the distances from a
  least-squares plane, 0.3 % outliers dropped, the face's outer 3 mm left out (where its side
  faces and mixed edge pixels meet it; uncertain whether the guideline allows that margin).
- **Part 3** repeats SD with the ball bar's two spheres seen from different robot stations,
  fused through the laser tracker: the error of the whole chain.
- Part 3's figure is reported as ``SD3``.
- Each parameter's figure is the largest |value| over its positions, judged against the MPE
  with the test's expanded uncertainty U (k = 2) by a decision rule (ISO 14253-1: conformance
  proven at figure <= MPE - U, non-conformance at figure > MPE + U, not provable between).
  The test's U is what the test itself adds: the artefacts' calibration certificates (the
  sphere's form and diameter, the bars' lengths, the plane's form), from the cell config; the
  scanner's own errors are what the test measures, not an uncertainty of it. The MPE comes
  from the cell config, for the camera resolution it was specified at; a scanner run at a
  coarser one (binning, the quick demo's quarter size) has its Part 2 MPEs scaled by the
  pixel's footprint (:func:`mpe_for_resolution`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scancell.analysis.decision import DEFAULT_RULE, FAIL, PASS, Zone, combine, decide
from scancell.analysis.fit import FitError, detect_sphere, fit_plane, fit_sphere
from scancell.analysis.uncertainty import along_normal

OUTLIER_SHARE = 0.003
PARAMETERS = ("PF", "PS", "SD", "F")


class AcceptanceError(ValueError):
    """An artefact not found in its scan, or a measurement that cannot be evaluated."""


@dataclass(frozen=True)
class MeasuringVolume:
    """A box in MCS (mm): ``size`` = (x, y, z) extent, centred at ``centre``."""

    size: tuple[float, float, float]
    centre: tuple[float, float, float]

    @property
    def l0(self) -> float:
        return float(np.linalg.norm(self.size))

    def corner(self, signs: np.ndarray, shrink: float = 1.0) -> np.ndarray:
        return np.asarray(self.centre) + 0.5 * shrink * np.asarray(signs) * np.asarray(self.size)


@dataclass(frozen=True)
class Placement:
    """One artefact position: where it goes in MCS and how it lies."""

    kind: str  # sphere | ballbar | plane
    index: int
    centre_mcs: np.ndarray  # mm
    direction_mcs: np.ndarray  # unit: ball bar axis, or plane normal (towards the scanner)

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "index": self.index,
                "centre_mcs": [round(float(v), 3) for v in self.centre_mcs],
                "direction_mcs": [round(float(v), 6) for v in self.direction_mcs]}


def _unit(v: Any) -> np.ndarray:
    a = np.asarray(v, float)
    return a / np.linalg.norm(a)


CORNERS = np.array([[sx, sy, sz] for sz in (-1, 1) for sy in (-1, 1) for sx in (-1, 1)], float)


def sphere_positions(volume: MeasuringVolume, n: int = 10) -> list[Placement]:
    """The centre, then the corners of the volume shrunk to 70 %, then to 35 %."""
    shrink = 0.7
    pts = [np.asarray(volume.centre, float)] + [volume.corner(c, shrink) for c in CORNERS]
    pts += [volume.corner(c, shrink / 2) for c in CORNERS]
    return [Placement("sphere", i, p, np.array([0.0, 0.0, -1.0])) for i, p in enumerate(pts[:n])]


def ballbar_positions(volume: MeasuringVolume, n: int = 7) -> list[Placement]:
    """The 4 space diagonals, then the face diagonals x-y, x-z, y-z, through the centre."""
    sx, sy, sz = volume.size
    dirs = [_unit([sx, sy, sz]), _unit([-sx, sy, sz]), _unit([sx, -sy, sz]), _unit([-sx, -sy, sz]),
            _unit([sx, sy, 0]), _unit([sx, 0, sz]), _unit([0, sy, sz])]
    c = np.asarray(volume.centre, float)
    return [Placement("ballbar", i, c, d) for i, d in enumerate(dirs[:n])]


def plane_positions(volume: MeasuringVolume, n: int = 6) -> list[Placement]:
    """Frontal at the far, middle and near third of the depth; tilted 30 deg either way about
    the vertical axis and 30 deg about the horizontal one."""
    c = np.asarray(volume.centre, float)
    dz = np.array([0.0, 0.0, volume.size[2] / 3])
    t = np.radians(30.0)
    out = [(c + dz, [0, 0, -1.0]), (c, [0, 0, -1.0]), (c - dz, [0, 0, -1.0]),
           (c, [np.sin(t), 0, -np.cos(t)]), (c, [-np.sin(t), 0, -np.cos(t)]),
           (c, [0, np.sin(t), -np.cos(t)])]
    return [Placement("plane", i, p, _unit(d)) for i, (p, d) in enumerate(out[:n])]


def _trim(residuals: np.ndarray, share: float = OUTLIER_SHARE) -> np.ndarray:
    """The residuals without the ``share`` with the largest magnitude."""
    r = np.asarray(residuals, float)
    keep = int(np.ceil(len(r) * (1 - share)))
    return r[np.argsort(np.abs(r))[:keep]]


def _near(points: np.ndarray, approx: np.ndarray | None, reach: float) -> np.ndarray:
    if approx is None:
        return points
    return points[np.linalg.norm(points - approx, axis=1) < reach]


def probing(points: np.ndarray, diameter_mm: float, approx_centre: np.ndarray | None = None,
            sigma_mm: np.ndarray | None = None) -> dict[str, Any]:
    """PF and PS of one sphere scan (mm). With the points' stated 1-sigma depth noise
    ``sigma_mm`` (along the left camera's optical axis; the points then in its frame, MCS) also
    ``PF_noise``: the PF that noise alone gives those points (:func:`noise_form`), each
    point's noise carried onto the sphere's radius."""
    r = diameter_mm / 2
    near = (np.ones(len(points), bool) if approx_centre is None
            else np.linalg.norm(points - approx_centre, axis=1) < 3 * r)
    pts = points[near]
    try:
        det = detect_sphere(pts, radius=r, inlier_mm=0.3)
        in_band = np.abs(np.linalg.norm(pts - det.center, axis=1) - r) < max(1.0, 0.1 * r)
        band = pts[in_band]
        fit = fit_sphere(band)
    except FitError as exc:
        raise AcceptanceError(f"sphere (diameter {diameter_mm} mm) not found: {exc}") from None
    res = _trim(np.linalg.norm(band - fit.center, axis=1) - fit.radius)
    out = {"PF": float(res.max() - res.min()), "PS": float(2 * fit.radius - diameter_mm),
           "points": len(band), "centre_mm": fit.center.round(4).tolist(),
           "diameter_mm": 2 * fit.radius}
    if sigma_mm is not None:
        # a point's depth noise moves it along its camera ray; the form sees its radial part
        radial = along_normal(band, (band - fit.center) / np.linalg.norm(band - fit.center, axis=1,
                                                                         keepdims=True))
        out["PF_noise"] = noise_form(np.asarray(sigma_mm, float)[near][in_band] * radial)
    return out


def noise_form(sigma_mm: np.ndarray, draws: int = 200, seed: int = 0) -> float:
    """The PF (mm) that the points' noise alone gives: the median, over ``draws`` Monte Carlo
    draws of independent Gaussian residuals of the stated 1-sigma ``sigma_mm``, of their range
    after the same OUTLIER_SHARE trim. A range statistic grows with the points and is set by the
    noisiest of them: at 1/4 camera resolution a 30 mm sphere's ~1 800 points of 0.03 mm give
    about 0.22 mm by noise alone."""
    sigma = sigma_mm[np.isfinite(sigma_mm)]
    rng = np.random.default_rng(seed)
    return float(np.median([np.ptp(_trim(rng.normal(0.0, sigma)))
                            for _ in range(draws)])) if len(sigma) else 0.0


def _sphere_centre(points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    det = detect_sphere(points, radius=radius, inlier_mm=0.3)
    band = np.abs(np.linalg.norm(points - det.center, axis=1) - radius) < max(1.0, 0.1 * radius)
    return fit_sphere(points[band]).center, band


def sphere_spacing(points: np.ndarray, length_mm: float, sphere_diameter_mm: float,
                   approx_ends: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, Any]:
    """SD of one ball-bar scan (mm): the two least-squares centres' distance minus the
    calibrated length. ``approx_ends``: roughly where the two spheres are (else found)."""
    r = sphere_diameter_mm / 2
    centres = []
    try:
        if approx_ends is not None:
            for end in approx_ends:
                centres.append(_sphere_centre(_near(points, np.asarray(end), 3 * r), r)[0])
        else:
            c1, band = _sphere_centre(points, r)
            rest = points[~band & (np.linalg.norm(points - c1, axis=1) > 1.5 * r)]
            centres = [c1, _sphere_centre(rest, r)[0]]
    except FitError as exc:
        raise AcceptanceError(f"ball bar sphere (diameter {sphere_diameter_mm} mm) not found: "
                              f"{exc}") from None
    d = float(np.linalg.norm(centres[0] - centres[1]))
    if abs(d - length_mm) > 0.1 * length_mm:
        raise AcceptanceError(f"ball bar: the two spheres found are {d:.1f} mm apart, not about "
                              f"{length_mm} mm: a wrong sphere?")
    return {"SD": d - length_mm, "length_mm": d,
            "centres_mm": [c.round(4).tolist() for c in centres]}


EDGE_MARGIN_MM = 3.0


def _inside_edges(points: np.ndarray, centroid: np.ndarray, normal: np.ndarray,
                  margin: float) -> np.ndarray:
    """Points farther than ``margin`` from the outline (2D convex hull in the plane) of
    ``points``: a plate's rim, where its side faces and mixed edge pixels meet the face, is
    not its face."""
    from scipy.spatial import ConvexHull

    u = np.cross(normal, [1.0, 0, 0] if abs(normal[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    uv = np.column_stack([(points - centroid) @ u, (points - centroid) @ np.cross(normal, u)])
    eq = ConvexHull(uv).equations  # a u + b v + c <= 0 inside, (a, b) unit
    return -(uv @ eq[:, :2].T + eq[:, 2]).max(axis=1) > margin


def flatness(points: np.ndarray, approx_centre: np.ndarray | None = None,
             approx_normal: np.ndarray | None = None, size_mm: float = 300.0,
             edge_margin_mm: float = EDGE_MARGIN_MM) -> dict[str, Any]:
    """F of one plane scan (mm): the range of the distances from the least-squares plane of
    the plane's face (found by RANSAC within 1 mm, then the points within 1 mm of its
    least-squares plane, the outer ``edge_margin_mm`` of the face left out), 0.3 % outliers
    dropped."""
    import open3d as o3d

    pts = _near(points, approx_centre, 0.75 * size_mm)
    if len(pts) < 100:
        raise AcceptanceError(f"plane: only {len(pts)} points near its position")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    _, inliers = pcd.segment_plane(1.0, 3, 500)
    if len(inliers) < 100:
        raise AcceptanceError("plane: no plane found in its scan")
    try:
        fit = fit_plane(pts[inliers])
        on = pts[np.abs((pts - fit.centroid) @ fit.normal) < 1.0]
        on = on[_inside_edges(on, fit.centroid, fit.normal, edge_margin_mm)]
        fit = fit_plane(on)
    except (FitError, ValueError) as exc:
        raise AcceptanceError(f"plane: {exc}") from None
    if approx_normal is not None and abs(fit.normal @ _unit(approx_normal)) < 0.8:
        raise AcceptanceError("plane: the plane found does not face the way the artefact was "
                              "placed")
    res = _trim(fit.residuals)
    return {"F": float(res.max() - res.min()), "points": len(on),
            "rms_mm": float(np.sqrt(np.mean(res**2)))}


def mpe_for_resolution(mpe_mm: dict[str, float], specified_width_px: int | None,
                       width_px: int | None) -> tuple[dict[str, float], dict[str, Any] | None]:
    """Part 2's MPEs (mm) for a scanner whose cameras deliver ``width_px`` across, when they
    were specified at ``specified_width_px``; the derivation beside them (None: not scaled).

    A fringe scanner resolves a fixed fraction of a pixel: its phase matching finds the
    disparity to σ_d pixels and its calibration the corners to a fraction of a pixel. Its
    depth error σ_z = z² σ_d / (b f) (stand-off z, base b, focal length f in pixels) and every
    length it reconstructs scale with the pixel's footprint z / f, and f in pixels is
    proportional to the image width for one sensor and lens (binned, or rendered at a lower
    resolution). So MPE = MPE_specified × specified_width / width. The factor is never below 1:
    a finer camera than the specification's promises nothing the specification does not."""
    if not specified_width_px or not width_px:
        return dict(mpe_mm), None
    factor = max(1.0, float(specified_width_px) / float(width_px))
    if factor == 1.0:
        return dict(mpe_mm), None
    return ({k: round(v * factor, 4) for k, v in mpe_mm.items()},
            {"specified_width_px": int(specified_width_px), "width_px": int(width_px),
             "factor": round(factor, 4), "specified_mm": dict(mpe_mm),
             "formula": "MPE x specified width / width: the pixel's footprint at the "
                        "stand-off (sigma_z = z^2 sigma_d / (b f), f in pixels)"})


@dataclass
class AcceptanceResult:
    """Per parameter: each position's value and the figure (largest |value|) against its MPE."""

    values: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    mpe: dict[str, float] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    #: how Part 2's MPEs were derived from the specified ones (:func:`mpe_for_resolution`)
    mpe_basis: dict[str, Any] | None = None
    #: the test's expanded uncertainty (k = 2, mm) per parameter: the artefacts' certificates
    test_u: dict[str, float] = field(default_factory=dict)
    #: the decision rule (:mod:`scancell.analysis.decision`)
    rule: str = DEFAULT_RULE

    def add(self, parameter: str, value: float, **info: Any) -> None:
        self.values.setdefault(parameter, []).append({"value_mm": float(value), **info})

    def figure(self, parameter: str) -> float | None:
        v = self.values.get(parameter)
        return None if not v else float(max(abs(x["value_mm"]) for x in v))

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        order = [*PARAMETERS, "SD3"]
        for p, v in sorted(self.values.items(), key=lambda kv: order.index(kv[0])
                           if kv[0] in order else len(order)):
            fig = self.figure(p)
            mpe = self.mpe.get(p)
            U = float(self.test_u.get(p, 0.0))
            verdict = None if mpe is None else decide(fig, U, Zone(-np.inf, mpe), self.rule)
            out[p] = {"figure_mm": fig, "mpe_mm": mpe, "U_mm": U, "positions": len(v),
                      "verdict": verdict, "pass": None if mpe is None else verdict == PASS,
                      "values": v}
        verdicts = [x["verdict"] for x in out.values() if x["verdict"] is not None]
        verdict = (None if not verdicts
                   else FAIL if self.errors else combine(verdicts))
        return {"parameters": out, "errors": self.errors, "verdict": verdict,
                "pass": None if verdict is None else verdict == PASS,
                "decision_rule": self.rule,
                "test_uncertainty": ("the artefacts' certificates, from the cell config"
                                     if self.test_u else "not stated: U = 0"),
                **({"mpe_basis": self.mpe_basis} if self.mpe_basis else {})}


def evaluate(samples: list[dict[str, Any]], clouds: dict[str, np.ndarray],
             world_clouds: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """The acceptance report of a job: ``samples`` (``scancell.AcceptanceSample``) and each
    scan's cloud (scan id -> MCS points, mm); for Part 3 samples, each station scan's cloud in
    the tracker frame (``world_clouds``: fused through the ECS and the hand-eye calibration).
    A scan that cannot be evaluated is named in ``errors`` and fails the test."""
    part2 = [s for s in samples if s.get("part", 2) != 3]
    part3 = [s for s in samples if s.get("part", 2) == 3]
    first = (part2 or samples or [{}])[0]
    mpe = dict(first.get("mpe_mm", {}))
    test_u = {k: v for k, v in (first.get("test_u_mm") or {}).items() if k != "SD3"}
    if part3 and "SD" in part3[0].get("mpe_mm", {}):
        mpe["SD3"] = part3[0]["mpe_mm"]["SD"]
    if part3 and "SD3" in (part3[0].get("test_u_mm") or {}):
        test_u["SD3"] = part3[0]["test_u_mm"]["SD3"]
    result = AcceptanceResult(mpe=mpe, mpe_basis=(part2 or [{}])[0].get("mpe_basis"),
                              test_u=test_u, rule=first.get("decision_rule") or DEFAULT_RULE)
    for s in part3:
        p, art = s["placement"], s["artefact"]
        scans = [st["scan_id"] for st in s["stations"]]
        where = f"ball bar (part 3) position {p['index'] + 1} (scans {', '.join(scans)})"
        missing = [sid for sid in scans if (world_clouds or {}).get(sid) is None]
        if missing:
            result.errors.append(f"{where}: no fused cloud for {', '.join(missing)}")
            continue
        c, d = np.asarray(p["centre_world"]), np.asarray(p["direction_world"])
        half = 0.5 * art["length_mm"] * d / np.linalg.norm(d)
        try:
            r = sphere_spacing(np.concatenate([world_clouds[sid] for sid in scans]),
                               art["length_mm"], art["sphere_diameter_mm"], (c - half, c + half))
        except AcceptanceError as exc:
            result.errors.append(f"{where}: {exc}")
            continue
        result.add("SD3", r["SD"], position=p["index"], length_mm=r["length_mm"],
                   scans=scans)
    for s in sorted(part2, key=lambda s: (s["placement"]["kind"], s["placement"]["index"])):
        p, art, sid = s["placement"], s["artefact"], s["scan_id"]
        where = f"{p['kind']} position {p['index'] + 1} (scan {sid})"
        cloud = clouds.get(sid)
        if cloud is None or len(cloud) == 0:
            result.errors.append(f"{where}: no cloud")
            continue
        centre, direction = np.asarray(p["centre_mcs"]), np.asarray(p["direction_mcs"])
        try:
            if p["kind"] == "sphere":
                r = probing(cloud, art["diameter_mm"], centre)
                result.add("PF", r["PF"], position=p["index"], points=r["points"], scan=sid)
                result.add("PS", r["PS"], position=p["index"], diameter_mm=r["diameter_mm"],
                           scan=sid)
            elif p["kind"] == "ballbar":
                half = 0.5 * art["length_mm"] * direction / np.linalg.norm(direction)
                r = sphere_spacing(cloud, art["length_mm"], art["sphere_diameter_mm"],
                                   (centre - half, centre + half))
                result.add("SD", r["SD"], position=p["index"], length_mm=r["length_mm"],
                           scan=sid)
            else:
                r = flatness(cloud, centre, direction, float(max(art["size_mm"])))
                result.add("F", r["F"], position=p["index"], points=r["points"], scan=sid)
        except AcceptanceError as exc:
            result.errors.append(f"{where}: {exc}")
    out = result.to_json()
    if part2:
        out["volume"] = part2[0].get("volume")
    return out
