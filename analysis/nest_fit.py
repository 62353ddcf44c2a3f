"""Where the tracker stands, from the fixed reference nests: a rigid best fit of the nests as
measured now (tracker frame, mm) onto their surveyed coordinates (``world``, mm)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scancell.analysis.handeye import kabsch


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
