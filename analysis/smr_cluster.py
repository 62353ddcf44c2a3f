"""An SMR cluster on the scanner (issue 19): its calibration in the scanner frame, and the
scanner's pose at a station from the SMRs the tracker sees, without J6 turns.

Frames and units: ``mcs`` is the scanner's measuring frame (the left camera, mm); ``world`` the
tracker's. The cluster is the SMR centres in ``mcs``. At a station the tracker measures the
visible SMRs in ``world``; the pose ``T_world_from_mcs`` is the weighted best fit of the
cluster onto them, each point weighted by the tracker's radial and transverse 1-sigma (as in
analysis/tracker_network.py). Its 6 x 6 covariance is over (rotation vector in ``world``, rad;
translation, mm), the same convention as the network's stations.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from scancell.analysis.handeye import kabsch
from scancell.analysis.tracker_network import TrackerSigma
from scancell.model.cell_geometry import CellGeometry
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

#: the smallest spread of the visible SMRs across their best line (mm) for a usable pose
MIN_SPREAD_MM = 20.0


class ClusterGeometryError(ValueError):
    """Too few SMRs, or SMRs on a line: the scanner's pose is not fixed by them."""


@dataclass(frozen=True)
class ClusterPose:
    T_world_from_mcs: np.ndarray
    #: 6 x 6 covariance of (rotation vector rad, translation mm) from the tracker's sigmas
    cov: np.ndarray
    #: SMR -> |measured - fitted| (mm)
    residual_mm: dict[str, float]
    #: the visible SMRs' spread: smallest over largest singular value of their centred
    #: positions (0: on a line), and the smallest spread itself (mm)
    conditioning: float
    spread_mm: float

    def sigma(self) -> dict[str, float]:
        """1-sigma of the pose: translation (mm) and rotation (arc seconds)."""
        return {"translation_mm": float(np.sqrt(np.trace(self.cov[3:, 3:]))),
                "rotation_arcsec": float(np.degrees(np.sqrt(np.trace(self.cov[:3, :3])))
                                         * 3600.0)}


def check_cluster_geometry(points: dict[str, np.ndarray], what: str) -> tuple[float, float]:
    """(conditioning, spread mm) of the SMRs; raises ClusterGeometryError for fewer than 3 or a
    line, naming them."""
    names = sorted(points)
    if len(names) < 3:
        raise ClusterGeometryError(f"{what}: {len(names)} SMR(s) ({', '.join(names) or 'none'}):"
                                   f" a pose needs at least 3 not on a line")
    p = np.array([points[n] for n in names], float)
    s = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    spread = float(s[1] / np.sqrt(len(names)))
    if spread < MIN_SPREAD_MM:
        raise ClusterGeometryError(f"{what}: SMRs {', '.join(names)} lie on a line (spread "
                                   f"{spread:.1f} mm across it, need {MIN_SPREAD_MM:g}): they do "
                                   f"not fix the rotation about it")
    return float(s[1] / s[0]), spread


def whitenings(measured_world: np.ndarray, sigma: TrackerSigma,
               T_world_from_tracker: np.ndarray | None = None) -> list[np.ndarray]:
    """Each tracker point's whitening of a world-frame difference (3 x 3, 1/mm): the beam runs
    from the tracker to the point, its range and angles each with their sigma."""
    Tt = np.eye(4) if T_world_from_tracker is None else np.asarray(T_world_from_tracker, float)
    return [sigma.whitening(Tt[:3, :3].T @ (p - Tt[:3, 3])) @ Tt[:3, :3].T
            for p in np.asarray(measured_world, float)]


