"""TI DLPC900 (LightCrafter 6500 / 9000) projector driver: patterns uploaded on the fly.

The driver renders the sequence's 8-bit patterns (``model/patterns.py``, through a projector-
response pre-compensation table when the spec has one), packs three into each 24-bit image,
uploads them run-length encoded (pattern-on-the-fly mode) and defines one LUT entry per pattern.
An upload is skipped when the controller already holds the same images.
"""

from __future__ import annotations

import hashlib
import logging
from typing import Any, ClassVar

import numpy as np
from scancell.devices.dlp_projector import DLP_OPTIONS, DlpProjector, ValidationFailed
from scancell.devices.errors import DeviceFault
from scancell.model.patterns import FringeSequence
from scancell.protocols import dlpc900 as c
from scancell.protocols.commands import CommandError
from scancell.protocols.dlpc350 import read_versions  # the DLPC900 sends the same four words

log = logging.getLogger(__name__)
PLANES = 3


def pattern_images(spec: dict[str, Any], width: int, height: int) -> list[np.ndarray]:
    """The 8-bit patterns (height x width) of a sequence spec, pre-compensated if it says so."""
    if spec.get("kind") == "levels":
        levels = [int(v) for v in spec.get("levels", [])]
        if not levels or min(levels) < 0 or max(levels) > 255:
            raise ValueError(f"levels must be 8-bit values, got {spec.get('levels')}")
        return [np.full((height, width), v, np.uint8) for v in levels]
    seq = FringeSequence.from_spec(spec)
    images = [seq.image(k, width, height) for k in range(len(seq))]
    pre = spec.get("precompensation")
    if pre is not None:
        lut = np.asarray(pre, np.int64)
        if lut.shape != (256,) or lut.min() < 0 or lut.max() > 255:
            raise ValueError("precompensation must be 256 values in 0 … 255")
        images = [lut.astype(np.uint8)[im] for im in images]
    return images


