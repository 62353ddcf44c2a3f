"""``scancell worker scan``: reassembles scans from the bus, decodes them, publishes the clouds.

Input: ``dev/*/image`` frames whose attachment meta is a ``scancell.ScanFrameMeta`` (``cmd/scan``
publishes them). Output per scan: ``scan/<station>/cloud`` (foxglove.PointCloud, frame
``mcs_<station>``: the scanner frame at that station; float32 x, y, z and uncertainty in mm;
quality, the smaller of the two cameras' fringe modulation, and intensity, the left camera's
background, both in whole DN as uint16: :func:`whole_dn`) and ``scan/<station>/result``
(``scancell.ScanResult``).
The decoding is the same :class:`ScanDecoder` as ``scancell decode``.

Any number of scan workers share the work (``workers/work_share.py``): every worker assembles
every scan, the scan's owner among the live workers decodes it, the others hold it until its
result is on the bus. When the owner is gone first, the next owner waits a second for what the
gone worker sent last (``WorkShare.grace_s``), then decodes the scan from what it holds (publishing
the cloud only if the gone worker had not) and names the gone worker in the
result (``taken_over_from``). Each scan is decoded once, and a taken-over scan gives the same
cloud, byte for byte.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scancell.analysis.phase import DecodeError, DecodeSettings
from scancell.analysis.phase_response import response_warning
from scancell.analysis.projector_response import ProjectorResponse, ResponseCalibrationError, fit_response
from scancell.analysis.scanner import ScanDecoder, ScanResult
from scancell.analysis.stereo_calibration import CalibrationError, StereoCalibration
from scancell.bus.protocol import BusLike, Latched
from scancell.bus.recent_ids import RecentIds
from scancell.model.patterns import PROJECTOR_WIDTH, FringeSequence
from scancell.protocols import foxglove_schemas as fg
from scancell.protocols import messages
from scancell.protocols.encoding import Attachment, EncodingError
from scancell.workers.base import ThreadedWorker, publish_worker_status
from scancell.workers.work_share import WorkShare

log = logging.getLogger(__name__)


def whole_dn(values: np.ndarray) -> np.ndarray:
    """Per-point image levels (DN) rounded to whole DN, as uint16 (any sensor up to 16 bits):
    a cloud's quality and intensity describe it, they are not measured, and as float32 noise
    they took 0.3 of a station cloud's compressed bytes in a recording (issue 37)."""
    return np.clip(np.rint(values), 0, 65535).astype(np.uint16)


@dataclass
class PendingScan:
    """A scan being reassembled: a fringe scan (``sequence``, any number of exposures) or a
    projector-response calibration's uniform ``levels``."""

    scan_id: str
    station: str
    sequence: FringeSequence | None
    patterns: int
    #: role -> (exposure index, pattern) -> image
    frames: dict[str, dict[tuple[int, int], np.ndarray]] = field(
        default_factory=lambda: {"left": {}, "right": {}})
    first_seen: float = field(default_factory=time.monotonic)
    stamp_ns: int = 0
    #: The job that took the scan and its kind (None: a plain cmd/scan).
    job_id: str | None = None
    job_kind: str | None = None
    exposures: int = 1
    exposure_us: dict[int, float | None] = field(default_factory=dict)
    precompensated: bool = False
    levels: list[int] | None = None
    #: another worker's cloud of this scan is on the bus already (its result is not)
    cloud_seen: bool = False
    #: the gone worker whose scan this worker took over
    taken_over_from: str | None = None

    def expected(self) -> set[tuple[int, int]]:
        return {(e, k) for e in range(self.exposures) for k in range(self.patterns)}

    def complete(self) -> bool:
        return all(len(self.frames[r]) == self.patterns * self.exposures for r in ("left", "right"))

    def missing(self) -> str:
        return "; ".join(f"{r}: (exposure, pattern) {sorted(self.expected() - set(f))}"
                         for r, f in self.frames.items()
                         if len(f) < self.patterns * self.exposures)

    def image_sets(self, role: str) -> list[list[np.ndarray]]:
        """One list of images per exposure, in pattern order."""
        return [[self.frames[role][e, k] for k in range(self.patterns)]
                for e in range(self.exposures)]


