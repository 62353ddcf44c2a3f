"""Rendered images of a planar chessboard for camera calibration, with the true corner positions.

The board lies in the z = 0 plane of its frame; inner corner (i, j) is at (i·s, j·s, 0).
Images are point-sampled, blurred by the camera PSF, given read noise and quantised to 8 bits.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scancell.model.transforms import make_T
from scancell.sim.optics import PinholeModel, StereoRig
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Chessboard:
    cols: int = 9  # inner corners along x
    rows: int = 7  # inner corners along y
    square_mm: float = 20.0

    def object_points(self) -> np.ndarray:
        """(cols*rows, 3) inner corners, row-major (x fastest), as OpenCV lists them."""
        j, i = np.mgrid[0 : self.rows, 0 : self.cols]
        return np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], axis=1) * self.square_mm


@dataclass
class TargetView:
    left: np.ndarray
    right: np.ndarray
    T_left_from_target: np.ndarray
    corners_left: np.ndarray  # (N, 2) true pixel positions
    corners_right: np.ndarray


def _box_filtered_checker(x: np.ndarray, y: np.ndarray, s: float) -> np.ndarray:
    """Share of each pixel's footprint that is black (0..1), the checker averaged over the
    pixel (ramp across each edge), so corners land where they are and not on the pixel grid."""
    def ramp(coord: np.ndarray) -> np.ndarray:
        g0, g1 = np.gradient(np.nan_to_num(coord))
        footprint = np.maximum(np.abs(g0) + np.abs(g1), 1e-6)  # mm per pixel along this axis
        cell = np.floor(coord / s)
        to_edge = s / 2 - np.abs(np.mod(coord, s) - s / 2)
        sign = np.where(np.mod(cell, 2) == 0, 1.0, -1.0)
        return sign * np.clip(to_edge / (footprint / 2), 0.0, 1.0)

    return (1.0 + ramp(x) * ramp(y)) / 2


def render_board(cam: PinholeModel, rays: np.ndarray, T_cam_from_target: np.ndarray,
                 board: Chessboard, rng: np.random.Generator, noise_dn: float = 1.0,
                 psf_sigma_px: float = 0.6) -> np.ndarray:
    R, p0 = T_cam_from_target[:3, :3], T_cam_from_target[:3, 3]
    n = R[:, 2]
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p0 @ n) / denom
    hit = rays * t[..., None]
    local = (hit - p0) @ R
    s = board.square_mm
    x, y = local[..., 0], local[..., 1]
    on_board = (t > 0) & (x > -1.6 * s) & (x < (board.cols + 0.6) * s) & \
        (y > -1.6 * s) & (y < (board.rows + 0.6) * s)
    in_squares = (x > -s) & (x < board.cols * s) & (y > -s) & (y < board.rows * s)
    black = _box_filtered_checker(x, y, s)
    albedo = np.where(in_squares, 0.85 + (0.06 - 0.85) * black, 0.85)
    cos_v = np.abs(denom)
    dn = np.where(on_board, 235.0 * albedo * (0.55 + 0.45 * cos_v), 12.0)
    if psf_sigma_px > 0:
        dn = cv2.GaussianBlur(dn, (0, 0), psf_sigma_px)
    dn = dn + rng.standard_normal(dn.shape) * noise_dn
    return np.clip(np.rint(dn), 0, 255).astype(np.uint8)


def _outline(board: Chessboard) -> np.ndarray:
    """The board's corners with the white margin the detector needs (target frame, mm)."""
    obj = board.object_points()
    margin = 1.7 * board.square_mm
    return np.array([[-margin, -margin, 0], [obj[:, 0].max() + margin, -margin, 0],
                     [-margin, obj[:, 1].max() + margin, 0],
                     [obj[:, 0].max() + margin, obj[:, 1].max() + margin, 0]])


def _wholly_in(cam: PinholeModel, T_cam_from_target: np.ndarray, outline: np.ndarray) -> bool:
    pts = outline @ T_cam_from_target[:3, :3].T + T_cam_from_target[:3, 3]
    if np.any(pts[:, 2] <= 0):
        return False
    uv = cam.project(pts)
    return not (np.any(uv < 2) or np.any(uv[:, 0] > cam.width - 3)
                or np.any(uv[:, 1] > cam.height - 3))


