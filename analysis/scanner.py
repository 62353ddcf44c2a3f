"""The scanner pipeline: two cameras' fringe images -> a cloud in MCS, with timings.

Used by ``scancell decode`` (files), ``scancell worker scan`` (the bus) and reprocessing, so all
three produce the same cloud from the same frames.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scancell.analysis.decode_limits import DecodeLimits, discontinuity_limits
from scancell.analysis.phase import DecodeError, DecodeSettings, PhaseMap, decode_exposures
from scancell.analysis.stereo import Cloud, Rectification, reconstruct, rectify
from scancell.analysis.stereo_calibration import StereoCalibration
from scancell.analysis.uncertainty import NoiseModel, column_sigma
from scancell.model.patterns import PROJECTOR_WIDTH, FringeSequence

IMAGE_SUFFIXES = (".png", ".tif", ".tiff")


@dataclass
class ScanResult:
    cloud: Cloud
    left: PhaseMap
    right: PhaseMap
    timings: dict[str, float] = field(default_factory=dict)


class ScanDecoder:
    """Decodes image sets of one calibrated scanner (rectification maps computed once)."""

    def __init__(self, calib: StereoCalibration, sequence: FringeSequence,
                 projector_width: int = PROJECTOR_WIDTH, settings: DecodeSettings | None = None,
                 noise: NoiseModel | None = None) -> None:
        self.calib = calib
        self.noise = noise or NoiseModel()
        self.sequence = sequence
        self.projector_width = projector_width
        self.settings = settings or DecodeSettings()
        self._rect: Rectification | None = None
        self._pool = ThreadPoolExecutor(2, thread_name_prefix="decode")

    @property
    def rect(self) -> Rectification:
        if self._rect is None:
            self._rect = rectify(self.calib)
        return self._rect

    def decode(self, left: Sequence[np.ndarray], right: Sequence[np.ndarray],
               names: tuple[Sequence[str], Sequence[str]] | None = None) -> ScanResult:
        """One exposure; raise DecodeError (or CalibrationError for a size mismatch) naming the
        problem."""
        return self.decode_exposures([left], [right], ([names[0]], [names[1]]) if names else None)

    def decode_exposures(self, left: Sequence[Sequence[np.ndarray]],
                         right: Sequence[Sequence[np.ndarray]],
                         names: tuple[Sequence[Sequence[str]], Sequence[Sequence[str]]] | None = None
                         ) -> ScanResult:
        """Image sets of one or more exposures (HDR: each pixel takes its best unsaturated
        exposure, :func:`decode_exposures`); the cloud carries per-point uncertainty."""
        if len(left) != len(right) or not left:
            raise DecodeError(f"{len(left)} left and {len(right)} right exposures: need the same "
                              f"number, at least one")
        for side, sets in (("left", left), ("right", right)):
            for imgs in sets:
                if imgs:
                    h, w = imgs[0].shape[:2]
                    self.calib.check_image_size(w, h, f"{side} images")
        t0 = time.perf_counter()
        rect = self.rect
        t1 = time.perf_counter()

        def one(i: int, sets: Sequence[Sequence[np.ndarray]]) -> PhaseMap:
            return decode_exposures(sets, self.sequence, self.projector_width, self.settings,
                                    names[i] if names else None)

        if self.settings.engine == "fast":
            # the numba kernels use every core already (and numba's default threading layer
            # must not be entered from two threads at once)
            pl, pr = (one(i, sets) for i, sets in enumerate((left, right)))
        else:
            futures = [self._pool.submit(one, i, sets) for i, sets in enumerate((left, right))]
            pl, pr = (f.result() for f in futures)
        t2 = time.perf_counter()
        for side, pm, sets in (("left", pl, left), ("right", pr, right)):
            if pm.valid.sum() < 0.001 * pm.valid.size:
                mean = float(np.mean([im.mean() for im in sets[0]]))
                raise DecodeError(
                    f"{side} images: only {pm.valid.sum()} pixels decodable ({pm.rejected}); mean "
                    f"intensity {mean:.1f}: all dark, saturated or no fringes in view")
        sigma = tuple(column_sigma(pm.modulation, pm.background, self.sequence,
                                   self.projector_width, self.noise) for pm in (pl, pr))
        steps: dict[str, float] = {}
        st = self.settings
        limits = DecodeLimits(bend_limit_px=st.bend_limit_px, step_limit_px=st.step_limit_px,
                              confidence_sigmas=st.confidence_sigmas)
        edges = tuple(discontinuity_limits(pm.column, s, limits) for pm, s in zip((pl, pr), sigma,
                                                                                  strict=True))
        cloud = reconstruct(self.calib, pl, pr, rect, None, (st.z_min_mm, st.z_max_mm), steps,
                            st.engine, sigma, edge_limits=edges, border_px=st.border_px)
        t3 = time.perf_counter()
        timings = {"rectify_maps": t1 - t0, "phase": t2 - t1, **steps, "total": t3 - t0}
        return ScanResult(cloud, pl, pr, timings)


class ImageSetError(ValueError):
    pass


def image_path(folder: Path, k: int) -> Path:
    for suffix in IMAGE_SUFFIXES:
        p = folder / f"{k:02d}{suffix}"
        if p.exists():
            return p
    raise ImageSetError(f"{folder / f'{k:02d}.png'}: missing (need {k:02d}.png, .tif or .tiff)")


def read_image(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ImageSetError(f"{path}: unreadable or not an image")
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.dtype not in (np.uint8, np.uint16):
        raise ImageSetError(f"{path}: {img.dtype} pixels; expected 8- or 16-bit")
    return img


@dataclass
class ExposureSet:
    """One exposure's images of both cameras, as read from disk."""

    exposure_us: float | None  # None: a plain DIR/left, DIR/right set
    left: list[np.ndarray]
    right: list[np.ndarray]
    names: tuple[list[str], list[str]]


