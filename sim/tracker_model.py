"""Laser tracker measurement model: noise from a published-style spec, line of sight, acceptance.

Uncertainty follows the ISO 10360-10 style MPE statements of current trackers:

- ADM distance: MPE = ±(10 µm + 0.3 µm/m · R)
- angular (transverse): MPE = ±(15 µm + 6 µm/m · R)

with typical values = half the MPE (the convention of Leica, FARO and API data sheets, which state
typical = MPE / 2). The model draws radial noise with sigma = typical ADM and two transverse
components with sigma = typical angular, all configurable. The tracker is at the world origin.

A point is given only when the beam reaches the SMR: the straight line from the tracker to the
SMR centre must not hit any object (part, stand, scanner housing) before the ball, and the beam
must fall inside the corner cube's acceptance cone (±30° around the opening for a 1.5" SMR);
otherwise the measurement is a beam break, never a point.

Beyond the noise, the mechanics profile (sim/mechanics.py) adds the systematic terms, the air's
refraction, the stand's drift and the SMRs' centring errors.
"""

from __future__ import annotations

import zlib
from collections.abc import Collection
from dataclasses import dataclass

import numpy as np
from scancell.sim import mechanics as mech
from scancell.sim.scene import Scene


@dataclass(frozen=True)
class TrackerSpec:
    adm_const_um: float = 10.0
    adm_per_m_um: float = 0.3
    angle_const_um: float = 15.0
    angle_per_m_um: float = 6.0
    typical_fraction: float = 0.5  # typical = half the MPE
    acceptance_half_angle_deg: float = 30.0

    def sigmas_mm(self, range_mm: float) -> tuple[float, float]:
        """(radial, transverse) 1-sigma in mm at ``range_mm``."""
        r_m = range_mm / 1000.0
        radial = self.typical_fraction * (self.adm_const_um + self.adm_per_m_um * r_m) / 1000
        trans = self.typical_fraction * (self.angle_const_um + self.angle_per_m_um * r_m) / 1000
        return radial, trans


class BeamBreak(Exception):
    """The beam does not reach the reflector (occluded or outside its acceptance angle)."""


@dataclass(frozen=True)
class TrackerReading:
    point_mm: np.ndarray
    sigma_mm: np.ndarray  # per world axis
    true_point_mm: np.ndarray


#: FindReflector locks on the reflector nearest the given position within 100 mm, or else on
#: the one nearest in direction within this cone (deg): the camera-aided search of current
#: trackers (docs/explanation/simulation.md, "Tracker station moves")
FIND_SEARCH_DEG = 5.0


