"""A simulated camera–projector rig looking at a flat target, with a known truth.

It renders what one camera records while the projector shows a pattern set
(:mod:`scancell.model.pattern_set`): the projector's 8-bit images, blurred by its lens, through
its response (the optics profile's gamma and contrast), onto a plane of known pose (a plain
sheet or a checkerboard of known squares), lit by ambient light too, seen through the
camera's lens (distortion, in-focus blur) by an EMVA 1288 sensor (shot and dark noise, 8, 12
or 16 bit). Every parameter comes from the optics profile (docs/explanation/simulation.md), so the same
effects that make the binocular cell unkind make this rig unkind.

Truth: the rig (``truth``), the plane (``Plane``), and per camera pixel the projector
coordinates it sees (``true_projector_coords``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scancell.analysis.projector_rig import CameraProjectorRig
from scancell.model.pattern_set import PatternSet
from scancell.sim.optics_profile import OpticsProfile, optics_profile


def rotation_matrix(axis, angle_rad: float) -> np.ndarray:
    """Rotation by ``angle_rad`` about ``axis`` (Rodrigues)."""
    a = np.asarray(axis, float)
    return cv2.Rodrigues((a / np.linalg.norm(a) * angle_rad).reshape(3, 1))[0]


#: projector lens blur at the working distance (1 sigma, projector px): a DLP's in-focus MTF
PROJECTOR_BLUR_PX = 0.7


def default_rig(scale: float = 1.0) -> CameraProjectorRig:
    """A rig like SLStudio's: a 1280 x 1024 camera (f 2400 px) and a 1280 x 800 projector
    (f 1900 px) 150 mm apart, converging on a point 450 mm ahead (18°), both with a little
    barrel distortion; ``scale`` shrinks the camera (tests render small images)."""
    w, h = round(1280 * scale), round(1024 * scale)
    f = 2400.0 * scale
    K_cam = np.array([[f, 0, w / 2 - 0.5 + 3.2 * scale], [0, f, h / 2 - 0.5 - 2.1 * scale], [0, 0, 1]])
    K_proj = np.array([[1900.0, 0, 639.5 + 4.0], [0, 1900.0, 399.5 + 20.0], [0, 0, 1]])
    c_proj = np.array([150.0, -10.0, 5.0])  # projector centre in the camera frame (mm)
    z = np.array([0.0, 12.0, 450.0]) - c_proj  # it looks at a point 450 mm before the camera
    z /= np.linalg.norm(z)
    x = np.cross([0.02, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: the projector's axes in the camera frame
    return CameraProjectorRig((w, h), K_cam, np.array([-0.06, 0.02, 0, 0, 0]), (1280, 800),
                              K_proj, np.array([-0.03, 0, 0, 0, 0]), R, -R @ c_proj, True,
                              source="simulated truth")


@dataclass
class Plane:
    """A flat target: ``T_cam_from_board`` (4 x 4, mm) puts its x, y plane in the camera frame.
    ``squares`` (mm) > 0: a checkerboard of ``cols`` x ``rows`` inner corners whose first inner
    corner is the board origin; else a uniform sheet of albedo ``white``."""

    T_cam_from_board: np.ndarray
    squares: float = 0.0
    cols: int = 9
    rows: int = 7
    white: float = 0.85
    black: float = 0.12

    def albedo(self, xy: np.ndarray, footprint: np.ndarray | None = None) -> np.ndarray:
        """Albedo at board points ``xy`` (H, W, 2, mm), averaged over each camera pixel's
        ``footprint`` (H, W, 2: its extent along the board's x and y, mm), as a sensor
        integrates over its pixel: each square edge is box-filtered along the axis it crosses,
        which is exact for a pixel whose footprint lines up with the squares. Without a
        footprint, the albedo at the point (the square edges are then hard)."""
        if self.squares <= 0:
            return np.full(xy.shape[:-1], self.white)
        q = xy / self.squares
        i = np.floor(q[..., 0])
        j = np.floor(q[..., 1])
        inside = (i >= -1) & (i <= self.cols - 1) & (j >= -1) & (j <= self.rows - 1)
        signs = []
        for axis, cell in ((0, i), (1, j)):
            parity = np.where(cell % 2 == 0, 1.0, -1.0)
            if footprint is None:
                signs.append(parity)
                continue
            f = q[..., axis] - cell
            edge_mm = np.minimum(f, 1 - f) * self.squares
            half = np.maximum(footprint[..., axis] / 2, 1e-9)
            signs.append(parity * np.clip(edge_mm / half, 0.0, 1.0))
        dark = 0.5 * (1 + signs[0] * signs[1])  # 1 on squares of even i + j
        dark = np.where(inside, dark, 0.0)
        return self.white + (self.black - self.white) * dark

    def corners_board(self) -> np.ndarray:
        """(cols·rows, 3) inner corners on the board (mm), row by row as OpenCV finds them."""
        g = np.mgrid[0:self.cols, 0:self.rows].T.reshape(-1, 2) * self.squares
        return np.column_stack([g, np.zeros(len(g))])


def board_pose(distance_mm: float, tilt_deg: tuple[float, float], centre_mm=(0.0, 0.0),
               size_mm: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """T_cam_from_board of a board whose centre lies ``distance_mm`` along the camera's view
    (offset by ``centre_mm``) tilted about its x and y axes."""
    R = rotation_matrix([1, 0, 0], np.radians(tilt_deg[0])) @ rotation_matrix([0, 1, 0],
                                                                                np.radians(tilt_deg[1]))
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.array([centre_mm[0], centre_mm[1], distance_mm]) - R @ np.array(
        [size_mm[0] / 2, size_mm[1] / 2, 0.0])
    return T


@dataclass
class RigSimulator:
    truth: CameraProjectorRig = field(default_factory=default_rig)
    optics: OpticsProfile = field(default_factory=lambda: optics_profile("realistic"))
    seed: int = 0
    bit_depth: int = 8  # 8, 12 (stored in 16-bit frames) or 16

    def __post_init__(self) -> None:
        self.rng = np.random.default_rng(self.seed)

    def geometry(self, plane: Plane) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per camera pixel: the board point (x, y, mm), the projector coordinates (u, v, px,
        NaN outside the projector or the board's plane behind the camera), and the light's
        cosine and distance factor."""
        w, h = self.truth.image_size
        rows, cols = np.mgrid[0:h, 0:w]
        rays = self.truth.camera_rays(rows.ravel(), cols.ravel())
        d = np.column_stack([rays, np.ones(len(rays))])
        R, t = plane.T_cam_from_board[:3, :3], plane.T_cam_from_board[:3, 3]
        n = R[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (n @ t) / (d @ n)
        X = d * s[:, None]
        X[s <= 0] = np.nan
        board = (X - t) @ R
        uv = self.truth._project(X)
        pw, ph = self.truth.projector_size
        outside = ~((uv[:, 0] >= -0.5) & (uv[:, 0] <= pw - 0.5) & (uv[:, 1] >= -0.5)
                    & (uv[:, 1] <= ph - 0.5))
        uv[outside] = np.nan
        c_proj = -self.truth.R.T @ self.truth.T
        to_proj = c_proj - X
        dist = np.linalg.norm(to_proj, axis=1)
        cos_p = np.abs(to_proj @ n) / dist
        d0 = np.nanmedian(dist)
        light = cos_p * (d0 / dist) ** 2
        return board[:, :2].reshape(h, w, 2), uv.reshape(h, w, 2), light.reshape(h, w), X.reshape(h, w, 3)

    def render(self, plane: Plane, spec: PatternSet, exposure: float = 1.0) -> list[np.ndarray]:
        """The camera's frames of every pattern of ``spec``."""
        board, uv, light, _ = self.geometry(plane)
        # each pixel's footprint on the board: how far its board point moves to the next pixel
        gy, gx = np.gradient(board, axis=(0, 1))
        albedo = plane.albedo(board, np.abs(gx) + np.abs(gy))
        pw, ph = self.truth.projector_size
        o = self.optics
        frames = []
        for k in range(len(spec)):
            prof = spec.frame_profile(k, pw, ph)
            if prof is None:
                value = np.zeros(uv.shape[:2])
            else:
                axis, values = prof
                shown = np.round(np.clip(values, 0, 1) * 255) / 255  # the 8-bit image
                blurred = cv2.GaussianBlur(shown.reshape(1, -1), (0, 0), PROJECTOR_BLUR_PX,
                                           borderType=cv2.BORDER_REPLICATE).ravel()
                coord = uv[..., 0] if axis == "x" else uv[..., 1]
                value = np.interp(coord, np.arange(len(values)), blurred)
            lit = np.isfinite(uv).all(-1)
            out = np.where(lit, o.projector_light(np.nan_to_num(value)), 0.0)
            radiance = albedo * (out * light + o.ambient)
            dn = np.nan_to_num(radiance) * (255.0 * o.exposure * 0.6 * exposure)
            dn = cv2.GaussianBlur(dn.astype(np.float32), (0, 0), o.psf_sigma_px)
            frames.append(self._sensor(dn))
        return frames

    def _sensor(self, dn: np.ndarray) -> np.ndarray:
        """EMVA 1288: electrons = dn / K with K = 255 / full well; shot noise, dark noise,
        quantised to the bit depth (12-bit values in 16-bit frames)."""
        o = self.optics
        k = 255.0 / o.full_well_e
        electrons = self.rng.poisson(np.maximum(dn / k, 0)).astype(np.float64)
        electrons += self.rng.normal(0.0, o.dark_noise_e, dn.shape)
        full = {8: 255, 12: 4095, 16: 65535}[self.bit_depth]
        value = np.clip(np.rint(electrons * k * full / 255.0), 0, full)
        return value.astype(np.uint8 if self.bit_depth == 8 else np.uint16)

    def true_projector_coords(self, plane: Plane) -> np.ndarray:
        return self.geometry(plane)[1]

    def true_points(self, plane: Plane) -> np.ndarray:
        return self.geometry(plane)[3]


#: the board poses ``write_captures`` uses in turn: (distance mm, tilt about x and y deg,
#: board centre offset mm); tilted 20-30° in every direction, as Zhang's method wants
BOARD_POSES = [(420, (20, 0), (0, 0)), (450, (-20, 10), (-22, 14)), (480, (0, 25), (24, -14)),
               (440, (15, -25), (18, 15)), (500, (-10, -15), (-25, -16)), (400, (25, 20), (-14, 10)),
               (460, (-25, -5), (25, 0)), (430, (5, 30), (-20, -12)), (470, (-15, 20), (10, 18)),
               (410, (10, -10), (-10, -16))]


def write_captures(args) -> int:
    """``scancell sim rig``: checkerboard poses, a plain sheet and the truth, on disk."""
    import json
    import sys
    from pathlib import Path

    from scancell.analysis.pattern_files import load_pattern_set
    from scancell.analysis.stereo_calibration import CalibrationError, ChessboardSpec
    from scancell.model.pattern_set import PatternSpecError
    from scancell.sim.profiles import ProfileError

    try:
        spec = load_pattern_set(args.patterns)
        board = ChessboardSpec.parse(args.target)
        sim = RigSimulator(default_rig(args.scale), optics_profile(args.profile), args.seed,
                           args.bit_depth)
    except (PatternSpecError, CalibrationError, ProfileError) as exc:
        print(f"scancell sim rig: {exc}", file=sys.stderr)
        return 2
    if not 0 <= args.poses <= len(BOARD_POSES):
        print(f"scancell sim rig: --poses {args.poses}: 0 to {len(BOARD_POSES)}", file=sys.stderr)
        return 2
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sim.truth.write(out / "rig_true.yaml")
    size = (board.cols - 1) * board.square_mm, (board.rows - 1) * board.square_mm

    def save(folder: Path, frames: list[np.ndarray]) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        for k, f in enumerate(frames):
            cv2.imwrite(str(folder / f"frame_{k:02d}.png"), f)

    for i, (d, tilt, centre) in enumerate(BOARD_POSES[:args.poses]):
        plane = Plane(board_pose(d, tilt, centre, size), board.square_mm, board.cols, board.rows)
        save(out / f"board_{i:02d}", sim.render(plane, spec))
        print(f"board pose {i + 1}/{args.poses} -> {out / f'board_{i:02d}'}")
    sheet = Plane(board_pose(450.0, (12.0, -18.0)))
    save(out / "plane", sim.render(sheet, spec))
    T = sheet.T_cam_from_board
    truth = {"plane_normal": T[:3, 2].tolist(), "plane_offset_mm": float(T[:3, 2] @ T[:3, 3]),
             "frame": "camera", "patterns": spec.to_dict(), "bit_depth": args.bit_depth,
             "profile": args.profile, "seed": args.seed}
    (out / "truth.json").write_text(json.dumps(truth, indent=2))
    pw, ph = sim.truth.projector_size
    (out / "patterns.json").write_text(json.dumps({**spec.to_dict(),
                                                   "projector": {"width": pw, "height": ph}},
                                                  indent=2))
    print(f"{len(spec)} frames a capture of {sim.truth.image_size[0]} x {sim.truth.image_size[1]} "
          f"px; the sheet's plane and the true rig -> {out}")
    return 0
