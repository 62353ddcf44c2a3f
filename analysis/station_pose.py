"""A station's scanner pose from what the tracker measured there, by either ECS method:

- ``j6`` (the seed paper's): the rear SMR at P1..P3 (J6 turns) gives ``T_world_from_ecs``; the
  hand-eye ``T_ecs_from_mcs`` gives the scanner.
- ``cluster`` (issue 19): the SMRs of the cluster the tracker saw at the station, fitted to the
  cluster's calibration in ``mcs`` (the hand-eye job measured it), give ``T_world_from_mcs``
  directly; weighted by the tracker's radial and transverse sigmas.

Both end in ``T_world_from_mcs``; the fuse worker keeps the frame tree ``world <- ecs_i <-
mcs_i`` with ``T_world_from_ecs = T_world_from_mcs · T_ecs_from_mcs⁻¹`` for a cluster station.
Units mm; ``world`` is the tracker's frame after the nests' re-location.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from scancell.analysis.handeye import kabsch
from scancell.analysis.smr_cluster import (
    ClusterGeometryError,
    cluster_pose_response,
    fit_cluster_pose,
)
from scancell.analysis.tracker_network import TrackerSigma
from scancell.model.ecs import DegenerateGeometry, ecs_for_frame
from scancell.protocols.plan import DEFAULT_J6_ANGLES_DEG, ECS_METHODS
from scipy.spatial.transform import Rotation


class StationPoseError(ValueError):
    """The station's tracker points do not give a pose (degenerate, or no calibration)."""


@dataclass(frozen=True)
class StationPose:
    """What a station's pose is built from; :meth:`T_world_from_mcs` rebuilds it from drawn
    points and a drawn hand-eye (the Monte Carlo of analysis/station_uncertainty.py)."""

    method: str
    #: the tracker points (world, mm), n x 3, and their 1-sigma per axis
    points_mm: np.ndarray
    sigma_mm: np.ndarray
    T_ecs_from_mcs: np.ndarray
    #: j6: the J6 angles the points were measured at, and the hand-eye's frame angles
    j6_deg: tuple[float, ...] = ()
    frame_j6_deg: tuple[float, ...] = ()
    #: cluster: the SMRs' names, their calibrated centres in mcs (n x 3) and 1-sigma
    names: tuple[str, ...] = ()
    cluster_mcs: np.ndarray | None = None
    cluster_sigma_mm: np.ndarray | None = None
    T_world_from_tracker: np.ndarray | None = None
    #: cluster: joint draws of the calibration (draws x n x 3, deviations in mcs, mm), from
    #: ``smr_cluster_draws`` of the hand-eye; None: its SMRs are drawn one by one
    cluster_draws: np.ndarray | None = None

    def T_world_from_mcs(self, points_mm: np.ndarray | None = None,
                         T_ecs_from_mcs: np.ndarray | None = None,
                         cluster_mcs: np.ndarray | None = None,
                         weighted: bool = False) -> np.ndarray:
        """The pose from these (or drawn) points, hand-eye and cluster. ``weighted``: the
        cluster fit weighted by the tracker's sigmas (the pose the fusion uses); otherwise a
        plain best fit, fast enough for Monte Carlo draws."""
        p = self.points_mm if points_mm is None else points_mm
        T_em = self.T_ecs_from_mcs if T_ecs_from_mcs is None else T_ecs_from_mcs
        if self.method == "j6":
            return ecs_for_frame(p, list(self.j6_deg), list(self.frame_j6_deg)) @ T_em
        c = self.cluster_mcs if cluster_mcs is None else cluster_mcs
        # the cluster was located in mcs through the hand-eye: a different hand-eye moves it
        # rigidly in mcs, so the station's pose carries the hand-eye's error as a J6 one does
        moved = np.linalg.inv(T_em) @ self.T_ecs_from_mcs
        c = c @ moved[:3, :3].T + moved[:3, 3]
        if weighted:
            return fit_cluster_pose(dict(zip(self.names, c, strict=True)),
                                    dict(zip(self.names, p, strict=True)), TrackerSigma(),
                                    self.T_world_from_tracker).T_world_from_mcs
        return kabsch(c, p)

    @cached_property
    def _weighted_fit(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The weighted cluster fit and how it moves with its inputs (A, B:
        :func:`scancell.analysis.smr_cluster.cluster_pose_response`)."""
        T = self.T_world_from_mcs(weighted=True)
        A, B = cluster_pose_response(self.cluster_mcs, self.points_mm, T, TrackerSigma(),
                                     self.T_world_from_tracker)
        return T, A, B

    def drawn_T_world_from_mcs(self, points_mm: np.ndarray, T_ecs_from_mcs: np.ndarray,
                               cluster_mcs: np.ndarray | None = None) -> np.ndarray:
        """The pose the fusion's estimator gives for drawn points, hand-eye and cluster: the
        J6 frame as it is; the cluster's weighted fit to first order about its answer (a
        Monte Carlo's draws move it by micrometres, where the first order is exact to far
        below them)."""
        if self.method == "j6":
            return self.T_world_from_mcs(points_mm, T_ecs_from_mcs)
        T0, A, B = self._weighted_fit
        c = self.cluster_mcs if cluster_mcs is None else cluster_mcs
        moved = np.linalg.inv(T_ecs_from_mcs) @ self.T_ecs_from_mcs
        c = c @ moved[:3, :3].T + moved[:3, 3]
        x = A @ (np.asarray(points_mm, float) - self.points_mm).ravel() \
            + B @ (c - self.cluster_mcs).ravel()
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec(x[:3]).as_matrix() @ T0[:3, :3]
        T[:3, 3] = T0[:3, 3] + x[3:]
        return T


def cluster_draws(draws: list[dict[str, Any]] | None, names: tuple[str, ...]
                  ) -> np.ndarray | None:
    """The joint draws of the cluster calibration for ``names`` (draws x n x 3, mm), or None
    when the hand-eye has none (an SMR a draw lacks deviates by 0 in it)."""
    if not draws:
        return None
    zero = [0.0, 0.0, 0.0]
    return np.array([[d.get(n, zero) for n in names] for d in draws], float)


def frame_angles(hand_eye: dict[str, Any]) -> list[float]:
    """The J6 angles of P1..P3 of the hand-eye calibration's ECS (relative, deg)."""
    return [0.0, *hand_eye.get("j6_angles_deg", list(DEFAULT_J6_ANGLES_DEG))[:2]]


