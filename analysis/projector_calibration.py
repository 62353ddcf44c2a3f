"""Calibrating a camera–projector rig from phase maps of a checkerboard.

The projector is calibrated as an inverse camera (Zhang & Huang, Opt. Eng. 45, 2006): in every
pose of a flat checkerboard the camera finds the inner corners in the fringes' background
image, and the decoded projector column and row maps give each corner's projector
coordinates. A corner's coordinates come from a local homography fitted to the decoded pixels
around it (Moreno & Taubin, "Simple, accurate, and robust projector-camera calibration", 3DIMPVT
2012), which a pure camera-to-projector homography makes exact for a flat board and which
averages the decode's noise over the window. Then both devices are calibrated by Zhang's method
(cv2.calibrateCamera, k1, k2 and tangential distortion) and their pose by cv2.stereoCalibrate:
``X_proj = R · X_cam + T``.

The pattern set must encode both projector axes (x and y).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
from scancell.analysis.pattern_decode import ViewDecode
from scancell.analysis.projector_rig import CameraProjectorRig
from scancell.analysis.stereo_calibration import CalibrationError, ChessboardSpec, find_corners

#: the local homography's window: half the square's size in the camera, at least this (px)
MIN_WINDOW_PX = 5
#: decoded pixels a corner's window needs (of (2 r + 1)² around it): fewer and the corner is
#: dropped from that pose
MIN_WINDOW_SHARE = 0.5


@dataclass
class PoseCorners:
    name: str
    camera: np.ndarray  # (N, 2) px
    projector: np.ndarray  # (N, 2) px, NaN where the decode did not cover the corner
    object_points: np.ndarray  # (N, 3) mm


@dataclass
class ProjectorCalibrationReport:
    rig: CameraProjectorRig
    poses_used: list[str]
    poses_rejected: dict[str, str]
    per_pose_rms_px: dict[str, tuple[float, float]] = field(default_factory=dict)

    def table(self) -> str:
        r = self.rig
        lines = [f"camera-projector calibration from {len(self.poses_used)} poses "
                 f"({len(self.poses_rejected)} rejected)",
                 f"  RMS reprojection: camera {r.rms['rms_camera_px']:.3f} px, projector "
                 f"{r.rms['rms_projector_px']:.3f} px, stereo {r.rms['rms_stereo_px']:.3f} px",
                 f"  f camera {r.K_cam[0, 0]:.1f} px, f projector {r.K_proj[0, 0]:.1f} px, "
                 f"baseline {r.baseline_mm:.2f} mm"]
        lines += [f"  rejected {n}: {why}" for n, why in self.poses_rejected.items()]
        return "\n".join(lines)


def corner_projector_coords(corners: np.ndarray, view: ViewDecode, window: int) -> np.ndarray:
    """Projector (u, v) of each camera corner by a local homography of the decoded pixels
    within ``window`` px (NaN where too few decoded)."""
    u_map, v_map = view.coords["x"], view.coords["y"]
    h, w = u_map.shape
    out = np.full((len(corners), 2), np.nan)
    need = MIN_WINDOW_SHARE * (2 * window + 1) ** 2
    for i, (cx, cy) in enumerate(corners):
        ix, iy = int(np.rint(cx)), int(np.rint(cy))
        x0, x1, y0, y1 = ix - window, ix + window + 1, iy - window, iy + window + 1
        if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
            continue
        uu, vv = u_map[y0:y1, x0:x1], v_map[y0:y1, x0:x1]
        ok = np.isfinite(uu) & np.isfinite(vv)
        if ok.sum() < need:
            continue
        ys, xs = np.nonzero(ok)
        src = np.column_stack([xs + x0, ys + y0]).astype(np.float64)
        dst = np.column_stack([uu[ok], vv[ok]]).astype(np.float64)
        H, _ = cv2.findHomography(src, dst, 0)
        if H is None:
            continue
        p = H @ np.array([cx, cy, 1.0])
        out[i] = p[:2] / p[2]
    return out


def pose_corners(name: str, view: ViewDecode, board: ChessboardSpec) -> PoseCorners | str:
    """One pose's corners in both devices, or why the pose cannot be used."""
    if "x" not in view.coords or "y" not in view.coords:
        return "the pattern set must encode both projector axes (x and y)"
    img = np.clip(view.background, 0, 255).astype(np.uint8)
    corners = find_corners(img, board)
    if corners is None:
        return f"no {board.cols} x {board.rows} board found in the fringes' background image"
    square_px = float(np.median(np.linalg.norm(np.diff(corners.reshape(board.rows, board.cols, 2),
                                                       axis=1), axis=2)))
    # The projector lights the board from one side: the sector detector's corners lean towards
    # the light (0.035 px on the simulated rig, its projector 150 mm aside), cornerSubPix's do
    # not (0.003 px, the same scatter). (On the binocular cell's evenly lit targets the sector
    # detector alone is the better one: test_scanner's calibration.)
    half = int(max(2, min(11, square_px / 4)))
    corners = cv2.cornerSubPix(view.background.astype(np.float32), corners.reshape(-1, 1, 2),
                               (half, half), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
                               ).reshape(-1, 2)
    window = max(MIN_WINDOW_PX, int(square_px / 2))
    proj = corner_projector_coords(corners, view, window)
    if np.isfinite(proj).all(1).sum() < 0.5 * len(corners):
        return (f"only {int(np.isfinite(proj).all(1).sum())} of {len(corners)} corners decoded in "
                f"the projector (is the board lit by the whole pattern?)")
    return PoseCorners(name, corners, proj, board.object_points().astype(np.float64))


