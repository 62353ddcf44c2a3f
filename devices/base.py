"""The device-plugin contract: one abstract base per kind (Robot, Tracker, Camera, Projector, Axis).

A driver subclasses a kind, implements the abstract coroutines and raises only the typed errors
of :mod:`scancell.devices.errors`. Public typed methods check limits and then call the driver's
underscore method, so no caller (command, job or script) can bypass a configured limit.

Methods decorated with :func:`operation` become daemon commands ``cmd/device/<name>/<op>``,
validated against the JSON Schema ``scancell.cmd.<schema>``.
"""

from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, ClassVar

import numpy as np
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.commands import CommandError
from scancell.protocols.encoding import Attachment, Encoded

Emit = Callable[[str, Encoded, Attachment], None]
OpHandler = Callable[[dict[str, Any]], Awaitable[dict[str, Any]]]


class HealthState(enum.StrEnum):
    OK = "ok"
    DEGRADED = "degraded"
    FAULT = "fault"


@dataclass(frozen=True)
class Health:
    """What a device says about itself. ``reason`` is a short machine-readable code."""

    state: HealthState
    reason: str = "ok"
    message: str = ""


OK = Health(HealthState.OK)


@dataclass(frozen=True)
class OperationSpec:
    name: str
    schema: str
    timeout_s: float
    #: Exclusive operations wait for the device link; others (stop, health) never queue.
    exclusive: bool = True
    #: A motion: stopped when the command times out or is aborted.
    motion: bool = False


def operation(schema: str, timeout_s: float = 10.0, exclusive: bool = True,
              motion: bool = False) -> Callable[[Callable], Callable]:
    """Mark ``async def op_<name>(self, request) -> dict`` as a daemon command whose request is
    validated against the JSON Schema ``scancell.cmd.<schema>``. ``motion=True``: the device
    moves, and the daemon stops it if the command times out or is aborted."""

    def mark(fn: Callable) -> Callable:
        name = fn.__name__.removeprefix("op_")
        fn.__scancell_operation__ = OperationSpec(name, schema, timeout_s, exclusive, motion)
        return fn

    return mark


class Device(ABC):
    """Base of every device. ``name`` is the config section; ``options`` its driver keys."""

    kind: ClassVar[str] = "device"
    #: JSON Schema of this driver's config keys (besides ``driver``), checked at config load.
    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {"type": "object"}
    #: If set, the daemon calls :meth:`poll_telemetry` at this period (s) while connected.
    telemetry_period_s: ClassVar[float | None] = None

    def __init__(self, name: str, options: Mapping[str, Any] | None = None) -> None:
        self.name = name
        self.options = dict(options or {})
        self._emit: Emit | None = None
        self._seq: dict[str, int] = {}

    # ---- lifecycle
    @abstractmethod
    async def connect(self) -> None:
        """Open the link; raise ConnectionLost or Timeout if the device cannot be reached."""

    @abstractmethod
    async def close(self) -> None:
        """Close the link. Never raises."""

    @abstractmethod
    async def health(self) -> Health:
        """Ask the device how it is; raise ConnectionLost if the link is gone."""

    async def poll_telemetry(self) -> None:  # noqa: B027 - optional hook
        """Publish periodic measurements (e.g. joint state) through :meth:`emit`."""

    # ---- publishing
    def set_emitter(self, emit: Emit | None) -> None:
        self._emit = emit

    def emit(
        self,
        stream: str,
        encoded: Encoded,
        stamp_ns: int,
        device_stamp_ns: int | None = None,
        meta: dict[str, Any] | None = None,
    ) -> None:
        """Publish a measurement on ``dev/<name>/<stream>`` (no-op without a daemon)."""
        seq = self._seq.get(stream, 0)
        self._seq[stream] = seq + 1
        if self._emit is not None:
            self._emit(stream, encoded, Attachment(stamp_ns, seq, device_stamp_ns, meta or {}))

    # ---- commands
    @classmethod
    def operation_specs(cls) -> dict[str, OperationSpec]:
        specs: dict[str, OperationSpec] = {}
        for klass in reversed(cls.__mro__):
            for attr in vars(klass).values():
                spec = getattr(attr, "__scancell_operation__", None)
                if spec is not None:
                    specs[spec.name] = spec
        return specs

    def operations(self) -> dict[str, tuple[OperationSpec, OpHandler]]:
        return {n: (s, getattr(self, "op_" + n)) for n, s in self.operation_specs().items()}

    @operation("device.health", timeout_s=5.0, exclusive=False)
    async def op_health(self, request: dict[str, Any]) -> dict[str, Any]:
        h = await self.health()
        return {"state": str(h.state), "reason": h.reason, "message": h.message}


