"""What a structured-light projector showed, as data: a pattern set.

A pattern set is a list of *groups*, each a run of consecutive frames of one kind on one
projector axis:

- ``phase_shift``: N frames ``I_n(x) = A + B·cos(2π·p·x/W − s·2π·n/N)``, n = 0 … N−1, with x
  the projector coordinate along ``axis`` (pixel centres 0 … W−1), W the projector's size along
  it, p the periods across W (or ``period_px`` = W/p), s the ``sign`` (+1: the phase steps
  forward, as ``model/patterns.py`` and SLStudio; −1: backward);
- ``gray_code``: ``bits`` frames, most significant bit first; frame b is bright where bit
  (bits−1−b) of the Gray code of the stripe index ``floor(x / stripe_px)`` is set (inverted when
  ``sign`` is −1). With ``inverse = true`` every bit frame is followed by its complement, and bits
  are decided by comparing the pair instead of against the phase-shift background;
- ``complementary_gray_code``: a Gray code with one more bit whose stripes are half a phase
  period (Zhang et al., "3-D shape measurement based on complementary Gray-code light", Opt.
  Lasers Eng. 50, 2012): its finest stripes, offset by half a period against the fringes, keep
  the fringe order right at the wraps, where a plain Gray code's edge and the phase's wrap meet.

``axis`` is ``"x"`` (the pattern varies along projector columns: vertical fringes, it encodes
the column) or ``"y"`` (rows). Groups follow each other in the frame sequence unless ``first``
places one (frame index, 0-based). Frames of the sequence that no group claims are ignored.

How each axis is unwrapped (``unwrap``): ``heterodyne`` (beats of neighbouring periods down to
one, the seed paper's), ``hierarchical`` (coarse to fine from a group of ≤ 1 period) or
``gray`` (a Gray code numbers the fringes of the finest phase group). Left out, it follows from
the groups: a Gray code → ``gray``; a group of ≤ 1 period → ``hierarchical``; else
``heterodyne``.

The spec, in TOML or JSON (``from_dict``)::

    name = "slstudio-2x3"
    frames = "frameSeq_*.png"       # optional glob or list; default: the folder's images by name
    [[groups]]
    kind = "phase_shift"
    axis = "x"
    periods = 16
    steps = 3
    [[groups]]
    kind = "phase_shift"
    axis = "x"
    periods = 1
    steps = 3
    [limits]                         # optional overrides of the decoder's derived limits
    min_modulation_dn = 6

Pure data and arithmetic: no I/O (``scancell.analysis.pattern_files`` reads spec files).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

AXES = ("x", "y")
KINDS = ("phase_shift", "gray_code", "complementary_gray_code")
UNWRAP_METHODS = ("heterodyne", "hierarchical", "gray")
#: the decoder limits a spec may set (analysis.decode_limits.DecodeLimits)
LIMIT_KEYS = ("min_modulation_dn", "order_margin", "bend_limit_px", "step_limit_px",
              "border_px", "z_min_mm", "z_max_mm", "noise_dn", "confidence_sigmas",
              "saturation_dn", "smooth_px")


class PatternSpecError(ValueError):
    """A pattern set spec that is inconsistent or incomplete; the message names the field."""


@dataclass(frozen=True)
class PhaseShiftGroup:
    axis: str
    steps: int
    periods: float | None = None  # periods across the axis; or period_px
    period_px: float | None = None
    sign: int = 1
    first: int | None = None
    A: float = 0.5
    B: float = 0.5
    kind: str = "phase_shift"

    @property
    def frame_count(self) -> int:
        return self.steps

    def periods_across(self, size: int) -> float:
        """Periods across a projector axis of ``size`` px."""
        return float(self.periods) if self.periods is not None else size / float(self.period_px)

    def profile(self, n: int, x: np.ndarray, size: int) -> np.ndarray:
        """Relative intensity (0 … 1) of step n at projector coordinates x (px)."""
        p = self.periods_across(size)
        return self.A + self.B * np.cos(2 * np.pi * p * np.asarray(x, float) / size
                                        - self.sign * 2 * np.pi * n / self.steps)


@dataclass(frozen=True)
class GrayCodeGroup:
    axis: str
    bits: int
    stripe_px: float | None = None  # finest stripe (px); default: the axis size / 2^bits
    inverse: bool = False  # every bit frame followed by its complement
    sign: int = 1
    first: int | None = None
    kind: str = "gray_code"

    @property
    def frame_count(self) -> int:
        return self.bits * (2 if self.inverse else 1)

    def stripe(self, size: int) -> float:
        return float(self.stripe_px) if self.stripe_px is not None else size / 2 ** self.bits

    def covers(self, size: int) -> bool:
        return 2 ** self.bits * self.stripe(size) >= size - 1e-6

    def bit_frame(self, b: int, x: np.ndarray, size: int) -> np.ndarray:
        """0/1 of bit frame b (0 = most significant) at projector coordinates x (px)."""
        index = np.floor(np.asarray(x, float) / self.stripe(size)).astype(np.int64)
        gray = index ^ (index >> 1)
        bit = (gray >> (self.bits - 1 - b)) & 1
        return bit if self.sign > 0 else 1 - bit

    def profile(self, k: int, x: np.ndarray, size: int) -> np.ndarray:
        """Relative intensity (0 or 1) of the group's frame k."""
        b, inverted = (divmod(k, 2) if self.inverse else (k, 0))
        bit = self.bit_frame(b, x, size).astype(float)
        return 1.0 - bit if inverted else bit


