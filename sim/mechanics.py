"""The simulated cell's mechanics and time: robot compliance, vibration and thermal growth,
tracker systematic errors, air refraction, stand drift and SMR centring, the scanner's warm-up.

Every parameter's value and source is in docs/explanation/simulation.md ("Mechanics and time"). A profile is a
set of values; each effect can be switched off on its own (:func:`mechanics_profile`), which puts
back the ``ideal`` profile's values of that effect's fields (the ablation in
benchmarks/RESULTS.md). Time-dependent effects are functions of the simulation clock (seconds,
:class:`scancell.sim.clock.SimClock`), so a seeded run is repeatable.

Frames: ``world`` is the tracker's frame when the cell was set up (sim time 0); mm, rad, s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scancell.sim.profiles import ProfileError as ProfileError  # re-exported
from scancell.sim.profiles import select_profile

#: standard gravity (m/s²)
G = 9.80665


@dataclass(frozen=True)
class MechanicsProfile:
    """All mechanical and time parameters of the simulated cell (docs/explanation/simulation.md)."""

    name: str = "ideal"
    # ---- time
    #: sim seconds one stationary tracker measurement takes (the tracker averages over it)
    tracker_shot_s: float = 0.05
    #: sim seconds one FindReflector takes (turning to the position, searching, locking on)
    tracker_find_s: float = 0.2
    #: sim seconds one projected pattern takes (exposure and readout)
    pattern_s: float = 0.0105
    #: frames rendered within this many sim seconds of a pose's first frame share its pose
    render_burst_s: float = 1.0
    # ---- robot: joint compliance under the scanner's weight
    payload_kg: float = 0.0
    #: the payload's centre of mass in the flange frame (mm): off the J6 axis, so J6 turns move it
    payload_com_in_flange_mm: tuple[float, float, float] = (35.0, -20.0, 130.0)
    joint_stiffness_nm_per_rad: tuple[float, ...] = (2.0e6, 1.6e6, 1.0e6, 2.4e5, 2.0e5, 1.0e5)
    # ---- robot: damped ringing after every move, and the vibration it holds still with
    ring_amplitude_mm: float = 0.0
    #: the speed override (fraction of the joints' maximum) a move rings ``ring_amplitude_mm``
    #: after; the amplitude grows in proportion to a move's speed
    ring_reference_speed: float = 0.2
    ring_hz: float = 9.0
    ring_damping: float = 0.05
    hold_vibration_rms_mm: float = 0.0
    hold_vibration_hz: float = 17.0
    # ---- robot: thermal growth of the arm's links (first-order approach to a warm arm)
    robot_expansion_ppm_per_k: float = 11.5
    robot_warmup_k: float = 0.0
    robot_warmup_tau_s: float = 3600.0
    # ---- tracker: ISO 10360-10 systematic terms (Muralikrishnan et al. 2009's model)
    adm_scale_ppm: float = 0.0
    adm_offset_mm: float = 0.0
    #: horizontal encoder eccentricity: first harmonic of the azimuth error (odd: two-face)
    encoder_eccentricity_arcsec: float = 0.0
    encoder_eccentricity_phase_deg: float = 35.0
    #: second harmonic of the azimuth error (even: invisible to a two-face test)
    encoder_second_harmonic_arcsec: float = 0.0
    #: vertical index offset (zenith angle; odd: two-face)
    vertical_index_arcsec: float = 0.0
    #: transverse beam offset (mm; odd: two-face)
    beam_offset_mm: float = 0.0
    # ---- tracker: air refraction. The true air of the cell, and the tracker's default
    air_temperature_c: float = 20.0
    air_temperature_rate_c_per_h: float = 0.0
    air_pressure_hpa: float = 1013.25
    air_humidity_pct: float = 50.0
    #: what the tracker assumes until it is told the weather (its power-on default)
    refraction_default: tuple[float, float, float] = (20.0, 1013.25, 50.0)
    #: the built-in weather station's error (°C, hPa, %), a fixed bias drawn per seed with
    #: these 1-sigmas
    weather_station_sigma: tuple[float, float, float] = (0.0, 0.0, 0.0)
    refraction: bool = False
    # ---- tracker: its stand drifts (settling exponentially, then thermal growth)
    stand_settle_mm: float = 0.0
    stand_settle_tau_s: float = 900.0
    stand_thermal_mm_per_h: float = 0.0
    stand_tilt_urad_per_h: float = 0.0
    # ---- tracker: SMR centring error (optical centre off the ball's centre), 1 sigma per axis
    smr_centring_mm: float = 0.0
    # ---- scanner: warm-up drift of the stereo geometry
    scanner_baseline_warmup_ppm: float = 0.0
    scanner_focal_warmup_ppm: float = 0.0
    scanner_warmup_tau_s: float = 1200.0


#: which fields each switchable effect owns
EFFECTS: dict[str, tuple[str, ...]] = {
    "compliance": ("payload_kg",),
    "vibration": ("ring_amplitude_mm", "hold_vibration_rms_mm"),
    "robot_thermal": ("robot_warmup_k",),
    "tracker_systematics": ("adm_scale_ppm", "adm_offset_mm", "encoder_eccentricity_arcsec",
                            "encoder_second_harmonic_arcsec", "vertical_index_arcsec",
                            "beam_offset_mm"),
    "refraction": ("refraction", "weather_station_sigma"),
    "stand_drift": ("stand_settle_mm", "stand_thermal_mm_per_h", "stand_tilt_urad_per_h"),
    "smr_centring": ("smr_centring_mm",),
    "scanner_warmup": ("scanner_baseline_warmup_ppm", "scanner_focal_warmup_ppm"),
}

IDEAL = MechanicsProfile()

REALISTIC = MechanicsProfile(
    name="realistic",
    payload_kg=9.0,
    ring_amplitude_mm=0.12,
    hold_vibration_rms_mm=0.015,
    robot_warmup_k=3.0,
    adm_scale_ppm=0.5,
    adm_offset_mm=0.004,
    encoder_eccentricity_arcsec=0.8,
    encoder_second_harmonic_arcsec=0.4,
    vertical_index_arcsec=0.6,
    beam_offset_mm=0.005,
    air_temperature_c=23.5,
    air_temperature_rate_c_per_h=0.8,
    air_pressure_hpa=985.0,
    air_humidity_pct=40.0,
    weather_station_sigma=(0.15, 0.5, 2.5),
    refraction=True,
    stand_settle_mm=0.03,
    stand_thermal_mm_per_h=0.02,
    stand_tilt_urad_per_h=5.0,
    smr_centring_mm=0.0025,
    scanner_baseline_warmup_ppm=40.0,
    scanner_focal_warmup_ppm=25.0,
)

PROFILES: dict[str, MechanicsProfile] = {"ideal": IDEAL, "realistic": REALISTIC}
DEFAULT_PROFILE = "realistic"


def mechanics_profile(name: str = DEFAULT_PROFILE, effects_off: tuple[str, ...] | list[str] = (),
                      **overrides: object) -> MechanicsProfile:
    """The named profile with the given effects switched off (their ideal values) and single
    fields overridden; ProfileError names an unknown profile, effect or field."""
    return select_profile("mechanics", PROFILES, EFFECTS, name, effects_off, overrides)


# ---------------------------------------------------------------------------- robot
def compliance_deflection(fk_world, q_rad: np.ndarray, p: MechanicsProfile) -> np.ndarray:
    """Joint deflections (rad) under the payload's weight at pose ``q_rad``: gravity's torque on
    joint i is ``−m g ∂z_com/∂q_i`` (world z up), and the joint yields by torque / stiffness.
    ``fk_world(q)`` gives ``T_world_from_flange``."""
    if p.payload_kg <= 0:
        return np.zeros(6)
    com = np.append(np.asarray(p.payload_com_in_flange_mm, float), 1.0)
    q = np.asarray(q_rad, float)
    z0 = (fk_world(q) @ com)[2]
    h = 1e-6
    dz = np.empty(6)
    for i in range(6):
        qi = q.copy()
        qi[i] += h
        dz[i] = ((fk_world(qi) @ com)[2] - z0) / h  # mm/rad
    torque_nm = -p.payload_kg * G * dz / 1000.0
    return torque_nm / np.asarray(p.joint_stiffness_nm_per_rad, float)


def ring_offset(t_since_move_s: float, direction: np.ndarray, p: MechanicsProfile) -> np.ndarray:
    """The flange's displacement (mm) ``t`` s after a move ended: a damped sinusoid of the arm's
    first mode, ``A e^(−ζωt) sin(ω_d t)`` along ``direction``."""
    if p.ring_amplitude_mm <= 0 or not 0 <= t_since_move_s < np.inf:
        return np.zeros(3)
    w = 2 * np.pi * p.ring_hz
    wd = w * np.sqrt(1 - p.ring_damping ** 2)
    a = p.ring_amplitude_mm * np.exp(-p.ring_damping * w * t_since_move_s)
    return direction * a * np.sin(wd * t_since_move_s + np.pi / 2)


def hold_offset(t_s: float, direction: np.ndarray, phase: float, p: MechanicsProfile,
                window_s: float = 0.0) -> np.ndarray:
    """The vibration the arm holds still with (mm), a sinusoid of RMS ``hold_vibration_rms_mm``;
    averaged over ``window_s`` from ``t_s`` (what a tracker averaging over a shot sees)."""
    if p.hold_vibration_rms_mm <= 0:
        return np.zeros(3)
    w = 2 * np.pi * p.hold_vibration_hz
    amp = np.sqrt(2.0) * p.hold_vibration_rms_mm
    if window_s <= 0:
        return direction * amp * np.sin(w * t_s + phase)
    mean = (np.cos(w * t_s + phase) - np.cos(w * (t_s + window_s) + phase)) / (w * window_s)
    return direction * amp * mean


def warmup(t_s: float, tau_s: float) -> float:
    """Share (0 … 1) of a first-order warm-up reached ``t_s`` after power-on."""
    return float(1.0 - np.exp(-max(t_s, 0.0) / tau_s))


def robot_growth(t_s: float, p: MechanicsProfile) -> float:
    """Relative growth of the arm's links (dimensionless) at sim time ``t_s``."""
    return p.robot_expansion_ppm_per_k * 1e-6 * p.robot_warmup_k * warmup(t_s,
                                                                            p.robot_warmup_tau_s)


