"""Where the tracker stands, from the fixed reference nests: a rigid best fit of the nests as
measured now (tracker frame, mm) onto their surveyed coordinates (``world``, mm)."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np
from scancell.analysis.handeye import kabsch
from scipy.spatial.transform import Rotation


class NestGeometryError(ValueError):
    """Too few nests, or nests on a line: the tracker's pose is not fixed by them."""


@dataclass(frozen=True)
class NestFit:
    #: the tracker's frame in ``world`` that best maps the measured nests onto their survey
    T_world_from_tracker: np.ndarray
    #: per nest: |survey − T · measured| after the fit (mm): how far the nests disagree
    residual_mm: dict[str, float]

    @property
    def rms_mm(self) -> float:
        return float(np.sqrt(np.mean(np.square(list(self.residual_mm.values())))))

    @property
    def worst(self) -> tuple[str, float]:
        name = max(self.residual_mm, key=self.residual_mm.__getitem__)
        return name, self.residual_mm[name]


def fit_nests(survey: dict[str, np.ndarray], measured: dict[str, np.ndarray]) -> NestFit:
    """Best fit of the nests in both maps (at least 3, not on a line)."""
    names = sorted(set(survey) & set(measured))
    if len(names) < 3:
        raise NestGeometryError(f"{len(names)} nests measured ({', '.join(names) or 'none'}): "
                                f"locating the tracker needs at least 3")
    ref = np.array([survey[n] for n in names], float)
    got = np.array([measured[n] for n in names], float)
    s = np.linalg.svd(ref - ref.mean(axis=0), compute_uv=False)
    if s[1] < 1e-3 * s[0] or s[1] < 10.0:
        raise NestGeometryError(f"nests {', '.join(names)} lie on a line: they do not fix the "
                                f"tracker's rotation about it")
    T = kabsch(got, ref)
    res = np.linalg.norm(ref - (got @ T[:3, :3].T + T[:3, 3]), axis=1)
    return NestFit(T, {n: float(r) for n, r in zip(names, res, strict=True)})


def nest_drift(survey: dict[str, np.ndarray], measured: dict[str, np.ndarray],
               T_world_from_tracker: np.ndarray) -> dict[str, float]:
    """Per nest, how far it appears from its survey through the tracker location in force (mm):
    the drift since the tracker was last located."""
    return {n: float(np.linalg.norm(np.asarray(survey[n], float)
                                    - (T_world_from_tracker[:3, :3] @ np.asarray(p, float)
                                       + T_world_from_tracker[:3, 3])))
            for n, p in measured.items() if n in survey}


def turned_about_head(T_world_from_tracker: np.ndarray, yaw_deg: float) -> np.ndarray:
    """A levelled tracker's set-up ``T_world_from_tracker`` (its readings' frame, the head at
    its origin) turned by ``yaw_deg`` about ``world``'s vertical (z) through the head."""
    T = np.asarray(T_world_from_tracker, float).copy()
    T[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix() @ T[:3, :3]
    return T


def _from_head(T_guess: np.ndarray, reading_mm: np.ndarray, survey_mm: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """A reading (the set-up's frame) and a surveyed point, both from the head in ``world``'s
    axes (mm)."""
    T = np.asarray(T_guess, float)
    return (T[:3, :3] @ np.asarray(reading_mm, float),
            np.asarray(survey_mm, float) - T[:3, 3])


def rough_location(T_guess: np.ndarray, survey: dict[str, np.ndarray],
                   measured: dict[str, np.ndarray]) -> np.ndarray:
    """Where a set-up stands from the nests found so far (readings in its frame, mm): their
    rigid best fit once three not on a line are found; before that ``T_guess`` turned about the
    head until the found nests' bearings match their survey's (a tracker set up by hand is
    levelled by its own level, so its unknown is the yaw it was turned to by eye)."""
    with contextlib.suppress(NestGeometryError):
        return fit_nests(survey, measured).T_world_from_tracker
    names = [n for n in measured if n in survey]
    if not names:
        return np.asarray(T_guess, float)
    turns = []
    for n in names:
        seen, want = _from_head(T_guess, measured[n], survey[n])
        turns.append(np.arctan2(want[1], want[0]) - np.arctan2(seen[1], seen[0]))
    mean_turn = np.angle(np.mean(np.exp(1j * np.asarray(turns))))
    return turned_about_head(T_guess, float(np.degrees(mean_turn)))


def off_by_more_than_a_turn(T_guess: np.ndarray, reading_mm: np.ndarray,
                            survey_mm: np.ndarray) -> float:
    """How far (mm) a reading (the set-up's frame) lies from a surveyed point however the
    set-up is turned about its head's vertical: the distance of their horizontal ranges and
    heights from the head, which no turn changes."""
    seen, want = _from_head(T_guess, reading_mm, survey_mm)
    return float(np.hypot(np.hypot(*seen[:2]) - np.hypot(*want[:2]), seen[2] - want[2]))
