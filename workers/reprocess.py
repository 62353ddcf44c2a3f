"""``scancell reprocess``: the analysis workers run on a recording, without a bus.

The recording's inputs (camera frames with their scan meta, tracker points, job events, hand-eye
samples) are delivered in their recorded order on an in-process :class:`LocalBus` to the same
worker classes that run live: the scan worker (stereo calibration from the recording's
``calib/stereo``) and the calibrate worker. Whatever the workers publish is written to ``OUT``:

- ``clouds/<station>_<scan_id>.ply``: every decoded scan (mm, MCS, fields quality, intensity);
- ``calibration/hand_eye/<job>.json`` (+ pairs CSV, ``active.json``): every hand-eye job;
- ``fusion/<job>/``: every scan_part job fused (PLY, E57, mesh, report), with the hand-eye
  calibration in force when the recording started (or one the recording itself computed);
- ``reprocess.json``: what came out of which scan and job, and any errors.

What the live workers published and the recorder kept (``scan/*/cloud``, ``calib/hand_eye``,
``fusion/**``, ``tf/**``) is not fed back in: it is what a reprocess is compared against. The one exception
is the hand-eye calibration in force at the start of the session, an input of fusion.
"""

from __future__ import annotations

import json
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scancell.bus.local import LocalBus
from scancell.bus.protocol import BusSample
from scancell.model.patterns import PROJECTOR_WIDTH
from scancell.protocols.encoding import EncodingError
from scancell.recorder.reading import RecordingError, info, samples, topic_matches

log = logging.getLogger(__name__)

#: Worker outputs: recorded from the live run, recomputed here, never fed back in.
OUTPUTS = ["scan/*/cloud", "scan/*/result", "calib/hand_eye", "calib/stereo", "fusion/**",
           "tf/**", "recorder/**"]
MAX_QUEUED_SCANS = 2
PROGRESS_EVERY = 200