def target_poses(rig: StereoRig, board: Chessboard, n: int, seed: int = 0,
                 distance_mm: tuple[float, float] = (560.0, 800.0),
                 max_tilt_deg: float = 35.0, only: str | None = None) -> list[np.ndarray]:
    """``n`` board poses in the left camera frame, fully visible in both cameras, spread over
    the field, the depth range and tilts up to ``max_tilt_deg``.

    ``only="left"`` or ``"right"``: poses wholly in that camera's image and not in the other's,
    aimed through a pixel drawn uniformly over its image: the views an operator adds so that
    the corners reach the image's edges, where the lens distortion is largest and the views
    both cameras see cannot go (a lens model is fitted only where its corners fall)."""
    rng = np.random.default_rng([seed, 7] if only is None else [seed, 7, only == "left"])
    centre = board.object_points().mean(axis=0)
    outline = _outline(board)
    T_right_from_left = np.linalg.inv(rig.T_mcs_from_right)
    mid = rig.T_mcs_from_right[:3, 3] / 2
    bisector = np.array([0.0, 0.0, 1.0]) + rig.T_mcs_from_right[:3, 2]
    bisector /= np.linalg.norm(bisector)
    poses: list[np.ndarray] = []
    tries = 0
    while len(poses) < n:
        tries += 1
        if tries > 500 * n:
            raise RuntimeError(f"could only place {len(poses)} of {n} target poses in view")
        tilt = rng.uniform(-max_tilt_deg, max_tilt_deg, 2)
        Rm = Rotation.from_euler("xyz", [tilt[0], tilt[1], rng.uniform(-20, 20)], degrees=True)
        d = rng.uniform(*distance_mm)
        if only is None:  # aim at a random point of the common field at depth d
            aim = mid + bisector * d
            aim[:2] += rng.uniform(-1, 1, 2) * d * np.array([0.09, 0.08])
        else:  # through a random pixel of that camera, at the depth d along the bisector
            cam, T_cam = ((rig.left, np.eye(4)) if only == "left"
                          else (rig.right, rig.T_mcs_from_right))
            uv = rng.uniform([0.0, 0.0], [cam.width - 1.0, cam.height - 1.0])
            ray = T_cam[:3, :3] @ cam.pixel_rays(uv[:1], uv[1:]).reshape(3)
            reach = (mid + bisector * d - T_cam[:3, 3]) @ bisector / (ray @ bisector)
            aim = T_cam[:3, 3] + ray * reach
        R = Rotation.from_euler("x", 180, degrees=True).as_matrix() @ Rm.as_matrix()
        T = make_T(R, aim - R @ centre)
        in_left = _wholly_in(rig.left, T, outline)
        in_right = _wholly_in(rig.right, T_right_from_left @ T, outline)
        if (in_left and in_right) if only is None else (
                (in_left and not in_right) if only == "left" else (in_right and not in_left)):
            poses.append(T)
    return poses


def render_calibration_set(rig: StereoRig, n: int = 15, seed: int = 0,
                           board: Chessboard | None = None, noise_dn: float = 1.0,
                           psf_sigma_px: float = 0.6, edge_views: int = 0) -> list[TargetView]:
    """Stereo views of the board at ``n`` poses with the true corners in both images, then
    ``edge_views`` per camera that only it sees wholly (``target_poses(only=...)``; the other
    image shows part of the board). The images are rendered in two threads (numpy and OpenCV
    release the GIL), each with its own noise stream, so the set is the same however the
    threads interleave."""
    from concurrent.futures import ThreadPoolExecutor

    board = board or Chessboard()
    rays = {"left": rig.left.pixel_rays(), "right": rig.right.pixel_rays()}
    T_right_from_left = np.linalg.inv(rig.T_mcs_from_right)
    obj = board.object_points()
    poses = target_poses(rig, board, n, seed)
    if edge_views:
        poses += [*target_poses(rig, board, edge_views, seed, only="left"),
                  *target_poses(rig, board, edge_views, seed, only="right")]

    def image(job: tuple[int, str]) -> np.ndarray:
        i, side = job
        cam = rig.left if side == "left" else rig.right
        T = poses[i] if side == "left" else T_right_from_left @ poses[i]
        rng = np.random.default_rng([seed, 8, i, side == "right"])
        return render_board(cam, rays[side], T, board, rng, noise_dn, psf_sigma_px)

    jobs = [(i, side) for i in range(len(poses)) for side in ("left", "right")]
    with ThreadPoolExecutor(2) as pool:
        images = list(pool.map(image, jobs))
    views = []
    for i, T in enumerate(poses):
        T_r = T_right_from_left @ T
        views.append(TargetView(images[2 * i], images[2 * i + 1], T,
                                rig.left.project(obj @ T[:3, :3].T + T[:3, 3]),
                                rig.right.project(obj @ T_r[:3, :3].T + T_r[:3, 3])))
    return views
