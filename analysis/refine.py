"""Optional refinement of the tracker-based fusion by multi-view ICP, held to the tracker prior.

Every station is already in ``world`` through its tracker transform. Open3D's pose graph gets one
node per station plus an anchor node for the tracker frame: pairwise point-to-plane ICP between
overlapping stations gives the relative edges, and an edge from the anchor to every station (the
identity, weighted by ``prior_weight``) holds each station to where the tracker put it. The
optimised corrections are reported per station. The refined model is an extra, never a silent
replacement of the tracker-based result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d
from scancell.analysis.fusion import FusionError
from scancell.model.transforms import rotation_angle_deg


@dataclass(frozen=True)
class Refinement:
    #: Per station: the correction applied in ``world`` (4x4), its size in mm and degrees.
    corrections: dict[str, np.ndarray]
    translation_mm: dict[str, float]
    rotation_deg: dict[str, float]
    pairs: int  # overlapping pairs used
    per_station: dict[str, np.ndarray]  # refined world points

    def to_json(self) -> dict:
        return {"pairs": self.pairs,
                "stations": {n: {"translation_mm": round(self.translation_mm[n], 5),
                                 "rotation_deg": round(self.rotation_deg[n], 5)}
                             for n in self.corrections}}


def _cloud(points: np.ndarray, voxel_mm: float, normal_radius_mm: float) -> o3d.geometry.PointCloud:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, float)))
    pcd = pcd.voxel_down_sample(voxel_mm)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_mm, max_nn=30))
    return pcd


def refine(per_station: dict[str, np.ndarray], voxel_mm: float = 1.0,
           max_distance_mm: float = 2.0, min_overlap: float = 0.1,
           prior_weight: float = 1.0) -> Refinement:
    """``per_station``: station name -> world points (mm) after the tracker transforms."""
    names = list(per_station)
    if len(names) < 2:
        raise FusionError("multi-view refinement needs at least two stations")
    clouds = [_cloud(per_station[n], voxel_mm, 4 * voxel_mm) for n in names]
    graph = o3d.pipelines.registration.PoseGraph()
    graph.nodes.append(o3d.pipelines.registration.PoseGraphNode(np.eye(4)))  # the tracker frame
    for _ in names:
        graph.nodes.append(o3d.pipelines.registration.PoseGraphNode(np.eye(4)))
    for i in range(len(names)):
        graph.edges.append(o3d.pipelines.registration.PoseGraphEdge(
            0, i + 1, np.eye(4), prior_weight * np.eye(6) * len(clouds[i].points),
            uncertain=False))
    pairs = 0
    method = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    for i in range(len(names)):
        for j in range(i + 1, len(names)):
            fit = o3d.pipelines.registration.registration_icp(
                clouds[j], clouds[i], max_distance_mm, np.eye(4), method)
            if fit.fitness < min_overlap:
                continue
            info = o3d.pipelines.registration.get_information_matrix_from_point_clouds(
                clouds[j], clouds[i], max_distance_mm, fit.transformation)
            # node poses map a station into world; the edge maps station j into station i
            graph.edges.append(o3d.pipelines.registration.PoseGraphEdge(
                j + 1, i + 1, fit.transformation, info, uncertain=True))
            pairs += 1
    if pairs == 0:
        raise FusionError("multi-view refinement: no two stations overlap")
    o3d.pipelines.registration.global_optimization(
        graph, o3d.pipelines.registration.GlobalOptimizationLevenbergMarquardt(),
        o3d.pipelines.registration.GlobalOptimizationConvergenceCriteria(),
        o3d.pipelines.registration.GlobalOptimizationOption(
            max_correspondence_distance=max_distance_mm, edge_prune_threshold=0.25,
            reference_node=0))
    anchor_inv = np.linalg.inv(graph.nodes[0].pose)
    corrections, tr, rot, refined = {}, {}, {}, {}
    for i, n in enumerate(names):
        T = anchor_inv @ graph.nodes[i + 1].pose
        corrections[n] = T
        tr[n] = float(np.linalg.norm(T[:3, 3]))
        rot[n] = rotation_angle_deg(T)
        p = np.asarray(per_station[n], float)
        refined[n] = p @ T[:3, :3].T + T[:3, 3]
    return Refinement(corrections, tr, rot, pairs, refined)