def _f(values: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(values, dtype=float).reshape(-1)]


# ====================================================================== Robot


@dataclass(frozen=True)
class RobotStatus:
    """Controller status, after ROS-Industrial's RobotStatus (tri-states as bool/None)."""

    mode: str = "auto"  # "auto" | "manual" | "unknown"
    e_stopped: bool = False
    drives_powered: bool = True
    motion_possible: bool = True
    in_motion: bool = False
    in_error: bool = False
    error_code: int = 0


class Robot(Device):
    """A 6-axis arm. Joints in rad, in the controller's joint convention; speed a 0..1 fraction."""

    kind = "robot"
    telemetry_period_s = 1 / 30
    joint_names: ClassVar[tuple[str, ...]] = ("J1", "J2", "J3", "J4", "J5", "J6")
    #: Driver's default joint limits (rad), shape (n, 2); config ``joint_limits_deg`` overrides.
    default_joint_limits_rad: ClassVar[np.ndarray] = np.radians(
        [[-180, 180], [-90, 160], [-180, 270], [-360, 360], [-125, 125], [-360, 360]]
    )

    @property
    def joint_limits_rad(self) -> np.ndarray:
        cfg = self.options.get("joint_limits_deg")
        return np.radians(np.asarray(cfg, dtype=float)) if cfg else self.default_joint_limits_rad

    def check_joints(self, q_rad: np.ndarray) -> np.ndarray:
        """Raise CommandError('out_of_range') unless ``q`` is finite and inside the limits."""
        q = np.asarray(q_rad, dtype=float).reshape(-1)
        n = len(self.joint_names)
        if q.shape != (n,):
            raise CommandError("invalid", f"{self.name}: expected {n} joints, got {q.size}")
        if not np.all(np.isfinite(q)):
            raise CommandError("out_of_range", f"{self.name}: joints must be finite: {_f(q)}")
        lim = self.joint_limits_rad
        for i, (v, (lo, hi)) in enumerate(zip(q, lim, strict=True)):
            if not lo <= v <= hi:
                raise CommandError(
                    "out_of_range",
                    f"{self.name}: {self.joint_names[i]} = {np.degrees(v):.3f} deg is outside "
                    f"[{np.degrees(lo):.1f}, {np.degrees(hi):.1f}] deg",
                )
        self.check_workspace(q)
        return q

    def check_workspace(self, q: np.ndarray) -> None:
        """Raise CommandError('out_of_range') if the flange at ``q`` (forward kinematics of the
        robot model, robot base frame, mm) leaves the configured ``workspace_mm`` box
        ``[[xmin, xmax], [ymin, ymax], [zmin, zmax]]``."""
        box = self.options.get("workspace_mm")
        if box is None:
            return
        from scancell.model.robot_model import RobotModel

        p = RobotModel().fk(q)[:3, 3]
        for axis, v, (lo, hi) in zip("xyz", p, box, strict=True):
            if not lo <= v <= hi:
                raise CommandError(
                    "out_of_range",
                    f"{self.name}: the flange would be at {axis} = {v:.1f} mm, outside the "
                    f"workspace [{lo:g}, {hi:g}] mm (at joints {_f(np.degrees(q))} deg)")

    @abstractmethod
    async def joints(self) -> np.ndarray:
        """Current joint positions (rad)."""

    async def move_joints(self, q_rad: np.ndarray, speed: float = 0.2) -> None:
        """Move to ``q_rad`` at ``speed`` (fraction of max joint speed) and wait until there."""
        q = self.check_joints(q_rad)
        if not 0.0 < speed <= 1.0:
            raise CommandError("out_of_range", f"{self.name}: speed {speed} not in (0, 1]")
        await self._move_joints(q, speed)

    @abstractmethod
    async def _move_joints(self, q_rad: np.ndarray, speed: float) -> None: ...

    @abstractmethod
    async def stop(self) -> None:
        """Stop motion now."""

    @abstractmethod
    async def status(self) -> RobotStatus: ...

    async def poll_telemetry(self) -> None:
        q = await self.joints()
        t = messages.now_ns()
        self.emit("joints", fg.encode_proto(fg.joint_states(
            list(self.joint_names), q, t)), t)

    @operation("robot.joints")
    async def op_joints(self, request: dict[str, Any]) -> dict[str, Any]:
        q = await self.joints()
        return {"joints_deg": _f(np.degrees(q)), "joints_rad": _f(q)}

    @operation("robot.move_joints", timeout_s=120.0, motion=True)
    async def op_move_joints(self, request: dict[str, Any]) -> dict[str, Any]:
        if "joints_rad" in request:
            q = np.asarray(request["joints_rad"], dtype=float)
        else:
            q = np.radians(np.asarray(request["joints_deg"], dtype=float))
        await self.move_joints(q, float(request.get("speed", 0.2)))
        return await self.op_joints({})

    @operation("robot.stop", timeout_s=2.0, exclusive=False)
    async def op_stop(self, request: dict[str, Any]) -> dict[str, Any]:
        await self.stop()
        return {"stopped": True}

    @operation("robot.status")
    async def op_status(self, request: dict[str, Any]) -> dict[str, Any]:
        return asdict(await self.status())