class ScanAssembler:
    """Collects frames by scan id; a scan is handed out once every pattern of both roles is in."""

    def __init__(self, max_age_s: float = 120.0) -> None:
        self.max_age_s = max_age_s
        self.pending: dict[str, PendingScan] = {}

    def add(self, meta: dict[str, Any], image: np.ndarray, stamp_ns: int) -> PendingScan | None:
        try:
            scan_id, role, k = str(meta["scan_id"]), str(meta["role"]), int(meta["pattern"])
            n = int(meta["patterns"])
            levels = [int(v) for v in meta["levels"]] if "levels" in meta else None
            seq = None if levels is not None else FringeSequence(
                tuple(float(p) for p in meta["periods"]), int(meta["steps"]))
            e, n_exp = int(meta.get("exposure_index", 0)), int(meta.get("exposures", 1))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"frame meta is not a ScanFrameMeta: {exc}") from None
        size = len(levels) if levels is not None else len(seq)  # type: ignore[arg-type]
        if role not in ("left", "right") or not 0 <= k < n or n != size:
            raise ValueError(f"scan {scan_id}: bad role {role!r} or pattern {k} of {n}")
        if not 0 <= e < n_exp <= 16:
            raise ValueError(f"scan {scan_id}: bad exposure {e} of {n_exp}")
        scan = self.pending.setdefault(scan_id, PendingScan(
            scan_id, str(meta.get("station", "0")), seq, n, job_id=meta.get("job_id"),
            job_kind=meta.get("job_kind"), exposures=n_exp,
            precompensated=bool(meta.get("precompensated", False)), levels=levels))
        if scan.exposures != n_exp or scan.patterns != n:
            raise ValueError(f"scan {scan_id}: frame of {n_exp} exposures x {n} patterns in a "
                             f"scan of {scan.exposures} x {scan.patterns}")
        scan.frames[role][e, k] = image
        scan.exposure_us[e] = meta.get("exposure_us")
        if k == 0 and e == 0 and role == "left":
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


#: fringe modulation (DN, at the pixel's best exposure) above which a pixel counts as lit by the
#: projector: the noise alone gives well under 1 DN
LIT_MODULATION_DN = 3.0


def lit_share(pm: Any) -> float:
    """Share of a camera's pixels the projector lights (modulation above the noise)."""
    return float(np.mean(pm.modulation >= LIT_MODULATION_DN))


def result_message(scan: PendingScan, result: ScanResult | None, error: str | None,
                   worker: str | None = None) -> dict[str, Any]:
    body: dict[str, Any] = {"scan_id": scan.scan_id, "station": scan.station, "ok": error is None,
                            "error": error, "worker": worker,
                            "taken_over_from": scan.taken_over_from}
    if result is not None:
        lit = {side: lit_share(pm) for side, pm in (("left", result.left), ("right", result.right))}
        body.update(points=len(result.cloud),
                    lit_share={k: round(v, 4) for k, v in lit.items()},
                    decoded_of_lit={side: round(pm.valid_share / lit[side], 4) if lit[side] else 0.0
                                    for side, pm in (("left", result.left),
                                                     ("right", result.right))},
                    valid_share={"left": round(result.left.valid_share, 4),
                                 "right": round(result.right.valid_share, 4)},
                    decode_limits={side: {"noise_dn": round(pm.noise_dn, 4),
                                          "min_modulation_dn": round(pm.min_modulation_dn, 3)}
                                   for side, pm in (("left", result.left), ("right", result.right))
                                   if pm.noise_dn is not None and pm.min_modulation_dn is not None},
                    response={"left": result.left.response, "right": result.right.response},
                    exposures=scan.exposures, precompensated=scan.precompensated,
                    timings_s={k: round(v, 4) for k, v in result.timings.items()})
    return body