# ---------------------------------------------------------------------------- scanner
def scanner_scales(t_s: float, p: MechanicsProfile) -> tuple[float, float]:
    """(baseline, focal length) relative to the cold scanner's, at sim time ``t_s``."""
    w = warmup(t_s, p.scanner_warmup_tau_s)
    return (1.0 + p.scanner_baseline_warmup_ppm * 1e-6 * w,
            1.0 + p.scanner_focal_warmup_ppm * 1e-6 * w)


# ---------------------------------------------------------------------------- tracker
def air_index(temperature_c: float, pressure_hpa: float, humidity_pct: float,
              wavelength_um: float = 0.633) -> float:
    """Refractive index of air (phase index) by the updated Edlén equation of Birch and Downs
    (Metrologia 30, 1993, and its 1994 correction), water vapour from the relative humidity
    by the Magnus formula."""
    s2 = 1.0 / wavelength_um ** 2
    ns = 1e-8 * (8342.54 + 2406147.0 / (130.0 - s2) + 15998.0 / (38.9 - s2))
    t = temperature_c
    p_pa = pressure_hpa * 100.0
    ntp = p_pa * ns / 96095.43 * (1 + 1e-8 * (0.601 - 0.00972 * t) * p_pa) / (1 + 0.003661 * t)
    f_pa = humidity_pct / 100.0 * 611.2 * np.exp(17.62 * t / (243.12 + t))
    return float(1.0 + ntp - f_pa * (3.7345 - 0.0401 * s2) * 1e-10)


