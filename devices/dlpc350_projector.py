"""TI DLPC350 (LightCrafter 4500) projector driver: 8-bit patterns from the controller's flash.

The DLPC350 takes no images over USB: its pattern sequences play 24-bit images stored in flash
(each holding three 8-bit patterns: G7-G0, R7-R0, B7-B0). The ``flash`` option states what the
cell's flash holds, as commissioning wrote it (docs/tutorials/first-real-cell.md):

    flash = [{kind = "fringe", periods = [70, 64, 59], steps = 3, first_image = 0},
             {kind = "levels", levels = [0, 15, ..., 255], first_image = 3}]

A fringe entry may carry the ``precompensation`` table it was flashed with; a pre-compensated
sequence loads only if such an entry exists (:meth:`unloadable` says why not otherwise).
"""

from __future__ import annotations

from typing import Any, ClassVar

from scancell.devices.dlp_projector import DLP_OPTIONS, DlpProjector, ValidationFailed
from scancell.devices.errors import DeviceFault, Timeout
from scancell.model.pattern_set import PatternSpecError, sequence_pattern_set
from scancell.protocols import dlpc350 as c
from scancell.protocols.commands import CommandError

PLANES = 3  # 8-bit patterns per 24-bit flash image
VALIDATION_POLLS = 50


#: JSON Schema of a flash layout (the driver's ``flash`` option, the emulator's flash).
FLASH_LAYOUT_SCHEMA: dict[str, Any] = {
    "type": "array",
    "items": {"type": "object", "required": ["kind", "first_image"],
              "additionalProperties": False, "properties": {
                  "kind": {"enum": ["fringe", "levels", "patterns"]},
                  "patterns": {"type": ["string", "object"]},
                  "first_image": {"type": "integer", "minimum": 0, "maximum": 255},
                  "periods": {"type": "array", "minItems": 1,
                              "items": {"type": "number", "exclusiveMinimum": 0}},
                  "steps": {"type": "integer", "minimum": 3},
                  "levels": {"type": "array", "minItems": 1,
                             "items": {"type": "integer", "minimum": 0, "maximum": 255}},
                  "precompensation": {"type": "array", "minItems": 256, "maxItems": 256,
                                      "items": {"type": "integer", "minimum": 0,
                                                "maximum": 255}}},
              "allOf": [{"if": {"properties": {"kind": {"const": "levels"}}},
                         "then": {"required": ["levels"]}},
                        {"if": {"properties": {"kind": {"const": "fringe"}}},
                         "then": {"required": ["periods"]}},
                        {"if": {"properties": {"kind": {"const": "patterns"}}},
                         "then": {"required": ["patterns"]}}]},
}