@dataclass
class ReprocessResult:
    out_dir: Path
    messages: int = 0
    seconds: float = 0.0
    scans: list[dict[str, Any]] = field(default_factory=list)
    clouds: dict[str, Path] = field(default_factory=dict)  # scan_id -> PLY
    hand_eye: list[dict[str, Any]] = field(default_factory=list)
    fusion: list[dict[str, Any]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        return {"out_dir": str(self.out_dir), "messages": self.messages,
                "seconds": round(self.seconds, 3), "scans": self.scans,
                "clouds": {k: str(v) for k, v in self.clouds.items()},
                "hand_eye": self.hand_eye, "fusion": self.fusion}


def recorded_stereo(path: str | Path) -> tuple[Any, int]:
    """The stereo calibration (and projector width) in force in the recording."""
    from scancell.analysis.stereo_calibration import StereoCalibration

    last = None
    for s in samples(path, ["calib/stereo"]):
        last = s
    if last is None:
        raise RecordingError(f"{path}: no calib/stereo in the recording (was a scan worker "
                             f"running?); give the scanner's calibration with --calib stereo.yaml")
    body = json.loads(last.payload)
    return StereoCalibration.from_json(body, f"{path}: calib/stereo"), int(
        body.get("projector_width", PROJECTOR_WIDTH))


class _Outputs:
    """Writes what the workers publish into the output folder."""

    def __init__(self, bus: LocalBus, out: Path, result: ReprocessResult) -> None:
        from scancell.analysis.cloud_io import write_ply

        self._write_ply = write_ply
        self.out = out
        self.result = result
        k = bus.keys
        self.subs = [bus.subscribe(k.scan_cloud("*"), self._cloud),
                     bus.subscribe(k.scan_result("*"), self._scan_result),
                     bus.subscribe(k.hand_eye, self._hand_eye),
                     bus.subscribe(k.fusion_report, lambda s: result.fusion.append(s.decode()))]

    def _cloud(self, s: BusSample) -> None:
        meta = s.attachment.meta
        try:
            pts, fields = s.cloud_arrays()
        except EncodingError as exc:
            log.error("%s: %s", s.key, exc)
            return
        path = self.out / "clouds" / f"{meta.get('station', 'x')}_{meta.get('scan_id', 'x')}.ply"
        path.parent.mkdir(parents=True, exist_ok=True)
        self._write_ply(path, pts, fields)
        self.result.clouds[str(meta.get("scan_id"))] = path

    def _scan_result(self, s: BusSample) -> None:
        self.result.scans.append(s.decode())

    def _hand_eye(self, s: BusSample) -> None:
        self.result.hand_eye.append(s.decode())


def recorded_simulator(path: str | Path) -> dict[str, Any] | None:
    """The ``[simulator]`` table of the cell config recorded in the file, or None (a real cell,
    or no config recorded)."""
    raw = info(path).metadata.get("scancell.config", {}).get("config")
    try:
        config = json.loads(raw) if raw else None
    except json.JSONDecodeError:
        return None
    simulator = config.get("simulator") if isinstance(config, dict) else None
    return simulator if isinstance(simulator, dict) and simulator.get("part", "car_rear") else None


def recording_truth(path: str | Path, truth_cell: str | Path | None = None
                    ) -> tuple[Any, str | None]:
    """The true part a reprocess of ``path`` reports true errors against, and where it came
    from: the simulated cell config ``truth_cell``, else the simulated cell recorded in the file,
    else (None, None): a real cell. Raises ValueError for a bad ``truth_cell``."""
    from scancell.workers.truth import truth_from_config, truth_from_options

    if truth_cell:
        return truth_from_config(truth_cell), f"the simulated cell {truth_cell}"
    simulator = recorded_simulator(path)
    if simulator is None:
        return None, None
    return truth_from_options(simulator), (
        f"the simulated cell recorded in {path} (part {simulator.get('part', 'car_rear')!r}, "
        f"seed {simulator.get('seed', 0)})")


def reprocess(path: str | Path, out_dir: str | Path, calib_file: str | Path | None = None,
              progress: bool = True, truth: Any = None,
              on_progress: Callable[[int, int], None] | None = None) -> ReprocessResult:
    """``truth``: points (world, mm) -> true distances to the part, simulation only.
    ``on_progress(messages read, messages in the file)``: every 200 messages and at the end."""
    from scancell.analysis.stereo_calibration import StereoCalibration
    from scancell.workers.calibrate import CalibrateWorker
    from scancell.workers.fuse import FuseSettings, FuseWorker
    from scancell.workers.scan import ScanWorker
    from tqdm import tqdm

    rec = info(path)
    if rec.cell is None:
        raise RecordingError(f"{path}: no scancell.session metadata: not a scancell recording")
    if calib_file is not None:
        calib, width = StereoCalibration.read(calib_file), PROJECTOR_WIDTH
    else:
        calib, width = recorded_stereo(path)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    result = ReprocessResult(out)
    bus = LocalBus(rec.cell)
    outputs = _Outputs(bus, out, result)
    scan_worker = ScanWorker(bus, calib, width)
    cal_worker = CalibrateWorker(bus, out / "calibration")
    fuse_worker = FuseWorker(bus, FuseSettings(out / "fusion", truth=truth))
    workers = (scan_worker, cal_worker, fuse_worker)
    for w in workers:
        w.start()
    t0 = time.monotonic()
    bar = tqdm(total=rec.messages, unit="msg", desc=f"reprocess {Path(path).name}",
               disable=not progress, file=sys.stderr)
    try:
        jobs_seen = False
        for n, s in enumerate(samples(path), 1):
            bar.update(1)
            if on_progress is not None and n % PROGRESS_EVERY == 0:
                on_progress(n, rec.messages)
            rel = bus.keys.relative(s.key)
            jobs_seen = jobs_seen or rel.startswith("job/")
            in_force = rel == "calib/hand_eye" and not jobs_seen
            if topic_matches(s.key, OUTPUTS) and not in_force:
                continue
            while scan_worker.pending() >= MAX_QUEUED_SCANS:  # bound the frames held in memory
                time.sleep(0.01)
            bus.deliver(s)
            result.messages += 1
        bar.set_description(f"reprocess {Path(path).name}: decoding the last scans")
        while any(w.pending() for w in workers):
            time.sleep(0.02)
        if on_progress is not None:
            on_progress(rec.messages, rec.messages)
    finally:
        bar.close()
        for w in workers:
            w.stop()
        for sub in outputs.subs:
            sub.undeclare()
        bus.close()
    result.seconds = time.monotonic() - t0
    (out / "reprocess.json").write_text(json.dumps(result.to_json(), indent=2))
    return result
