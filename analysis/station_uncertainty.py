"""Uncertainty of each station and each point by Monte Carlo over every modelled source, as
SpatialAnalyzer's uncertainty field analysis does: draw each source from its stated 1-sigma,
rebuild the station's transform ``T_world_from_mcs = ECS(P1..P3) · T_ecs_from_mcs`` and move its
points; the spread of the points' displacement along the surface normal is their uncertainty.
That is the component a distance to the true surface (the true error) or to another station's
surface (the overlap metric) sees: a point moved along the surface is not in error. The depth
noise moves a point along its camera ray, which meets the surface at an angle: its normal
component is the depth error times ``(c·n) / c_z`` for the point c and the normal n in MCS.

Sources and where their 1-sigma comes from (docs/explanation/metrology.md, "Uncertainty"):

==================  =======  ==============================================================
source              scope    stated 1-sigma
==================  =======  ==============================================================
tracker_noise       station  each averaged point's own sigma (the tracker's, /√repeats)
tracker_systematic  job      half the tracker's stated per-shot sigma, common to the points
                             (an even split of its stated typical error into random and
                             systematic parts: an assumption)
refraction          job      range scale from the weather's uncertainty (or 10 ppm unknown)
tracker_location    job      the nests' location of the tracker (fit RMS, or drift allowed)
settling            station  the arm's residual motion between P1 and the scan
hand_eye            scanner  the calibration's covariance as a move in MCS (its rotation and
                             translation correlated), or its two sigmas if not stated
cluster_calibration scanner  the cluster SMRs' calibrated centres: one of the calibration's
                             joint draws (its SMRs move together: a common error of the ECS,
                             the fit of a tipped pose), plus independently what of each SMR's
                             stated sigma the draws do not explain; stations whose pose came
                             from the SMR cluster only
scanner_scale       scanner  the scanner's scale stability (warm-up), ppm
scanner_noise       point    each point's depth noise (the scanner's noise model), scaled in
                             each draw by the model's own stated accuracy (a relative 1-sigma)
==================  =======  ==============================================================

``job`` sources are common to the stations between two re-locations or calibrations and fixed
in the tracker's frame: they move the whole model alike and cancel in overlaps. ``scanner``
sources are common too but fixed in the scanner: each station carries the same error turned
with its own orientation, so two stations that look from different directions disagree by it
(:func:`scanner_fixed_overlap`). ``station`` and ``point`` sources differ per station.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scancell.analysis.metrics import mean_spacing, normals
from scancell.analysis.station_pose import StationPose
from scancell.analysis.uncertainty import along_normal
from scancell.model.transforms import make_T
from scipy.spatial.transform import Rotation

ARCSEC = np.pi / 180 / 3600

SCOPES = {"tracker_noise": "station", "tracker_systematic": "job", "refraction": "job",
          "tracker_location": "job", "settling": "station", "hand_eye": "scanner",
          "cluster_calibration": "scanner", "scanner_scale": "scanner", "scanner_noise": "point"}


#: the scanner sources that move every station's cloud by one error fixed in the scanner
RIGID_IN_SCANNER = ("hand_eye", "scanner_scale")


@dataclass(frozen=True)
class StatedSources:
    """The stated 1-sigma of the sources (mm, ppm, arcsec) a station's job knows."""

    refraction_ppm: float = 10.0
    tracker_systematic_mm: float = 0.0
    location_mm: float = 0.0
    settle_mm: float = 0.0
    scanner_scale_ppm: float = 0.0
    hand_eye_translation_mm: float = 0.0
    hand_eye_rotation_arcsec: float = 0.0
    #: the hand-eye's 6 x 6 covariance as a move in MCS (rotation vector rad, translation mm;
    #: ``HandEyeResult.covariance_mcs``); None: a calibration from before it was stated, drawn
    #: from the two sigmas as if independent (which overstates its effect at the points)
    hand_eye_covariance: tuple[tuple[float, ...], ...] | None = None
    #: relative 1-sigma of the scanner's noise model itself (0.15: it predicts 15 % too much or
    #: too little noise), one factor per draw common to the station's points
    scanner_noise_rel: float = 0.0
    #: the tracker's frame origin in world (refraction scales ranges about it)
    tracker_origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @classmethod
    def from_json(cls, d: dict[str, Any] | None, hand_eye: dict[str, Any]) -> StatedSources:
        d = dict(d or {})
        return cls(refraction_ppm=float(d.get("refraction_ppm", 10.0)),
                   tracker_systematic_mm=float(d.get("tracker_systematic_mm", 0.0)),
                   location_mm=float(d.get("location_mm", 0.0)),
                   settle_mm=float(d.get("settle_mm", 0.0)),
                   scanner_scale_ppm=float(d.get("scanner_scale_ppm", 0.0)),
                   hand_eye_translation_mm=float(hand_eye.get("translation_sigma_mm") or 0.0),
                   hand_eye_rotation_arcsec=float(hand_eye.get("rotation_sigma_arcsec") or 0.0),
                   hand_eye_covariance=(None if hand_eye.get("covariance_mcs") is None else
                                        tuple(tuple(map(float, r))
                                              for r in hand_eye["covariance_mcs"])),
                   scanner_noise_rel=float(d.get("scanner_noise_rel", 0.0)),
                   tracker_origin_mm=tuple(d.get("tracker_origin_mm", (0.0, 0.0, 0.0))))