def true_air(t_s: float, p: MechanicsProfile) -> tuple[float, float, float]:
    """The cell's true air (°C, hPa, % RH) at sim time ``t_s``."""
    return (p.air_temperature_c + p.air_temperature_rate_c_per_h * t_s / 3600.0,
            p.air_pressure_hpa, p.air_humidity_pct)


def stand_drift(t_s: float, direction: np.ndarray, tilt_axis: np.ndarray,
                p: MechanicsProfile) -> np.ndarray:
    """``T_world_from_tracker`` at sim time ``t_s``: the stand settles exponentially along
    ``direction``, grows upwards and tilts about ``tilt_axis`` (unit, horizontal)."""
    h = t_s / 3600.0
    shift = (direction * p.stand_settle_mm * warmup(t_s, p.stand_settle_tau_s)
             + np.array([0.0, 0.0, p.stand_thermal_mm_per_h * h]))
    angle = p.stand_tilt_urad_per_h * 1e-6 * h
    k = np.asarray(tilt_axis, float)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    T = np.eye(4)
    T[:3, :3] = np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    T[:3, 3] = shift
    return T


ARCSEC = np.pi / 180 / 3600


def tracker_systematics(p_tracker: np.ndarray, face: int, range_scale: float,
                        prof: MechanicsProfile) -> np.ndarray:
    """What the tracker reports for a true point ``p_tracker`` (its own frame, mm) in ``face``
    (1 front, 2 back): the range scaled (ADM scale and refraction) and offset; the azimuth and
    zenith angles moved by the encoder's harmonics, the vertical index and the beam offset. The
    odd terms change sign with the face, as a two-face test shows them (Muralikrishnan et al.,
    J. Res. NIST 114, 2009)."""
    x, y, z = (float(v) for v in p_tracker)
    r = float(np.linalg.norm(p_tracker))
    az = np.arctan2(y, x)
    zen = np.arccos(np.clip(z / r, -1, 1))
    sign = 1.0 if face == 1 else -1.0
    phi = np.radians(prof.encoder_eccentricity_phase_deg)
    r2 = r * (1 + prof.adm_scale_ppm * 1e-6) * range_scale + prof.adm_offset_mm
    beam = prof.beam_offset_mm / r
    az2 = (az + sign * prof.encoder_eccentricity_arcsec * ARCSEC * np.sin(az - phi)
           + prof.encoder_second_harmonic_arcsec * ARCSEC * np.sin(2 * (az - phi))
           + sign * beam / max(np.sin(zen), 1e-3))
    zen2 = zen + sign * (prof.vertical_index_arcsec * ARCSEC + beam)
    return r2 * np.array([np.sin(zen2) * np.cos(az2), np.sin(zen2) * np.sin(az2), np.cos(zen2)])
