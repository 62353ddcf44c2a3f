"""Where an estimated stereo calibration puts MCS against the simulated rig's true left camera.

A calibration defines its own MCS: a principal point off by δ px turns every left ray, and so
every triangulated point, by δ/f rad. A hand-eye calibrated with the same scanner absorbs that
turn, so the fused model does not suffer it; but the hand-eye then differs from the true
mounting by it. This module measures the turn (and shift) so that the hand-eye can be judged
against the frame it was actually calibrated in.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scancell.analysis.handeye import kabsch, rotation_angle_arcsec
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.sim.optics import StereoRig


@dataclass(frozen=True)
class FrameOffset:
    #: the rigid map from the true left camera frame to the calibration's MCS (mm)
    T_cal_from_true: np.ndarray
    #: what no rigid map explains: RMS of the triangulated points about it (mm)
    residual_rms_mm: float

    @property
    def rotation_arcsec(self) -> float:
        return rotation_angle_arcsec(self.T_cal_from_true[:3, :3])

    @property
    def translation_mm(self) -> float:
        return float(np.linalg.norm(self.T_cal_from_true[:3, 3]))


def calibrated_frame_offset(rig: StereoRig, calib: StereoCalibration,
                            depths_mm: tuple[float, ...] = (500.0, 600.0, 700.0),
                            grid: int = 15) -> FrameOffset:
    """Points over the left camera's field at ``depths_mm`` (true left frame), seen by both true
    cameras, triangulated with ``calib``: the Kabsch fit of the true points to the triangulated
    ones. Points the right camera does not see are left out."""
    left, right = rig.left, rig.right
    u, v = np.meshgrid(np.linspace(0.05, 0.95, grid) * left.width,
                       np.linspace(0.05, 0.95, grid) * left.height)
    rays = left.pixel_rays(u[0], v[:, 0]).reshape(-1, 3)
    true = np.concatenate([rays / rays[:, 2:3] * z for z in depths_mm])
    T_right_from_left = np.linalg.inv(rig.T_mcs_from_right)
    in_right = true @ T_right_from_left[:3, :3].T + T_right_from_left[:3, 3]
    pl, pr = left.project(true), right.project(in_right)
    seen = ((pr[:, 0] >= 0) & (pr[:, 0] < right.width) & (pr[:, 1] >= 0)
            & (pr[:, 1] < right.height) & (in_right[:, 2] > 0))
    true, pl, pr = true[seen], pl[seen], pr[seen]
    nl = cv2.undistortPoints(pl.reshape(-1, 1, 2), calib.K1, calib.D1).reshape(-1, 2)
    nr = cv2.undistortPoints(pr.reshape(-1, 1, 2), calib.K2, calib.D2).reshape(-1, 2)
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = np.hstack([calib.R, calib.T.reshape(3, 1)])
    h = cv2.triangulatePoints(P1, P2, nl.T, nr.T)
    measured = (h[:3] / h[3]).T
    T = kabsch(true, measured)
    moved = true @ T[:3, :3].T + T[:3, 3]
    return FrameOffset(T, float(np.sqrt(np.mean(np.sum((moved - measured) ** 2, axis=1)))))