@dataclass
class StationUncertainty:
    #: per source: mean |displacement along the surface normal| over the points (mm), its share
    share_mm: dict[str, float]
    #: the station's mean |error| (mm) at 2.5 % and 97.5 % of the draws: the 95 % interval
    interval_mm: tuple[float, float]
    #: per point of the station's even sample (every ``step``-th point; a full-size station's
    #: 3.5 M would be 28 MB a station, kept for the whole job): 1-sigma of the displacement
    #: along the surface normal, all sources (mm)
    point_sigma_mm: np.ndarray = field(repr=False)
    #: the stated sources drawn
    stated: StatedSources = field(default_factory=StatedSources, repr=False)
    #: the station's move over the draws of every source but the points' noise (None: not
    #: drawn)
    pose: PoseCovariance | None = field(default=None, repr=False)

    def to_json(self) -> dict[str, Any]:
        return {"share_mm": {k: round(v, 5) for k, v in self.share_mm.items()},
                "interval95_mm": [round(v, 5) for v in self.interval_mm],
                "point_u95_mm": {"mean": round(float(1.96 * self.point_sigma_mm.mean()), 5),
                                 "max": round(float(1.96 * self.point_sigma_mm.max()), 5)}}


def _rot(rng: np.random.Generator, sigma_rad: float) -> np.ndarray:
    v = rng.normal(0.0, sigma_rad, 3)
    a = float(np.linalg.norm(v))
    if a < 1e-15:
        return np.eye(3)
    k = v / a
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


def _scanner_error(source: str, rng: np.random.Generator, T_em: np.ndarray, s: StatedSources
                   ) -> tuple[np.ndarray, float]:
    """One draw of a ``scanner`` source: the hand-eye it gives and the scanner's scale."""
    T_em2 = T_em.copy()
    scale = 1.0
    if source == "hand_eye" and s.hand_eye_covariance is not None:
        d = rng.multivariate_normal(np.zeros(6), np.asarray(s.hand_eye_covariance),
                                    method="eigh")
        T_em2 = T_em @ make_T(Rotation.from_rotvec(d[:3]).as_matrix(), d[3:])
    elif source == "hand_eye":
        T_em2[:3, :3] = _rot(rng, s.hand_eye_rotation_arcsec * ARCSEC / np.sqrt(3)) @ T_em[:3, :3]
        T_em2[:3, 3] = T_em[:3, 3] + rng.normal(0.0, s.hand_eye_translation_mm / np.sqrt(3), 3)
    elif source == "scanner_scale":
        scale = 1.0 + rng.normal(0.0, s.scanner_scale_ppm * 1e-6)
    return T_em2, scale


def _cluster_error(rng: np.random.Generator, pose: StationPose) -> np.ndarray:
    """One draw of the cluster calibration's error at the station's SMRs (n x 3, mm)."""
    sigma = np.asarray(pose.cluster_sigma_mm, float)
    draws = pose.cluster_draws
    if draws is None or not len(draws):
        return rng.standard_normal(sigma.shape) * sigma
    rest = np.sqrt(np.maximum(0.0, sigma**2 - draws.var(axis=0)))
    return draws[rng.integers(len(draws))] + rng.standard_normal(sigma.shape) * rest


