"""``scancell worker scan``: reassembles scans from the bus, decodes them, publishes the clouds.

Input: ``dev/*/image`` frames whose attachment meta is a ``scancell.ScanFrameMeta`` (``cmd/scan``
publishes them). Output per scan: ``scan/<station>/cloud`` (foxglove.PointCloud, frame
``mcs_<station>``: the scanner frame at that station,
mm, fields x, y, z, quality, intensity) and ``scan/<station>/result`` (``scancell.ScanResult``).
The decoding is the same :class:`ScanDecoder` as ``scancell decode``.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scancell.analysis.phase import DecodeError
from scancell.analysis.phase_response import response_warning
from scancell.analysis.scanner import ScanDecoder, ScanResult
from scancell.analysis.stereo_calibration import CalibrationError, StereoCalibration
from scancell.bus.protocol import BusLike, Latched
from scancell.model.patterns import PROJECTOR_WIDTH, FringeSequence
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.encoding import Attachment, EncodingError
from scancell.workers.base import ThreadedWorker

log = logging.getLogger(__name__)


@dataclass
class PendingScan:
    scan_id: str
    station: str
    sequence: FringeSequence
    patterns: int
    frames: dict[str, dict[int, np.ndarray]] = field(default_factory=lambda: {"left": {}, "right": {}})
    first_seen: float = field(default_factory=time.monotonic)
    stamp_ns: int = 0
    #: The job that took the scan and its kind (None: a plain cmd/scan).
    job_id: str | None = None
    job_kind: str | None = None

    def complete(self) -> bool:
        return all(len(self.frames[r]) == self.patterns for r in ("left", "right"))

    def missing(self) -> str:
        return "; ".join(f"{r}: patterns {sorted(set(range(self.patterns)) - set(f))}"
                         for r, f in self.frames.items() if len(f) < self.patterns)


class ScanAssembler:
    """Collects frames by scan id; a scan is handed out once every pattern of both roles is in."""

    def __init__(self, max_age_s: float = 120.0) -> None:
        self.max_age_s = max_age_s
        self.pending: dict[str, PendingScan] = {}

    def add(self, meta: dict[str, Any], image: np.ndarray, stamp_ns: int) -> PendingScan | None:
        try:
            scan_id, role, k = str(meta["scan_id"]), str(meta["role"]), int(meta["pattern"])
            seq = FringeSequence(tuple(float(p) for p in meta["periods"]), int(meta["steps"]))
            n = int(meta["patterns"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"frame meta is not a ScanFrameMeta: {exc}") from None
        if role not in ("left", "right") or not 0 <= k < n or n != len(seq):
            raise ValueError(f"scan {scan_id}: bad role {role!r} or pattern {k} of {n}")
        scan = self.pending.setdefault(scan_id, PendingScan(
            scan_id, str(meta.get("station", "0")), seq, n, job_id=meta.get("job_id"),
            job_kind=meta.get("job_kind")))
        scan.frames[role][k] = image
        if k == 0 and role == "left":
            scan.stamp_ns = stamp_ns
        if scan.complete():
            return self.pending.pop(scan_id)
        return None

    def expire(self) -> list[PendingScan]:
        now = time.monotonic()
        old = [s for s in self.pending.values() if now - s.first_seen > self.max_age_s]
        for s in old:
            del self.pending[s.scan_id]
        return old


def result_message(scan: PendingScan, result: ScanResult | None, error: str | None) -> dict[str, Any]:
    body: dict[str, Any] = {"scan_id": scan.scan_id, "station": scan.station, "ok": error is None,
                            "error": error}
    if result is not None:
        body.update(points=len(result.cloud),
                    valid_share={"left": round(result.left.valid_share, 4),
                                 "right": round(result.right.valid_share, 4)},
                    response={"left": result.left.response, "right": result.right.response},
                    timings_s={k: round(v, 4) for k, v in result.timings.items()})
    return body


class ScanWorker(ThreadedWorker[PendingScan]):
    """Subscribes on ``bus``, decodes complete scans in a worker thread, publishes results."""

    thread_name = "scan-worker"

    def __init__(self, bus: BusLike, calib: StereoCalibration,
                 projector_width: int = PROJECTOR_WIDTH) -> None:
        super().__init__(bus)
        self.calib = calib
        self.projector_width = projector_width
        self.assembler = ScanAssembler()
        self._decoders: dict[FringeSequence, ScanDecoder] = {}
        self._lock = threading.Lock()
        self._calib_pub: Latched | None = None
        self.done = 0

    def on_start(self) -> None:
        self._calib_pub = self.bus.latched(self.bus.keys.stereo)
        self._calib_pub.publish(messages.encode_json(
            {**self.calib.to_json(), "projector_width": self.projector_width},
            "scancell.StereoCalibration"))
        self.subscribe(self.bus.keys.dev("*", "image"), self._on_frame,
                       lambda key, exc: log.warning("%s: %s", key, exc))

    def on_stop(self) -> None:
        if self._calib_pub is not None:
            self._calib_pub.close()

    def _on_frame(self, sample: Any) -> None:
        meta = sample.attachment.meta
        if "scan_id" not in meta:
            return  # a live image, not part of a scan
        try:
            image = fg.image_array(sample.decode())
            with self._lock:
                complete = self.assembler.add(meta, image, sample.attachment.stamp_ns)
                expired = self.assembler.expire()
        except (ValueError, EncodingError) as exc:
            log.warning("%s: dropped frame: %s", sample.key, exc)
            return
        for scan in expired:
            log.error("scan %s (station %s) incomplete after %.0f s, dropped: %s", scan.scan_id,
                      scan.station, self.assembler.max_age_s, scan.missing())
            self._publish_result(scan, None, f"incomplete: {scan.missing()}")
        if complete is not None:
            self.submit(complete)

    def decoder(self, seq: FringeSequence) -> ScanDecoder:
        if seq not in self._decoders:
            self._decoders[seq] = ScanDecoder(self.calib, seq, self.projector_width)
        return self._decoders[seq]

    def process(self, scan: PendingScan) -> ScanResult | None:
        left = [scan.frames["left"][k] for k in range(scan.patterns)]
        right = [scan.frames["right"][k] for k in range(scan.patterns)]
        try:
            result = self.decoder(scan.sequence).decode(left, right)
        except (DecodeError, CalibrationError) as exc:
            log.error("scan %s (station %s): %s", scan.scan_id, scan.station, exc)
            self._publish_result(scan, None, str(exc))
            return None
        c = result.cloud
        fields = {"quality": c.quality, "intensity": c.intensity}
        if c.uncertainty is not None:
            fields["uncertainty"] = c.uncertainty
        msg = fg.point_cloud(c.points, scan.stamp_ns or messages.now_ns(), f"mcs_{scan.station}",
                             fields)
        meta = {"scan_id": scan.scan_id, "station": scan.station, "points": len(c),
                "job_id": scan.job_id, "job_kind": scan.job_kind,
                "response": {"left": result.left.response, "right": result.right.response}}
        for side, pm in (("left", result.left), ("right", result.right)):
            if pm.response and not pm.response["linear"]:
                log.warning("scan %s station %s: %s", scan.scan_id, scan.station,
                            response_warning(side, pm.response))
        self.bus.publish(self.bus.keys.scan_cloud(scan.station), fg.encode_proto(msg),
                         Attachment(scan.stamp_ns or messages.now_ns(), self.done, None, meta))
        self._publish_result(scan, result, None)
        log.info("scan %s station %s: %d points in %.2f s", scan.scan_id, scan.station, len(c),
                 result.timings["total"])
        return result

    def _publish_result(self, scan: PendingScan, result: ScanResult | None, error: str | None) -> None:
        self.bus.publish_json(self.bus.keys.scan_result(scan.station),
                              result_message(scan, result, error), "scancell.ScanResult")

    def handle(self, scan: PendingScan) -> None:
        try:
            self.process(scan)
        finally:
            self.done += 1