def station_pose(record: dict[str, Any], hand_eye: dict[str, Any],
                 method: str | None = None) -> StationPose:
    """The :class:`StationPose` of a ``scancell.StationEcs`` record under the hand-eye
    calibration ``hand_eye`` (``scancell.HandEye``), by the record's ``ecs_method`` or by
    ``method`` (a cluster station measured with ``compare_ecs`` holds the J6 points too);
    raises StationPoseError naming the station and what is missing."""
    name = record.get("station", "?")
    T_em = np.asarray(hand_eye["T_ecs_from_mcs"], float)
    method = method or record.get("ecs_method", "j6")
    if method == "j6" and "points_mm" not in record:
        raise StationPoseError(f"station {name}: no J6 points (measured by "
                               f"{record.get('ecs_method')!r} without compare_ecs)")
    if method == "j6":
        pts = np.asarray(record["points_mm"], float)
        sig = np.broadcast_to(np.asarray(record.get("sigma_mm", 0.0), float), pts.shape)
        pose = StationPose("j6", pts, np.array(sig), T_em, tuple(record["j6_deg"]),
                           tuple(frame_angles(hand_eye)))
    elif method == "cluster":
        cal = hand_eye.get("smr_cluster") or {}
        measured = record.get("smr_points_mm") or {}
        names = tuple(sorted(n for n in measured if n in cal))
        if not cal:
            raise StationPoseError(f"station {name}: measured by the SMR cluster, but the "
                                   f"hand-eye calibration {hand_eye.get('job_id', '?')} has no "
                                   f"cluster calibration (smr_cluster)")
        missing = sorted(set(measured) - set(cal))
        if len(names) < 3:
            raise StationPoseError(f"station {name}: {len(names)} calibrated SMRs seen "
                                   f"({', '.join(names) or 'none'}; not calibrated: "
                                   f"{', '.join(missing) or 'none'}): a pose needs 3")
        sig = record.get("smr_sigma_mm") or {}
        pose = StationPose(
            "cluster", np.array([measured[n] for n in names], float),
            np.array([sig.get(n, [0.0, 0.0, 0.0]) for n in names], float), T_em,
            names=names, cluster_mcs=np.array([cal[n]["mcs_mm"] for n in names], float),
            cluster_sigma_mm=np.array([cal[n].get("sigma_mm", [0.0] * 3) for n in names],
                                      float),
            T_world_from_tracker=(np.asarray(record["T_world_from_tracker"], float)
                                  if record.get("T_world_from_tracker") is not None else None),
            cluster_draws=cluster_draws(hand_eye.get("smr_cluster_draws"), names))
    else:
        raise StationPoseError(f"station {name}: unknown ecs_method {method!r} (one of "
                               f"{', '.join(ECS_METHODS)})")
    try:
        pose.T_world_from_mcs(weighted=True)
    except (DegenerateGeometry, ClusterGeometryError) as exc:
        raise StationPoseError(f"station {name}: {exc}") from None
    return pose


def station_T_world_from_ecs(record: dict[str, Any], hand_eye: dict[str, Any]) -> np.ndarray:
    """``T_world_from_ecs`` of a station (both methods); raises StationPoseError."""
    pose = station_pose(record, hand_eye)
    return pose.T_world_from_mcs(weighted=True) @ np.linalg.inv(pose.T_ecs_from_mcs)