def _draw_move(sources: set[str], rng: np.random.Generator, pose: StationPose,
               s: StatedSources) -> tuple[np.ndarray, np.ndarray]:
    """One draw of the given sources' move of the station's points in world: ``X → M X + t``
    (M 3 x 3, t mm). Every source but the points' own noise moves the station rigidly
    (with the scanner's scale, a similarity)."""
    pts, sig, T_em = pose.points_mm, pose.sigma_mm, pose.T_ecs_from_mcs
    p = pts.copy()
    origin = np.asarray(s.tracker_origin_mm, float)
    if "tracker_noise" in sources:
        p = p + rng.standard_normal(p.shape) * sig
    if "tracker_systematic" in sources:
        p = p + rng.normal(0.0, s.tracker_systematic_mm, 3)
    if "refraction" in sources:
        p = origin + (p - origin) * (1.0 + rng.normal(0.0, s.refraction_ppm * 1e-6))
    if "tracker_location" in sources:
        p = p + rng.normal(0.0, s.location_mm / np.sqrt(3), 3)
    T_em2 = _scanner_error("hand_eye", rng, T_em, s)[0] if "hand_eye" in sources else T_em
    scale = _scanner_error("scanner_scale", rng, T_em, s)[1] if "scanner_scale" in sources \
        else 1.0
    cluster = pose.cluster_mcs
    if "cluster_calibration" in sources and cluster is not None:
        cluster = cluster + _cluster_error(rng, pose)
    T = pose.drawn_T_world_from_mcs(p, T_em2, cluster)
    T0 = pose.drawn_T_world_from_mcs(pose.points_mm, T_em)
    if scale == 1.0 and np.array_equal(T, T0):  # nothing drawn moves it: exactly no move
        M, t = np.eye(3), np.zeros(3)
    else:
        M = scale * T[:3, :3] @ T0[:3, :3].T
        t = T[:3, 3] - M @ T0[:3, 3]
    if "settling" in sources:
        t = t + rng.normal(0.0, s.settle_mm / np.sqrt(3), 3)
    return M, t


def _draw(sources: set[str], rng: np.random.Generator, pose: StationPose, cloud: np.ndarray,
          noise: np.ndarray, normal: np.ndarray, s: StatedSources, X0: np.ndarray,
          moves: list[tuple[np.ndarray, np.ndarray]] | None = None) -> np.ndarray:
    """One draw of the given sources: each point's displacement along its surface normal
    (``normal``, world; mm). ``noise``: each point's depth noise already carried onto the
    normal (mm). ``moves``: where the draw's move of the station (:func:`_draw_move`) is
    appended."""
    M, t = _draw_move(sources, rng, pose, s)
    if moves is not None:
        moves.append((M, t))
    d = np.einsum("ij,ij->i", X0 @ (M - np.eye(3)).T + t, normal)
    if "scanner_noise" in sources:
        k = max(0.0, 1.0 + rng.normal(0.0, s.scanner_noise_rel))
        d = d + rng.standard_normal(len(d)) * noise * k
    return d


