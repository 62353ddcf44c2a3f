"""The path of the robot's external axis: a straight rail, or a track of straight and curved
modules (the curved track modules rail makers sell by radius and angle) that carries the robot
round a part too large to measure from one side.

A rail position ``s`` (mm, what the axis drive reports) is the distance along the path from its
start, which is where the robot base stands at ``T_world_from_base``; on a curved module the
carriage, and the base with it, turns with the path's heading. Before the start and past the
end the path runs straight on (a plain rail is the path with no modules).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


class RailPathError(ValueError):
    """A ``rail_path`` table has a malformed module."""


@dataclass(frozen=True)
class RailModule:
    """One module of track: ``length_mm`` of it, turning by ``turn_deg`` over that length
    (0: straight; + turns left, anticlockwise seen from above)."""

    length_mm: float
    turn_deg: float = 0.0


@dataclass(frozen=True)
class RailPath:
    """The axis's path in world: it starts at the base's position heading along ``axis``
    (a horizontal unit vector) and follows ``modules`` in order."""

    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    modules: tuple[RailModule, ...] = ()

    @property
    def length_mm(self) -> float:
        return float(sum(m.length_mm for m in self.modules))

    @property
    def max_turn_per_mm(self) -> float:
        """The track's sharpest turn (rad per mm of travel): 0 on a straight rail. A base that
        travels ``d`` mm turns at most ``d`` times this."""
        return max((abs(np.radians(m.turn_deg)) / m.length_mm for m in self.modules),
                   default=0.0)

    def offset(self, s_mm: float) -> tuple[np.ndarray, float]:
        """Where the base stands at rail position ``s_mm`` relative to its start: the
        displacement (world, mm) and the turn about world z (rad) since the start."""
        a = np.asarray(self.axis, float)
        heading = float(np.arctan2(a[1], a[0]))
        pos = np.zeros(3)
        left = float(s_mm)
        if left < 0 or not self.modules:
            return np.array([np.cos(heading), np.sin(heading), 0.0]) * left, 0.0
        turned = 0.0
        for m in self.modules:
            step = min(left, m.length_mm)
            pos += _advance(heading + turned, step, np.radians(m.turn_deg) * step / m.length_mm)
            turned += np.radians(m.turn_deg) * step / m.length_mm
            left -= step
            if left <= 0:
                return pos, turned
        h = heading + turned
        return pos + np.array([np.cos(h), np.sin(h), 0.0]) * left, turned

    def base_at(self, T_world_from_base: np.ndarray, s_mm: float | None) -> np.ndarray:
        """The robot base's pose (world, mm) at rail position ``s_mm`` (None: the start)."""
        T = np.array(T_world_from_base, float)
        if not s_mm:
            return T
        d, turn = self.offset(s_mm)
        c, s = np.cos(turn), np.sin(turn)
        Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        T[:3, :3] = Rz @ T[:3, :3]
        T[:3, 3] += d
        return T

    @classmethod
    def from_table(cls, axis: Any, modules: Any) -> RailPath:
        """From ``rail_axis`` (3 numbers) and ``rail_path`` (a list of ``{length_mm, turn_deg}``
        tables, or absent: a straight rail)."""
        a = np.asarray(axis if axis is not None else (0.0, 1.0, 0.0), float)
        if a.shape != (3,) or abs(a[2]) > 1e-9 or not np.linalg.norm(a) > 0:
            raise RailPathError(f"rail_axis must be 3 numbers, horizontal and not zero, got "
                                f"{axis!r}")
        out = []
        for i, m in enumerate(modules or ()):
            if not isinstance(m, dict) or "length_mm" not in m or set(m) - {"length_mm",
                                                                            "turn_deg"}:
                raise RailPathError(f"rail_path[{i}]: a module is {{length_mm, turn_deg}}, "
                                    f"got {m!r}")
            length, turn = float(m["length_mm"]), float(m.get("turn_deg", 0.0))
            if not length > 0 or not abs(turn) < 360:
                raise RailPathError(f"rail_path[{i}]: length_mm must be > 0 and |turn_deg| < "
                                    f"360, got {length}, {turn}")
            out.append(RailModule(length, turn))
        return cls(tuple(float(v) for v in a / np.linalg.norm(a)), tuple(out))

    def to_table(self) -> list[dict[str, float]]:
        return [{"length_mm": m.length_mm, "turn_deg": m.turn_deg} for m in self.modules]


def _advance(heading: float, length: float, turn: float) -> np.ndarray:
    """Displacement along an arc of ``length`` turning by ``turn`` (rad) from ``heading``."""
    if abs(turn) < 1e-12:
        return np.array([np.cos(heading), np.sin(heading), 0.0]) * length
    r = length / turn  # signed: + turns left
    return np.array([r * (np.sin(heading + turn) - np.sin(heading)),
                     -r * (np.cos(heading + turn) - np.cos(heading)), 0.0])