# ====================================================================== Tracker


@dataclass(frozen=True)
class TrackerMeasurement:
    """An SMR centre in the tracker's frame (``world``), mm, with its 1-sigma per axis (mm)."""

    point_mm: np.ndarray
    sigma_mm: np.ndarray
    stamp_ns: int
    device_stamp_ns: int | None = None
    reflector: str = "SMR1.5"

    def to_json(self) -> dict[str, Any]:
        return {
            "frame": "world",
            "point_mm": _f(self.point_mm),
            "sigma_mm": _f(self.sigma_mm),
            "stamp_ns": self.stamp_ns,
            "device_stamp_ns": self.device_stamp_ns,
            "reflector": self.reflector,
        }


@dataclass(frozen=True)
class TrackerStatus:
    beam_locked: bool
    reflector: str = "SMR1.5"
    temperature_c: float | None = None
    pressure_hpa: float | None = None
    humidity_pct: float | None = None


class Tracker(Device):
    """A laser tracker measuring one spherically mounted retroreflector (SMR)."""

    kind = "tracker"

    @abstractmethod
    async def measure(self) -> TrackerMeasurement:
        """Measure the SMR centre; raise BeamBroken if the beam is not locked."""

    @abstractmethod
    async def status(self) -> TrackerStatus: ...

    async def find_reflector(self, approx_mm: np.ndarray) -> None:
        """Search and lock on the reflector near ``approx_mm`` (world, mm)."""
        raise CommandError("invalid", f"{self.name}: this tracker driver cannot search a reflector")

    async def set_environment(self, temperature_c: float, pressure_hpa: float,
                              humidity_pct: float) -> None:
        """The air (°C, hPa, % RH) the tracker's refraction correction uses from now on."""
        raise CommandError("invalid", f"{self.name}: this tracker driver cannot be told the "
                                      f"weather")

    async def set_face(self, face: int) -> None:
        """Measure in face 1 (front) or 2 (back) from now on."""
        raise CommandError("invalid", f"{self.name}: this tracker driver cannot change face")

    async def measure_published(self, meta: dict[str, Any] | None = None) -> TrackerMeasurement:
        """:meth:`measure`, and the measurement on ``dev/<tracker>/point`` (every shot a
        command or a job takes is on the bus, hence in the recording)."""
        m = await self.measure()
        self.emit("point", messages.encode_json(m.to_json(), "scancell.TrackerPoint"), m.stamp_ns,
                  m.device_stamp_ns, meta)
        return m

    @operation("tracker.measure", timeout_s=10.0)
    async def op_measure(self, request: dict[str, Any]) -> dict[str, Any]:
        return (await self.measure_published(request.get("meta"))).to_json()

    @operation("tracker.status")
    async def op_status(self, request: dict[str, Any]) -> dict[str, Any]:
        return asdict(await self.status())