def calibrate_camera_projector(poses: Sequence[PoseCorners | tuple[str, str]],
                               camera_size: tuple[int, int],
                               projector_size: tuple[int, int]) -> ProjectorCalibrationReport:
    """Both devices' intrinsics and their pose from ≥ 4 usable poses; ``poses`` may hold
    (name, reason) pairs of rejected ones, which the report lists."""
    used = [p for p in poses if isinstance(p, PoseCorners)]
    rejected = {p[0]: p[1] for p in poses if not isinstance(p, PoseCorners)}
    if len(used) < 4:
        raise CalibrationError(f"only {len(used)} usable board pose(s); at least 4 are needed "
                               f"(rejected: {rejected})")
    obj_c, cam_c, obj_p, proj_p, obj_s, cam_s, proj_s = [], [], [], [], [], [], []
    for p in used:
        ok = np.isfinite(p.projector).all(1)
        obj_c.append(p.object_points.astype(np.float32))
        cam_c.append(p.camera.astype(np.float32))
        obj_p.append(p.object_points[ok].astype(np.float32))
        proj_p.append(p.projector[ok].astype(np.float32))
        obj_s.append(p.object_points[ok].astype(np.float32))
        cam_s.append(p.camera[ok].astype(np.float32))
        proj_s.append(p.projector[ok].astype(np.float32))
    flags = cv2.CALIB_FIX_K3
    rms_c, Kc, Dc, rv_c, tv_c = cv2.calibrateCamera(obj_c, cam_c, camera_size, None, None, flags=flags)
    rms_p, Kp, Dp, rv_p, tv_p = cv2.calibrateCamera(obj_p, proj_p, projector_size, None, None,
                                                    flags=flags)
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    rms_s, Kc, Dc, Kp, Dp, R, T, _, _ = cv2.stereoCalibrate(
        obj_s, cam_s, proj_s, Kc, Dc, Kp, Dp, camera_size, criteria=criteria,
        flags=cv2.CALIB_USE_INTRINSIC_GUESS | flags)
    per_pose = {}
    for p, rc, tc, rp, tp, o, pp in zip(used, rv_c, tv_c, rv_p, tv_p, obj_p, proj_p, strict=True):
        ec = cv2.projectPoints(p.object_points, rc, tc, Kc, Dc)[0].reshape(-1, 2) - p.camera
        ep = cv2.projectPoints(o.astype(np.float64), rp, tp, Kp, Dp)[0].reshape(-1, 2) - pp
        per_pose[p.name] = (float(np.sqrt(np.mean(np.sum(ec ** 2, 1)))),
                            float(np.sqrt(np.mean(np.sum(ep ** 2, 1)))))
    rig = CameraProjectorRig(camera_size, Kc, Dc.reshape(-1), projector_size, Kp, Dp.reshape(-1), R,
                             T.reshape(3), True,
                             {"rms_camera_px": float(rms_c), "rms_projector_px": float(rms_p),
                              "rms_stereo_px": float(rms_s)}, "phase-map calibration")
    return ProjectorCalibrationReport(rig, [p.name for p in used], rejected, per_pose)