Group = PhaseShiftGroup | GrayCodeGroup


@dataclass(frozen=True)
class PatternSet:
    """An ordered pattern set; see the module doc. ``width``/``height``: the projector (px) if
    the spec states it (the rig file states it otherwise)."""

    groups: tuple[Group, ...]
    name: str = ""
    unwrap: dict[str, str] = field(default_factory=dict)
    frames: tuple[str, ...] | str | None = None  # a glob, a list of names, or None
    limits: dict[str, float] = field(default_factory=dict)
    width: int | None = None
    height: int | None = None
    #: where the spec came from (its file, or "preset NAME"), for messages
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if not self.groups:
            raise PatternSpecError("a pattern set needs at least one group")
        placed = self.placement()
        used: dict[int, int] = {}
        for gi, (start, g) in enumerate(zip(placed, self.groups, strict=True)):
            for k in range(start, start + g.frame_count):
                if k in used:
                    raise PatternSpecError(f"groups[{gi}] and groups[{used[k]}] both claim frame {k}")
                used[k] = gi
        for axis in self.axes:
            method = self.method(axis)
            if method not in UNWRAP_METHODS:
                raise PatternSpecError(f"unwrap.{axis} = {method!r}: one of {', '.join(UNWRAP_METHODS)}")
            phases = self.phase_groups(axis)
            if not phases:
                raise PatternSpecError(f"axis {axis}: a Gray code alone gives whole stripes; add a "
                                       f"phase_shift group on that axis")
            grays = self.gray_groups(axis)
            if method == "gray" and len(grays) != 1:
                raise PatternSpecError(f"axis {axis}: unwrap 'gray' needs exactly one Gray-code "
                                       f"group, found {len(grays)}")
            if method != "gray" and len(phases) < 2 and not grays:
                p = phases[0].periods
                if p is None or p > 1 + 1e-9:
                    raise PatternSpecError(
                        f"axis {axis}: one phase_shift group of {p or 'period_px'} periods cannot be "
                        f"unwrapped; add a coarser group or a Gray code")
        bad = sorted(set(self.limits) - set(LIMIT_KEYS))
        if bad:
            raise PatternSpecError(f"limits: unknown key(s) {bad}; known: {', '.join(LIMIT_KEYS)}")

    # -- structure ---------------------------------------------------------------------------
    def placement(self) -> list[int]:
        """First frame index of every group."""
        out, nxt = [], 0
        for g in self.groups:
            start = nxt if g.first is None else int(g.first)
            out.append(start)
            nxt = start + g.frame_count
        return out

    def __len__(self) -> int:
        """Frames the sequence needs (the last frame any group claims, plus one)."""
        return max(s + g.frame_count for s, g in zip(self.placement(), self.groups, strict=True))

    @property
    def axes(self) -> tuple[str, ...]:
        return tuple(a for a in AXES if any(g.axis == a for g in self.groups))

    def phase_groups(self, axis: str) -> list[PhaseShiftGroup]:
        return [g for g in self.groups if g.axis == axis and isinstance(g, PhaseShiftGroup)]

    def gray_groups(self, axis: str) -> list[GrayCodeGroup]:
        return [g for g in self.groups if g.axis == axis and isinstance(g, GrayCodeGroup)]

    def frames_of(self, group: Group) -> range:
        i = self.groups.index(group)
        start = self.placement()[i]
        return range(start, start + group.frame_count)

    def method(self, axis: str) -> str:
        if axis in self.unwrap:
            return self.unwrap[axis]
        if self.gray_groups(axis):
            return "gray"
        phases = self.phase_groups(axis)
        if any(g.periods is not None and g.periods <= 1 + 1e-9 for g in phases):
            return "hierarchical"
        return "heterodyne"

    def check_projector(self, width: int, height: int, where: str = "pattern set") -> None:
        """PatternSpecError unless every Gray code covers its axis of a ``width`` x ``height``
        projector."""
        for i, g in enumerate(self.groups):
            size = width if g.axis == "x" else height
            if isinstance(g, GrayCodeGroup) and not g.covers(size):
                raise PatternSpecError(
                    f"{where}: groups[{i}] ({g.kind}, {g.bits} bits of {g.stripe(size):g} px "
                    f"stripes) numbers {2 ** g.bits * g.stripe(size):g} px, short of the projector's "
                    f"{size} px along {g.axis}: it needs {int(np.ceil(np.log2(size / g.stripe(size))))} "
                    f"bits")

    def shows_the_same(self, other: PatternSet) -> bool:
        """Whether both project the same frames (names, unwrapping and limits aside)."""
        return self.groups == other.groups and self.placement() == other.placement()

    # -- rendering ---------------------------------------------------------------------------
    def frame_profile(self, k: int, size_x: int, size_y: int) -> tuple[str, np.ndarray] | None:
        """(axis, relative intensity along that axis, float 0 … 1) of frame k; None for a frame
        no group claims."""
        for start, g in zip(self.placement(), self.groups, strict=True):
            if start <= k < start + g.frame_count:
                size = size_x if g.axis == "x" else size_y
                return g.axis, g.profile(k - start, np.arange(size, dtype=float), size)
        return None

    def image(self, k: int, width: int, height: int) -> np.ndarray:
        """Frame k as an 8-bit projector image (height x width); black where no group claims
        it."""
        prof = self.frame_profile(k, width, height)
        if prof is None:
            return np.zeros((height, width), np.uint8)
        axis, values = prof
        line = np.round(np.clip(values, 0, 1) * 255).astype(np.uint8)
        return (np.tile(line, (height, 1)) if axis == "x"
                else np.tile(line[:, None], (1, width)))

    # -- conversion --------------------------------------------------------------------------
    def fringe_sequence(self):
        """The equivalent :class:`~scancell.model.patterns.FringeSequence` (x only, phase shift
        only, one step count, consecutive from frame 0, periods given, sign +1), or None."""
        from scancell.model.patterns import FringeSequence

        if self.axes != ("x",) or any(not isinstance(g, PhaseShiftGroup) for g in self.groups):
            return None
        steps = {g.steps for g in self.groups}
        if (len(steps) != 1 or any(g.periods is None or g.sign != 1 for g in self.groups)
                or self.placement() != [i * g.steps for i, g in enumerate(self.groups)]):
            return None
        g0 = self.groups[0]
        return FringeSequence(tuple(float(g.periods) for g in self.groups), steps.pop(), g0.A, g0.B)

    @classmethod
    def from_fringe_sequence(cls, seq, method: str = "heterodyne", name: str = "") -> PatternSet:
        return cls(tuple(PhaseShiftGroup("x", seq.steps, float(p), A=seq.A, B=seq.B)
                         for p in seq.periods), name=name, unwrap={"x": method})

    @classmethod
    def from_dict(cls, spec: dict[str, Any], where: str = "pattern set") -> PatternSet:
        """Build from a parsed TOML/JSON spec; PatternSpecError naming ``where`` and the field."""
        if not isinstance(spec, dict):
            raise PatternSpecError(f"{where}: expected a table, got {type(spec).__name__}")
        known = {"name", "groups", "unwrap", "frames", "limits", "projector", "description"}
        extra = sorted(set(spec) - known)
        if extra:
            raise PatternSpecError(f"{where}: unknown key(s) {extra}; known: {sorted(known)}")
        raw = spec.get("groups")
        if not isinstance(raw, list) or not raw:
            raise PatternSpecError(f"{where}: 'groups' must be a non-empty list of tables")
        groups = tuple(_group(g, f"{where}: groups[{i}]") for i, g in enumerate(raw))
        unwrap = spec.get("unwrap", {})
        if isinstance(unwrap, str):
            unwrap = {a: unwrap for a in AXES}
        if not isinstance(unwrap, dict) or set(unwrap) - set(AXES):
            raise PatternSpecError(f"{where}: 'unwrap' is a method name or a table of x/y methods")
        frames = spec.get("frames")
        if frames is not None and not (isinstance(frames, str) or (
                isinstance(frames, list) and all(isinstance(f, str) for f in frames))):
            raise PatternSpecError(f"{where}: 'frames' is a glob or a list of file names")
        limits = spec.get("limits", {})
        if not isinstance(limits, dict) or not all(isinstance(v, int | float) for v in limits.values()):
            raise PatternSpecError(f"{where}: 'limits' is a table of numbers")
        proj = spec.get("projector", {})
        try:
            return cls(groups, str(spec.get("name", "")),
                       {a: unwrap[a] for a in AXES if a in unwrap and any(g.axis == a for g in groups)},
                       frames if frames is None or isinstance(frames, str) else tuple(frames),
                       {k: float(v) for k, v in limits.items()},
                       int(proj["width"]) if "width" in proj else None,
                       int(proj["height"]) if "height" in proj else None, where)
        except PatternSpecError as exc:
            raise PatternSpecError(f"{where}: {exc}") from None

    def to_dict(self) -> dict[str, Any]:
        """The spec as a TOML/JSON-ready table (``from_dict`` reads it back)."""
        out: dict[str, Any] = {"name": self.name, "groups": []}
        for g in self.groups:
            d: dict[str, Any] = {"kind": g.kind, "axis": g.axis}
            if isinstance(g, PhaseShiftGroup):
                d["steps"] = g.steps
                d.update({"periods": g.periods} if g.periods is not None else {"period_px": g.period_px})
            else:
                d["bits"] = g.bits
                if g.stripe_px is not None:
                    d["stripe_px"] = g.stripe_px
                if g.inverse:
                    d["inverse"] = True
            if g.sign != 1:
                d["sign"] = g.sign
            if g.first is not None:
                d["first"] = g.first
            out["groups"].append(d)
        if self.unwrap:
            out["unwrap"] = dict(self.unwrap)
        if self.frames is not None:
            out["frames"] = self.frames if isinstance(self.frames, str) else list(self.frames)
        if self.limits:
            out["limits"] = dict(self.limits)
        if self.width or self.height:
            out["projector"] = {k: v for k, v in (("width", self.width), ("height", self.height)) if v}
        return out