def exposure_folders(root: Path) -> list[tuple[float | None, Path]]:
    """The exposure folders of an image directory: ``DIR`` itself when it has ``left``/``right``,
    else every ``DIR/exp_<µs>`` (sorted by exposure); ImageSetError if neither or both."""
    if not root.is_dir():
        raise ImageSetError(f"{root}: no such directory")
    exp = []
    for d in root.glob("exp_*"):
        if d.is_dir():
            try:
                exp.append((float(d.name[4:]), d))
            except ValueError:
                raise ImageSetError(f"{d}: exposure folders are named exp_<µs>, e.g. exp_10000"
                                    ) from None
    plain = (root / "left").is_dir() or (root / "right").is_dir()
    if exp and plain:
        raise ImageSetError(f"{root}: has both left/right and exp_<µs> folders; use one layout")
    if exp:
        return sorted(exp, key=lambda e: e[0])
    return [(None, root)]


def read_exposure_sets(folder: str | Path, count: int) -> list[ExposureSet]:
    """``DIR/left``, ``DIR/right`` (one exposure) or ``DIR/exp_<µs>/left``, ``…/right`` (any
    number); every image of every exposure must have the same size and type."""
    sets = []
    for exposure, d in exposure_folders(Path(folder)):
        left, right, names = read_image_set(d, count)
        sets.append(ExposureSet(exposure, left, right, names))
    first = sets[0]
    for s in sets[1:]:
        a, b = first.left[0], s.left[0]
        if a.shape != b.shape or a.dtype != b.dtype:
            raise ImageSetError(f"{s.names[0][0]}: {b.shape[1]} x {b.shape[0]} {b.dtype} differs "
                                f"from {first.names[0][0]}: {a.shape[1]} x {a.shape[0]} {a.dtype} "
                                f"(all exposures must match)")
    return sets


def read_image_set(folder: str | Path, count: int) -> tuple[list[np.ndarray], list[np.ndarray],
                                                            tuple[list[str], list[str]]]:
    """``DIR/left/00.png …`` and ``DIR/right/00.png …`` (k = j·N + n, two digits)."""
    root = Path(folder)
    if not root.is_dir():
        raise ImageSetError(f"{root}: no such directory")
    out: dict[str, list[np.ndarray]] = {}
    names: dict[str, list[str]] = {}
    for side in ("left", "right"):
        d = root / side
        if not d.is_dir():
            raise ImageSetError(f"{d}: missing (expected {root}/left/00.png … and {root}/right/00.png …)")
        paths = [image_path(d, k) for k in range(count)]
        with ThreadPoolExecutor(2) as pool:  # PNG decoding releases the GIL
            out[side] = list(pool.map(read_image, paths))
        names[side] = [str(p) for p in paths]
    first = out["left"][0]
    for side in ("left", "right"):
        for img, name in zip(out[side], names[side], strict=True):
            if img.shape != first.shape or img.dtype != first.dtype:
                raise ImageSetError(f"{name}: {img.shape[1]} x {img.shape[0]} {img.dtype} differs "
                                    f"from {names['left'][0]}: {first.shape[1]} x {first.shape[0]} "
                                    f"{first.dtype}")
    return out["left"], out["right"], (names["left"], names["right"])
