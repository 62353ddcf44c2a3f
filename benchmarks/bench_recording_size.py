"""Recording size: how small the camera frames of a station get, losslessly, at the recorder's rate.

Frames: one car-rear station of the simulated cell at full size (2448 x 2048 mono8, the
`realistic` optics: EMVA sensor noise, blur, ambient), both cameras, the 3 x 3 fringe sequence
at two exposures (1 x and 4 x the nominal, as an HDR scan takes them).

Codecs, each lossless, on one core:
- MCAP chunk compression of ``foxglove.RawImage``: none (the reference, today's default before
  issue 37), lz4, zstd at mcap's level (3) and at level 1;
- ``foxglove.CompressedImage`` PNG (OpenCV): zlib level 1 with its default strategy, with the
  RLE strategy, and scancell's (``fg.png_image``: the fast filter set, Huffman only).

Figures: bytes against the uncompressed frames (the ratio the issue asks ≤ 0.40 of), and MB/s of
frames compressed on one core, against the recorder's rate: 2 cameras x 5 MP x 30 fps =
300 MB/s. Then the station's frames through ``SessionFile`` with the default settings: the file's
size against the frames' bytes, and every frame read back pixel for pixel.

Run: .venv/bin/python benchmarks/bench_recording_size.py  (or `make bench`)
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import cv2
import lz4.frame
import numpy as np
import zstandard
from scancell.model.patterns import FringeSequence
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols.encoding import Attachment
from scancell.recorder.reading import samples
from scancell.recorder.session_file import FileSettings, SessionFile
from scancell.sim.cell import SimCell, SimCellConfig

RECORDER_RATE_MB_S = 2 * 2448 * 2048 * 30 / 1e6
RAW = "foxglove.RawImage"
EXPOSURES = (1.0, 4.0)


def station_frames() -> list[np.ndarray]:
    cell = SimCell(SimCellConfig(camera_scale=1.0))
    target = cell.cfg.T_world_from_part[:3, 3] + [-200.0, 0, 0]
    cell.move_joints(cell.ik_for_mcs(cell.mcs_pose_looking_at(target, 600.0)))
    seq = FringeSequence()
    cell.load_sequence(seq)
    n = seq.steps * len(seq.periods)
    return [cell.render(role, k, brightness=b) for b in EXPOSURES for role in ("left", "right")
            for k in range(n)]


def codecs() -> dict[str, object]:
    z3, z1 = zstandard.ZstdCompressor(level=3), zstandard.ZstdCompressor(level=1)
    png = [cv2.IMWRITE_PNG_COMPRESSION, 1]
    return {
        "none (reference)": lambda b, img: b,
        "lz4 chunks": lambda b, img: lz4.frame.compress(b),
        "zstd-3 chunks (mcap)": lambda b, img: z3.compress(b),
        "zstd-1 chunks": lambda b, img: z1.compress(b),
        "PNG-1 CompressedImage": lambda b, img: cv2.imencode(".png", img, png)[1],
        "PNG-RLE CompressedImage": lambda b, img: cv2.imencode(
            ".png", img, [*png, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE])[1],
        "PNG scancell": lambda b, img: fg.png_image(fg.decode_proto(b, RAW)).data,
    }


def main() -> int:
    t0 = time.perf_counter()
    frames = station_frames()
    print(f"{len(frames)} frames of {frames[0].shape[1]} x {frames[0].shape[0]} rendered in "
          f"{time.perf_counter() - t0:.1f} s; lit share {np.mean(frames[0] > 10):.2f}")
    payloads = [fg.encode_proto(fg.raw_image(f, 0, "cam")).payload for f in frames]
    raw = sum(len(p) for p in payloads)
    print(f"\n{'codec':26s} {'ratio':>6s} {'MB/s':>7s} {'x rate':>7s}   (recorder rate "
          f"{RECORDER_RATE_MB_S:.0f} MB/s)")
    for name, fn in codecs().items():
        t = time.perf_counter()
        size = 0
        for p, img in zip(payloads, frames, strict=True):
            size += len(fn(p, img))
        dt = time.perf_counter() - t
        rate = raw / dt / 1e6
        print(f"{name:26s} {size / raw:6.3f} {rate:7.0f} {rate / RECORDER_RATE_MB_S:7.2f}")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "station.mcap"
        f = SessionFile(path, FileSettings())
        t = time.perf_counter()
        for k, p in enumerate(payloads):
            f.write("scancell/bench/dev/cam_left/image", "application/protobuf",
                    RAW, p, Attachment(k, k), k)
        f.close()
        dt = time.perf_counter() - t
        same = all(np.array_equal(fg.image_array(s.decode()), img)
                   for s, img in zip(samples(path), frames, strict=True))
        print(f"\nSessionFile, default settings: {path.stat().st_size / raw:.3f} of the frames' "
              f"bytes, {raw / dt / 1e6:.0f} MB/s, every frame read back identical: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
