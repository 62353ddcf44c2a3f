"""The simulated scanner's optics: projector response and defocus, camera sensor (EMVA 1288) and
depth of field, surface paints with a specular lobe, ambient light; the named profiles.

Every parameter's value and source is listed in docs/explanation/simulation.md. A profile is a set of
values; each effect can be switched off on its own (:func:`optics_profile`), which puts back the
``ideal`` profile's values of that effect's fields (the ablation in benchmarks/RESULTS.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scancell.sim.profiles import ProfileError as ProfileError  # re-exported
from scancell.sim.profiles import select_profile


@dataclass(frozen=True)
class Paint:
    """Blinn–Phong reflectance: radiance factor ``kd + ks · (s + 8)/8 · cos^s(n·h)`` (the
    energy-normalised lobe; kd is the diffuse albedo, ks the specular reflectance)."""

    kd: float
    ks: float = 0.0
    shininess: float = 1.0


@dataclass(frozen=True)
class OpticsProfile:
    """All optical parameters of the simulated scanner and part (see docs/explanation/simulation.md)."""

    name: str = "ideal"
    # ---- projector
    #: light output = black + (1 - black) · v^gamma for the 8-bit pattern value v in [0, 1]
    projector_gamma: float = 1.0
    #: full-white to full-black light ratio (inf: perfectly black)
    projector_contrast: float = float("inf")
    #: projector lens: aperture (f-number) and focus distance (mm); f_number inf: no defocus
    projector_f_number: float = float("inf")
    projector_focus_mm: float = 650.0
    #: DMD micromirror pitch (mm), which with the focal length in pixels gives the lens's
    projector_pitch_mm: float = 0.0076
    # ---- cameras
    #: "read": constant read noise ``read_noise_dn`` (ideal); "emva": EMVA 1288 linear model
    sensor_model: str = "read"
    read_noise_dn: float = 1.0
    quantum_efficiency: float = 0.65
    full_well_e: float = 10700.0
    dark_noise_e: float = 2.95
    dark_current_e_per_s: float = 5.0
    #: camera lens: aperture and focus distance; f_number inf: no depth-of-field blur
    camera_f_number: float = float("inf")
    camera_focus_mm: float = 650.0
    camera_pitch_mm: float = 0.00345
    #: in-focus blur (diffraction and lens MTF), 1 sigma (px at full resolution)
    psf_sigma_px: float = 0.6
    # ---- surfaces
    #: paints of the part's regions; "uniform": every region the same matte paint
    paints: str = "uniform"
    uniform_paint: Paint = Paint(0.6)
    body_paint: Paint = Paint(0.6)
    bumper_paint: Paint = Paint(0.6)
    plate_paint: Paint = Paint(0.6)
    #: ambient irradiance relative to the projector's full white at the working distance
    ambient: float = 0.08
    #: DN of a white (kd = 1) diffuse surface under full white at the nominal exposure, 8-bit
    exposure: float = 1.3

    @cached_property
    def projector_black(self) -> float:
        return 0.0 if not np.isfinite(self.projector_contrast) else 1.0 / self.projector_contrast

    def projector_light(self, v: np.ndarray) -> np.ndarray:
        """Relative light output (0 … 1) for pattern values v in [0, 1] (already 8-bit)."""
        b = self.projector_black
        return b + (1.0 - b) * np.clip(v, 0.0, 1.0) ** self.projector_gamma

    def paint_table(self) -> list[Paint]:
        """Paints by region index: 0 default/uniform, 1 body, 2 bumper, 3 licence plate."""
        if self.paints == "uniform":
            return [self.uniform_paint] * 4
        return [self.uniform_paint, self.body_paint, self.bumper_paint, self.plate_paint]


#: which fields each switchable effect owns
EFFECTS: dict[str, tuple[str, ...]] = {
    "projector_response": ("projector_gamma", "projector_contrast"),
    "projector_defocus": ("projector_f_number", "projector_focus_mm"),
    "sensor_noise": ("sensor_model", "read_noise_dn"),
    "depth_of_field": ("camera_f_number", "camera_focus_mm"),
    "paints": ("paints",),
    "ambient": ("ambient",),
}

IDEAL = OpticsProfile()

REALISTIC = OpticsProfile(
    name="realistic",
    projector_gamma=2.2,
    projector_contrast=1000.0,
    projector_f_number=2.0,
    projector_focus_mm=650.0,
    sensor_model="emva",
    camera_f_number=8.0,
    camera_focus_mm=650.0,
    psf_sigma_px=0.55,
    paints="regions",
    body_paint=Paint(0.08, 0.04, 300.0),
    bumper_paint=Paint(0.55, 0.04, 60.0),
    plate_paint=Paint(0.85, 0.0, 1.0),
    ambient=0.25,
    exposure=1.3,
)

PROFILES: dict[str, OpticsProfile] = {"ideal": IDEAL, "realistic": REALISTIC}
#: the simulated cell's profile when its config names none
DEFAULT_PROFILE = "realistic"


def optics_profile(name: str = DEFAULT_PROFILE, effects_off: tuple[str, ...] | list[str] = (),
                   **overrides: object) -> OpticsProfile:
    """The named profile with the given effects switched off (their ideal values) and single
    fields overridden; ProfileError names an unknown profile, effect or field."""
    return select_profile("optics", PROFILES, EFFECTS, name, effects_off, overrides)


def defocus_px_per_unit(focal_px: float, pitch_mm: float, f_number: float,
                        focus_mm: float) -> float:
    """k of the defocus blur ``sigma = k · |d − s| / d`` (px of the device, 1 sigma) of a point
    at distance d from a thin lens of focal length f = ``focal_px · pitch_mm`` at f-number N,
    focused at s = ``focus_mm``: the blur circle on the sensor has the diameter
    ``f² / (N (s − f)) · |d − s| / d`` (mm), and a uniform disc of diameter c has sigma c/4.
    0 for a pinhole (N infinite)."""
    if not np.isfinite(f_number):
        return 0.0
    f = focal_px * pitch_mm
    return f * f / (f_number * (focus_mm - f)) / pitch_mm / 4.0


def response_harmonics(profile: OpticsProfile, A: float, B: float,
                       precompensation: np.ndarray | None = None, harmonics: int = 12
                       ) -> np.ndarray:
    """Fourier cosine coefficients c_0 … c_harmonics of the light along one fringe,
    ``light(θ) = Σ c_k cos(kθ)``, for the pattern value ``A + B cos θ`` quantised to 8 bits,
    optionally pre-compensated by a 256-entry look-up table (value sent for each value wanted),
    then through the projector's response."""
    theta = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
    level = np.clip(np.rint((A + B * np.cos(theta)) * 255), 0, 255).astype(np.int64)
    if precompensation is not None:
        level = np.asarray(precompensation, np.int64)[level]
    light = profile.projector_light(level / 255.0)
    spectrum = np.fft.rfft(light) / len(theta)
    c = 2 * spectrum.real[: harmonics + 1]
    c[0] /= 2
    return c.astype(np.float64)


def level_light(profile: OpticsProfile, level: float) -> float:
    """Light output of a uniform pattern of value ``level`` in [0, 1], sent as 8 bits."""
    v = int(np.clip(np.rint(level * 255), 0, 255))
    return float(profile.projector_light(np.array(v / 255.0)))