def locate(flash: list[dict[str, Any]], spec: dict[str, Any]) -> list[tuple[int, int]] | str:
    """(flash image, plane) of each pattern of ``spec``, or why the flash does not hold them."""
    if spec.get("kind") == "levels":
        where: dict[int, tuple[int, int]] = {}
        for entry in flash:
            if entry["kind"] == "levels":
                for i, v in enumerate(entry["levels"]):
                    where.setdefault(int(v), (entry["first_image"] + i // PLANES, i % PLANES))
        missing = [int(v) for v in spec.get("levels", []) if int(v) not in where]
        if missing:
            return f"levels {missing} are not in the projector's flash"
        return [where[int(v)] for v in spec["levels"]]
    try:
        wanted = sequence_pattern_set(spec)
    except PatternSpecError as exc:
        return str(exc)
    pre = spec.get("precompensation")
    for entry in flash:
        if (entry["kind"] != "levels" and sequence_pattern_set(entry).shows_the_same(wanted)
                and entry.get("precompensation") == pre):
            return [(entry["first_image"] + k // PLANES, k % PLANES) for k in range(len(wanted))]
    what = "pre-compensated " if pre is not None else ""
    seq = wanted.fringe_sequence()
    held = (f"fringes of periods {list(seq.periods)} x {seq.steps} steps" if seq is not None
            else f"pattern set {wanted.name or wanted.to_dict()['groups']}")
    return (f"the projector's flash holds no {what}{held} "
            f"(a DLPC350 plays flash images only: flash them, docs/tutorials/first-real-cell.md)")


def images_needed(flash: list[dict[str, Any]]) -> int:
    """How many flash images a layout describes."""
    def patterns(e: dict[str, Any]) -> int:
        if e["kind"] == "levels":
            return len(e["levels"])
        return len(sequence_pattern_set(e))

    return max((e["first_image"] + -(-patterns(e) // PLANES) for e in flash), default=0)


class Dlpc350Projector(DlpProjector):
    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {
        "type": "object",
        "properties": {**DLP_OPTIONS, "flash": FLASH_LAYOUT_SCHEMA},
        "required": ["url", "flash"],
        "additionalProperties": False,
    }
    names = c.NAMES

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self.flash: list[dict[str, Any]] = list(self.options.get("flash", []))
        self._placed: list[tuple[int, int]] = []
        self._exposure = 0

    async def _on_connect(self) -> None:
        await self.write(c.POWER_CONTROL, b"\x00")
        await self._start_stop(c.STOP)
        await self.write(c.DISP_MODE, b"\x01")
        await self.write(c.PAT_DISP_MODE, bytes([c.SOURCE_FLASH]))
        await self.write(c.PAT_TRIG_MODE, bytes([c.TRIGGER_INTERNAL]))
        invert = int(bool(self.options.get("trigger_out_invert", False)))
        await self.write(c.TRIG_OUT1_CTL, bytes([invert, 0xBB, 0xBB]))  # 0xBB: no delay
        images = (await self.read(c.NUM_IMAGE_IN_FLASH))[0]
        needed = images_needed(self.flash)
        if images < needed:
            raise DeviceFault(f"{self.name}: the flash holds {images} images, the 'flash' option "
                              f"describes {needed}: the option does not match the firmware")

    async def _faults(self) -> list[str]:
        faults = c.hardware_faults((await self.read(c.STATUS_HW))[0])
        if not (await self.read(c.STATUS_SYS))[0] & c.SYS_MEMORY_TEST_PASSED:
            faults.append("internal memory test failed")
        return faults

    def unloadable(self, spec: dict[str, Any]) -> str | None:
        placed = locate(self.flash, spec)
        return placed if isinstance(placed, str) else None

    async def load_sequence(self, spec: dict[str, Any]) -> int:
        placed = locate(self.flash, spec)
        if isinstance(placed, str):
            raise CommandError("invalid", f"{self.name}: {placed}")
        self._exposure = self._exposure_us(spec, c.MIN_EXPOSURE_US[7])
        await self._start_stop(c.STOP)
        await self._program(placed, repeat=False)
        self._placed = placed
        self._full = True
        self.patterns = len(placed)
        return self.patterns

    async def _program(self, placed: list[tuple[int, int]], repeat: bool) -> None:
        """Write the pattern and image LUTs for ``placed`` and validate them (stopped)."""
        images: list[int] = []
        entries: list[c.LutEntry] = []
        for image, plane in placed:
            swap = not images or images[-1] != image
            if swap:
                images.append(image)
            entries.append(c.LutEntry(pattern=plane, bit_depth=8, buffer_swap=swap))
        await self.write(c.PAT_EXPO_PRD, c.exposure_period(self._exposure, self._exposure))
        await self.write(c.PAT_CONFIG, c.PatternConfig(len(entries), repeat, len(entries),
                                                       len(images)).pack())
        await self._mailbox(c.MAILBOX_PATTERN, c.pack_lut(entries))
        # dlpc350_api.cpp: a two-entry image LUT goes in swapped order
        lut = bytes(images[::-1] if len(images) == 2 else images)
        await self._mailbox(c.MAILBOX_IMAGE, lut)
        await self._validate()

    async def _mailbox(self, box: int, data: bytes) -> None:
        await self.write(c.MBOX_CONTROL, bytes([box]))
        await self.write(c.MBOX_ADDRESS, b"\x00")
        await self.write(c.MBOX_DATA, data)
        await self.write(c.MBOX_CONTROL, b"\x00")

    async def _validate(self) -> None:
        await self.write(c.LUT_VALID, b"\x00")
        for _ in range(VALIDATION_POLLS):
            status = (await self.read(c.LUT_VALID))[0]
            if not status & c.VALID_BUSY:
                break
        else:
            raise Timeout(f"{self.name}: the controller still validates after "
                          f"{VALIDATION_POLLS} polls")
        errors, warnings = c.describe_validation(status)
        if errors:
            raise ValidationFailed(f"{self.name}: sequence validation failed (status "
                                   f"0x{status:02X}): " + "; ".join(errors + warnings))

    async def _program_all(self) -> None:
        await self._program(self._placed, repeat=False)

    async def _program_one(self, index: int) -> None:
        await self._program([self._placed[index]], repeat=True)
