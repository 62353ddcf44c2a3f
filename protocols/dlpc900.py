"""The DLPC900 (LightCrafter 6500 / 9000) USB commands a scanner needs, and its enhanced
run-length image format. Pure: no I/O.

After TI's DLPC900 programmer's guide (DLPU018): pattern-on-the-fly mode, in which the host
uploads 24-bit images (each carrying 24 one-bit or 3 eight-bit patterns) and defines a pattern
LUT over them. Multi-byte fields are LSB first.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from scancell.protocols.dlp_hid import GET_VERSION as GET_VERSION
from scancell.protocols.dlp_hid import PAT_START_STOP as PAT_START_STOP
from scancell.protocols.dlp_hid import START as START
from scancell.protocols.dlp_hid import STOP as STOP
from scancell.protocols.dlp_hid import read_u24, u24

VID, PID = 0x0451, 0xC900

READ_ERROR_CODE = 0x0100        # read: 1 byte, the last command's error code
READ_ERROR_DESCRIPTION = 0x0101  # read: ASCII text of the last error
POWER_MODE = 0x0200             # 1 byte: 0 normal, 1 standby, 2 reset
DMD_IDLE = 0x0201               # 1 byte: 0 normal, 1 idle (DLPU018 2.3.1.2 DMD standby and idle)
CURTAIN_COLOR = 0x1100          # 6 bytes: red, green, blue intensity (u16 each)
STATUS_HW = 0x1A0A
STATUS_SYS = 0x1A0B
STATUS_MAIN = 0x1A0C
DISP_MODE = 0x1A1B              # 1 byte: 0 video, 1 pre-stored pattern, 2 video pattern, 3 on-the-fly
TRIG_OUT1_CTL = 0x1A1D          # 5 bytes: invert, rising delay (s16 us), falling delay (s16 us)
TRIG_OUT2_CTL = 0x1A1E          # 5 bytes: as TRIG_OUT1_CTL (TI's DLPC900 API writes five)
BMP_LOAD_INIT = 0x1A2A          # 6 bytes: image index (u16), bytes incl. the 48-byte header (u32)
BMP_LOAD = 0x1A2B               # u16 chunk length + chunk
LUT_CONFIG = 0x1A31             # 6 bytes: LUT entries (u16, 11 bits), patterns to display (u32)
LUT_DEFINE = 0x1A34             # 12 bytes, see LutDefinition
MIN_EXPOSURE = 0x1A42           # read: minimum exposure (us) per bit depth: 8 x u16, 4 x u32

NAMES = {
    READ_ERROR_CODE: "READ_ERROR_CODE", READ_ERROR_DESCRIPTION: "READ_ERROR_DESCRIPTION",
    POWER_MODE: "POWER_MODE", DMD_IDLE: "DMD_IDLE", GET_VERSION: "GET_VERSION",
    CURTAIN_COLOR: "CURTAIN_COLOR",
    STATUS_HW: "STATUS_HW", STATUS_SYS: "STATUS_SYS", STATUS_MAIN: "STATUS_MAIN",
    DISP_MODE: "DISP_MODE", TRIG_OUT1_CTL: "TRIG_OUT1_CTL", TRIG_OUT2_CTL: "TRIG_OUT2_CTL",
    PAT_START_STOP: "PAT_START_STOP", BMP_LOAD_INIT: "BMP_LOAD_INIT", BMP_LOAD: "BMP_LOAD",
    LUT_CONFIG: "LUT_CONFIG", LUT_DEFINE: "LUT_DEFINE", MIN_EXPOSURE: "MIN_EXPOSURE",
}
WRITE_LENGTH: dict[int, int | None] = {
    POWER_MODE: 1, DMD_IDLE: 1, CURTAIN_COLOR: 6, DISP_MODE: 1, TRIG_OUT1_CTL: 5, TRIG_OUT2_CTL: 5,
    PAT_START_STOP: 1, BMP_LOAD_INIT: 6, BMP_LOAD: None, LUT_CONFIG: 6, LUT_DEFINE: 12,
}
READABLE = {READ_ERROR_CODE, READ_ERROR_DESCRIPTION, POWER_MODE, DMD_IDLE, GET_VERSION,
            CURTAIN_COLOR,
            STATUS_HW, STATUS_SYS, STATUS_MAIN, DISP_MODE, TRIG_OUT1_CTL, TRIG_OUT2_CTL,
            LUT_CONFIG, MIN_EXPOSURE}

MODE_VIDEO, MODE_PRESTORED, MODE_VIDEO_PATTERN, MODE_ON_THE_FLY = 0, 1, 2, 3
#: Largest pattern LUT (DLPU018 LUT configuration: 400 entries for every DMD but the DLP5500).
MAX_LUT_ENTRIES = 400
#: 24-bit images the on-the-fly memory holds (DLPU018 BMP load: image index 0 ... 17).
MAX_IMAGES = 18
#: Largest BMP_LOAD chunk: 512-byte buffer minus the command and the chunk length.
MAX_CHUNK = 504

#: Minimum pattern exposure (us) per bit depth 1 ... 8 for the DLP6500 DMD (DLPU018, pattern
#: exposure table); the controller reports its own with MIN_EXPOSURE.
MIN_EXPOSURE_US = (105, 304, 394, 823, 1215, 1487, 1998, 4046)
MAX_EXPOSURE_US = (1 << 24) - 1

#: READ_ERROR_CODE values (DLPU018, Read Error Code).
ERROR_CODES = {
    0: "no error", 1: "batch file checksum error", 2: "device failure",
    3: "invalid command number", 4: "incompatible controller and DMD combination",
    5: "command not allowed in the current mode", 6: "invalid command parameter",
    7: "item referred to by the parameter is not present", 8: "out of resource (RAM or flash)",
    9: "invalid BMP compression type", 10: "pattern bit number out of range",
    11: "pattern BMP not present", 12: "pattern dark time out of range",
    13: "signal delay parameter out of range", 14: "pattern exposure time out of range",
    15: "pattern number out of range", 16: "invalid pattern definition",
    17: "pattern image memory address out of range", 255: "internal error",
}
ERR_INVALID_COMMAND, ERR_NOT_ALLOWED, ERR_INVALID_PARAMETER = 3, 5, 6
ERR_NOT_PRESENT, ERR_OUT_OF_RESOURCE, ERR_BAD_COMPRESSION = 7, 8, 9
ERR_BIT_NUMBER, ERR_BMP_MISSING, ERR_DARK_TIME = 10, 11, 12
ERR_EXPOSURE, ERR_PATTERN_NUMBER, ERR_PATTERN_DEFINITION = 14, 15, 16
#: The codes that mean "this pattern sequence breaks a rule" rather than "the device failed".
RULE_ERRORS = {ERR_BIT_NUMBER, ERR_DARK_TIME, ERR_EXPOSURE, ERR_PATTERN_NUMBER,
               ERR_PATTERN_DEFINITION}

HW_INIT_DONE = 0x01
HW_INCOMPATIBLE = 0x02
HW_DRC_ERROR = 0x04
HW_FORCED_SWAP_ERROR = 0x08
HW_SEQUENCE_ABORT = 0x40
HW_SEQUENCE_ERROR = 0x80
MAIN_DMD_PARKED = 0x01
MAIN_SEQUENCE_RUNNING = 0x02


@dataclass(frozen=True)
class LutDefinition:
    """One Pattern Display LUT Definition (12 bytes). ``bit_position`` is the first bit of the
    pattern in its 24-bit image (0 ... 23; an 8-bit pattern at 0, 8 or 16)."""

    index: int
    exposure_us: int
    bit_depth: int = 8
    led: int = 0b111
    wait_trigger: bool = False
    dark_us: int = 0
    disable_trigger2: bool = False
    image_index: int = 0
    bit_position: int = 0
    clear_after: bool = True

    def pack(self) -> bytes:
        if not 1 <= self.bit_depth <= 8:
            raise ValueError(f"bit depth {self.bit_depth} not in 1 ... 8")
        options = (int(self.clear_after) | (self.bit_depth - 1) << 1 | (self.led & 7) << 4
                   | int(self.wait_trigger) << 7)
        last = (self.image_index & 0x7FF) | (self.bit_position & 0x1F) << 11
        return (struct.pack("<H", self.index) + u24(self.exposure_us) + bytes([options])
                + u24(self.dark_us) + bytes([int(self.disable_trigger2)])
                + struct.pack("<H", last))

    @classmethod
    def unpack(cls, data: bytes) -> LutDefinition:
        if len(data) != 12:
            raise ValueError(f"a LUT definition is 12 bytes, got {len(data)}")
        (index,) = struct.unpack_from("<H", data, 0)
        options = data[5]
        (last,) = struct.unpack_from("<H", data, 10)
        return cls(index=index, exposure_us=read_u24(data, 2), bit_depth=((options >> 1) & 7) + 1,
                   led=(options >> 4) & 7, wait_trigger=bool(options >> 7),
                   dark_us=read_u24(data, 6), disable_trigger2=bool(data[9] & 1),
                   image_index=last & 0x7FF, bit_position=last >> 11,
                   clear_after=bool(options & 1))


def lut_config(entries: int, patterns: int) -> bytes:
    """LUT_CONFIG: ``entries`` LUT entries, ``patterns`` to display (0: repeat forever)."""
    if not 1 <= entries <= MAX_LUT_ENTRIES:
        raise ValueError(f"{entries} LUT entries not in 1 ... {MAX_LUT_ENTRIES}")
    return struct.pack("<HI", entries, patterns)


def read_lut_config(data: bytes) -> tuple[int, int]:
    entries, patterns = struct.unpack_from("<HI", data)
    return entries & 0x7FF, patterns


def bmp_load_init(image_index: int, size: int) -> bytes:
    return struct.pack("<HI", image_index, size)


def bmp_chunks(encoded: bytes) -> list[bytes]:
    """BMP_LOAD data of each message: chunk length (u16) and up to 504 bytes."""
    return [struct.pack("<H", len(c)) + c
            for c in (encoded[i:i + MAX_CHUNK] for i in range(0, len(encoded), MAX_CHUNK))]


def min_exposures(values: tuple[int, ...] = MIN_EXPOSURE_US,
                  extended: tuple[int, ...] = (0, 0, 0, 0)) -> bytes:
    """MIN_EXPOSURE reply: 1 ... 8-bit minima (u16), then 10, 12, 14, 16-bit ones (u32)."""
    return struct.pack("<8H4I", *values, *extended)


def read_min_exposures(data: bytes) -> tuple[int, ...]:
    """The 1 ... 8-bit minimum exposures (us) of a MIN_EXPOSURE reply."""
    return struct.unpack_from("<8H", data)


def exposure_problem(d: LutDefinition) -> tuple[int, str] | None:
    """(error code, message) if a pattern definition breaks the exposure rules, else None."""
    lo = MIN_EXPOSURE_US[d.bit_depth - 1]
    if not lo <= d.exposure_us <= MAX_EXPOSURE_US:
        return ERR_EXPOSURE, (f"pattern {d.index}: exposure {d.exposure_us} us outside "
                              f"{lo} ... {MAX_EXPOSURE_US} us for {d.bit_depth}-bit patterns")
    # DLPU018's own pattern-on-the-fly example defines a 2-bit pattern at bit position 1: a
    # pattern may start at any bit that leaves its depth inside the 24-bit image
    if d.bit_position + d.bit_depth > 24:
        return ERR_BIT_NUMBER, (f"pattern {d.index}: bits {d.bit_position} ... "
                                f"{d.bit_position + d.bit_depth - 1} pass the 24-bit image")
    return None


# ---------------------------------------------------------------- images (DLPU018 §2.4)
HEADER_BYTES = 48
SIGNATURE = b"Spld"
UNCOMPRESSED, RLE, ENHANCED_RLE = 0, 1, 2


def merge_planes(patterns: list[np.ndarray], bit_depth: int = 8) -> np.ndarray:
    """Pack up to 24 // bit_depth patterns (H x W, values < 2**bit_depth) into one 24-bit image
    (uint32): pattern i in bits ``i*bit_depth ...``."""
    if not patterns or len(patterns) * bit_depth > 24:
        raise ValueError(f"{len(patterns)} patterns of {bit_depth} bits do not fill one 24-bit "
                         f"image")
    out = np.zeros(patterns[0].shape, np.uint32)
    for i, p in enumerate(patterns):
        out |= (np.asarray(p, np.uint32) & ((1 << bit_depth) - 1)) << (i * bit_depth)
    return out


def plane(image24: np.ndarray, bit_position: int, bit_depth: int) -> np.ndarray:
    """The pattern stored at ``bit_position`` of a 24-bit image, as uint8."""
    return ((image24 >> bit_position) & ((1 << bit_depth) - 1)).astype(np.uint8)


def _count(n: int) -> bytes:
    if not 0 < n < 1 << 15:
        raise ValueError(f"run length {n} cannot be encoded")
    return bytes([n]) if n < 128 else bytes([(n & 0x7F) | 0x80, n >> 7])


def _pixel(v: int) -> bytes:
    return bytes([(v >> 16) & 0xFF, (v >> 8) & 0xFF, v & 0xFF])


def _run_end(mask: np.ndarray, j: int) -> int:
    """The first index from ``j`` on where ``mask`` is False (len(mask) if none)."""
    rest = mask[j:]
    k = int(np.argmin(rest))
    return len(mask) if rest[k] else j + k


def _encode_row(row: np.ndarray, prev: np.ndarray | None) -> bytearray:
    w = len(row)
    if prev is not None and np.array_equal(row, prev):
        return bytearray(b"\x00\x01" + _count(w) + b"\x00\x00")
    same_prev = np.zeros(w, bool) if prev is None else row == prev
    same_next = np.append(row[1:] == row[:-1], False)
    fresh = ~same_prev & ~same_next  # neither copied nor part of a repeat
    out = bytearray()
    j = 0
    while j < w:
        if same_prev[j]:
            k = _run_end(same_prev, j)
            out += b"\x00\x01" + _count(k - j)
        elif same_next[j]:
            k = _run_end(same_next & ~same_prev, j) + 1
            out += _count(k - j) + _pixel(int(row[j]))
        else:
            k = _run_end(fresh, j)
            if k - j == 1:
                out += b"\x01" + _pixel(int(row[j]))
            else:
                out += b"\x00" + _count(k - j) + b"".join(_pixel(int(v)) for v in row[j:k])
        j = k
    return out + b"\x00\x00"


def encode_image(image24: np.ndarray) -> bytes:
    """A 24-bit image (H x W uint32) in the enhanced run-length format, with its 48-byte header,
    padded to a multiple of 4 bytes."""
    image = np.asarray(image24, np.uint32)
    h, w = image.shape
    body = bytearray()
    for i in range(h):
        body += _encode_row(image[i], image[i - 1] if i else None)
    body += b"\x00\x01\x00"
    size = HEADER_BYTES + len(body)
    size += -size % 4
    header = (SIGNATURE + struct.pack("<HHI", w, h, size) + b"\xff" * 8 + b"\0\0\0\0"
              + bytes([0, ENHANCED_RLE, 1]) + bytes(21))
    return (header + body).ljust(size, b"\0")


def read_header(data: bytes) -> tuple[int, int, int, int]:
    """(width, height, total bytes, compression) of an image's 48-byte header."""
    if len(data) < HEADER_BYTES:
        raise ValueError(f"image of {len(data)} bytes is shorter than its 48-byte header")
    if data[:4] != SIGNATURE:
        raise ValueError(f"image signature {data[:4]!r} is not {SIGNATURE!r}")
    w, h, size = struct.unpack_from("<HHI", data, 4)
    return w, h, size, data[25]