# ====================================================================== Camera


@dataclass(frozen=True)
class CameraSettings:
    exposure_us: float
    gain_db: float
    trigger: str  # "software" | "hardware" | "free_run"


@dataclass(frozen=True)
class Frame:
    """One camera image (uint8 or uint16, H x W) with its acquisition time."""

    image: np.ndarray
    stamp_ns: int
    seq: int
    device_stamp_ns: int | None = None
    meta: dict[str, Any] = field(default_factory=dict)
    #: Trigger inputs the camera had counted when it exposed this frame (None if unknown).
    trigger_count: int | None = None


class Camera(Device):
    """An area camera. ``settings`` holds what the camera was last configured to."""

    kind = "camera"

    def __init__(self, name: str, options: Mapping[str, Any] | None = None) -> None:
        super().__init__(name, options)
        o = self.options
        self.settings = CameraSettings(float(o.get("exposure_us", 10000.0)),
                                       float(o.get("gain_db", 0.0)), str(o.get("trigger", "software")))

    def updated_settings(self, exposure_us: float | None = None, gain_db: float | None = None,
                         trigger: str | None = None) -> CameraSettings:
        """The current settings with the given fields replaced (None: unchanged)."""
        s = self.settings
        return CameraSettings(s.exposure_us if exposure_us is None else float(exposure_us),
                              s.gain_db if gain_db is None else float(gain_db),
                              s.trigger if trigger is None else str(trigger))

    @abstractmethod
    async def configure(
        self, exposure_us: float | None = None, gain_db: float | None = None,
        trigger: str | None = None,
    ) -> CameraSettings: ...

    @abstractmethod
    async def trigger(self) -> None:
        """Issue a software trigger (no-op for hardware or free-run triggering)."""

    @abstractmethod
    async def grab(self, timeout_s: float = 2.0) -> Frame:
        """Return the next frame; raise Timeout if none arrives in ``timeout_s``."""

    async def pending(self) -> int:
        """Frames acquired but not yet taken by :meth:`grab`."""
        return 0

    async def flush(self) -> int:
        """Drop frames acquired but not taken; return how many."""
        n = 0
        while await self.pending():
            await self.grab(1.0)
            n += 1
        return n

    def publish_frame(self, frame: Frame, meta: dict[str, Any] | None = None) -> None:
        msg = fg.raw_image(frame.image, frame.stamp_ns, self.name)
        self.emit("image", fg.encode_proto(msg), frame.stamp_ns, frame.device_stamp_ns,
                  {**frame.meta, **(meta or {})})

    @operation("camera.configure")
    async def op_configure(self, request: dict[str, Any]) -> dict[str, Any]:
        return asdict(await self.configure(**request))

    @operation("camera.grab", timeout_s=10.0)
    async def op_grab(self, request: dict[str, Any]) -> dict[str, Any]:
        await self.trigger()
        frame = await self.grab(float(request.get("timeout_s", 2.0)))
        self.publish_frame(frame, request.get("meta"))
        img = frame.image
        return {"width": int(img.shape[1]), "height": int(img.shape[0]), "dtype": str(img.dtype),
                "stamp_ns": frame.stamp_ns, "seq": frame.seq, "mean": float(img.mean())}


# ====================================================================== Projector