@dataclass(frozen=True)
class PoseCovariance:
    """The spread of a station's move over the Monte Carlo draws, as a point's displacement
    ``D(X) = B (X - centre) + c`` (world, mm) is linear in its 12 numbers ``θ = (B, c)``: their
    covariance. A point's 1-sigma along a unit normal n is ``sqrt(J Σ Jᵀ)``, J = (n ⊗ (X -
    centre), n): exact for the drawn moves (all similarities), with no sampling of points."""

    centre: np.ndarray  # (3,) world, mm
    cov: np.ndarray  # (12, 12)

    @classmethod
    def of_moves(cls, moves: list[tuple[np.ndarray, np.ndarray]], centre: np.ndarray
                 ) -> PoseCovariance:
        theta = np.array([np.r_[(M - np.eye(3)).ravel(), (M - np.eye(3)) @ centre + t]
                          for M, t in moves])
        return cls(np.asarray(centre, float), np.cov(theta, rowvar=False))

    def sigma_along(self, points: np.ndarray, normals: np.ndarray, chunk: int = 500_000
                    ) -> np.ndarray:
        """Each point's 1-sigma (mm, float32) along its unit normal (world, N x 3 each)."""
        out = np.empty(len(points), np.float32)
        for a in range(0, len(points), chunk):
            y = np.asarray(points[a:a + chunk], float) - self.centre
            n = np.asarray(normals[a:a + chunk], float)
            J = np.empty((len(y), 12))
            J[:, :9] = (n[:, :, None] * y[:, None, :]).reshape(len(y), 9)
            J[:, 9:] = n
            # J Σ Jᵀ row by row through one matrix product (a three-operand einsum took 3 s
            # for a full-size station's 4.4 M points, this 0.2 s)
            out[a:a + chunk] = np.sqrt(np.maximum(np.einsum("ij,ij->i", J @ self.cov, J), 0))
        return out


#: the points a sample's normals are fitted in: enough for a neighbourhood of ~28 at 6 x their
#: spacing over a whole station
NORMAL_POINTS = 100_000


#: a cloud's normal sample: its step, the sampled points (MCS, mm, float64) and their unit
#: normals (None: fewer than 3 points)
DenseNormals = tuple[int, np.ndarray, np.ndarray | None]