class Dlpc900Projector(DlpProjector):
    OPTIONS_SCHEMA: ClassVar[dict[str, Any]] = {
        "type": "object",
        "properties": {**DLP_OPTIONS,
                       "dmd": {"type": "array", "items": {"type": "integer", "minimum": 1},
                               "minItems": 2, "maxItems": 2},
                       "dark_us": {"type": "integer", "minimum": 0}},
        "required": ["url"],
        "additionalProperties": False,
    }
    names = c.NAMES

    def __init__(self, name: str, options: dict[str, Any] | None = None) -> None:
        super().__init__(name, options)
        self.width, self.height = (int(v) for v in self.options.get("dmd", (1920, 1080)))
        self._uploaded: str | None = None
        self._definitions: list[c.LutDefinition] = []
        self._full = False
        self.min_exposure_us: tuple[int, ...] = c.MIN_EXPOSURE_US

    async def _on_connect(self) -> None:
        data = await self.read(c.GET_VERSION, min_bytes=16)
        self.versions = {k: str(v) for k, v in read_versions(data).items()}
        self.min_exposure_us = c.read_min_exposures(await self.read(c.MIN_EXPOSURE, min_bytes=16))
        self._uploaded = None
        await self.write(c.POWER_MODE, b"\x00")
        await self.write(c.PAT_START_STOP, bytes([c.STOP]))
        await self.write(c.DISP_MODE, bytes([c.MODE_ON_THE_FLY]))
        invert = int(bool(self.options.get("trigger_out_invert", False)))
        await self.write(c.TRIG_OUT1_CTL, bytes([invert, 0, 0, 0, 0]))

    async def _command_failed(self, command: int) -> Exception:
        code = (await self.read(c.READ_ERROR_CODE))[0]
        what = c.ERROR_CODES.get(code, f"error code {code}")
        try:
            text = (await self.read(c.READ_ERROR_DESCRIPTION, min_bytes=0)).split(b"\0")[0]
            detail = text.decode("ascii", "replace")
        except DeviceFault:
            detail = ""
        message = (f"{self.name}: {c.NAMES.get(command, hex(command))} refused: {what}"
                   + (f" ({detail})" if detail and detail != what else ""))
        if code in (c.ERR_EXPOSURE, c.ERR_BIT_NUMBER, c.ERR_PATTERN_NUMBER, 12, 16):
            return ValidationFailed(message)
        return DeviceFault(message)

    async def _status(self) -> tuple[list[str], bool]:
        hw = (await self.read(c.STATUS_HW))[0]
        main = (await self.read(c.STATUS_MAIN))[0]
        faults = []
        if not hw & c.HW_INIT_DONE:
            faults.append("internal initialisation failed")
        if hw & c.HW_INCOMPATIBLE:
            faults.append("incompatible controller or DMD")
        if hw & (c.HW_DRC_ERROR | c.HW_FORCED_SWAP_ERROR | c.HW_SEQUENCE_ABORT
                 | c.HW_SEQUENCE_ERROR):
            faults.append(f"sequencer/DMD error (hardware status 0x{hw:02X})")
        return faults, bool(main & c.MAIN_SEQUENCE_RUNNING)

    async def load_sequence(self, spec: dict[str, Any]) -> int:
        try:
            patterns = pattern_images(spec, self.width, self.height)
        except (ValueError, TypeError, KeyError) as exc:
            raise CommandError("invalid", f"{self.name}: {exc}") from None
        if len(patterns) > c.MAX_IMAGES * PLANES:
            raise CommandError("out_of_range", f"{self.name}: {len(patterns)} patterns exceed "
                                               f"the {c.MAX_IMAGES * PLANES} 8-bit patterns of "
                                               f"the on-the-fly memory")
        exposure = self._exposure_us(spec, self.min_exposure_us[7])
        dark = int(self.options.get("dark_us", 0))
        self._definitions = [c.LutDefinition(index=k, exposure_us=exposure, dark_us=dark,
                                             image_index=k // PLANES,
                                             bit_position=8 * (k % PLANES))
                             for k in range(len(patterns))]
        await self.write(c.PAT_START_STOP, bytes([c.STOP]))
        await self._define(self._definitions)
        images = [c.merge_planes(patterns[i:i + PLANES]) for i in range(0, len(patterns), PLANES)]
        digest = hashlib.sha1(b"".join(im.tobytes() for im in images)).hexdigest()
        if digest != self._uploaded:
            self._uploaded = None
            for index in reversed(range(len(images))):  # DLPU018: load in reverse order
                encoded = c.encode_image(images[index])
                await self.write(c.BMP_LOAD_INIT, c.bmp_load_init(index, len(encoded)))
                for chunk in c.bmp_chunks(encoded):
                    await self.write(c.BMP_LOAD, chunk)
            self._uploaded = digest
        await self._configure(len(self._definitions), len(self._definitions))
        self._full = True
        self.patterns = len(patterns)
        return self.patterns

    async def _define(self, definitions: list[c.LutDefinition]) -> None:
        for d in definitions:
            await self.write(c.LUT_DEFINE, d.pack())

    async def _configure(self, entries: int, patterns: int) -> None:
        await self.write(c.LUT_CONFIG, c.lut_config(entries, patterns))

    async def play(self) -> None:
        if not self._full:
            await self.write(c.PAT_START_STOP, bytes([c.STOP]))
            await self._define(self._definitions)
            await self._configure(len(self._definitions), len(self._definitions))
            self._full = True
        await self.write(c.PAT_START_STOP, bytes([c.START]))

    async def _stop(self) -> None:
        await self.write(c.PAT_START_STOP, bytes([c.STOP]))

    async def _show_one(self, index: int) -> None:
        d = self._definitions[index]
        one = c.LutDefinition(index=0, exposure_us=d.exposure_us, dark_us=d.dark_us,
                              image_index=d.image_index, bit_position=d.bit_position)
        await self.write(c.PAT_START_STOP, bytes([c.STOP]))
        await self._define([one])
        await self._configure(1, 0)
        self._full = False
        await self.write(c.PAT_START_STOP, bytes([c.START]))