def _number(d: dict, key: str, where: str, kind=float, positive: bool = True):
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or (kind is int and v != int(v)):
        what = "an integer" if kind is int else "a number"
        raise PatternSpecError(f"{where}.{key} = {v!r}: expected {what}")
    if positive and v <= 0:
        raise PatternSpecError(f"{where}.{key} = {v!r}: must be positive")
    return kind(v)


#: the keys each kind of group takes besides kind, axis, sign and first
_GROUP_KEYS = {"phase_shift": ("steps", "periods", "period_px"),
               "gray_code": ("bits", "stripe_px", "inverse"),
               "complementary_gray_code": ("bits", "stripe_px", "inverse")}


def _group(d: Any, where: str) -> Group:
    if not isinstance(d, dict):
        raise PatternSpecError(f"{where}: expected a table")
    kind = d.get("kind")
    if kind not in KINDS:
        raise PatternSpecError(f"{where}.kind = {kind!r}: one of {', '.join(KINDS)}")
    axis = d.get("axis", "x")
    if axis not in AXES:
        raise PatternSpecError(f"{where}.axis = {axis!r}: 'x' (columns) or 'y' (rows)")
    sign = d.get("sign", 1)
    if sign not in (1, -1):
        raise PatternSpecError(f"{where}.sign = {sign!r}: 1 or -1")
    first = _number(d, "first", where, int, positive=False) if "first" in d else None
    if first is not None and first < 0:
        raise PatternSpecError(f"{where}.first = {first}: a frame index, 0 or more")
    extra = sorted(set(d) - {"kind", "axis", "sign", "first", *_GROUP_KEYS[kind]})
    if extra:
        raise PatternSpecError(f"{where}: unknown key(s) {extra} for a {kind} group")
    need = "steps" if kind == "phase_shift" else "bits"
    if need not in d:
        raise PatternSpecError(f"{where}: a {kind} group needs {need!r}")
    if kind == "phase_shift":
        steps = _number(d, "steps", where, int)
        if steps < 3:
            raise PatternSpecError(f"{where}.steps = {steps}: phase shifting needs at least 3 steps")
        if ("periods" in d) == ("period_px" in d):
            raise PatternSpecError(f"{where}: give exactly one of 'periods' (across the projector) "
                                   f"and 'period_px'")
        periods = _number(d, "periods", where) if "periods" in d else None
        period_px = _number(d, "period_px", where) if "period_px" in d else None
        return PhaseShiftGroup(axis, steps, periods, period_px, sign, first)
    bits = _number(d, "bits", where, int)
    if bits > 16:
        raise PatternSpecError(f"{where}.bits = {bits}: at most 16")
    stripe = _number(d, "stripe_px", where) if "stripe_px" in d else None
    inverse = d.get("inverse", False)
    if not isinstance(inverse, bool):
        raise PatternSpecError(f"{where}.inverse = {inverse!r}: true or false")
    return GrayCodeGroup(axis, bits, stripe, inverse, sign, first, kind)


