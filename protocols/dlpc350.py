"""The DLPC350 (LightCrafter 4500) USB commands a scanner needs. Pure: no I/O.

Commands, payloads and bit fields after TI's DLPC350 programmer's guide (DLPU010) and TI's
``dlpc350_api.cpp`` (the LightCrafter 4500 GUI's host API). Multi-byte fields are LSB first.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from scancell.protocols.dlp_hid import GET_VERSION as GET_VERSION
from scancell.protocols.dlp_hid import PAT_START_STOP as PAT_START_STOP
from scancell.protocols.dlp_hid import START as START
from scancell.protocols.dlp_hid import STOP as STOP
from scancell.protocols.dlp_hid import read_u24, u24

VID, PID = 0x0451, 0x6401

POWER_CONTROL = 0x0200      # 1 byte: 0 normal, 1 standby
SW_RESET = 0x0802
LED_CURRENT = 0x0B01        # 3 bytes: red, green, blue PWM
SOURCE_SEL = 0x1A00         # 1 byte: bits 2:0 source (0 parallel, 1 test pattern, 2 flash, 3 FPD)
LED_ENABLE = 0x1A07         # 1 byte: bit 3 sequencer control, bits 0-2 R, G, B
STATUS_HW = 0x1A0A
STATUS_SYS = 0x1A0B
STATUS_MAIN = 0x1A0C
LUT_VALID = 0x1A1A          # write: start validation; read: status bits (bit 7 = busy)
DISP_MODE = 0x1A1B          # 1 byte: 0 video, 1 pattern sequence
TRIG_OUT1_CTL = 0x1A1D      # 3 bytes: invert, rising delay, falling delay (107.2 ns steps)
TRIG_OUT2_CTL = 0x1A1E      # 2 bytes: invert, rising delay
PAT_DISP_MODE = 0x1A22      # 1 byte: 0 video port (RGB/FPD-link), 3 internal flash
PAT_TRIG_MODE = 0x1A23      # 1 byte: 0 VSYNC, 1 internal/external, 2-4 others
PAT_EXPO_PRD = 0x1A29       # 8 bytes: exposure us (u32), frame period us (u32)
PAT_CONFIG = 0x1A31         # 4 bytes: entries-1, repeat, patterns for TRIG_OUT2 - 1, images-1
MBOX_ADDRESS = 0x1A32       # 1 byte: offset in the open mailbox
MBOX_CONTROL = 0x1A33       # 1 byte: 0 close, 1 image LUT, 2 pattern LUT
MBOX_DATA = 0x1A34          # variable: image indices (1 byte each) or LUT entries (3 bytes each)
NUM_IMAGE_IN_FLASH = 0x1A42
FIRMWARE_TAG = 0x1AFF       # read: up to 32 ASCII characters
#: Display settings a scanner leaves alone but a client may set: command -> (name, data bytes).
#: Names as TI's DLPC350 API (dlpc350_api.h, its CmdList) spells them.
SETTING_NAMES: dict[int, tuple[str, int]] = {
    0x0609: ("DMD_PARK", 1), 0x1008: ("FLIP_LONG", 1), 0x1009: ("FLIP_SHORT", 1),
    0x100A: ("BUFFER_FREEZE", 1), 0x1203: ("TPG_SEL", 1), 0x1A02: ("PIXEL_FORMAT", 1),
    0x1A03: ("CLK_SEL", 1), 0x1A05: ("PWM_INVERT", 1), 0x1A0E: ("GAMMA_CTL", 1),
    0x1A30: ("INVERT_DATA", 1), 0x1A37: ("CHANNEL_SWAP", 1), 0x1A35: ("TRIG_IN1_DELAY", 4)}
SETTINGS = {cmd: n for cmd, (_, n) in SETTING_NAMES.items()}

NAMES = {
    POWER_CONTROL: "POWER_CONTROL", GET_VERSION: "GET_VERSION", SW_RESET: "SW_RESET",
    LED_CURRENT: "LED_CURRENT", SOURCE_SEL: "SOURCE_SEL", LED_ENABLE: "LED_ENABLE",
    STATUS_HW: "STATUS_HW", STATUS_SYS: "STATUS_SYS", STATUS_MAIN: "STATUS_MAIN",
    LUT_VALID: "LUT_VALID", DISP_MODE: "DISP_MODE", TRIG_OUT1_CTL: "TRIG_OUT1_CTL",
    TRIG_OUT2_CTL: "TRIG_OUT2_CTL", PAT_DISP_MODE: "PAT_DISP_MODE", PAT_TRIG_MODE: "PAT_TRIG_MODE",
    PAT_START_STOP: "PAT_START_STOP", PAT_EXPO_PRD: "PAT_EXPO_PRD", PAT_CONFIG: "PAT_CONFIG",
    MBOX_ADDRESS: "MBOX_ADDRESS", MBOX_CONTROL: "MBOX_CONTROL", MBOX_DATA: "MBOX_DATA",
    NUM_IMAGE_IN_FLASH: "NUM_IMAGE_IN_FLASH", FIRMWARE_TAG: "FIRMWARE_TAG",
    **{cmd: name for cmd, (name, _) in SETTING_NAMES.items()},
}

#: Data bytes of each write (None: variable). A write of another length is refused.
WRITE_LENGTH: dict[int, int | None] = {
    POWER_CONTROL: 1, SW_RESET: 0, LED_CURRENT: 3, SOURCE_SEL: 1, LED_ENABLE: 1, LUT_VALID: 1,
    DISP_MODE: 1, TRIG_OUT1_CTL: 3, TRIG_OUT2_CTL: 2, PAT_DISP_MODE: 1, PAT_TRIG_MODE: 1,
    PAT_START_STOP: 1, PAT_EXPO_PRD: 8, PAT_CONFIG: 4, MBOX_ADDRESS: 1, MBOX_CONTROL: 1,
    MBOX_DATA: None, **SETTINGS,
}
READABLE = {POWER_CONTROL, GET_VERSION, LED_CURRENT, SOURCE_SEL, LED_ENABLE, STATUS_HW, STATUS_SYS,
            STATUS_MAIN, LUT_VALID, DISP_MODE, TRIG_OUT1_CTL, TRIG_OUT2_CTL, PAT_DISP_MODE,
            PAT_TRIG_MODE, PAT_START_STOP, PAT_EXPO_PRD, PAT_CONFIG, NUM_IMAGE_IN_FLASH,
            FIRMWARE_TAG, *SETTINGS}

#: entries of the pattern and image LUT mailboxes (MBOX_ADDRESS takes 0-127)
LUT_ENTRIES = 128
SOURCE_VIDEO = 0            # PAT_DISP_MODE value: patterns streamed through the video port
SOURCE_FLASH = 3            # PAT_DISP_MODE value: patterns from the flash images
TRIGGER_INTERNAL = 1        # PAT_TRIG_MODE 1: internal (or TRIG_IN) trigger
MAILBOX_IMAGE, MAILBOX_PATTERN = 1, 2

#: Minimum exposure (us) per bit depth 1 ... 8 (DLPU010, pattern sequence timing; the same table
#: the LightCrafter 4500 GUI enforces).
MIN_EXPOSURE_US = (235, 700, 1570, 1700, 2000, 2500, 4500, 8333)
#: The exposure must equal the frame period or be shorter than it by at least this (us).
MIN_DARK_US = 230

# LUT_VALID read: status bits (DLPU010, Validate Data command response)
VALID_EXPOSURE = 0x01
VALID_PATTERN_NUMBER = 0x02
VALID_TRIGGER_OUT1 = 0x04
VALID_POST_VECTOR = 0x08
VALID_PERIOD_DIFFERENCE = 0x10
VALID_BUSY = 0x80
VALIDATION_ERRORS = {
    VALID_EXPOSURE: "exposure or frame period invalid: the exposure must equal the frame period "
                    "or be shorter by ≥ 230 µs, and be at least the bit depth's minimum",
    VALID_PATTERN_NUMBER: "a pattern number in the LUT is invalid for its bit depth, or an image "
                          "index is not in flash",
}
VALIDATION_WARNINGS = {
    VALID_TRIGGER_OUT1: "continuous trigger out 1 request or overlapping black sectors",
    VALID_POST_VECTOR: "post vector not inserted before an externally triggered vector",
    VALID_PERIOD_DIFFERENCE: "frame period − exposure is less than 230 µs",
}

# status bits (DLPU010 §2.1)
HW_INIT_DONE = 0x01
HW_DRC_ERROR = 0x04
HW_FORCED_SWAP_ERROR = 0x08
HW_SEQUENCE_ABORT = 0x40
HW_SEQUENCE_ERROR = 0x80
SYS_MEMORY_TEST_PASSED = 0x01
MAIN_DMD_PARKED = 0x01
MAIN_SEQUENCE_RUNNING = 0x02
MAIN_BUFFER_FROZEN = 0x04


@dataclass(frozen=True)
class LutEntry:
    """One 24-bit pattern-LUT word (``DLPC350_AddToPatLut``): ``pattern`` is the bit plane (1 bit:
    0-23, 24 black) or plane group (8 bit: 0 = G7-G0, 1 = R7-R0, 2 = B7-B0) of the image."""

    pattern: int
    bit_depth: int = 8
    trigger: int = 0            # 0 internal/external, 1 external positive, 2 negative, 3 none
    led: int = 0b111            # bit 0 red, 1 green, 2 blue
    invert: bool = False
    insert_black: bool = True
    buffer_swap: bool = False
    trigger_out_previous: bool = False

    def pack(self) -> int:
        if not 1 <= self.bit_depth <= 8:
            raise ValueError(f"bit depth {self.bit_depth} not in 1 ... 8")
        return ((self.trigger & 3) | (self.pattern & 0x3F) << 2 | (self.bit_depth & 0xF) << 8
                | (self.led & 7) << 12 | self.invert << 16 | self.insert_black << 17
                | self.buffer_swap << 18 | self.trigger_out_previous << 19)

    @classmethod
    def unpack(cls, word: int) -> LutEntry:
        return cls(pattern=(word >> 2) & 0x3F, bit_depth=(word >> 8) & 0xF, trigger=word & 3,
                   led=(word >> 12) & 7, invert=bool(word >> 16 & 1),
                   insert_black=bool(word >> 17 & 1), buffer_swap=bool(word >> 18 & 1),
                   trigger_out_previous=bool(word >> 19 & 1))


def pack_lut(entries: list[LutEntry]) -> bytes:
    """MBOX_DATA bytes of a pattern LUT (3 bytes per entry)."""
    return b"".join(u24(e.pack()) for e in entries)


def unpack_lut(data: bytes) -> list[LutEntry]:
    if len(data) % 3:
        raise ValueError(f"pattern LUT data of {len(data)} bytes is not whole 3-byte entries")
    return [LutEntry.unpack(read_u24(data, i)) for i in range(0, len(data), 3)]


def max_pattern_number(bit_depth: int) -> int:
    """The largest valid pattern number of a LUT entry at ``bit_depth`` (1 bit: 24 = black)."""
    return 24 if bit_depth == 1 else 24 // bit_depth - 1


def exposure_period(exposure_us: int, period_us: int) -> bytes:
    return struct.pack("<II", exposure_us, period_us)


def read_exposure_period(data: bytes) -> tuple[int, int]:
    return struct.unpack_from("<II", data)


@dataclass(frozen=True)
class PatternConfig:
    """PAT_CONFIG: LUT entries, repeat, patterns per TRIG_OUT2 pulse, image-LUT entries."""

    entries: int
    repeat: bool
    trig_out2_patterns: int
    images: int

    def pack(self) -> bytes:
        for name in ("entries", "trig_out2_patterns", "images"):
            if not 1 <= getattr(self, name) <= 256:
                raise ValueError(f"{name} = {getattr(self, name)} not in 1 ... 256")
        return bytes([self.entries - 1, int(self.repeat), self.trig_out2_patterns - 1,
                      self.images - 1])

    @classmethod
    def unpack(cls, data: bytes) -> PatternConfig:
        return cls(data[0] + 1, bool(data[1]), data[2] + 1, data[3] + 1)


def validation_status(exposure_us: int, period_us: int, entries: list[LutEntry | None],
                      image_lut: list[int | None], images_in_flash: int, config: PatternConfig,
                      source: int = SOURCE_FLASH) -> int:
    """The Validate Data status bits the controller reports for a pattern sequence (the image
    LUT counts only for patterns from flash); None: a LUT entry never written."""
    status = 0
    depth = max((e.bit_depth for e in entries if e is not None), default=1)
    dark = period_us - exposure_us
    if (dark < 0 or 0 < dark < MIN_DARK_US or exposure_us < MIN_EXPOSURE_US[depth - 1]
            or exposure_us <= 0):
        status |= VALID_EXPOSURE
    if 0 < dark < MIN_DARK_US:
        status |= VALID_PERIOD_DIFFERENCE
    flash = source == SOURCE_FLASH
    if (not entries or config.entries != len(entries)
            or any(e is None or not 1 <= e.bit_depth <= 8
                   or e.pattern > max_pattern_number(e.bit_depth) for e in entries)
            or (flash and (config.images != len(image_lut)
                          or any(i is None or not 0 <= i < images_in_flash for i in image_lut)
                          or not entries[0].buffer_swap))):
        status |= VALID_PATTERN_NUMBER
    return status


def describe_validation(status: int) -> tuple[list[str], list[str]]:
    """(errors, warnings) named by the Validate Data status bits."""
    errors = [text for bit, text in VALIDATION_ERRORS.items() if status & bit]
    warnings = [text for bit, text in VALIDATION_WARNINGS.items() if status & bit]
    return errors, warnings


def hardware_faults(hw: int) -> list[str]:
    faults = []
    if not hw & HW_INIT_DONE:
        faults.append("internal initialisation failed")
    if hw & HW_DRC_ERROR:
        faults.append("DMD reset controller error")
    if hw & HW_FORCED_SWAP_ERROR:
        faults.append("forced swap error")
    if hw & HW_SEQUENCE_ABORT:
        faults.append("sequencer abort")
    if hw & HW_SEQUENCE_ERROR:
        faults.append("sequencer error")
    return faults
