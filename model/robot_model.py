"""Kinematics of a FANUC M-710iC/50-class 6-axis arm: DH model, forward and numerical inverse.

Geometry (mm) and limits follow FANUC's M-710iC/50 data sheet (reach 2050 mm): J2 axis 565 mm
above the base and 150 mm forward of J1, upper arm 870 mm, J3 offset 170 mm, forearm 1016 mm,
wrist-to-flange 175 mm. Joint ranges J1 360°, J2 225°, J3 440°, J4 720°, J5 250°, J6 720°; max
speeds 175, 175, 175, 250, 250, 355 °/s. The values are of the published class, not a calibrated
robot: the system never trusts the robot's kinematics for accuracy, so this only has to be a
realistic way to place the scanner.

Joint convention: standard DH angles plus offsets, with J3 not coupled to J2 (FANUC controllers
report J3 relative to the horizon; a driver converts). Home [0, 0, 0, 0, -90, 0]° points the
flange straight down in front of the robot.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class DHRow:
    a: float  # mm
    alpha: float  # rad
    d: float  # mm
    offset: float  # rad, added to the joint angle


M710IC_DH = (
    DHRow(150.0, -np.pi / 2, 565.0, 0.0),
    DHRow(870.0, 0.0, 0.0, -np.pi / 2),
    DHRow(170.0, -np.pi / 2, 0.0, 0.0),
    DHRow(0.0, np.pi / 2, 1016.0, 0.0),
    DHRow(0.0, -np.pi / 2, 0.0, 0.0),
    DHRow(0.0, 0.0, 175.0, 0.0),
)
M710IC_LIMITS_DEG = np.array(
    [[-180, 180], [-90, 135], [-160, 280], [-360, 360], [-125, 125], [-360, 360]], float)
M710IC_SPEED_DEG_S = np.array([175, 175, 175, 250, 250, 355], float)
M710IC_REACH_MM = 2050.0  # wrist centre from the J2 axis height, data sheet


def dh_matrix(row: DHRow, q: float) -> np.ndarray:
    th = q + row.offset
    ct, st = np.cos(th), np.sin(th)
    ca, sa = np.cos(row.alpha), np.sin(row.alpha)
    return np.array([
        [ct, -st * ca, st * sa, row.a * ct],
        [st, ct * ca, -ct * sa, row.a * st],
        [0.0, sa, ca, row.d],
        [0.0, 0.0, 0.0, 1.0],
    ])


class IKError(ValueError):
    """No joint solution inside the limits reaches the pose."""


@dataclass
class RobotModel:
    """Forward and inverse kinematics. Poses are ``T_base_from_flange`` (4x4, mm)."""

    dh: tuple[DHRow, ...] = M710IC_DH
    limits_rad: np.ndarray = field(default_factory=lambda: np.radians(M710IC_LIMITS_DEG))
    max_speed_rad_s: np.ndarray = field(default_factory=lambda: np.radians(M710IC_SPEED_DEG_S))
    reach_mm: float = M710IC_REACH_MM

    def within_reach(self, T_base_from_flange: np.ndarray) -> bool:
        """Whether the wrist centre of a flange pose lies within the arm's reach of the
        shoulder (J1 axis at the J2 height): a quick test before inverse kinematics."""
        wrist = T_base_from_flange[:3, 3] - self.dh[5].d * T_base_from_flange[:3, 2]
        return bool(np.linalg.norm(wrist - [0.0, 0.0, self.dh[0].d]) <= self.reach_mm)

    def fk(self, q_rad: np.ndarray) -> np.ndarray:
        return self._frames(q_rad)[-1]

    def _frames(self, q_rad: np.ndarray) -> list[np.ndarray]:
        """The base frame and each link's frame after it (7 poses, base frame, mm)."""
        out = [np.eye(4)]
        for row, q in zip(self.dh, np.asarray(q_rad, float), strict=True):
            out.append(out[-1] @ dh_matrix(row, q))
        return out

    def within_limits(self, q_rad: np.ndarray) -> bool:
        q = np.asarray(q_rad, float)
        return bool(np.all(q >= self.limits_rad[:, 0] - 1e-9) and
                    np.all(q <= self.limits_rad[:, 1] + 1e-9))

    def ik(self, T_target: np.ndarray, seed_rad: np.ndarray | None = None,
           tol_mm: float = 1e-3, tol_rad: float = 1e-6) -> np.ndarray:
        """Numerical IK (bounded least squares on position and rotation-vector error).

        Tries the seed, then a few standard seeds; raises IKError if none converges.
        """
        seeds = [] if seed_rad is None else [np.asarray(seed_rad, float)]
        seeds += [np.radians(s) for s in ([0, 0, 0, 0, -90, 0], [0, 20, -10, 0, -60, 0],
                                          [0, -20, 20, 0, -90, 0], [30, 10, 0, 90, -45, -90],
                                          [-30, 10, 0, -90, -45, 90])]
        lo, hi = self.limits_rad[:, 0], self.limits_rad[:, 1]
        R_t = T_target[:3, :3]
        p_t = T_target[:3, 3]

        def residual(q: np.ndarray) -> np.ndarray:
            T = self.fk(q)
            rot = _rotvec(R_t.T @ T[:3, :3])
            return np.concatenate([T[:3, 3] - p_t, 1000.0 * rot])  # 1 mrad ~ 1 mm

        def jacobian(q: np.ndarray) -> np.ndarray:
            """d residual / dq: the arm's geometric Jacobian, its angular rows taken through
            the inverse left Jacobian of SO(3) at the rotation error (finite differences took
            seven forward kinematics a step, and most of a plan's time)."""
            frames = self._frames(q)
            p_e = frames[-1][:3, 3]
            z = np.array([F[:3, 2] for F in frames[:-1]])
            o = np.array([F[:3, 3] for F in frames[:-1]])
            J = np.empty((6, 6))
            J[:3] = np.cross(z, p_e - o).T
            rot = _rotvec(R_t.T @ frames[-1][:3, :3])
            J[3:] = 1000.0 * _left_jacobian_inverse(rot) @ R_t.T @ z.T
            return J

        best = None
        for s in seeds:
            s = np.clip(s, lo + 1e-6, hi - 1e-6)
            sol = least_squares(residual, s, jac=jacobian, bounds=(lo, hi), xtol=1e-12,
                                ftol=1e-12, gtol=1e-12, max_nfev=400)
            r = residual(sol.x)
            if np.linalg.norm(r[:3]) < tol_mm and np.linalg.norm(r[3:]) / 1000 < tol_rad:
                return sol.x
            if best is None or sol.cost < best.cost:
                best = sol
        err = residual(best.x)
        raise IKError(f"pose unreachable inside joint limits: best residual "
                      f"{np.linalg.norm(err[:3]):.2f} mm, "
                      f"{np.degrees(np.linalg.norm(err[3:]) / 1000):.3f} deg")

    def joint_levers_mm(self, tool_mm: float) -> np.ndarray:
        """(6,) bounds (mm) on how far a point within ``tool_mm`` of the flange's origin stands
        from each joint's axis, in any pose: a turn of ``dq[i]`` rad moves it at most
        ``dq[i] * lever[i]``. Joint i turns about its DH z axis: its row's ``d`` runs along that
        axis, its ``a`` and every later row's ``a`` and ``d`` away from it. The first three are
        also bounded by the reach (the wrist centre within ``reach_mm`` of the J2 height on the
        J1 axis, plus the shoulder offset and the wrist-to-flange)."""
        rows = self.dh
        chain = np.array([abs(r.a) + sum(abs(n.a) + abs(n.d) for n in rows[i + 1:])
                          for i, r in enumerate(rows)]) + tool_mm
        reach = self.reach_mm + abs(rows[0].a) + abs(rows[5].d) + tool_mm
        return np.minimum(chain, np.where(np.arange(6) < 3, reach, np.inf))

    def travel_time(self, q_from: np.ndarray, q_to: np.ndarray, speed: float) -> float:
        """Time (s) of a synchronised joint move at ``speed`` x max joint speed."""
        dq = np.abs(np.asarray(q_to, float) - np.asarray(q_from, float))
        return float(np.max(dq / (self.max_speed_rad_s * speed)))


def _rotvec(R: np.ndarray) -> np.ndarray:
    """The rotation vector (rad) of a rotation matrix: SciPy's ``as_rotvec`` without building a
    ``Rotation`` (which cost the IK's residual half its time); SciPy near 180 degrees."""
    cos = 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)
    axis = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if cos > 0.9999:  # small angles: the skew part is the rotation vector to 1e-12
        return axis * (1.0 + float(axis @ axis) / 6.0)
    if cos < -0.99:
        return Rotation.from_matrix(R).as_rotvec()
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    return axis * (angle / np.sin(angle))


def _left_jacobian_inverse(phi: np.ndarray) -> np.ndarray:
    """J_l^-1 of SO(3) at rotation vector ``phi``: d log(exp(d^) R) / d d at d = 0."""
    theta = float(np.linalg.norm(phi))
    K = np.array([[0.0, -phi[2], phi[1]], [phi[2], 0.0, -phi[0]], [-phi[1], phi[0], 0.0]])
    if theta < 1e-6:
        return np.eye(3) - 0.5 * K + K @ K / 12.0
    c = 1.0 / theta**2 - (1.0 + np.cos(theta)) / (2.0 * theta * np.sin(theta))
    return np.eye(3) - 0.5 * K + c * (K @ K)