# -- presets -----------------------------------------------------------------------------------
PRESETS: dict[str, dict[str, Any]] = {
    # the seed paper's 3 frequencies x 3 steps, the scanner's default (model/patterns.py)
    "heterodyne-3x3": {"name": "heterodyne-3x3", "unwrap": "heterodyne", "groups": [
        {"kind": "phase_shift", "axis": "x", "periods": p, "steps": 3} for p in (70, 64, 59)]},
    # SLStudio's CodecPhaseShift2x3: 3 steps of 16 periods, then 3 steps of the 1-period cue
    "slstudio-2x3": {"name": "slstudio-2x3", "unwrap": "hierarchical", "groups": [
        {"kind": "phase_shift", "axis": "x", "periods": 16, "steps": 3},
        {"kind": "phase_shift", "axis": "x", "periods": 1, "steps": 3}]},
    # SLStudio's CodecPhaseShift2x3 in both directions (CodecDirBoth): its 12-frame sequences,
    # columns as above, then rows (16 periods across the rows, then the cue)
    "slstudio-2x3-xy": {"name": "slstudio-2x3-xy", "unwrap": "hierarchical", "groups": [
        {"kind": "phase_shift", "axis": "x", "periods": 16, "steps": 3},
        {"kind": "phase_shift", "axis": "x", "periods": 1, "steps": 3},
        {"kind": "phase_shift", "axis": "y", "periods": 16, "steps": 3},
        {"kind": "phase_shift", "axis": "y", "periods": 1, "steps": 3}]},
    # Gray code + 4-step phase shift: 32 fringes numbered by a 6-bit complementary Gray code
    # (64 stripes of half a fringe), columns only
    "gray-phase": {"name": "gray-phase", "unwrap": "gray", "groups": [
        {"kind": "phase_shift", "axis": "x", "periods": 32, "steps": 4},
        {"kind": "complementary_gray_code", "axis": "x", "bits": 6}]},
    # the same on both projector axes (columns, then rows): what a camera-projector rig's
    # calibration needs, and a scan whose points come from the projector's ray
    "gray-phase-xy": {"name": "gray-phase-xy", "unwrap": "gray", "groups": [
        {"kind": "phase_shift", "axis": "x", "periods": 32, "steps": 4},
        {"kind": "complementary_gray_code", "axis": "x", "bits": 6},
        {"kind": "phase_shift", "axis": "y", "periods": 20, "steps": 4},
        {"kind": "complementary_gray_code", "axis": "y", "bits": 6}]},
}
DEFAULT_PRESET = "heterodyne-3x3"


