"""How well a scan of a flat checkerboard came out: coverage, flatness and the board's plane.

- coverage: the share of camera pixels inside the board's outer inner corners (the convex hull
  of the corners found in the fringes' background image) that became points;
- flatness: the RMS (and the largest) distance of those points from their own best-fit plane
  (total least squares), with no smoothing beyond the decoder's;
- an independent reference: the board's plane from its corners alone (cv2.solvePnP with the
  camera's intrinsics), against which the points' mean offset and spread are given (mm, along
  that plane's normal).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np
from scancell.analysis.stereo_calibration import ChessboardSpec, find_corners


@dataclass
class BoardCheck:
    board_pixels: int
    coverage: float  # 0 … 1
    flatness_rms_mm: float
    flatness_max_mm: float
    pnp_offset_mm: float  # mean of the points' distances to the corners' plane
    pnp_spread_mm: float  # their standard deviation

    def as_dict(self) -> dict[str, float]:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in asdict(self).items()}


class BoardNotFound(ValueError):
    pass


def check_board(points: np.ndarray, pixels: np.ndarray, background: np.ndarray, K: np.ndarray,
                D: np.ndarray, board: ChessboardSpec) -> BoardCheck:
    """``points`` (N, 3, camera frame, mm) seen at camera ``pixels`` (N, 2: x, y);
    ``background``: the fringes' mean intensity (DN), in which the board is found."""
    img = np.clip(background, 0, 255).astype(np.uint8)
    corners = find_corners(img, board)
    if corners is None:
        raise BoardNotFound(f"no {board.cols} x {board.rows} board in the background image")
    hull = cv2.convexHull(corners.astype(np.float32)).astype(np.int32)
    mask = np.zeros(img.shape, np.uint8)
    cv2.fillConvexPoly(mask, hull, 1)
    inside = mask.astype(bool)
    sel = inside[pixels[:, 1], pixels[:, 0]]
    P = points[sel].astype(np.float64)
    if len(P) < 3:
        return BoardCheck(int(inside.sum()), 0.0, float("nan"), float("nan"), float("nan"),
                          float("nan"))
    centre = P.mean(0)
    normal = np.linalg.svd(P - centre, full_matrices=False)[2][2]
    r = (P - centre) @ normal
    _, rvec, tvec = cv2.solvePnP(board.object_points().astype(np.float64), corners.astype(np.float64),
                                  K, D)
    n_pnp = cv2.Rodrigues(rvec)[0][:, 2]
    d = P @ n_pnp - n_pnp @ tvec.ravel()
    return BoardCheck(int(inside.sum()), float(sel.sum() / inside.sum()),
                      float(np.sqrt(np.mean(r ** 2))), float(np.abs(r).max()), float(d.mean()),
                      float(d.std()))
