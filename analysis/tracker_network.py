"""Tracker stations tied together by fixed reference nests: one weighted bundle with
covariances, after SpatialAnalyzer's Unified Spatial Metrology Network (USMN).

The tracker measures the cell's reference nests from each of its stations. The bundle solves
every station's pose and every nest's position at once (scipy least squares), each measurement
weighted by the tracker's own uncertainty: a radial 1-sigma (the ADM) along the beam and a
transverse one (the angle encoders x range) across it. There are no chained best fits: a station
that sees a nest another station sees is tied to it directly, and the errors of one move do not
pile up on the next.

Frames and units: the datum is the first station, ``world`` = its tracker frame (as the cell's
``world`` is the tracker's frame today); every other station k is ``T_world_from_station[k]``;
points in mm. The covariance of a station is 6 x 6 over (rotation vector in ``world``, rad;
translation, mm): the station's true pose is ``Exp(w) R``, ``t + dt`` with (w, dt) ~ N(0, C).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scancell.analysis.handeye import kabsch
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation


class NetworkError(ValueError):
    """The network cannot fix a station: too few common nests, or nests on a line."""


@dataclass(frozen=True)
class TrackerSigma:
    """The tracker's 1-sigma per measured point: radial ``radial_um + radial_per_m_um``·range and
    transverse ``transverse_um + transverse_per_m_um``·range (µm; ISO 10360-10 style, the
    typical values are half the MPE)."""

    radial_um: float = 5.0
    radial_per_m_um: float = 0.15
    transverse_um: float = 7.5
    transverse_per_m_um: float = 3.0

    def sigmas_mm(self, range_mm: float) -> tuple[float, float]:
        r_m = range_mm / 1000.0
        return ((self.radial_um + self.radial_per_m_um * r_m) / 1000.0,
                (self.transverse_um + self.transverse_per_m_um * r_m) / 1000.0)

    def whitening(self, p_tracker: np.ndarray) -> np.ndarray:
        """W with Wᵀ W = Σ⁻¹ for a point measured at ``p_tracker`` (its own frame, mm)."""
        rng = float(np.linalg.norm(p_tracker))
        u = p_tracker / rng
        s_r, s_t = self.sigmas_mm(rng)
        P = np.outer(u, u)
        return P / s_r + (np.eye(3) - P) / s_t


@dataclass
class NetworkSolution:
    #: station -> T_world_from_station (4x4); the first station is the identity (the datum)
    stations: dict[str, np.ndarray]
    #: station -> 6x6 covariance of (rotation vector rad, translation mm); zeros for the datum
    station_cov: dict[str, np.ndarray]
    #: nest -> position in world (mm), and its 3x3 covariance (mm²)
    nests: dict[str, np.ndarray]
    nest_cov: dict[str, np.ndarray]
    #: (station, nest) -> |measured - predicted| (mm) after the fit
    residual_mm: dict[tuple[str, str], float] = field(default_factory=dict)
    #: (station, nest) -> the same residual in units of its own 1-sigma (whitened norm)
    residual_sigma: dict[tuple[str, str], float] = field(default_factory=dict)
    #: sum of squared whitened residuals / degrees of freedom (about 1 when the sigmas are right)
    variance_factor: float = float("nan")
    dof: int = 0

    def station_sigma(self, station: str) -> dict[str, float]:
        """The station's 1-sigma: translation (mm, the root of the covariance's trace over the
        three axes) and rotation (arc seconds, likewise)."""
        c = self.station_cov[station]
        return {"translation_mm": float(np.sqrt(np.trace(c[3:, 3:]))),
                "rotation_arcsec": float(np.degrees(np.sqrt(np.trace(c[:3, :3]))) * 3600.0)}

    def worst(self) -> tuple[tuple[str, str], float]:
        """The measurement that fits worst, in sigmas."""
        key = max(self.residual_sigma, key=self.residual_sigma.__getitem__)
        return key, self.residual_sigma[key]


def solve_network(measured: dict[str, dict[str, np.ndarray]], sigma: TrackerSigma,
                  order: list[str] | None = None) -> NetworkSolution:
    """``measured``: station -> nest -> the nest's centre in that station's tracker frame (mm).
    ``order``: the stations, datum first (default: as given). Raises NetworkError naming the
    station that at least 3 nests (not on a line) do not tie to the stations before it."""
    order = list(order or measured)
    if len(order) < 1 or any(s not in measured for s in order):
        raise NetworkError(f"stations {order} not all measured")
    nests = sorted({n for s in order for n in measured[s]})
    # initial values: the datum's nests, then each station by best fit to the nests known so far
    X0: dict[str, np.ndarray] = {n: np.asarray(p, float) for n, p in measured[order[0]].items()}
    T0: dict[str, np.ndarray] = {order[0]: np.eye(4)}
    for s in order[1:]:
        common = sorted(set(measured[s]) & set(X0))
        _check_tie(s, common, np.array([X0[n] for n in common]) if common else np.zeros((0, 3)))
        T = kabsch(np.array([measured[s][n] for n in common], float),
                   np.array([X0[n] for n in common]))
        T0[s] = T
        for n, p in measured[s].items():
            X0.setdefault(n, T[:3, :3] @ np.asarray(p, float) + T[:3, 3])
    missing = [n for n in nests if n not in X0]
    if missing:
        raise NetworkError(f"nests {missing} are not tied to the datum station")
    obs = [(s, n, np.asarray(measured[s][n], float), sigma.whitening(np.asarray(measured[s][n],
                                                                                float)))
           for s in order for n in sorted(measured[s])]
    free = order[1:]
    s_idx = {s: i for i, s in enumerate(free)}
    n_idx = {n: i for i, n in enumerate(nests)}
    n_s = 6 * len(free)

    def unpack(x: np.ndarray, R_ref: dict[str, np.ndarray]):
        poses = {order[0]: (np.eye(3), np.zeros(3))}
        for s, i in s_idx.items():
            w, t = x[6 * i:6 * i + 3], x[6 * i + 3:6 * i + 6]
            poses[s] = (Rotation.from_rotvec(w).as_matrix() @ R_ref[s], t)
        X = x[n_s:].reshape(-1, 3)
        return poses, X

    def residuals(x: np.ndarray, R_ref: dict[str, np.ndarray]) -> np.ndarray:
        poses, X = unpack(x, R_ref)
        out = np.empty(3 * len(obs))
        for k, (s, n, m, W) in enumerate(obs):
            R, t = poses[s]
            out[3 * k:3 * k + 3] = W @ (R.T @ (X[n_idx[n]] - t) - m)
        return out

    def pack(T: dict[str, np.ndarray], X: dict[str, np.ndarray]) -> np.ndarray:
        x = np.zeros(n_s + 3 * len(nests))
        for s, i in s_idx.items():
            x[6 * i + 3:6 * i + 6] = T[s][:3, 3]
        for n, i in n_idx.items():
            x[n_s + 3 * i:n_s + 3 * i + 3] = X[n]
        return x

    R_ref = {s: T0[s][:3, :3] for s in free}
    sol = least_squares(residuals, pack(T0, X0), args=(R_ref,), method="lm", x_scale="jac")
    poses, X = unpack(sol.x, R_ref)
    # linearize again at the solution (rotation vectors 0 there): the covariance's frame
    R_ref = {s: poses[s][0] for s in free}
    T_sol = {s: _pose(*poses[s]) for s in order}
    x_sol = pack(T_sol, {n: X[i] for n, i in n_idx.items()})
    fin = least_squares(residuals, x_sol, args=(R_ref,), method="lm", x_scale="jac", max_nfev=50)
    poses, X = unpack(fin.x, R_ref)
    J = fin.jac
    try:
        C = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        raise NetworkError("the network's normal equations are singular: a station or nest "
                           "is not fixed by the measurements") from None
    r = fin.fun
    dof = len(r) - len(fin.x)
    out = NetworkSolution(
        stations={s: _pose(*poses[s]) for s in order},
        station_cov={order[0]: np.zeros((6, 6)), **{
            s: C[6 * i:6 * i + 6, 6 * i:6 * i + 6] for s, i in s_idx.items()}},
        nests={n: X[i] for n, i in n_idx.items()},
        nest_cov={n: C[n_s + 3 * i:n_s + 3 * i + 3, n_s + 3 * i:n_s + 3 * i + 3]
                  for n, i in n_idx.items()},
        variance_factor=float(r @ r / dof) if dof > 0 else float("nan"), dof=dof)
    for k, (s, n, m, _) in enumerate(obs):
        R, t = poses[s]
        d = R.T @ (X[n_idx[n]] - t) - m
        out.residual_mm[(s, n)] = float(np.linalg.norm(d))
        out.residual_sigma[(s, n)] = float(np.linalg.norm(r[3 * k:3 * k + 3]))
    return out


def _pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def _check_tie(station: str, common: list[str], points: np.ndarray) -> None:
    if len(common) < 3:
        raise NetworkError(f"station {station} sees {len(common)} nest(s) the stations before "
                           f"it measured ({', '.join(common) or 'none'}): at least 3 tie it in")
    s = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    if s[1] < 10.0 or s[1] < 1e-3 * s[0]:
        raise NetworkError(f"station {station}: its common nests {', '.join(common)} lie on a "
                           f"line; they do not fix its rotation about it")


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """(rotation vector rad, translation mm) of ``T_est`` against ``T_true``, in the
    covariance's convention: R_true = Exp(w) R_est, t_true = t_est + dt, returns -(w, dt)."""
    w = Rotation.from_matrix(T_est[:3, :3] @ T_true[:3, :3].T).as_rotvec()
    return np.concatenate([w, T_est[:3, 3] - T_true[:3, 3]])
