"""``[metrology]`` of a cell config: the weather for the tracker's refraction correction,
settle detection before tracker points, and the reference nests of drift control
(docs/explanation/metrology.md). Lengths mm, times s, nests in ``world``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from scancell.protocols import tracker_line


@dataclass(frozen=True)
class ScannerCheck:
    """``[metrology.scanner_check]``: a calibrated ball bar fixed in the cell and the taught
    pose (joints, deg; rail, mm) from which the scanner sees it. The job scans it at its start
    and every ``every`` stations; the fuse worker reports its length (scale) and its spheres'
    form, and warns past ``warn_ppm`` or ``warn_form_mm``."""

    #: the taught robot pose from which the scanner sees the bar
    joints_deg: tuple[float, ...]
    #: the bar's calibrated centre distance (its certificate)
    length_mm: float
    #: the bar's spheres' calibrated diameter
    sphere_diameter_mm: float
    #: the rail position of the taught pose (None: the rail stays)
    axis_mm: float | None = None
    #: scan the bar at the job's start and every this many stations
    every: int = 4
    #: warn when the bar's measured length is off by more than this
    warn_ppm: float = 100.0
    #: warn when a sphere's form error exceeds this
    warn_form_mm: float = 0.05

    def to_json(self) -> dict[str, Any]:
        return {"length_mm": self.length_mm, "sphere_diameter_mm": self.sphere_diameter_mm,
                "warn_ppm": self.warn_ppm, "warn_form_mm": self.warn_form_mm}

    @classmethod
    def from_table(cls, t: dict[str, Any]) -> ScannerCheck:
        return cls(**{**t, "joints_deg": tuple(float(v) for v in t["joints_deg"])})


SCANNER_CHECK_KEYS = set(ScannerCheck.__dataclass_fields__)


def check_scanner_check(t: Any) -> str | None:
    """The first problem of a ``[metrology.scanner_check]`` table, or None."""
    where = "scanner_check"
    if not isinstance(t, dict):
        return f"{where}: must be a table"
    unknown = set(t) - SCANNER_CHECK_KEYS
    if unknown:
        return (f"{where}.{sorted(unknown)[0]}: unknown key (known: "
                f"{', '.join(sorted(SCANNER_CHECK_KEYS))})")
    for key in ("joints_deg", "length_mm", "sphere_diameter_mm"):
        if key not in t:
            return f"{where}.{key}: missing"
    q = t["joints_deg"]
    if not (isinstance(q, list) and len(q) == 6 and all(_number(v) for v in q)):
        return f"{where}.joints_deg: must be the 6 joint angles (deg) of the taught pose, got {q!r}"
    for key in ("length_mm", "sphere_diameter_mm", "warn_ppm", "warn_form_mm"):
        v = t.get(key, 1.0)
        if not (_number(v) and v > 0):
            return f"{where}.{key}: must be a positive number, got {v!r}"
    if "axis_mm" in t and not _number(t["axis_mm"]):
        return f"{where}.axis_mm: must be a number (rail position, mm), got {t['axis_mm']!r}"
    every = t.get("every", 1)
    if not (isinstance(every, int) and not isinstance(every, bool) and every >= 1):
        return f"{where}.every: must be an integer >= 1, got {every!r}"
    return None


def _number(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


@dataclass(frozen=True)
class MetrologySettings:
    """``[metrology]``, defaults filled in (lengths mm, times s)."""

    #: "tracker": the tracker's own weather station; "config": the values below; None: the
    #: cell states no weather (every job warns that the tracker corrects for its own setting)
    weather: str | None = None
    #: weather = "config": the air temperature the tracker corrects refraction for
    air_temperature_c: float | None = None
    #: weather = "config": the air pressure
    air_pressure_hpa: float | None = None
    #: weather = "config": the relative humidity
    humidity_pct: float | None = None
    #: wait before each tracker point until the arm has settled (False: measure at once, as a
    #: cell without the defence would; for ablation studies)
    settle: bool = True
    #: settled when ``settle_window`` consecutive readings lie within this of their mean (on
    #: top of twice the tracker's stated noise)
    settle_tolerance_mm: float = 0.010
    #: how many consecutive tracker readings must agree
    settle_window: int = 4
    #: the longest a tracker point waits for the arm to settle (then not_settled)
    settle_timeout_s: float = 15.0
    #: reference nests (world, mm) by name, surveyed when the cell was commissioned
    nests: dict[str, tuple[float, float, float]] = field(default_factory=dict)
    #: the scan job measures the nests at its start, every this many stations and its end
    nest_check_every: int = 4
    #: tracker shots averaged per nest
    nest_repeats: int = 3
    #: re-locate the tracker when a nest moved more than this since the last location
    drift_tolerance_mm: float = 0.010
    #: the nests disagree (one knocked, or the tracker moved more than rigidly) beyond this
    nest_fit_tolerance_mm: float = 0.05
    #: the fewest nests that may locate the tracker
    min_nests: int = 3
    # ---- the stated 1-sigmas of the Monte Carlo uncertainty (docs/explanation/metrology.md)
    #: the weather's uncertainty (°C, hPa, % RH): a tracker weather station's stated accuracy
    weather_uncertainty: tuple[float, float, float] = (0.3, 1.0, 5.0)
    #: the scanner's scale stability (ppm): its warm-up and thermal drift
    scanner_scale_ppm: float = 20.0
    #: the scanner's noise model's own relative accuracy (1-sigma): on the simulator with the
    #: true calibration its median |error| / sigma is within 5 % of a Gaussian's, and the
    #: realistic demo's overlaps see 0.83 of it (benchmarks/RESULTS.md)
    scanner_noise_rel: float = 0.15
    #: the tracker's location when no nests check it (mm): its stand's stability
    unchecked_location_mm: float = 0.03
    #: the scanner check on a ball bar fixed in the cell (None: no check)
    scanner_check: ScannerCheck | None = None

    def refraction_ppm(self, weather_applied: bool) -> float:
        """The range scale's 1-sigma (ppm) from the weather's uncertainty (−0.93 ppm/°C,
        +0.27 ppm/hPa, −0.0085 ppm/% RH); 10 ppm when the tracker was told no weather."""
        if not weather_applied:
            return 10.0
        t, p, h = self.weather_uncertainty
        return float((0.93 * t) ** 2 + (0.27 * p) ** 2 + (0.0085 * h) ** 2) ** 0.5

    @classmethod
    def from_table(cls, t: dict[str, Any]) -> MetrologySettings:
        nests = {str(k): tuple(float(v) for v in p) for k, p in t.get("nests", {}).items()}
        values = {k: v for k, v in t.items() if k not in ("nests", "scanner_check")}
        if "scanner_check" in t:
            values["scanner_check"] = ScannerCheck.from_table(t["scanner_check"])
        if "weather_uncertainty" in values:
            values["weather_uncertainty"] = tuple(float(v) for v in values["weather_uncertainty"])
        return cls(**{**values, "nests": nests})


METROLOGY_KEYS = {f for f in MetrologySettings.__dataclass_fields__}


def check_table(t: dict[str, Any]) -> str | None:
    """The first problem of a ``[metrology]`` table as ``"key: problem"``, or None."""
    unknown = set(t) - METROLOGY_KEYS
    if unknown:
        return f"{sorted(unknown)[0]}: unknown key (known: {', '.join(sorted(METROLOGY_KEYS))})"
    weather = t.get("weather")
    if weather not in (None, "tracker", "config"):
        return f"weather: must be \"tracker\" or \"config\", got {weather!r}"
    if weather == "config":
        values = [t.get(k) for k in ("air_temperature_c", "air_pressure_hpa", "humidity_pct")]
        missing = [k for k, v in zip(("air_temperature_c", "air_pressure_hpa", "humidity_pct"),
                                     values, strict=True) if v is None]
        if missing:
            return f"{missing[0]}: missing (weather = \"config\" needs all three values)"
        problem = tracker_line.environment_problem(*(float(v) for v in values))
        if problem:
            return f"weather: {problem}"
    if not isinstance(t.get("settle", True), bool):
        return f"settle: must be true or false, got {t['settle']!r}"
    for key in ("settle_tolerance_mm", "settle_timeout_s", "drift_tolerance_mm",
                "nest_fit_tolerance_mm", "scanner_scale_ppm", "scanner_noise_rel",
                "unchecked_location_mm"):
        v = t.get(key, 1.0)
        if not (isinstance(v, int | float) and not isinstance(v, bool) and v > 0):
            return f"{key}: must be a positive number, got {v!r}"
    for key, lo in (("settle_window", 2), ("nest_check_every", 1), ("nest_repeats", 1),
                    ("min_nests", 3)):
        v = t.get(key, lo)
        if not (isinstance(v, int) and not isinstance(v, bool) and v >= lo):
            return f"{key}: must be an integer >= {lo}, got {v!r}"
    wu = t.get("weather_uncertainty", [1, 1, 1])
    if not (isinstance(wu, list | tuple) and len(wu) == 3
            and all(isinstance(v, int | float) and v >= 0 for v in wu)):
        return f"weather_uncertainty: must be 3 non-negative numbers (°C, hPa, %), got {wu!r}"
    nests = t.get("nests", {})
    if not isinstance(nests, dict) or not all(
            isinstance(p, list) and len(p) == 3 and all(isinstance(v, int | float) for v in p)
            for p in nests.values()):
        return "nests: must map each nest's name to its x, y, z (world, mm)"
    if nests and len(nests) < max(4, int(t.get("min_nests", 3))):
        return f"nests: drift control needs at least 4 nests, got {len(nests)}"
    if "scanner_check" in t:
        return check_scanner_check(t["scanner_check"])
    return None


