"""What the tracker's noise does to a station: the ECS error budget of the fusion report.

Each station's pose comes from tracker points with a stated 1-sigma each (P1..P3 of the J6
turns, or the SMRs of the cluster). Drawing those points again from their uncertainty and
rebuilding the pose moves the station's cloud; the
mean shift along the scanner's view (which the overlap and true errors mostly see on a smooth
part) is the error the tracker alone puts into that station. Set beside the measured overlap
error, it tells whether the tracker or the rest (scanner, calibrations) dominates.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scancell.analysis.station_pose import StationPose


def ecs_noise_effect(pose: StationPose, cloud_mcs: np.ndarray, trials: int = 100,
                     seed: int = 0) -> float:
    """Mean |shift along the view| (mm) of the cloud's points (MCS, mm) when the station's
    tracker points (world, mm) are drawn from their 1-sigma (per axis, mm); Monte Carlo over
    ``trials`` draws."""
    pts, sig = pose.points_mm, pose.sigma_mm
    sample = np.asarray(cloud_mcs, float)
    sample = sample[:: max(1, len(sample) // 2000)]
    T0 = pose.T_world_from_mcs()
    X0 = sample @ T0[:3, :3].T + T0[:3, 3]
    view = T0[:3, 2]
    rng = np.random.default_rng(seed)
    shifts = []
    for _ in range(trials):
        T = pose.T_world_from_mcs(pts + rng.standard_normal(pts.shape) * sig)
        X = sample @ T[:3, :3].T + T[:3, 3]
        shifts.append(float(np.abs((X - X0) @ view).mean()))
    return float(np.mean(shifts))


def budget(ecs_noise_mm: dict[str, float], overlap_mean_mm: float | None,
           true_mean_mm: float | None, hand_eye_rms_mm: float | None,
           sources: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """The report's error budget: each modelled source's share of the overlap and the true error
    (``sources``, from :func:`scancell.analysis.station_uncertainty.budget_by_source`), their
    combination beside what was measured, and which source dominates. Without ``sources`` only
    the tracker's noise is named and the rest is what it leaves unexplained."""
    out: dict[str, Any] = {"ecs_noise_mm": {k: round(v, 5) for k, v in ecs_noise_mm.items()}}
    if true_mean_mm is not None:
        out["true_mean_mm"] = true_mean_mm
    if hand_eye_rms_mm is not None:
        out["hand_eye_rms_mm"] = hand_eye_rms_mm
    if sources:
        out["sources"] = sources
        out["overlap_predicted_mm"] = float(np.sqrt(sum(v["overlap_mm"] ** 2
                                                        for v in sources.values())))
        out["true_predicted_mm"] = float(np.sqrt(sum(v["true_mm"] ** 2 for v in sources.values())))
        if overlap_mean_mm is not None:
            out["overlap_measured_mm"] = overlap_mean_mm
        top = max(sources, key=lambda k: sources[k]["true_mm"])
        out["dominant"] = f"{top} ({sources[top]['true_mm']:.4f} mm of the true error)"
        return out
    if not ecs_noise_mm:
        return out
    ecs = float(np.mean(list(ecs_noise_mm.values())))
    out["ecs_noise_mean_mm"] = ecs
    if overlap_mean_mm is not None:
        # two stations meet in an overlap, each with its own ECS error
        predicted = np.sqrt(2.0) * ecs
        rest = float(np.sqrt(max(overlap_mean_mm**2 - predicted**2, 0.0)))
        out["overlap_predicted_from_tracker_mm"] = float(predicted)
        out["overlap_rest_mm"] = rest
        out["dominant"] = ("the tracker's noise in each station's ECS" if predicted >= rest else
                           "the rest: the scanner, the robot between the J6 turns and the "
                           "calibrations (more than the tracker's noise in the ECS)")
    return out
