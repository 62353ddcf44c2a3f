"""Stereo camera calibration (Zhang's method, OpenCV) and its file format.

File: OpenCV FileStorage YAML with ``image_width, image_height, K1, D1, K2, D2, R, T`` where
X_right = R·X_left + T in mm (the cv2.stereoCalibrate convention); calibration reports add
``rms_left_px, rms_right_px, rms_stereo_px`` when known, and the parameters' 1-sigma
(:data:`SIGMA_KEYS`, a leave-one-view-out jackknife) when the views allowed it.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scancell.model.transforms import rotation_angle_deg

log = logging.getLogger(__name__)

REQUIRED_KEYS = ("image_width", "image_height", "K1", "D1", "K2", "D2", "R", "T")
RMS_KEYS = ("rms_left_px", "rms_right_px", "rms_stereo_px")
#: 1-sigma of the left camera's focal lengths and principal point (px), and of where the
#: calibration puts MCS's axes against the true left camera (arcsec): a principal point off by
#: δ px turns MCS by δ/f rad about the other image axis
SIGMA_KEYS = ("sigma_left_fx_px", "sigma_left_fy_px", "sigma_left_cx_px", "sigma_left_cy_px",
              "sigma_frame_arcsec")
ARCSEC_PER_RAD = 180.0 / np.pi * 3600.0


class CalibrationError(ValueError):
    """A calibration file or a calibration image set is unusable; the message says why."""


def open_storage(path: Path) -> cv2.FileStorage:
    """An OpenCV FileStorage file opened for reading; CalibrationError naming the file."""
    if not path.is_file():
        raise CalibrationError(f"{path}: no such calibration file")
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise CalibrationError(f"{path}: not an OpenCV FileStorage file: {exc.err}") from None
    if not fs.isOpened():
        raise CalibrationError(f"{path}: cannot be opened as OpenCV FileStorage")
    return fs


@dataclass
class StereoCalibration:
    image_size: tuple[int, int]  # (width, height) px
    K1: np.ndarray
    D1: np.ndarray
    K2: np.ndarray
    D2: np.ndarray
    R: np.ndarray  # X_right = R @ X_left + T
    T: np.ndarray  # (3,) mm
    rms: dict[str, float] = field(default_factory=dict)
    #: :data:`SIGMA_KEYS` when known
    sigma: dict[str, float] = field(default_factory=dict)

    @property
    def baseline_mm(self) -> float:
        return float(np.linalg.norm(self.T))

    def check_image_size(self, width: int, height: int, where: str = "images") -> None:
        if (width, height) != tuple(self.image_size):
            raise CalibrationError(
                f"{where} are {width} x {height} but the calibration is for "
                f"{self.image_size[0]} x {self.image_size[1]}")

    def write(self, path: str | Path) -> None:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        try:
            fs.write("image_width", int(self.image_size[0]))
            fs.write("image_height", int(self.image_size[1]))
            for key in ("K1", "D1", "K2", "D2", "R"):
                value = np.asarray(getattr(self, key), float)
                fs.write(key, value.reshape(1, -1) if key.startswith("D") else value)
            fs.write("T", np.asarray(self.T, float).reshape(3, 1))
            for key, value in {**self.rms, **self.sigma}.items():
                fs.write(key, float(value))
        finally:
            fs.release()

    @classmethod
    def read(cls, path: str | Path) -> StereoCalibration:
        p = Path(path)
        fs = open_storage(p)
        try:
            values = {}
            for key in REQUIRED_KEYS:
                node = fs.getNode(key)
                if node.empty():
                    raise CalibrationError(f"{p}: missing key {key!r} (needs {', '.join(REQUIRED_KEYS)})")
                values[key] = int(node.real()) if key.startswith("image_") else node.mat()
                if not key.startswith("image_") and values[key] is None:
                    raise CalibrationError(f"{p}: key {key!r} is not a matrix")
            optional = {}
            for key in RMS_KEYS + SIGMA_KEYS:
                node = fs.getNode(key)
                if not node.empty():
                    optional[key] = float(node.real())
        finally:
            fs.release()
        return cls._checked(values, {k: v for k, v in optional.items() if k in RMS_KEYS},
                            str(p), {k: v for k, v in optional.items() if k in SIGMA_KEYS})

    @classmethod
    def _checked(cls, values: dict[str, Any], rms: dict[str, float],
                 where: str, sigma: dict[str, float] | None = None) -> StereoCalibration:
        shapes = {"K1": (3, 3), "K2": (3, 3), "R": (3, 3)}
        for key, shape in shapes.items():
            if values[key].shape != shape:
                raise CalibrationError(f"{where}: {key} must be 3 x 3, got {values[key].shape}")
        if values["T"].size != 3:
            raise CalibrationError(f"{where}: T must have 3 values, got {values['T'].size}")
        if values["image_width"] <= 0 or values["image_height"] <= 0:
            raise CalibrationError(f"{where}: image_width and image_height must be positive")
        return cls((values["image_width"], values["image_height"]), values["K1"],
                   values["D1"].reshape(-1), values["K2"], values["D2"].reshape(-1), values["R"],
                   values["T"].reshape(3), rms, dict(sigma or {}))

    def to_json(self) -> dict[str, Any]:
        """As ``scancell.StereoCalibration`` (what ``calib/stereo`` carries): exact float64."""
        out: dict[str, Any] = {"image_width": int(self.image_size[0]),
                               "image_height": int(self.image_size[1])}
        for key in ("K1", "D1", "K2", "D2", "R", "T"):
            out[key] = np.asarray(getattr(self, key), float).tolist()
        out["rms"] = dict(self.rms)
        if self.sigma:
            out["sigma"] = dict(self.sigma)
        return out

    @classmethod
    def from_json(cls, obj: Any, where: str = "calib/stereo") -> StereoCalibration:
        if not isinstance(obj, dict):
            raise CalibrationError(f"{where}: expected a JSON object")
        missing = [k for k in REQUIRED_KEYS if k not in obj]
        if missing:
            raise CalibrationError(f"{where}: missing key {missing[0]!r}")
        try:
            values: dict[str, Any] = {k: int(obj[k]) if k.startswith("image_")
                                      else np.asarray(obj[k], float) for k in REQUIRED_KEYS}
            rms = {str(k): float(v) for k, v in (obj.get("rms") or {}).items()}
            sigma = {str(k): float(v) for k, v in (obj.get("sigma") or {}).items()}
        except (TypeError, ValueError, AttributeError) as exc:
            raise CalibrationError(f"{where}: {exc}") from None
        return cls._checked(values, rms, where, sigma)


# ---------------------------------------------------------------------------- calibration


@dataclass(frozen=True)
class ChessboardSpec:
    cols: int = 9  # inner corners along the board's x
    rows: int = 7
    square_mm: float = 20.0

    @classmethod
    def parse(cls, text: str) -> ChessboardSpec:
        """``"9x7x20"``: inner corners along x and y, square size in mm."""
        try:
            c, r, s = text.lower().split("x")
            spec = cls(int(c), int(r), float(s))
        except ValueError:
            raise CalibrationError(f"target {text!r}: expected COLSxROWSxSQUARE_MM, e.g. 9x7x20 "
                                   f"(inner corners and square size)") from None
        if spec.cols < 3 or spec.rows < 3 or spec.square_mm <= 0:
            raise CalibrationError(f"target {text!r}: needs >= 3 x 3 inner corners and a positive square")
        return spec

    def object_points(self) -> np.ndarray:
        j, i = np.mgrid[0:self.rows, 0:self.cols]
        return (np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], 1) * self.square_mm).astype(np.float32)


#: images wider than this are searched for the board at half size, then refined at full size
HALF_SIZE_SEARCH_PX = 1600


def find_corners(image: np.ndarray, board: ChessboardSpec) -> np.ndarray | None:
    """Sub-pixel inner corners (N, 2) in OpenCV's order, or None if the board is not found.

    A large image is searched at half size (OpenCV's sector-based detector, with its accuracy
    flag) and each corner refined on the full image by ``cornerSubPix``: on rendered 2448 x
    2048 boards 0.23 s against 1.1 s for the detector at full size, with corner errors of
    0.028-0.040 px RMS against 0.014-0.073 px (true corners known)."""
    big = image.shape[1] > HALF_SIZE_SEARCH_PX
    seen = cv2.resize(image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA) if big else image
    found, corners = cv2.findChessboardCornersSB(
        seen, (board.cols, board.rows), flags=cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_EXHAUSTIVE)
    if not found:
        # a dark image (SLStudio's board pose 4: mean 21 DN) is found once its histogram is
        # equalised, which the accuracy flag's search does not do
        found, corners = cv2.findChessboardCornersSB(
            seen, (board.cols, board.rows),
            flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE)
    if not found:
        return None
    c = corners.reshape(-1, 2).astype(np.float32)
    if big:
        # a half-size pixel's centre lies at (2 i + 0.5) in the full image
        c = c * 2.0 + 0.5
        square_px = float(np.median(np.linalg.norm(np.diff(c.reshape(board.rows, board.cols, 2),
                                                           axis=1), axis=2)))
        half = int(max(2, min(11, square_px / 4)))
        c = cv2.cornerSubPix(image, c.reshape(-1, 1, 2), (half, half), (-1, -1),
                             (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 50, 1e-4)
                             ).reshape(-1, 2)
    # A board with an even number of squares both ways looks the same turned by 180 deg, and the
    # detector may start from either end: start at the image's top-left so both cameras agree.
    if float(np.dot(c[-1] - c[0], (1.0, 1.0))) < 0:
        c = c[::-1].copy()
    return c


@dataclass
class CalibrationReport:
    calibration: StereoCalibration
    views_used: list[str]
    views_rejected: dict[str, str]
    per_view_rms_px: dict[str, float]
    warnings: list[str]
    #: views whose board only one camera saw wholly, by camera: its lens model's, not the pose's
    single_camera_views: dict[str, int] = field(default_factory=dict)

    def table(self) -> str:
        c = self.calibration
        single = self.single_camera_views
        lines = [f"stereo calibration from {len(self.views_used)} views "
                 f"({len(self.views_rejected)} rejected)"
                 + (f"; the lens models also from {single.get('left', 0)} views of the left "
                    f"camera alone and {single.get('right', 0)} of the right"
                    if any(single.values()) else ""),
                 f"  RMS reprojection: left {c.rms['rms_left_px']:.3f} px, right "
                 f"{c.rms['rms_right_px']:.3f} px, stereo {c.rms['rms_stereo_px']:.3f} px",
                 f"  baseline {c.baseline_mm:.3f} mm, convergence "
                 f"{rotation_angle_deg(c.R):.2f} deg",
                 f"  f left {c.K1[0, 0]:.1f} px, f right {c.K2[0, 0]:.1f} px"]
        if c.sigma:
            lines.append(f"  1-sigma (jackknife over the views): left principal point "
                         f"{c.sigma['sigma_left_cx_px']:.2f} / {c.sigma['sigma_left_cy_px']:.2f} "
                         f"px, focal length {c.sigma['sigma_left_fx_px']:.2f} px; MCS's axes "
                         f"against the true camera {c.sigma['sigma_frame_arcsec']:.0f}\" (the "
                         f"hand-eye absorbs this)")
        for name, why in self.views_rejected.items():
            lines.append(f"  rejected {name}: {why}")
        lines += [f"  WARNING: {w}" for w in self.warnings]
        return "\n".join(lines)


def _refine_stereo(obj_pts: list[np.ndarray], left_pts: list[np.ndarray],
                   right_pts: list[np.ndarray], K1: np.ndarray, D1: np.ndarray, K2: np.ndarray,
                   D2: np.ndarray, size: tuple[int, int], flags: int) -> tuple:
    """Both cameras and their pose refined together from the single-camera start: (rms, K1,
    D1, K2, D2, R, T). Measured on the simulated rig (8 view sets at 1/4 size) the joint
    refinement leaves 0.03-0.17 mm of non-rigid error over the measuring volume where the
    extrinsics alone (intrinsics fixed) leave 0.06-0.24 mm; the refinement may turn MCS
    further, which the hand-eye absorbs."""
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-10)
    rms, K1, D1, K2, D2, R, T, _, _ = cv2.stereoCalibrate(
        obj_pts, left_pts, right_pts, K1.copy(), D1.copy(), K2.copy(), D2.copy(), size,
        criteria=criteria, flags=cv2.CALIB_USE_INTRINSIC_GUESS | flags)
    return rms, K1, D1, K2, D2, R, T


def jackknife_sigma(obj_pts: list[np.ndarray], left_pts: list[np.ndarray],
                    right_pts: list[np.ndarray], K1: np.ndarray, D1: np.ndarray,
                    K2: np.ndarray, D2: np.ndarray, size: tuple[int, int], flags: int
                    ) -> dict[str, float]:
    """:data:`SIGMA_KEYS` from refining the calibration without each view in turn (started
    from the full solution): σ² = (n−1)/n Σ (θ_i − θ̄)².

    OpenCV's own ``stdDeviationsIntrinsics`` take the corner errors as independent with the
    reprojection RMS; a corner detector's errors are not (a view's corners share a bias), and
    on the simulated rig at 1/4 size one view set's principal point was 4.6 of their sigmas off
    (3.55 px against 0.76 px). Dropping whole views keeps what a view shares. Measured the
    same way, the jackknife's errors in units of its sigma had an RMS of 1.7 for cx and 1.5
    for cy over 8 view sets: still optimistic, less so. Fewer than 5 views: {}."""
    n = len(obj_pts)
    if n < 5:
        return {}
    params = []
    for i in range(n):
        keep = [j for j in range(n) if j != i]
        K = _refine_stereo([obj_pts[j] for j in keep], [left_pts[j] for j in keep],
                           [right_pts[j] for j in keep], K1, D1, K2, D2, size, flags)[1]
        params.append((K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    p = np.asarray(params)
    sd = np.sqrt((n - 1) / n * np.sum((p - p.mean(axis=0)) ** 2, axis=0))
    frame = float(np.hypot(sd[2] / K1[0, 0], sd[3] / K1[1, 1])) * ARCSEC_PER_RAD
    return dict(zip(SIGMA_KEYS, [*(float(v) for v in sd), frame], strict=True))


def _coverage_warnings(corners: Sequence[np.ndarray], size: tuple[int, int], side: str,
                       normals_deg: Sequence[float]) -> list[str]:
    w, h = size
    pts = np.concatenate(corners)
    grid = np.zeros((3, 3), bool)
    gx = np.clip((pts[:, 0] / w * 3).astype(int), 0, 2)
    gy = np.clip((pts[:, 1] / h * 3).astype(int), 0, 2)
    grid[gy, gx] = True
    out = []
    if grid.sum() < 8:
        out.append(f"{side} camera: corners cover only {grid.sum()} of 9 image regions; "
                   f"move the target into the corners of the field")
    if len(normals_deg) and max(normals_deg) < 20.0:
        out.append(f"{side} camera: the target was never tilted more than {max(normals_deg):.0f} "
                   f"deg; tilt it 20-45 deg in several directions for a stable focal length")
    return out


def calibrate_stereo(pairs: Sequence[tuple[str, np.ndarray, np.ndarray]],
                     board: ChessboardSpec) -> CalibrationReport:
    """Calibrate both cameras and their pose from (name, left image, right image) views."""
    if not pairs:
        raise CalibrationError("no image pairs given")
    size = (pairs[0][1].shape[1], pairs[0][1].shape[0])
    obj = board.object_points()
    used, rejected = [], {}
    obj_pts, left_pts, right_pts = [], [], []
    for name, left, right in pairs:
        for img, side in ((left, "left"), (right, "right")):
            if (img.shape[1], img.shape[0]) != size:
                raise CalibrationError(f"{name} ({side}): size {img.shape[1]} x {img.shape[0]} "
                                       f"differs from the first view's {size[0]} x {size[1]}")
    # OpenCV's detector runs without the GIL: two threads took 2 x 9 views at 2448 x 2048 from
    # 2.9 s to 1.9 s per image on this 2-core machine
    with ThreadPoolExecutor(max(1, min(4, os.cpu_count() or 1))) as pool:
        found = list(pool.map(lambda img: find_corners(img, board),
                              [img for _, left, right in pairs for img in (left, right)]))
    mono: dict[str, list[np.ndarray]] = {"left": [], "right": []}
    for k, (name, _, _) in enumerate(pairs):
        cl, cr = found[2 * k], found[2 * k + 1]
        if cl is None and cr is None:
            rejected[name] = "board not found in either image"
            continue
        if cl is None or cr is None:  # a view of one camera: its lens model, not the pair's pose
            mono["left" if cr is None else "right"].append(cl if cr is None else cr)
            continue
        used.append(name)
        obj_pts.append(obj)
        left_pts.append(cl)
        right_pts.append(cr)
    if len(used) < 4:
        raise CalibrationError(f"the board was found in both images of only {len(used)} view "
                               f"pair(s); at least 4 are needed (rejected: {rejected})")
    flags = cv2.CALIB_FIX_K3
    all_left, all_right = left_pts + mono["left"], right_pts + mono["right"]
    rms_l, K1, D1, rv_l, tv_l = cv2.calibrateCamera([obj] * len(all_left), all_left, size, None,
                                                    None, flags=flags)
    rms_r, K2, D2, _, _ = cv2.calibrateCamera([obj] * len(all_right), all_right, size, None, None,
                                              flags=flags)
    rv_l, tv_l = rv_l[:len(used)], tv_l[:len(used)]
    # the pair's views then refine both lens models with their pose (from the start the single
    # cameras' views give, edges included): on the simulated rig at 1/4 size, 12 pairs and 6
    # views per camera alone left 0.019-0.095 mm of non-rigid error over the field (mean
    # 0.056) where the pairs alone left 0.046-0.157 (mean 0.088), and the lens models fixed
    # at the single cameras' 0.062-0.127 (5 view sets each)
    rms_s, K1, D1, K2, D2, R, T = _refine_stereo(obj_pts, left_pts, right_pts, K1, D1, K2, D2,
                                                 size, flags)
    per_view = {}
    tilts = []
    for name, o, pl, rv, tv in zip(used, obj_pts, left_pts, rv_l, tv_l, strict=True):
        proj, _ = cv2.projectPoints(o, rv, tv, K1, D1)
        per_view[name] = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - pl) ** 2, 1))))
        normal = cv2.Rodrigues(rv)[0][:, 2]
        tilts.append(float(np.degrees(np.arccos(abs(normal[2])))))
    warnings = (_coverage_warnings(all_left, size, "left", tilts)
                + _coverage_warnings(all_right, size, "right", tilts))
    median = float(np.median(list(per_view.values())))
    for name, e in per_view.items():
        if e > 3 * median and e > 0.3:
            warnings.append(f"view {name}: reprojection {e:.2f} px, {e / median:.1f}x the median "
                            f"(blur, motion or a misdetected board?)")
    if rms_s > 0.5:
        warnings.append(f"stereo RMS {rms_s:.2f} px is high: check focus and the target's flatness")
    calib = StereoCalibration(size, K1, D1.reshape(-1), K2, D2.reshape(-1), R, T.reshape(3),
                              {"rms_left_px": float(rms_l), "rms_right_px": float(rms_r),
                               "rms_stereo_px": float(rms_s)},
                              jackknife_sigma(obj_pts, left_pts, right_pts, K1, D1, K2, D2, size,
                                              flags))
    for w in warnings:
        log.warning("calibration: %s", w)
    return CalibrationReport(calib, used, rejected, per_view, warnings,
                             {side: len(v) for side, v in mono.items()})