def cluster_pose_response(cluster_mcs: np.ndarray, measured_world: np.ndarray,
                          T_world_from_mcs: np.ndarray, sigma: TrackerSigma,
                          T_world_from_tracker: np.ndarray | None = None
                          ) -> tuple[np.ndarray, np.ndarray]:
    """How :func:`fit_cluster_pose`'s answer ``T_world_from_mcs`` moves with its inputs, to
    first order (Gauss-Newton at the fit): the change ``x = (rotation vector, rad; shift, mm)``,
    with ``R = exp([ω]) R₀`` and ``t = t₀ + τ``, is ``A δw + B δc`` for changes δw of the
    measured points (world, n x 3, flattened) and δc of the cluster's centres (mcs, likewise).
    A Monte Carlo of the pose then draws the estimator the fusion uses at the cost of two
    matrix products."""
    c = np.asarray(cluster_mcs, float)
    R0 = np.asarray(T_world_from_mcs, float)[:3, :3]
    Ws = whitenings(measured_world, sigma, T_world_from_tracker)
    n = len(c)
    J = np.zeros((3 * n, 6))
    Wblk = np.zeros((3 * n, 3 * n))
    for i, (ci, W) in enumerate(zip(c, Ws, strict=True)):
        q = R0 @ ci
        skew = np.array([[0, -q[2], q[1]], [q[2], 0, -q[0]], [-q[1], q[0], 0]])
        J[3 * i:3 * i + 3] = W @ np.hstack([-skew, np.eye(3)])
        Wblk[3 * i:3 * i + 3, 3 * i:3 * i + 3] = W
    solve = np.linalg.solve(J.T @ J, J.T)  # 6 x 3n
    # the residual W (R c + t − w): ∂/∂w = −W, ∂/∂c = W R₀
    A = solve @ Wblk
    B = -solve @ Wblk @ np.kron(np.eye(n), R0)
    return A, B


