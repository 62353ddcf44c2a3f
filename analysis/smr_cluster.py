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

from dataclasses import dataclass

import numpy as np
from scancell.analysis.handeye import kabsch
from scancell.analysis.tracker_network import TrackerSigma
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
    Tt = np.eye(4) if T_world_from_tracker is None else np.asarray(T_world_from_tracker, float)
    Ws = []
    for p in w:  # the beam runs from the tracker to the point
        p_tracker = Tt[:3, :3].T @ (p - Tt[:3, 3])
        Wt = sigma.whitening(p_tracker)
        Ws.append(Wt @ Tt[:3, :3].T)  # whitening of a world-frame difference
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