def presets_of_length(frames: int) -> list[str]:
    """The presets that take ``frames`` frames (for a message on a count that does not fit)."""
    return [name for name in PRESETS if len(preset(name)) == frames]


def preset(name: str) -> PatternSet:
    if name not in PRESETS:
        raise PatternSpecError(f"no preset {name!r}; presets: {', '.join(PRESETS)}")
    return PatternSet.from_dict(PRESETS[name], f"preset {name}")


def sequence_pattern_set(spec: dict[str, Any]) -> PatternSet:
    """The pattern set a projector sequence spec (the ``load_sequence`` command, a DLPC350 flash
    entry) describes: kind ``"fringe"`` (``periods``, ``steps``: the scanner's phase-shift
    fringes) or kind ``"patterns"`` (``patterns``: a preset name or a pattern-set table).
    PatternSpecError otherwise."""
    kind = spec.get("kind", "fringe")
    if kind == "patterns":
        value = spec.get("patterns")
        if isinstance(value, str):
            return preset(value)
        if isinstance(value, dict):
            return PatternSet.from_dict(value, "patterns")
        raise PatternSpecError("kind 'patterns' needs 'patterns': a preset name or a pattern-set table")
    if kind != "fringe":
        raise PatternSpecError(f"sequence kind {kind!r}: 'fringe', 'patterns' or 'levels'")
    from scancell.model.patterns import FringeSequence

    try:
        return PatternSet.from_fringe_sequence(FringeSequence.from_spec(spec))
    except ValueError as exc:
        raise PatternSpecError(str(exc)) from None