def fit_cluster_pose(cluster_mcs: dict[str, np.ndarray], measured_world: dict[str, np.ndarray],
                     sigma: TrackerSigma, T_world_from_tracker: np.ndarray | None = None
                     ) -> ClusterPose:
    """The scanner's pose from the visible SMRs (those in both maps). ``T_world_from_tracker``
    places the tracker (its range and beam direction weight each point; default: at the
    origin of ``world``)."""
    names = sorted(set(cluster_mcs) & set(measured_world))
    conditioning, spread = check_cluster_geometry({n: cluster_mcs[n] for n in names},
                                                  "cluster pose")
    c = np.array([cluster_mcs[n] for n in names], float)
    w = np.array([measured_world[n] for n in names], float)
    Ws = whitenings(w, sigma, T_world_from_tracker)
    T0 = kabsch(c, w)

    def residuals(x: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(x[:3]).as_matrix() @ T0[:3, :3]
        pred = c @ R.T + x[3:]
        return np.concatenate([W @ (q - m) for W, q, m in zip(Ws, pred, w, strict=True)])

    sol = least_squares(residuals, np.concatenate([np.zeros(3), T0[:3, 3]]), method="lm")
    R = Rotation.from_rotvec(sol.x[:3]).as_matrix() @ T0[:3, :3]
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, sol.x[3:]
    J = sol.jac  # at rotation vector ~0 about T0, which the fit barely moves
    cov = np.linalg.inv(J.T @ J)
    res = np.linalg.norm(c @ R.T + T[:3, 3] - w, axis=1)
    return ClusterPose(T, cov, {n: float(r) for n, r in zip(names, res, strict=True)},
                       conditioning, spread)


@dataclass(frozen=True)
class ClusterCalibration:
    #: SMR -> centre in ``mcs`` (mm)
    points_mcs: dict[str, np.ndarray]
    #: SMR -> 1-sigma of each coordinate of its centre (mm), from the scatter over the poses
    sigma_mm: dict[str, np.ndarray]
    #: SMR -> how many poses saw it
    seen: dict[str, int]

    def to_json(self) -> dict[str, object]:
        return {n: {"mcs_mm": self.points_mcs[n].round(4).tolist(),
                    "sigma_mm": self.sigma_mm[n].round(5).tolist(), "poses": self.seen[n]}
                for n in sorted(self.points_mcs)}


def calibrate_cluster(poses: list[np.ndarray], measured_world: list[dict[str, np.ndarray]],
                      min_poses: int = 2) -> ClusterCalibration:
    """The cluster in ``mcs`` from poses whose ``T_world_from_mcs`` is known (the hand-eye job's
    ball poses, through its ECS and the hand-eye calibration) and the SMRs the tracker measured
    at each. Every SMR seen from ``min_poses`` poses or more is kept; raises
    ClusterGeometryError when fewer than 3, or a line, remain."""
    if len(poses) != len(measured_world):
        raise ValueError(f"{len(poses)} poses but {len(measured_world)} sets of SMRs")
    per: dict[str, list[np.ndarray]] = {}
    for T, seen in zip(poses, measured_world, strict=True):
        T = np.asarray(T, float)
        for n, p in seen.items():
            per.setdefault(n, []).append(T[:3, :3].T @ (np.asarray(p, float) - T[:3, 3]))
    kept = {n: np.array(v) for n, v in per.items() if len(v) >= min_poses}
    points = {n: v.mean(axis=0) for n, v in kept.items()}
    check_cluster_geometry(points, f"cluster calibration ({len(poses)} poses)")
    sigma = {n: v.std(axis=0, ddof=1) / np.sqrt(len(v)) for n, v in kept.items()}
    return ClusterCalibration(points, sigma, {n: len(v) for n, v in kept.items()})


def cluster_turns(facing: Callable[[float], Iterable[str]], candidates_deg: Iterable[float],
                  sightings: int = 3, first: Iterable[float] = ()) -> list[float]:
    """J6 turns (deg, relative) for the cluster's calibration: after the turns ``first`` (the
    ECS's, whose SMRs count), greedily the candidate that adds the most sightings still
    missing until each SMR ``facing(turn)`` can name is seen from ``sightings`` turns or no
    candidate adds one. ``facing(turn)`` names the SMRs that face the tracker at that turn."""
    first = [float(a) for a in first]
    seen_at = {float(a): set(facing(float(a))) for a in candidates_deg}
    for a in first:
        seen_at.setdefault(a, set(facing(a)))
    count: dict[str, int] = {n: 0 for names in seen_at.values() for n in names}
    chosen = list(first)
    for a in chosen:
        for n in seen_at[a]:
            count[n] += 1

    def gain(a: float) -> int:
        return sum(1 for n in seen_at[a] if count[n] < sightings)

    while True:
        left = [a for a in seen_at if a not in chosen]
        if not left:
            break
        best = max(left, key=lambda a: (gain(a), -abs(a)))
        if gain(best) == 0:
            break
        chosen.append(best)
        for n in seen_at[best]:
            count[n] += 1
    return chosen[len(first):]


def locate_by_cluster(cal: ClusterCalibration, measured_world: list[dict[str, np.ndarray]],
                      sigma: TrackerSigma, T_world_from_tracker: np.ndarray | None = None
                      ) -> dict[str, tuple[np.ndarray, np.ndarray, int]]:
    """SMRs not in ``cal`` located in ``mcs`` from poses where the tracker saw them beside >= 3
    calibrated ones: at each such pose the scanner's pose is fitted to the calibrated SMRs
    (:func:`fit_cluster_pose`) and the others carried into ``mcs`` through it. Returns name ->
    (centre in mcs, 1-sigma per axis: the pose's covariance and the tracker's, and the scatter
    over the poses, mm, how many poses). Poses with fewer than 3 calibrated SMRs are skipped."""
    found: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    Tt = np.eye(4) if T_world_from_tracker is None else np.asarray(T_world_from_tracker, float)
    for seen in measured_world:
        known = {n: p for n, p in seen.items() if n in cal.points_mcs}
        new = {n: np.asarray(p, float) for n, p in seen.items() if n not in cal.points_mcs}
        if not new or len(known) < 3:
            continue
        try:
            fit = fit_cluster_pose(cal.points_mcs, known, sigma, Tt)
        except ClusterGeometryError:
            continue
        R, t = fit.T_world_from_mcs[:3, :3], fit.T_world_from_mcs[:3, 3]
        for n, p in new.items():
            p_mcs = R.T @ (p - t)
            # p_mcs = Rᵀ Exp(-w)(p - t - dt): its Jacobian in (w, dt), plus the point's own noise
            d = p - t
            J = np.hstack([R.T @ np.array([[0, -d[2], d[1]], [d[2], 0, -d[0]], [-d[1], d[0], 0]]),
                           -R.T])
            W = sigma.whitening(Tt[:3, :3].T @ (p - Tt[:3, 3])) @ Tt[:3, :3].T
            cov = J @ fit.cov @ J.T + R.T @ np.linalg.inv(W.T @ W) @ R
            found.setdefault(n, []).append((p_mcs, np.sqrt(np.diag(cov))))
    out = {}
    for n, v in found.items():
        pts = np.array([p for p, _ in v])
        own = np.sqrt(np.mean([s ** 2 for _, s in v], axis=0) / len(v))
        scatter = pts.std(axis=0, ddof=1) / np.sqrt(len(v)) if len(v) > 1 else np.zeros(3)
        out[n] = (pts.mean(axis=0), np.hypot(own, scatter), len(v))
    return out


def cluster_tilts(geometry: CellGeometry, q0_rad: np.ndarray, known: set[str],
                  wanted: set[str], poses: int = 2) -> list[tuple[np.ndarray, set[str]]]:
    """Robot poses (joints, rad) near ``q0_rad`` at which SMRs of ``wanted`` face the tracker
    together with >= 3 of ``known`` (so :func:`locate_by_cluster` can place them). For each
    pair of a wanted and a known SMR the scanner is turned about its cluster's centre, the
    least from ``q0_rad``, until the beam runs along the bisector of their two openings
    (or a little nearer either, in steps of 5 %: the SMRs sit off the centre, so their
    beams differ by a few degrees), and solved by the robot model inside its joint limits.
    Greedy: up to ``poses`` poses for each wanted SMR any candidate shows; each with the SMRs
    facing there."""
    from scancell.model.robot_model import IKError

    T0 = geometry.T_world_from_mcs(q0_rad, None)
    nominal = geometry.cluster_nominal()
    centre_mcs = np.mean([c for c, _ in nominal.values()], axis=0)
    centre = T0[:3, :3] @ centre_mcs + T0[:3, 3]
    beam = np.asarray(geometry.tracker_world_mm, float) - centre
    b = T0[:3, :3].T @ (beam / np.linalg.norm(beam))  # the beam in mcs now
    base_inv = np.linalg.inv(geometry.base_at(None))
    T_fm_inv = np.linalg.inv(geometry.T_flange_from_mcs)
    candidates: list[tuple[np.ndarray, set[str]]] = []
    tried: set[tuple] = set()
    for w in sorted(wanted):
        for k in sorted(known):
            ow, ok = nominal[w][1], nominal[k][1]
            pair = tuple(np.round(np.concatenate([ow, ok]), 6))
            if pair in tried:  # SMRs of one face share their opening: one search per face pair
                continue
            tried.add(pair)
            for f in np.arange(0.3, 0.71, 0.05):
                target = f * ow + (1 - f) * ok
                if np.linalg.norm(target) < 1e-6:
                    continue
                target /= np.linalg.norm(target)
                # R_small maps the wanted beam direction onto the present one (both in mcs)
                axis = np.cross(target, b)
                angle = np.arctan2(np.linalg.norm(axis), float(target @ b))
                R_small = (Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
                           if np.linalg.norm(axis) > 1e-9 else np.eye(3))
                T = np.eye(4)
                T[:3, :3] = T0[:3, :3] @ R_small
                T[:3, 3] = centre - T[:3, :3] @ centre_mcs
                try:
                    q = geometry.robot.ik(base_inv @ T @ T_fm_inv, q0_rad)
                except IKError:
                    continue
                facing = set(geometry.facing_smrs(q, None))
                if facing & wanted and len(facing & known) >= 3:
                    candidates.append((q, facing))
    chosen: list[tuple[np.ndarray, set[str]]] = []
    count = {n: 0 for n in wanted}
    while candidates:
        best = max(candidates, key=lambda c: (sum(count[n] < poses for n in c[1] & wanted),
                                              len(c[1] & known)))
        if not any(count[n] < poses for n in best[1] & wanted):
            break
        chosen.append(best)
        candidates.remove(best)
        for n in best[1] & wanted:
            count[n] += 1
    return chosen