def decode_image(data: bytes) -> np.ndarray:
    """Decode an uncompressed or enhanced-RLE image (with header) to H x W uint32."""
    w, h, _, compression = read_header(data)
    body = memoryview(data)[HEADER_BYTES:]
    if compression == UNCOMPRESSED:
        raw = np.frombuffer(body[:w * h * 3], np.uint8)
        if raw.size < w * h * 3:
            raise ValueError(f"uncompressed image truncated: {raw.size} of {w * h * 3} bytes")
        px = raw.reshape(h, w, 3).astype(np.uint32)
        return px[..., 0] << 16 | px[..., 1] << 8 | px[..., 2]
    if compression != ENHANCED_RLE:
        raise ValueError(f"compression type {compression} is not supported (0 or 2)")
    out = np.zeros((h, w), np.uint32)
    i = x = y = 0

    def count() -> int:
        nonlocal i
        n = body[i]
        i += 1
        if n & 0x80:
            n = (n & 0x7F) | body[i] << 7
            i += 1
        return n

    def pixel() -> int:
        nonlocal i
        v = body[i] << 16 | body[i + 1] << 8 | body[i + 2]
        i += 3
        return v

    try:
        while True:
            if body[i] != 0:
                n = count()
                out[y, x:x + n] = pixel()
                x += n
            elif body[i + 1] == 0:
                i += 2
                y, x = y + 1, 0
            elif body[i + 1] == 1:
                i += 2
                n = count()
                if n == 0:
                    break
                if y == 0:
                    raise ValueError("copy from the previous line in the first line")
                out[y, x:x + n] = out[y - 1, x:x + n]
                x += n
            else:
                i += 1
                n = count()
                for _ in range(n):
                    out[y, x] = pixel()
                    x += 1
            if x > w or y > h:
                raise ValueError(f"run overflows the {w} x {h} image at line {y}")
    except IndexError:
        raise ValueError(f"image data ends before the end-of-image code (line {y} of {h})") \
            from None
    return out