def dense_normals(cloud: np.ndarray) -> DenseNormals:
    """Every ``step``-th point of ``cloud`` (MCS, mm), :data:`NORMAL_POINTS` of them, and the
    normal of each: the least-squares plane of its neighbours within 6 x their spacing (the
    metric tool's construction). Its sign is arbitrary."""
    step = max(1, len(cloud) // NORMAL_POINTS)
    dense = np.asarray(cloud[::step], float)
    return step, dense, (normals(dense, 6.0 * mean_spacing(dense)) if len(dense) >= 3 else None)


def sample_normals(cloud: np.ndarray, sample: int, dense: DenseNormals | None = None
                   ) -> tuple[np.ndarray, int]:
    """Unit normals (MCS) of every ``step``-th point of ``cloud`` (MCS, mm) and the ``step``
    (about ``len(cloud) / sample``), taken from :func:`dense_normals` (given, or fitted)."""
    dense_step, _, n = dense or dense_normals(cloud)
    step = dense_step * max(1, len(cloud) // max(1, sample) // dense_step)
    if n is None:
        return np.tile([0.0, 0.0, 1.0], (len(cloud[::step]), 1)), step
    return n[:: step // dense_step], step


def every_point_normals(cloud: np.ndarray, dense: DenseNormals | None = None) -> np.ndarray:
    """A unit normal (MCS, either sign) for every point of ``cloud`` (MCS, mm): that of
    the nearest point of :func:`dense_normals` (given, or fitted; a full-size station's 3.5 M
    neighbourhoods would take most of a fuse worker's time)."""
    from scipy.spatial import cKDTree

    _, points, n = dense or dense_normals(cloud)
    if n is None:
        return np.tile([0.0, 0.0, -1.0], (len(cloud), 1))
    _, nearest = cKDTree(points).query(np.asarray(cloud, np.float32), workers=-1)
    return n[nearest]


def point_sigmas(u: StationUncertainty, cloud_mcs: np.ndarray, T_world_from_mcs: np.ndarray,
                 depth_sigma_mm: np.ndarray | float, dense: DenseNormals | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Every point's 1-sigma along its surface normal (mm, float32 each): its own noise (the
    depth noise carried onto the normal, scaled by the noise model's stated accuracy) and its
    station pose's share (:class:`PoseCovariance`, every other source). Independent: the total
    is their root sum of squares."""
    n_mcs = every_point_normals(cloud_mcs, dense)
    noise = (np.broadcast_to(np.asarray(depth_sigma_mm, float), (len(cloud_mcs),))
             * along_normal(cloud_mcs, n_mcs)
             * np.sqrt(1.0 + u.stated.scanner_noise_rel ** 2)).astype(np.float32)
    if u.pose is None:
        return noise, np.zeros(len(cloud_mcs), np.float32)
    R, t = T_world_from_mcs[:3, :3], T_world_from_mcs[:3, 3]
    world = np.asarray(cloud_mcs, float) @ R.T + t
    return noise, u.pose.sigma_along(world, n_mcs @ R.T)


def sampled(pose: StationPose, cloud: np.ndarray, point_noise_mm: np.ndarray | float,
            sample: int, dense: DenseNormals | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """What :func:`_draw` works on: the sampled points (MCS), their depth noise carried onto
    the normal, their normals and positions in world, and the sampling step."""
    noise = np.broadcast_to(np.asarray(point_noise_mm, float), (len(cloud),))
    n_mcs, step = sample_normals(cloud, sample, dense)
    c = cloud[::step]
    with np.errstate(divide="ignore", invalid="ignore"):
        along_normal = np.abs(np.einsum("ij,ij->i", c, n_mcs) / c[:, 2])
    n = np.nan_to_num(noise[::step]) * np.nan_to_num(along_normal, nan=1.0, posinf=1.0)
    T0 = pose.drawn_T_world_from_mcs(pose.points_mm, pose.T_ecs_from_mcs)
    return c, n, n_mcs @ T0[:3, :3].T, c @ T0[:3, :3].T + T0[:3, 3], step


def station_uncertainty(pose: StationPose, cloud_mcs: np.ndarray,
                        point_noise_mm: np.ndarray | float, stated: StatedSources,
                        trials: int = 200, sample: int = 2000, seed: int = 0,
                        dense: DenseNormals | None = None) -> StationUncertainty:
    """Monte Carlo of one station: its pose's tracker points (world, mm) with their 1-sigma,
    the hand-eye and cluster calibrations, the station's cloud (MCS, mm) and its per-point
    depth noise (mm, along the left camera's optical axis). ``dense``: the cloud's
    :func:`dense_normals`, if already fitted."""
    cloud = np.asarray(cloud_mcs, float)
    c, n, normal, X0, _ = sampled(pose, cloud, point_noise_mm, sample, dense)
    args = (pose, c, n, normal, stated, X0)
    share = {}
    for k, src in enumerate(SCOPES):
        rng = np.random.default_rng([seed, k])
        share[src] = float(np.mean([np.abs(_draw({src}, rng, *args)).mean()
                                    for _ in range(trials)]))
    rng = np.random.default_rng([seed, 99])
    moves: list[tuple[np.ndarray, np.ndarray]] = []
    draws = np.array([_draw(set(SCOPES), rng, *args, moves=moves) for _ in range(trials)])
    station = np.abs(draws).mean(axis=1)
    lo, hi = np.percentile(station, [2.5, 97.5])
    return StationUncertainty(share, (float(lo), float(hi)), draws.std(axis=0), stated,
                              PoseCovariance.of_moves(moves, X0.mean(axis=0)))


def station_sigmas(name: str, pose: StationPose, cloud_mcs: np.ndarray,
                   depth_sigma_mm: np.ndarray | None, stated: StatedSources,
                   T_world_from_mcs: np.ndarray
                   ) -> tuple[StationUncertainty, tuple[np.ndarray, np.ndarray] | None]:
    """A station's Monte Carlo (seeded by its name: the live fusion and a recording's give the
    same) and, where its points carry their depth noise, each point's noise and pose share
    along its normal (:func:`point_sigmas`)."""
    import zlib

    dense = dense_normals(cloud_mcs)  # fitted once for both
    u = station_uncertainty(pose, cloud_mcs, 0.0 if depth_sigma_mm is None else depth_sigma_mm,
                            stated, seed=zlib.crc32(name.encode()), dense=dense)
    sigmas = (None if depth_sigma_mm is None
              else point_sigmas(u, cloud_mcs, T_world_from_mcs, depth_sigma_mm, dense))
    return u, sigmas


def pose_sigma(sigmas: tuple[np.ndarray, np.ndarray] | None) -> float:
    """A station's pose 1-sigma along the normal, the RMS over its points (mm; 0 unknown)."""
    if sigmas is None or not len(sigmas[1]):
        return 0.0
    return float(np.sqrt(np.mean(np.square(sigmas[1], dtype=np.float64))))


def scanner_fixed_overlap(clouds_world: dict[str, np.ndarray],
                          T_world_from_ecs: dict[str, np.ndarray], T_ecs_from_mcs: np.ndarray,
                          pairs: list[tuple[str, str]], stated: StatedSources,
                          trials: int = 100, sample: int = 1000, radius_mm: float = 3.0,
                          seed: int = 0) -> dict[str, float]:
    """The overlap error (mm) each ``scanner`` source puts between stations: one draw of the
    source for the whole job, each station moving its points (world, mm) with it in its own
    orientation; at the points of A (sampled) within ``radius_mm`` of B, the mean |difference
    of the two displacements along A's view|, averaged over the pairs and the draws. A pair
    without overlap is left out; no pair gives 0."""
    from scipy.spatial import cKDTree

    T_em = np.asarray(T_ecs_from_mcs, float)
    overlaps = []
    for a, b in pairs:
        pa, pb = np.asarray(clouds_world[a], float), np.asarray(clouds_world[b], float)
        if not len(pa) or not len(pb):
            continue
        x = pa[:: max(1, len(pa) // sample)]
        d, _ = cKDTree(pb[:: max(1, len(pb) // 20000)]).query(x, distance_upper_bound=radius_mm)
        x = x[np.isfinite(d)]
        if len(x):
            view = (np.asarray(T_world_from_ecs[a], float) @ T_em)[:3, 2]
            overlaps.append((a, b, x, view))
    out = {}
    for k, src in enumerate(RIGID_IN_SCANNER):
        if not overlaps:
            out[src] = 0.0
            continue
        rng = np.random.default_rng([seed, k])
        errs = []
        for _ in range(trials):
            T_em2, scale = _scanner_error(src, rng, T_em, stated)
            moved = {}
            for a, b, x, view in overlaps:
                for n in (a, b):
                    T_we = np.asarray(T_world_from_ecs[n], float)
                    T = T_we @ T_em
                    p = (x - T[:3, 3]) @ T[:3, :3]  # the overlap points in the station's MCS
                    T2 = T_we @ T_em2
                    moved[n] = (p * scale) @ T2[:3, :3].T + T2[:3, 3] - x
                errs.append(float(np.abs((moved[a] - moved[b]) @ view).mean()))
        out[src] = float(np.mean(errs))
    return out


def budget_by_source(stations: dict[str, StationUncertainty],
                     scanner_overlap_mm: dict[str, float] | None = None
                     ) -> dict[str, dict[str, Any]]:
    """Each source's share of the true error (mean over stations, mm) and of the overlap
    error: a station or point source differs between the two stations of an overlap (√2 of its
    share); a job source moves both alike and cancels; a scanner source's overlap share is
    ``scanner_overlap_mm`` (:func:`scanner_fixed_overlap`; without it, 0: unknown)."""
    out: dict[str, dict[str, Any]] = {}
    for src, scope in SCOPES.items():
        v = float(np.mean([u.share_mm[src] for u in stations.values()])) if stations else 0.0
        if src not in RIGID_IN_SCANNER and scope == "scanner":
            # the cluster's calibration: fixed in the scanner, but two stations fitted to
            # different SMRs of it disagree by it as independent stations would (at most)
            ov = float(np.sqrt(2.0)) * v
        elif scope == "scanner":
            ov = (scanner_overlap_mm or {}).get(src, 0.0)
        else:
            ov = 0.0 if scope == "job" else float(np.sqrt(2.0)) * v
        out[src] = {"scope": scope, "true_mm": round(v, 5), "overlap_mm": round(ov, 5)}
    return out


def coverage(intervals: dict[str, tuple[float, float]], true_mm: dict[str, float]
             ) -> dict[str, Any]:
    """The share of stations whose true error lies inside their predicted 95 % interval."""
    names = sorted(set(intervals) & set(true_mm))
    inside = {n: bool(intervals[n][0] <= true_mm[n] <= intervals[n][1]) for n in names}
    return {"share": (sum(inside.values()) / len(inside)) if inside else None,
            "stations": len(inside), "outside": sorted(n for n, ok in inside.items() if not ok)}
