"""Projector response calibration: uniform levels seen by both cameras -> the response curve
and the pre-compensation look-up table that linearises the projected fringes (active
compensation).

Input: for each camera, one image per projected uniform 8-bit level (the levels must include 0
and 255). Per camera, the pixels that the projector lights (full white clearly above black), that
never saturate and never sit at the sensor's floor are used; at each level their normalised
response ``(I(v) − I(0)) / (I(255) − I(0))`` is averaged (median, robust to highlights and
shadows). The cameras' curves are averaged into the projector's response R(v) on [0, 1], made
monotone, and a power law ``R = v^γ`` is fitted for the report.

The pre-compensation table gives, for each 8-bit value v wanted, the value u to send so that
R(u) is closest to v/255.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.json_file import read_json

#: the file stored next to the stereo calibration (stereo.yaml)
RESPONSE_FILE = "projector_response.json"
#: a lit pixel: full white at least this many DN above black
MIN_SPAN_DN = 20.0
#: pixels at or above this in any level are saturated and unusable
SATURATION_DN = 254.5
#: fewer usable pixels than this per camera and the fit is refused
MIN_PIXELS = 200
def spread_levels(count: int) -> list[int]:
    """``count`` 8-bit levels spread evenly from 0 to 255."""
    return sorted({round(i * 255 / (count - 1)) for i in range(count)})


#: 18 levels from 0 to 255, every 15
DEFAULT_LEVELS = tuple(spread_levels(18))


def check_levels(levels: Sequence[int]) -> list[int]:
    """The levels as ints; ResponseCalibrationError unless they are at least 3 different 8-bit
    values increasing from 0 to 255."""
    lv = [int(v) for v in levels]
    if len(set(lv)) < 3:
        raise ResponseCalibrationError(
            f"levels {lv}: need at least 3 different levels (0, 255 and some between)")
    if lv != sorted(set(lv)) or lv[0] != 0 or lv[-1] != 255:
        raise ResponseCalibrationError(f"levels {lv}: must increase from 0 to 255")
    return lv


class ResponseCalibrationError(ValueError):
    """The level images cannot give a response (all dark, all saturated, too few levels...)."""


@dataclass
class ProjectorResponse:
    """A projector's measured response (light output against 8-bit pattern value)."""

    levels: list[int]
    response: list[float]  # normalised light at each level (0 at 0, 1 at 255)
    per_camera: dict[str, list[float]]
    pixels: dict[str, int]
    gamma: float  # power law fitted to ``response``
    fit_rms: float  # RMS of the power law's residuals (normalised light)
    job_id: str | None = None

    def curve(self, v: np.ndarray) -> np.ndarray:
        """Normalised light at pattern values v in [0, 1] (linear between measured levels)."""
        return np.interp(np.asarray(v, float) * 255.0, self.levels, self.response)

    def precompensation(self) -> np.ndarray:
        """256 ints: the value to send for each value wanted."""
        sent = np.arange(256)
        light = self.curve(sent / 255.0)
        wanted = np.arange(256) / 255.0
        idx = np.clip(np.searchsorted(light, wanted), 1, 255)
        closer_low = np.abs(light[idx - 1] - wanted) <= np.abs(light[idx] - wanted)
        return np.where(closer_low, idx - 1, idx).astype(np.int64)

    def to_json(self) -> dict[str, Any]:
        return {"levels": self.levels, "response": [round(r, 6) for r in self.response],
                "per_camera": {k: [round(r, 6) for r in v] for k, v in self.per_camera.items()},
                "pixels": self.pixels, "gamma": round(self.gamma, 4),
                "fit_rms": round(self.fit_rms, 5), "job_id": self.job_id,
                "precompensation": self.precompensation().tolist()}

    @classmethod
    def from_json(cls, obj: Any, where: str = "projector response") -> ProjectorResponse:
        try:
            levels = [int(v) for v in obj["levels"]]
            response = [float(r) for r in obj["response"]]
            out = cls(levels, response, {str(k): [float(r) for r in v] for k, v in
                                         (obj.get("per_camera") or {}).items()},
                      {str(k): int(v) for k, v in (obj.get("pixels") or {}).items()},
                      float(obj["gamma"]), float(obj.get("fit_rms", 0.0)), obj.get("job_id"))
        except (KeyError, TypeError, ValueError) as exc:
            raise ResponseCalibrationError(f"{where}: not a projector response ({exc})") from None
        if len(levels) != len(response) or len(levels) < 3 or levels != sorted(set(levels)):
            raise ResponseCalibrationError(f"{where}: levels must be >= 3 increasing values with "
                                           f"one response each")
        return out

    def write(self, path: str | Path) -> None:
        """Atomically (a failed write keeps the previous file)."""
        p = Path(path)
        tmp = p.with_name(f".{p.name}.tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=1))
        os.replace(tmp, p)

    @classmethod
    def read(cls, path: str | Path) -> ProjectorResponse:
        return cls.from_json(read_json(path, ResponseCalibrationError), str(path))


def camera_curve(levels: Sequence[int], images: Sequence[np.ndarray], camera: str
                 ) -> tuple[np.ndarray, int]:
    """Normalised response at each level seen by one camera, and the pixels used."""
    stack = np.stack([np.asarray(i, np.float32) for i in images])
    if stack.ndim != 3:
        raise ResponseCalibrationError(f"{camera}: expected single-channel images")
    scale = 255.0 / float(np.iinfo(images[0].dtype).max) if np.issubdtype(
        images[0].dtype, np.integer) else 1.0
    stack *= np.float32(scale)
    lo, hi = levels.index(0), levels.index(255)
    black, white = stack[lo], stack[hi]
    if float(np.percentile(white, 99)) < MIN_SPAN_DN:
        raise ResponseCalibrationError(
            f"{camera}: all dark (full white reaches {np.percentile(white, 99):.1f} DN at the "
            f"99th percentile): is the projector on and aimed at a surface, the exposure long "
            f"enough?")
    saturated = (stack >= SATURATION_DN).any(axis=0)
    lit = (white - black) >= MIN_SPAN_DN
    usable = lit & ~saturated & (black > 0.5)
    if usable.sum() < MIN_PIXELS:
        why = ("saturated" if (lit & saturated).sum() > 0.5 * max(lit.sum(), 1)
               else "too few lit pixels")
        raise ResponseCalibrationError(
            f"{camera}: {why}: {int(usable.sum())} usable pixels ({int(lit.sum())} lit, "
            f"{int((lit & saturated).sum())} of them saturated at some level); shorten the "
            f"exposure or lower the gain" if why == "saturated" else
            f"{camera}: {why}: {int(usable.sum())} usable pixels (need {MIN_PIXELS})")
    span = (white - black)[usable]
    curve = np.array([float(np.median((s[usable] - black[usable]) / span)) for s in stack])
    return curve, int(usable.sum())


def fit_response(levels: Sequence[int], images: Mapping[str, Sequence[np.ndarray]],
                 job_id: str | None = None) -> ProjectorResponse:
    """The projector's response from each camera's level images (see the module doc)."""
    lv = check_levels(levels)
    if not images:
        raise ResponseCalibrationError("no camera images")
    curves, pixels = {}, {}
    for camera, imgs in images.items():
        if len(imgs) != len(lv):
            raise ResponseCalibrationError(f"{camera}: {len(imgs)} images for {len(lv)} levels")
        shapes = {i.shape for i in imgs}
        if len(shapes) > 1:
            raise ResponseCalibrationError(f"{camera}: images differ in size: {sorted(shapes)}")
        curves[camera], pixels[camera] = camera_curve(lv, imgs, camera)
    response = np.mean(list(curves.values()), axis=0)
    response = np.clip(np.maximum.accumulate(response), 0.0, None)
    response = (response - response[0]) / max(response[-1] - response[0], 1e-9)
    if np.ptp(response[1:-1]) < 1e-3 and len(lv) > 3:
        raise ResponseCalibrationError("the response does not change between levels: is the "
                                       "projector showing the levels?")
    x = np.asarray(lv[1:-1], float) / 255.0
    y = response[1:-1]
    ok = y > 1e-3
    gamma = float(np.sum(np.log(x[ok]) * np.log(y[ok])) / np.sum(np.log(x[ok]) ** 2)) \
        if ok.sum() >= 1 else float("nan")
    fit_rms = float(np.sqrt(np.mean((x ** gamma - y) ** 2))) if np.isfinite(gamma) else float("nan")
    return ProjectorResponse(lv, response.tolist(), {k: v.tolist() for k, v in curves.items()},
                             pixels, gamma, fit_rms, job_id)