class TrackerModel:
    """The tracker at ``position_mm`` (world; its frame's axes are the world's until its stand
    drifts). Besides noise it has the systematic errors, refraction, stand drift and SMR
    centring of ``mechanics`` (sim/mechanics.py), measured in ``face`` 1 (front) or 2 (back),
    with the air the tracker was told (``air_set``: °C, hPa, % RH)."""

    def __init__(self, spec: TrackerSpec | None = None, rng: np.random.Generator | None = None,
                 position_mm: np.ndarray | None = None,
                 mechanics: mech.MechanicsProfile | None = None, seed: int = 0) -> None:
        self.spec = spec or TrackerSpec()
        self.rng = rng or np.random.default_rng(0)
        #: where the tracker stood first: its readings keep this origin after a move (the
        #: instrument reports in its own frame; the cell's ``world`` was its frame there)
        self.home = np.zeros(3) if position_mm is None else np.asarray(position_mm, float)
        #: the tracker's base in world (its head at the translation): moved by :meth:`move_to`
        self.T_world_from_base = np.eye(4)
        self.T_world_from_base[:3, 3] = self.home
        self.mech = mechanics or mech.IDEAL
        self.seed = seed
        self.face = 1
        self.air_set: tuple[float, float, float] = self.mech.refraction_default
        #: a refraction index the tracker was told directly (emScon SetRefractionParams), used
        #: instead of the index of ``air_set`` until the air is set again
        self.index_set: float | None = None
        drift = np.random.default_rng([seed, 7])
        d = drift.normal(size=3)
        self._drift_dir = d / np.linalg.norm(d)
        a = drift.normal(size=2)
        self._tilt_axis = np.array([a[0], a[1], 0.0]) / np.linalg.norm(a)
        self._station_bias = drift.normal(size=3) * np.asarray(self.mech.weather_station_sigma)

    # ------------------------------------------------------------------ environment
    def weather_station(self, t_s: float) -> tuple[float, float, float]:
        """What the tracker's own weather station reads at ``t_s`` (°C, hPa, % RH)."""
        true = mech.true_air(t_s, self.mech)
        return tuple(float(v + b) for v, b in zip(true, self._station_bias, strict=True))

    def range_scale(self, t_s: float) -> float:
        """Reported / true range from refraction: the tracker converts its optical path with
        the index of the air it was told, the beam travels through the true air."""
        if not self.mech.refraction:
            return 1.0
        return mech.air_index(*mech.true_air(t_s, self.mech)) / self.index_in_use

    @property
    def index_in_use(self) -> float:
        """The refraction index the tracker converts its optical path with."""
        return self.index_set if self.index_set is not None else mech.air_index(*self.air_set)

    def move_to(self, T_world_from_base: np.ndarray) -> None:
        """Set the tracker up elsewhere: its base (head at the translation) at
        ``T_world_from_base``. It measures in its own frame there, so its readings of the same
        points change by the move: the job locates it on the reference nests."""
        self.T_world_from_base = np.asarray(T_world_from_base, float).copy()

    @property
    def position(self) -> np.ndarray:
        """The tracker head in world (mm), where it stands now (its stand's drift aside)."""
        return self.T_world_from_base[:3, 3]

    def T_world_from_readings(self, t_s: float | None = None) -> np.ndarray:
        """The frame its readings are in, in ``world``: the head's frame with home's origin
        (``world`` itself where it stood first), at sim time ``t_s`` (None: without the
        stand's drift)."""
        T = self.T_world_from_base.copy() if t_s is None else self.T_world_from_tracker(t_s)
        T[:3, 3] -= T[:3, :3] @ self.home
        return T

    def to_world(self, point_mm: np.ndarray, t_s: float) -> np.ndarray:
        """A point given in the tracker's readings' frame (mm) in ``world``, by its true pose."""
        T = self.T_world_from_readings(t_s)
        return T[:3, :3] @ np.asarray(point_mm, float) + T[:3, 3]

    def find(self, approx_mm: np.ndarray, reflectors_world: dict[str, np.ndarray], t_s: float
             ) -> str | None:
        """The reflector FindReflector locks on for ``approx_mm`` (its readings' frame): the
        nearest within 100 mm, else the nearest in direction within FIND_SEARCH_DEG; None."""
        if not reflectors_world:
            return None
        p = self.to_world(approx_mm, t_s)
        best = min(reflectors_world, key=lambda k: np.linalg.norm(reflectors_world[k] - p))
        if np.linalg.norm(reflectors_world[best] - p) <= 100.0:
            return best
        head = self.position
        u = (p - head) / np.linalg.norm(p - head)

        def angle(k: str) -> float:
            v = reflectors_world[k] - head
            return float(np.degrees(np.arccos(np.clip(u @ v / np.linalg.norm(v), -1.0, 1.0))))

        best = min(reflectors_world, key=angle)
        return best if angle(best) <= FIND_SEARCH_DEG else None

    def T_world_from_tracker(self, t_s: float) -> np.ndarray:
        """The tracker head's frame in ``world`` at sim time ``t_s`` (its stand drifts)."""
        return self.T_world_from_base @ mech.stand_drift(t_s, self._drift_dir, self._tilt_axis,
                                                          self.mech)

    def centring_offset(self, target: str) -> np.ndarray:
        """The optical centre of ``target``'s SMR off its ball's centre, in the SMR's frame."""
        rng = np.random.default_rng([self.seed, 8, zlib.crc32(target.encode())])
        return rng.normal(size=3) * self.mech.smr_centring_mm

    # ------------------------------------------------------------------ measuring
    def beam_check(self, center: np.ndarray, opening_dir: np.ndarray, radius_mm: float,
                   scene: Scene, exclude: Collection[str] = ()) -> None:
        """Raise BeamBreak if the beam cannot lock on an SMR at ``center``."""
        to_smr = center - self.position
        dist = float(np.linalg.norm(to_smr))
        u = to_smr / dist
        cos_acc = float(np.dot(-u, opening_dir / np.linalg.norm(opening_dir)))
        if cos_acc < np.cos(np.radians(self.spec.acceptance_half_angle_deg)):
            angle = np.degrees(np.arccos(np.clip(cos_acc, -1, 1)))
            raise BeamBreak(f"beam {angle:.1f} deg off the SMR axis (acceptance "
                            f"+/-{self.spec.acceptance_half_angle_deg:.0f} deg)")
        if scene.occluded(self.position, u[None], np.array([dist - radius_mm - 0.5]),
                          exclude=exclude)[0]:
            raise BeamBreak("beam occluded before the SMR")

    def measure(self, center: np.ndarray, R_smr: np.ndarray, target: str, t_s: float
                ) -> TrackerReading:
        """The reading of an SMR whose ball is centred at ``center`` (world, mm) and turned by
        ``R_smr``, at sim time ``t_s``: in the tracker's own (drifted) frame, with its
        systematic errors, refraction and noise. The beam must have been checked."""
        optical = center + R_smr @ self.centring_offset(target)
        T_wt = self.T_world_from_tracker(t_s)
        local = T_wt[:3, :3].T @ (optical - T_wt[:3, 3])
        reported = mech.tracker_systematics(local, self.face, self.range_scale(t_s), self.mech)
        dist = float(np.linalg.norm(reported))
        u = reported / dist
        a = np.cross(u, [0.0, 0.0, 1.0])
        if np.linalg.norm(a) < 1e-6:
            a = np.cross(u, [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(u, a)
        s_r, s_t = self.spec.sigmas_mm(dist)
        e = self.rng.normal(size=3)
        point = self.home + reported + u * s_r * e[0] + a * s_t * e[1] + b * s_t * e[2]
        B = np.stack([u, a, b], axis=1)
        cov = B @ np.diag([s_r**2, s_t**2, s_t**2]) @ B.T
        return TrackerReading(point, np.sqrt(np.diag(cov)), np.asarray(center, float).copy())
