"""What loading the scanner's patterns costs on a TI LightCrafter link.

- DLPC900: the 9 fringe patterns at 1920 x 1080 packed into 3 24-bit images and run-length
  encoded (``protocols/dlpc900.py``): encode time beside OpenCV's PNG encoder on the same
  images in the same run, bytes, HID reports, and the time those reports take on the real
  link: USB 1.1 full-speed HID (DLPU018 §1.2), one 64-byte report per 1 ms interrupt frame;
- each driver against its emulator over TCP: ``load_sequence`` (first upload, then the cached
  one the HDR exposures of a station reuse) and ``play``.

Run: .venv/bin/python benchmarks/bench_projector_link.py  (or `make bench`)
"""

from __future__ import annotations

import asyncio
import statistics
import threading
import time
from collections.abc import Callable

import cv2
import numpy as np
from scancell.devices.dlp_projector import DlpProjector
from scancell.devices.dlpc350_projector import Dlpc350Projector
from scancell.devices.dlpc900_projector import Dlpc900Projector, pattern_images
from scancell.protocols import dlp_hid
from scancell.protocols import dlpc900 as c
from scancell.sim.dlp_emulator import DEFAULT_FLASH, DlpEmulatorServer

FRINGES = {"kind": "fringe", "periods": [70, 64, 59], "steps": 3}
REPORT_INTERVAL_S = 1e-3  # USB 1.1 full-speed interrupt endpoint, bInterval 1 ms


def median_time(fn: Callable[[], object], runs: int = 3) -> float:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def encoding() -> None:
    patterns = pattern_images(FRINGES, 1920, 1080)
    images = [c.merge_planes(patterns[i:i + 3]) for i in range(0, 9, 3)]
    encoded = [c.encode_image(im) for im in images]
    t_rle = median_time(lambda: [c.encode_image(im) for im in images])
    bgr = [np.stack([(im >> s & 0xFF).astype(np.uint8) for s in (16, 8, 0)], -1) for im in images]
    t_png = median_time(lambda: [cv2.imencode(".png", b) for b in bgr])
    for im, e in zip(images, encoded, strict=True):
        assert np.array_equal(c.decode_image(e), im)
    nbytes = sum(len(e) for e in encoded)
    messages = sum(len(c.bmp_chunks(e)) for e in encoded)
    reports = sum(len(dlp_hid.to_reports(dlp_hid.encode_request(dlp_hid.Request(c.BMP_LOAD, ch))))
                  for e in encoded for ch in c.bmp_chunks(e))
    raw = 3 * 1920 * 1080 * 3
    print("DLPC900 upload of the 9 fringe patterns (3 images of 1920 x 1080 x 24 bit)")
    print(f"  enhanced RLE: {nbytes} bytes ({raw / nbytes:.0f}x smaller than raw), "
          f"{messages} BMP_LOAD messages, {reports} HID reports")
    print(f"  on USB 1.1 full-speed HID (1 report/ms): {reports * REPORT_INTERVAL_S:.2f} s")
    print(f"  encode: {t_rle * 1e3:.0f} ms; OpenCV PNG of the same images in this run: "
          f"{t_png * 1e3:.0f} ms; ratio {t_rle / t_png:.2f}")


class Emulator:
    def __init__(self, model: str, dmd: tuple[int, int]) -> None:
        self.loop = asyncio.new_event_loop()
        self.server = DlpEmulatorServer(model, port=0, flash=DEFAULT_FLASH, dmd=dmd)
        self.thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self.thread.start()
        asyncio.run_coroutine_threadsafe(self.server.start(), self.loop).result(10)

    def stop(self) -> None:
        asyncio.run_coroutine_threadsafe(self.server.close(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)


async def link(proj: DlpProjector, label: str) -> None:
    await proj.connect()
    t0 = time.perf_counter()
    await proj.load_sequence(FRINGES)
    first = time.perf_counter() - t0
    again = []
    for _ in range(3):
        t0 = time.perf_counter()
        await proj.load_sequence(FRINGES)
        again.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    await proj.play()
    t_play = time.perf_counter() - t0
    await proj.close()
    print(f"  {label}: load {first * 1e3:.0f} ms, again {statistics.median(again) * 1e3:.0f} ms, "
          f"play {t_play * 1e3:.1f} ms")


def main() -> int:
    encoding()
    print("drivers against their emulators over TCP (loopback):")
    e350 = Emulator("dlpc350", (1280, 800))
    e900 = Emulator("dlpc900", (1920, 1080))
    try:
        asyncio.run(link(Dlpc350Projector("p", {"url": f"socket://127.0.0.1:{e350.server.port}",
                                                "flash": DEFAULT_FLASH}), "DLPC350 (flash LUT)"))
        asyncio.run(link(Dlpc900Projector("p", {"url": f"socket://127.0.0.1:{e900.server.port}"}),
                         "DLPC900 (upload)"))
    finally:
        e350.stop()
        e900.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
