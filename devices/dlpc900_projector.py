"""TI DLPC900 (LightCrafter 6500 / 9000) projector driver: patterns uploaded on the fly.

The driver renders the sequence's 8-bit patterns (``model/patterns.py``, through a projector-
response pre-compensation table when the spec has one), packs three into each 24-bit image,
uploads them run-length encoded (pattern-on-the-fly mode) and defines one LUT entry per pattern.
An upload is skipped when the controller already holds the same sequence (the HDR exposures
of a station load it again with another exposure).
"""

from __future__ import annotations

import json
import logging
from typing import Any, ClassVar

import numpy as np
from scancell.devices.dlp_projector import DLP_OPTIONS, DlpProjector, ValidationFailed
from scancell.devices.errors import DeviceFault
from scancell.model.pattern_set import sequence_pattern_set
from scancell.protocols import dlpc900 as c
from scancell.protocols.commands import CommandError

log = logging.getLogger(__name__)
PLANES = 3


def pattern_images(spec: dict[str, Any], width: int, height: int) -> list[np.ndarray]:
    """The 8-bit patterns (height x width) of a sequence spec, pre-compensated if it says so."""
    if spec.get("kind") == "levels":
        levels = [int(v) for v in spec.get("levels", [])]
        if not levels or min(levels) < 0 or max(levels) > 255:
            raise ValueError(f"levels must be 8-bit values, got {spec.get('levels')}")
        return [np.full((height, width), v, np.uint8) for v in levels]
    patterns = sequence_pattern_set(spec)
    images = [patterns.image(k, width, height) for k in range(len(patterns))]
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
        self._uploaded: tuple[str, int] | None = None  # (spec key, patterns) the controller holds
        self._definitions: list[c.LutDefinition] = []
        self.min_exposure_us: tuple[int, ...] = c.MIN_EXPOSURE_US

    async def _on_connect(self) -> None:
        self.min_exposure_us = c.read_min_exposures(await self.read(c.MIN_EXPOSURE, min_bytes=16))
        self._uploaded = None
        await self.write(c.POWER_MODE, b"\x00")
        await self._start_stop(c.STOP)
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
        if code in c.RULE_ERRORS:
            return ValidationFailed(message)
        return DeviceFault(message)

    async def _faults(self) -> list[str]:
        hw = (await self.read(c.STATUS_HW))[0]
        faults = []
        if not hw & c.HW_INIT_DONE:
            faults.append("internal initialisation failed")
        if hw & c.HW_INCOMPATIBLE:
            faults.append("incompatible controller or DMD")
        if hw & (c.HW_DRC_ERROR | c.HW_FORCED_SWAP_ERROR | c.HW_SEQUENCE_ABORT
                 | c.HW_SEQUENCE_ERROR):
            faults.append(f"sequencer/DMD error (hardware status 0x{hw:02X})")
        return faults

    async def load_sequence(self, spec: dict[str, Any]) -> int:
        key = json.dumps({k: v for k, v in spec.items() if k != "display_us"}, sort_keys=True)
        cached = self._uploaded is not None and self._uploaded[0] == key
        if cached:  # the HDR exposures of a station: the same images, another exposure
            n = self._uploaded[1]
        else:
            try:
                patterns = pattern_images(spec, self.width, self.height)
            except (ValueError, TypeError, KeyError) as exc:
                raise CommandError("invalid", f"{self.name}: {exc}") from None
            n = len(patterns)
            if n > c.MAX_IMAGES * PLANES:
                raise CommandError("out_of_range", f"{self.name}: {n} patterns exceed the "
                                                   f"{c.MAX_IMAGES * PLANES} 8-bit patterns of "
                                                   f"the on-the-fly memory")
        exposure = self._exposure_us(spec, self.min_exposure_us[7])
        dark = int(self.options.get("dark_us", 0))
        self._definitions = [c.LutDefinition(index=k, exposure_us=exposure, dark_us=dark,
                                             image_index=k // PLANES,
                                             bit_position=8 * (k % PLANES))
                             for k in range(n)]
        await self._start_stop(c.STOP)
        await self._define(self._definitions)
        if not cached:
            self._uploaded = None
            images = [c.merge_planes(patterns[i:i + PLANES]) for i in range(0, n, PLANES)]
            for index in reversed(range(len(images))):  # DLPU018: load in reverse order
                encoded = c.encode_image(images[index])
                await self.write(c.BMP_LOAD_INIT, c.bmp_load_init(index, len(encoded)))
                for chunk in c.bmp_chunks(encoded):
                    await self.write(c.BMP_LOAD, chunk)
            self._uploaded = (key, n)
        await self.write(c.LUT_CONFIG, c.lut_config(n, n))
        self._full = True
        self.patterns = n
        return n

    async def _define(self, definitions: list[c.LutDefinition]) -> None:
        for d in definitions:
            await self.write(c.LUT_DEFINE, d.pack())

    async def _program_all(self) -> None:
        n = len(self._definitions)
        await self._define(self._definitions)
        await self.write(c.LUT_CONFIG, c.lut_config(n, n))

    async def _program_one(self, index: int) -> None:
        d = self._definitions[index]
        await self._define([c.LutDefinition(index=0, exposure_us=d.exposure_us, dark_us=d.dark_us,
                                            image_index=d.image_index,
                                            bit_position=d.bit_position)])
        await self.write(c.LUT_CONFIG, c.lut_config(1, 0))  # 0: repeat until stopped