class ScanWorker(ThreadedWorker[PendingScan]):
    """Subscribes on ``bus``, decodes complete scans in a worker thread, publishes results."""

    thread_name = "scan-worker"

    def __init__(self, bus: BusLike, calib: StereoCalibration,
                 projector_width: int = PROJECTOR_WIDTH, response_path: Path | None = None,
                 worker_id: str | None = None, settings: DecodeSettings | None = None) -> None:
        super().__init__(bus)
        #: the decode settings of every scan (a cell's ``[scanner] decode_limits`` on top)
        self.settings = settings or DecodeSettings()
        self.share = WorkShare(bus, "scan", worker_id)
        self.share.on_departure = self._take_over
        #: complete scans another live worker owns, by scan id, until their result is seen
        self.standby: dict[str, PendingScan] = {}
        #: scan ids whose result is on the bus, and whose cloud is (the last few thousand)
        self._finished = RecentIds()
        self._clouds_seen = RecentIds()
        self._published = RecentIds()  # the scans this worker answered
        self._answering: Any = None
        #: scan ids this worker decoded, in order
        self.decoded: list[str] = []
        self._decoding: PendingScan | None = None
        self._status_pub: Latched | None = None
        self.calib = calib
        #: where the projector response is kept: next to the stereo calibration
        self.response_path = response_path
        self._response_pub: Latched | None = None
        self.projector_width = projector_width
        self.assembler = ScanAssembler()
        self._decoders: dict[FringeSequence, ScanDecoder] = {}
        #: (job, camera) whose far-from-linear response was told once; later scans say it in
        #: the log's INFO (a 323-station job said it 646 times)
        self._response_told = RecentIds()
        self._lock = threading.Lock()
        self._calib_pub: Latched | None = None
        self.done = 0

    def on_start(self) -> None:
        k = self.bus.keys
        self.share.watch()
        self.subscribe(k.scan_result("*"), self._on_result_seen)
        self.subscribe(k.scan_cloud("*"), self._on_cloud_seen)
        self.subscribe(k.projector_response_result, self._on_result_seen)
        self._calib_pub = self.bus.latched(self.bus.keys.stereo)
        self._calib_pub.publish(messages.encode_json(
            {**self.calib.to_json(), "projector_width": self.projector_width},
            "scancell.StereoCalibration"))
        self.subscribe(self.bus.keys.dev("*", "image"), self._on_frame,
                       lambda key, exc: log.warning("%s: %s", key, exc))
        if self.response_path is not None and self.response_path.is_file():
            try:
                self._publish_response(ProjectorResponse.read(self.response_path))
            except ResponseCalibrationError as exc:
                log.error("%s; fringes will not be pre-compensated", exc)
        self._answering = self.bus.answer(k.worker_answered("scan", self.share.worker_id),
                                          self._on_asked, "scancell.WorkerAnswered")
        # the token last (WorkShare.join)
        self.share.join()
        self._status_pub = self.bus.latched(
            self.bus.keys.worker_status("scan", self.share.worker_id))
        self.publish_status()

    def on_stop(self) -> None:
        self.share.stop()
        if self._answering is not None:
            try:
                self._answering.undeclare()
            except Exception as exc:  # a closed session
                log.debug("scan worker: %s", exc)
        for pub in (self._calib_pub, self._response_pub, self._status_pub):
            if pub is not None:
                pub.close()

    def _publish_response(self, response: ProjectorResponse) -> None:
        if self._response_pub is None:
            self._response_pub = self.bus.latched(self.bus.keys.projector_response)
        self._response_pub.publish(messages.encode_json(response.to_json(),
                                                        "scancell.ProjectorResponse"))

    def calibrate_response(self, scan: PendingScan) -> dict[str, Any]:
        """Fit the projector response from a calibrate_projector job's level frames; on success
        store it (the previous file is replaced atomically) and latch it; either way answer on
        calib/projector_response/result. A failed fit keeps the previous response."""
        body: dict[str, Any] = {"job_id": scan.job_id, "ok": False, "error": None}
        try:
            response = fit_response(scan.levels or [], {r: scan.image_sets(r)[0]
                                                        for r in ("left", "right")}, scan.job_id)
            if self.response_path is not None:
                response.write(self.response_path)
            self._publish_response(response)
            body.update(ok=True, gamma=response.gamma, fit_rms=response.fit_rms,
                        levels=response.levels, response=response.response,
                        pixels=response.pixels,
                        file=str(self.response_path) if self.response_path else None)
            log.info("projector response from %s: gamma %.3f (fit RMS %.4f), stored in %s",
                     scan.job_id, response.gamma, response.fit_rms, self.response_path)
        except ResponseCalibrationError as exc:
            body["error"] = str(exc)
            log.error("projector response from %s: %s; the previous response is kept",
                      scan.job_id, exc)
        except OSError as exc:
            body["error"] = f"{self.response_path}: cannot write: {exc.strerror or exc}"
            log.error("projector response from %s: %s", scan.job_id, body["error"])
        self.bus.publish_json(self.bus.keys.projector_response_result, body,
                              "scancell.ProjectorResponseResult")
        return body

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
            if self.share.mine(scan.scan_id):
                log.error("scan %s (station %s) incomplete after %.0f s, dropped: %s",
                          scan.scan_id, scan.station, self.assembler.max_age_s, scan.missing())
                self._publish_result(scan, None, f"incomplete: {scan.missing()}")
        if complete is not None:
            self._dispatch(complete)

    # ---------------------------------------------------------------- sharing the work
    @staticmethod
    def _finish_key(scan: PendingScan) -> str:
        """What the scan's result names: its scan id, or a response calibration's job."""
        return f"job:{scan.job_id}" if scan.levels is not None else scan.scan_id

    def publish_status(self) -> None:
        """``workers/scan/<id>/status`` (latched): what this worker decodes, queues and holds."""
        if self._status_pub is None:
            return
        with self._lock:
            standby = sorted(self.standby)
        now = self._decoding
        body = {"worker": self.share.worker_id, "kind": "scan", "pid": os.getpid(),
                "decoding": None if now is None else {"scan_id": now.scan_id,
                                                      "station": now.station,
                                                      "job_id": now.job_id},
                "queued": max(self.pending() - (now is not None), 0), "standby": standby,
                "decoded": len(self.decoded), "members": self.share.members,
                "load_1min": round(os.getloadavg()[0], 2), "stamp_ns": messages.now_ns()}
        publish_worker_status(self._status_pub, body)

    def _dispatch(self, scan: PendingScan) -> None:
        with self._lock:
            if self._finish_key(scan) in self._finished:
                return  # its owner was faster than this worker's assembly
            mine = self.share.mine(scan.scan_id)
            scan.cloud_seen = scan.scan_id in self._clouds_seen
            if not mine:
                self.standby[scan.scan_id] = scan
        if mine:
            self.submit(scan)
        self.publish_status()

    def _on_result_seen(self, sample: Any) -> None:
        try:
            body = sample.decode()
            key = str(body["scan_id"]) if "scan_id" in body else f"job:{body['job_id']}"
        except (EncodingError, KeyError, TypeError, ValueError):
            return
        with self._lock:
            self._finished.add(key)
            held = [sid for sid, sc in self.standby.items() if self._finish_key(sc) == key]
            for sid in held:
                del self.standby[sid]
        if held:
            self.publish_status()

    def _on_cloud_seen(self, sample: Any) -> None:
        sid = sample.attachment.meta.get("scan_id")
        with self._lock:
            self._clouds_seen.add(str(sid))  # its assembly here may complete later
            if sid in self.standby:
                self.standby[sid].cloud_seen = True

    def _take_over(self, worker: str) -> None:
        with self._lock:
            mine = [sid for sid in self.standby if self.share.mine(sid)]
            taken = [self.standby.pop(sid) for sid in mine]
        for scan in taken:
            scan.taken_over_from = worker
            log.warning("scan worker %s: taking over scan %s (station %s) from %s, which is gone"
                        "%s", self.share.worker_id, scan.scan_id, scan.station, worker,
                        " (its cloud is on the bus; publishing the result)" if scan.cloud_seen
                        else "")
            self.submit(scan)

    def decoder(self, seq: FringeSequence) -> ScanDecoder:
        if seq not in self._decoders:
            self._decoders[seq] = ScanDecoder(self.calib, seq, self.projector_width, self.settings)
        return self._decoders[seq]

    def process(self, scan: PendingScan) -> ScanResult | None:
        assert scan.sequence is not None
        try:
            result = self.decoder(scan.sequence).decode_exposures(scan.image_sets("left"),
                                                                  scan.image_sets("right"))
        except (DecodeError, CalibrationError) as exc:
            log.error("scan %s (station %s): %s", scan.scan_id, scan.station, exc)
            self._publish_result(scan, None, str(exc))
            return None
        c = result.cloud
        fields = {"quality": whole_dn(c.quality), "intensity": whole_dn(c.intensity)}
        if c.uncertainty is not None:
            fields["uncertainty"] = c.uncertainty
        msg = fg.point_cloud(c.points, scan.stamp_ns or messages.now_ns(), f"mcs_{scan.station}",
                             fields)
        meta = {"scan_id": scan.scan_id, "station": scan.station, "points": len(c),
                "job_id": scan.job_id, "job_kind": scan.job_kind, "worker": self.share.worker_id,
                "exposures_us": [scan.exposure_us.get(e) for e in range(scan.exposures)],
                "precompensated": scan.precompensated,
                "response": {"left": result.left.response, "right": result.right.response}}
        for side, pm in (("left", result.left), ("right", result.right)):
            if pm.response and not pm.response["linear"]:
                told = f"{scan.job_id or scan.scan_id}\0{side}"
                log.log(logging.INFO if told in self._response_told else logging.WARNING,
                        "scan %s station %s: %s", scan.scan_id, scan.station,
                        response_warning(side, pm.response))
                self._response_told.add(told)
        with self._lock:  # another worker may have answered while this one decoded
            answered = self._finish_key(scan) in self._finished
            cloud_seen = scan.cloud_seen or scan.scan_id in self._clouds_seen
        if not answered and scan.levels is None:
            answered = self.answered_elsewhere(scan.scan_id)
        if answered:
            log.warning("scan %s (station %s): another worker answered while this one decoded; "
                        "nothing published", scan.scan_id, scan.station)
            return result
        with self._lock:
            self._published.add(scan.scan_id)
        if not cloud_seen:
            self.bus.publish(self.bus.keys.scan_cloud(scan.station), fg.encode_proto(msg),
                             Attachment(scan.stamp_ns or messages.now_ns(), self.done, None, meta))
        self._publish_result(scan, result, None)
        log.info("scan %s station %s: %d points in %.2f s", scan.scan_id, scan.station, len(c),
                 result.timings["total"])
        return result

    def answered_elsewhere(self, scan_id: str) -> bool:
        """Whether another scan worker says it answered ``scan_id``: asked on the bus just
        before publishing, so a worker that stalled or was cut off while another took its scan
        over does not answer a second time."""
        try:
            answers = self.bus.ask(self.bus.keys.worker_answered("scan", "*"),
                                   {"scan_id": scan_id}, "scancell.WorkerAnswered", 2.0)
        except Exception as exc:  # no bus: nobody else can have answered
            log.debug("scan %s: asking the other workers: %s", scan_id, exc)
            return False
        by = [a.get("worker") for a in answers
              if a.get("answered") and a.get("worker") != self.share.worker_id]
        if by:
            log.warning("scan %s: worker %s answered it while this worker (%s) was away; "
                        "nothing published", scan_id, by[0], self.share.worker_id)
        return bool(by)

    def _on_asked(self, request: dict[str, Any]) -> dict[str, Any]:
        scan_id = str(request.get("scan_id", ""))
        with self._lock:
            done = scan_id in self._published
        return {"worker": self.share.worker_id, "scan_id": scan_id, "answered": done}

    def _publish_result(self, scan: PendingScan, result: ScanResult | None, error: str | None) -> None:
        if scan.levels is None and error is not None and self.answered_elsewhere(scan.scan_id):
            return  # an incomplete or failed scan another worker answered meanwhile
        with self._lock:
            self._published.add(scan.scan_id)
        if scan.levels is not None:
            self.bus.publish_json(self.bus.keys.projector_response_result,
                                  {"job_id": scan.job_id, "ok": False, "error": error},
                                  "scancell.ProjectorResponseResult")
            return
        self.bus.publish(self.bus.keys.scan_result(scan.station), messages.encode_json(
            result_message(scan, result, error, self.share.worker_id), "scancell.ScanResult"),
            Attachment(messages.now_ns(), self.done, None,
                       {"scan_id": scan.scan_id, "station": scan.station,
                        "job_id": scan.job_id, "worker": self.share.worker_id}))

    def handle(self, scan: PendingScan) -> None:
        self.decoded.append(scan.scan_id)
        self._decoding = scan
        self.publish_status()
        try:
            if scan.levels is not None:
                self.calibrate_response(scan)
            else:
                self.process(scan)
        finally:
            self.done += 1
            self._decoding = None
            self.publish_status()
