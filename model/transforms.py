"""Homogeneous transforms (4x4, mm) and rotations, as every layer uses them.

Names follow docs/explanation/frames-and-units.md: ``T_<to>_from_<from>`` maps ``<from>``
coordinates into ``<to>``.
"""

from __future__ import annotations

import numpy as np


def make_T(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """A 4x4 transform from a rotation (3x3) and a translation (mm); identity parts if None."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def rot_x(deg: float) -> np.ndarray:
    """3x3 rotation about x by ``deg`` degrees."""
    a = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


def rot_y(deg: float) -> np.ndarray:
    """3x3 rotation about y by ``deg`` degrees."""
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def T_rot_z(deg: float) -> np.ndarray:
    """4x4 rotation about z by ``deg`` degrees (a J6 turn in the flange frame)."""
    t = np.radians(deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]
    return T


def apply_T(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Points (N x 3, mm) mapped by the 4x4 transform ``T``."""
    return pts @ T[:3, :3].T + T[:3, 3]


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle (degrees) of the rotation ``R`` (3x3), e.g. of ``R_a @ R_b.T`` between two
    orientations."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R[:3, :3]) - 1) / 2, -1.0, 1.0))))


def look_at_flange(target: np.ndarray, view: np.ndarray, standoff_mm: float,
                   rig_mid_in_flange: np.ndarray) -> np.ndarray:
    """``T_world_from_flange`` that puts ``target`` (world, mm) on the scanner's bisector (the
    flange z axis) ``standoff_mm`` in front of the rig midpoint, looking along ``view``, with the
    baseline (flange x) horizontal (world z up)."""
    v = np.asarray(view, float)
    v = v / np.linalg.norm(v)
    x = np.cross([0.0, 0.0, -1.0], v)
    x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([0.0, 1.0, 0.0])
    R = np.stack([x, np.cross(v, x), v], axis=1)
    return make_T(R, np.asarray(target, float) - v * standoff_mm - R @ rig_mid_in_flange)
