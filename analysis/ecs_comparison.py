"""The two ECS methods on the same stations: a cluster station measured with ``compare_ecs``
holds the SMR cluster's points and the paper's J6 points at one robot pose, and one scan. Each
method's transform puts the scan in the tracker's frame; against the part's true surface (in
simulation) each shows its own error, and the time each method took at the station."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from scancell.analysis.station_pose import StationPoseError, station_pose
from scipy.spatial.transform import Rotation

ARCSEC_PER_RAD = 180 / np.pi * 3600


def ecs_comparison(records: dict[str, dict[str, Any]], clouds: dict[str, np.ndarray],
                   hand_eye: dict[str, Any],
                   truth: Callable[[np.ndarray], np.ndarray] | None = None
                   ) -> dict[str, Any] | None:
    """Per station measured both ways (``records``: station -> ``scancell.StationEcs``;
    ``clouds``: station -> points in ``mcs``, mm): for ``cluster`` and ``j6`` the mean
    |distance| of the scan to the true surface (mm; ``truth`` gives signed distances of world
    points) and the tracker's time at the station (s: the cluster's shots; the J6 method's
    P1 and turns), and how far apart the two poses put the scan (mean over its points, mm) and
    their rotation (arcsec). None when no station was measured both ways."""
    stations: dict[str, Any] = {}
    for name in sorted(records):
        rec, cloud = records[name], clouds.get(name)
        if rec.get("ecs_method") != "cluster" or "points_mm" not in rec or cloud is None:
            continue
        if not len(cloud):
            continue
        try:
            T = {m: station_pose(rec, hand_eye, m).T_world_from_mcs(weighted=True)
                 for m in ("cluster", "j6")}
        except StationPoseError as exc:
            stations[name] = {"error": str(exc)}
            continue
        pts = {m: cloud @ T[m][:3, :3].T + T[m][:3, 3] for m in T}
        timing = rec.get("timing_s") or {}
        entry: dict[str, Any] = {
            "cluster": {"seconds": timing.get("tracker"),
                        "smrs": sorted(rec.get("smr_points_mm") or {})},
            "j6": {"seconds": round(timing.get("compare_p1", 0.0)
                                    + timing.get("compare_j6_turns", 0.0), 2)},
            "apart_mm": round(float(np.linalg.norm(pts["cluster"] - pts["j6"], axis=1).mean()),
                              5),
            "rotation_apart_arcsec": round(float(np.linalg.norm(Rotation.from_matrix(
                T["cluster"][:3, :3] @ T["j6"][:3, :3].T).as_rotvec()) * ARCSEC_PER_RAD), 2)}
        if truth is not None:
            for m in T:
                entry[m]["true_error_mm"] = round(float(np.abs(truth(pts[m])).mean()), 5)
        stations[name] = entry
    if not stations:
        return None
    ok = [e for e in stations.values() if "error" not in e]

    def mean(method: str, key: str) -> float | None:
        v = [e[method].get(key) for e in ok if e[method].get(key) is not None]
        return round(float(np.mean(v)), 5) if v else None

    return {"stations": stations,
            "mean": {m: {k: mean(m, k) for k in ("true_error_mm", "seconds")}
                     for m in ("cluster", "j6")}}