class Projector(Device):
    """A pattern projector. A sequence spec is a dict:

    - the scanner's fringe sequence ``{"kind": "fringe", "steps": 3, "periods": [70, 64, 59]}``,
      optionally with ``"precompensation"``: 256 ints, the 8-bit value to project for each
      value wanted (the inverse of a projector-response calibration);
    - any pattern set ``{"kind": "patterns", "patterns": "gray-phase"}`` (a preset name or a
      pattern-set table, :mod:`scancell.model.pattern_set`), also with an optional
      ``"precompensation"``;
    - uniform levels ``{"kind": "levels", "levels": [0, 15, …, 255]}``: pattern k lights the
      whole image at levels[k] (a projector-response calibration).
    """

    kind = "projector"
    #: The projector runs a loaded sequence itself (:meth:`play`), one trigger-out pulse per
    #: pattern; otherwise acquisition steps it with :meth:`show`.
    plays_sequences: ClassVar[bool] = False

    @abstractmethod
    async def load_sequence(self, spec: dict[str, Any]) -> int:
        """Load a pattern sequence; return its number of patterns. ``display_us`` in the spec,
        if given, is the least time (µs) each pattern must stay up (the cameras' exposure)."""

    def unloadable(self, spec: dict[str, Any]) -> str | None:
        """Why this projector cannot load ``spec`` (e.g. patterns not in its flash), or None."""
        return None

    async def play(self) -> None:
        """Start the loaded sequence once; each pattern pulses trigger out (plays_sequences)."""
        raise NotImplementedError(f"{self.name}: this projector is stepped with show()")

    @abstractmethod
    async def show(self, index: int) -> None:
        """Project pattern ``index`` of the loaded sequence (-1: dark)."""

    @operation("projector.load_sequence", timeout_s=30.0)
    async def op_load_sequence(self, request: dict[str, Any]) -> dict[str, Any]:
        return {"patterns": await self.load_sequence(request)}

    @operation("projector.show")
    async def op_show(self, request: dict[str, Any]) -> dict[str, Any]:
        await self.show(int(request["index"]))
        return {"index": int(request["index"])}


# ====================================================================== Axis


class Axis(Device):
    """An external axis (turntable in rad or rail in mm, as ``units`` says)."""

    kind = "axis"
    units: ClassVar[str] = "mm"

    @property
    def limits(self) -> tuple[float, float]:
        lo, hi = self.options.get("limits", (-1e9, 1e9))
        return float(lo), float(hi)

    async def move_to(self, position: float, speed: float = 0.5) -> None:
        lo, hi = self.limits
        if not (np.isfinite(position) and lo <= position <= hi):
            raise CommandError("out_of_range",
                               f"{self.name}: position {position} {self.units} outside [{lo}, {hi}]")
        if not 0.0 < speed <= 1.0:
            raise CommandError("out_of_range", f"{self.name}: speed {speed} not in (0, 1]")
        await self._move_to(float(position), float(speed))

    @abstractmethod
    async def _move_to(self, position: float, speed: float) -> None: ...

    @abstractmethod
    async def position(self) -> float: ...

    @abstractmethod
    async def home(self) -> None: ...

    @abstractmethod
    async def stop(self) -> None: ...

    async def reset_fault(self) -> None:
        """Acknowledge a drive fault and make the axis ready to move again."""
        raise CommandError("invalid", f"{self.name}: this axis driver has no fault reset")

    @operation("axis.move_to", timeout_s=120.0, motion=True)
    async def op_move_to(self, request: dict[str, Any]) -> dict[str, Any]:
        await self.move_to(float(request["position"]), float(request.get("speed", 0.5)))
        return {"position": await self.position(), "units": self.units}

    @operation("axis.position")
    async def op_position(self, request: dict[str, Any]) -> dict[str, Any]:
        return {"position": await self.position(), "units": self.units}

    @operation("axis.home", timeout_s=120.0, motion=True)
    async def op_home(self, request: dict[str, Any]) -> dict[str, Any]:
        await self.home()
        return {"position": await self.position(), "units": self.units}

    @operation("axis.reset_fault", timeout_s=10.0)
    async def op_reset_fault(self, request: dict[str, Any]) -> dict[str, Any]:
        await self.reset_fault()
        return {"position": await self.position(), "units": self.units}

    @operation("axis.stop", timeout_s=2.0, exclusive=False)
    async def op_stop(self, request: dict[str, Any]) -> dict[str, Any]:
        await self.stop()
        return {"stopped": True}


KINDS: dict[str, type[Device]] = {
    c.kind: c for c in (Robot, Tracker, Camera, Projector, Axis)
}
