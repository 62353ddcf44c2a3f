"""Hand-eye calibration ``T_ecs_from_mcs`` from ball centres seen by scanner and tracker.

Each pair is one ball position: its centre in MCS (scanner) and in ECS (tracker point taken
into the end coordinate system). The transform is the SVD (Kabsch) solution of
``ecs ≈ R · mcs + t`` with the reflection guard. The robust mode removes pairs that no rigid
motion can fit together with the others — a typo in a table, a ball knocked between the scan
and the tracker measurement — and says which and why. Uncertainty by Monte Carlo with the
point noise the residuals show.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scancell.model.transforms import rotation_angle_deg
from scipy.spatial.transform import Rotation


class HandEyeError(ValueError):
    """Not enough or degenerate pairs; the message names the problem."""


@dataclass(frozen=True)
class Pair:
    id: str
    ecs: np.ndarray  # (3,) mm
    mcs: np.ndarray  # (3,) mm


def kabsch(mcs: np.ndarray, ecs: np.ndarray) -> np.ndarray:
    """4x4 ``T`` minimising Σ |ecs_i − (R·mcs_i + t)|² (proper rotation, det R = +1)."""
    a, b = np.asarray(mcs, float), np.asarray(ecs, float)
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    H = (a - ca).T @ (b - cb)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = cb - R @ ca
    return T


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ T[:3, :3].T + T[:3, 3]


def rotation_angle_arcsec(R: np.ndarray) -> float:
    return rotation_angle_deg(R) * 3600


@dataclass
class HandEyeResult:
    T_ecs_from_mcs: np.ndarray
    rms_mm: float
    residuals_mm: dict[str, float]
    excluded: list[dict[str, str]]
    rotation_sigma_arcsec: float
    translation_sigma_mm: float
    leave_one_out_mm: dict[str, float] = field(default_factory=dict)
    used: list[str] = field(default_factory=list)
    #: 6 x 6 covariance of the calibration's error as a move in MCS, ``T_true = T · δ`` with
    #: δ = (rotation vector, rad; translation, mm): its rotation and translation are strongly
    #: correlated (the fit pivots about the balls' centroid, not about MCS's origin), which the
    #: two sigmas above cannot say
    covariance_mcs: np.ndarray | None = None

    def to_json(self) -> dict:
        out = {"T_ecs_from_mcs": self.T_ecs_from_mcs.tolist(), "rms_mm": self.rms_mm,
               "residuals_mm": self.residuals_mm, "excluded": self.excluded,
               "rotation_sigma_arcsec": self.rotation_sigma_arcsec,
               "translation_sigma_mm": self.translation_sigma_mm,
               "leave_one_out_mm": self.leave_one_out_mm, "used": self.used}
        if self.covariance_mcs is not None:
            out["covariance_mcs"] = self.covariance_mcs.tolist()
        return out

    def table(self) -> str:
        lines = [f"hand-eye T_ecs_from_mcs from {len(self.used)} pairs "
                 f"({len(self.excluded)} excluded): RMS {self.rms_mm:.4f} mm, rotation 1-sigma "
                 f"{self.rotation_sigma_arcsec:.1f}\", translation 1-sigma "
                 f"{self.translation_sigma_mm:.4f} mm",
                 f"  {'id':>8s} {'residual mm':>12s} {'leave-one-out mm':>17s}"]
        for i in self.used:
            lines.append(f"  {i:>8s} {self.residuals_mm[i]:12.4f} "
                         f"{self.leave_one_out_mm.get(i, float('nan')):17.4f}")
        for e in self.excluded:
            lines.append(f"  excluded {e['id']}: {e['reason']}")
        lines.append("  T_ecs_from_mcs =")
        lines += ["    [" + ", ".join(f"{v:12.6f}" for v in row) + "]" for row in self.T_ecs_from_mcs]
        return "\n".join(lines)


def check_pairs(pairs: Sequence[Pair]) -> None:
    if len(pairs) < 3:
        raise HandEyeError(f"hand-eye needs at least 3 pairs, got {len(pairs)}")
    seen: set[str] = set()
    for p in pairs:
        if p.id in seen:
            raise HandEyeError(f"duplicate pair id {p.id!r}")
        seen.add(p.id)
        for side, v in (("ecs", p.ecs), ("mcs", p.mcs)):
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise HandEyeError(f"pair {p.id!r}: {side} is not 3 finite numbers: {v}")
    for side in ("ecs", "mcs"):
        pts = np.array([getattr(p, side) for p in pairs])
        s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
        if s[0] < 1e-6 or s[1] < 1e-3 * s[0]:
            raise HandEyeError(f"the {side} points are {'coincident' if s[0] < 1e-6 else 'collinear'}"
                               f": the rotation about their line is undetermined; spread the "
                               f"ball over the field and depth")


def _distance_mismatch(pairs: Sequence[Pair], i: int, others: Sequence[int]) -> float:
    e, m = pairs[i].ecs, pairs[i].mcs
    return float(max(abs(np.linalg.norm(e - pairs[j].ecs) - np.linalg.norm(m - pairs[j].mcs))
                     for j in others))


def solve_hand_eye(pairs: Sequence[Pair], robust: bool = True, threshold_mm: float | None = None,
                   mc_samples: int = 400, seed: int = 0) -> HandEyeResult:
    """``T_ecs_from_mcs`` with residuals, exclusions, leave-one-out and Monte Carlo sigmas.

    Robust mode: while at least 4 pairs remain, the pair with the largest leave-one-out error
    is excluded if that error exceeds ``threshold_mm`` (default: 5 x the robust residual scale
    of the remaining pairs, at least 0.05 mm).
    """
    check_pairs(pairs)
    idx = list(range(len(pairs)))
    excluded: list[dict[str, str]] = []
    ecs = np.array([p.ecs for p in pairs], float)
    mcs = np.array([p.mcs for p in pairs], float)

    def loo(use: list[int]) -> dict[int, float]:
        out = {}
        for i in use:
            rest = [j for j in use if j != i]
            T = kabsch(mcs[rest], ecs[rest])
            out[i] = float(np.linalg.norm(_apply(T, mcs[i]) - ecs[i]))
        return out

    while robust and len(idx) >= 4:
        errs = loo(idx)
        worst = max(idx, key=lambda i: errs[i])
        rest = [j for j in idx if j != worst]
        T = kabsch(mcs[rest], ecs[rest])
        res_rest = np.linalg.norm(_apply(T, mcs[rest]) - ecs[rest], axis=1)
        scale = 1.4826 * float(np.median(res_rest)) * np.sqrt(len(rest) / max(len(rest) - 2, 1))
        limit = threshold_mm if threshold_mm is not None else max(5.0 * scale, 0.05)
        if errs[worst] <= limit:
            break
        mismatch = _distance_mismatch(pairs, worst, rest)
        excluded.append({"id": pairs[worst].id, "reason": (
            f"leave-one-out error {errs[worst]:.3f} mm > {limit:.3f} mm: its distances to the "
            f"other balls differ by up to {mismatch:.3f} mm between ECS and MCS (a typo, or the "
            f"ball moved between the scan and the tracker measurement)")})
        idx = rest
    if len(idx) < 3:
        raise HandEyeError("fewer than 3 consistent pairs remain")
    use = idx
    T = kabsch(mcs[use], ecs[use])
    res = np.linalg.norm(_apply(T, mcs[use]) - ecs[use], axis=1)
    rms = float(np.sqrt(np.mean(res**2)))
    loo_errs = loo(use) if len(use) >= 4 else {}
    # Monte Carlo: point noise as the residuals show it, split between both sides
    dof = max(3 * len(use) - 6, 1)
    sigma = np.sqrt(float(np.sum(res**2)) / dof) / np.sqrt(2.0)
    rng = np.random.default_rng(seed)
    angles, shifts, moves = [], [], []
    for _ in range(mc_samples):
        Tk = kabsch(mcs[use] + rng.normal(0, sigma, (len(use), 3)),
                    ecs[use] + rng.normal(0, sigma, (len(use), 3)))
        angles.append(rotation_angle_arcsec(Tk[:3, :3] @ T[:3, :3].T))
        shifts.append(Tk[:3, 3] - T[:3, 3])
        delta = np.linalg.solve(T, Tk)
        moves.append(np.concatenate([Rotation.from_matrix(delta[:3, :3]).as_rotvec(),
                                     delta[:3, 3]]))
    rot_sigma = float(np.sqrt(np.mean(np.square(angles)))) if angles else 0.0
    trans_sigma = float(np.sqrt(np.mean(np.sum(np.square(shifts), axis=1)))) if shifts else 0.0
    covariance = (np.asarray(moves).T @ np.asarray(moves)) / len(moves) if moves else None
    return HandEyeResult(
        T, rms, {pairs[i].id: float(r) for i, r in zip(use, res, strict=True)}, excluded,
        rot_sigma, trans_sigma, {pairs[i].id: v for i, v in loo_errs.items()},
        [pairs[i].id for i in use], covariance)
