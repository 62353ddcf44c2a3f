"""The recorder: every sample on ``scancell/<cell>/**`` into one MCAP file per session.

A session is a job (``<job_id>.mcap``, from its ``running`` event until ``job_linger_s`` after
its end, or after the last sample naming the job if that came later, and not before every scan
whose frames it holds has its ``scan/<station>/result``, nor before the answer a live worker owes
the job (:data:`ANSWERS`: a ``scan_part`` job's ``fusion/report``, a ``calibrate_hand_eye`` job's
``calib/hand_eye``, awaited while a worker of that kind holds its liveliness token), at most
``job_max_linger_s`` after the end; so the workers' outputs land in it however far a loaded
worker lags), or, between jobs, an ``idle-<time>.mcap`` file split every ``split_s`` seconds or
``split_bytes`` bytes.

The linger holds across jobs: when the next job starts while the last one's file lingers, both
are open. A sample that names its job (the job's events, frames and clouds through their
attachment's ``job_id``, reports through their JSON ``job_id``) goes to that job's file; any
other sample (tracker points, joints, status, transforms) goes to every open file.

Nothing is lost silently. Samples go through a bounded queue (``queue_bytes``) to one writer
thread; if it ever overflows, the sample is dropped, counted per key expression, named in a log
line, published as a ``dropped`` event on ``recorder/<name>/event`` and counted in the status on
``recorder/<name>/status`` (which is recorded too, and summed up in the file's ``scancell.recorder``
metadata). A chunk is closed and handed to the OS at least every ``flush_interval_s`` (0.5 s), so
after a crash ``scancell record recover`` gets everything but the last half second. A write error
(disk full, unwritable path) closes the file, is published as an ``error`` event and logged, and
the recorder tries again with a new file at the next session; whoever embeds it keeps running.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from scancell.bus import Bus, BusSample
from scancell.bus.recent_ids import RecentIds
from scancell.protocols import messages
from scancell.protocols.encoding import EncodingError
from scancell.recorder.reading import topic_matches
from scancell.recorder.session_file import IMAGE_SCHEMAS, FileSettings, SessionFile

log = logging.getLogger(__name__)

#: Keys whose last sample is written again at the start of every session file (and attached as a
#: file), so a session alone holds the calibrations in force.
LATCHED = ("calib/stereo", "calib/hand_eye")
TERMINAL_STATES = ("done", "failed", "aborted")


@dataclass(frozen=True)
class OwedAnswer:
    """The answer a kind of worker publishes for a job of some kind once it has ended."""

    worker_kind: str  # its liveliness tokens: ``workers/<worker_kind>/*``
    key: str  # relative to ``scancell/<cell>/``; the answer's JSON names the job (``job_id``)
    states: tuple[str, ...]  # the job's end states the worker answers


#: ``[recorder] frames``: which camera frames are written
FRAME_POLICIES = ("all", "first_exposure", "none")

#: job kind -> the answer its file waits for (workers/fuse.py, workers/calibrate.py)
ANSWERS = {
    "scan_part": OwedAnswer("fuse", "fusion/report", TERMINAL_STATES),
    "calibrate_hand_eye": OwedAnswer("calibrate", "calib/hand_eye", ("done",)),
}


@dataclass(frozen=True)
class RecorderSettings:
    """The ``[recorder]`` table of a cell config, and the options of ``scancell record``."""

    #: where the session files go (made if missing)
    directory: str = "recordings"
    #: the recorder's name in recorder/<name>/status and event
    name: str = "recorder"
    #: key expressions relative to ``scancell/<cell>/`` to record
    topics: tuple[str, ...] = ("**",)
    #: key expressions to leave out
    exclude: tuple[str, ...] = ()
    #: the queue between zenoh and the writer; a sample that does not fit is dropped, counted and
    #: reported
    queue_bytes: int = 1 << 30
    #: an idle file (between jobs) is closed and a new one started after this long
    split_s: float = 600.0
    #: ... or once it holds this many bytes
    split_bytes: int = 4 << 30
    #: a job's file stays open this long after the job's end and its last sample
    job_linger_s: float = 10.0
    #: the longest a job's file waits for the results of its scans after the job's end
    job_max_linger_s: float = 180.0
    #: how often recorder/<name>/status is published
    status_period_s: float = 1.0
    #: after a write error, the wait before a new file is tried
    retry_s: float = 5.0
    #: Which camera frames go into the files (:data:`FRAME_POLICIES`): "all" keeps every frame,
    #: so a recording reprocesses to the same clouds; "first_exposure" keeps an HDR scan's first
    #: exposure only (its frames say ``exposures: 1``, ``exposures_taken: N``); "none" keeps
    #: clouds and results only.
    frames: str = "all"
    #: Frames go into uncompressed chunks while the queue holds more than this share of
    #: ``queue_bytes``: a burst faster than the compressor (zstd: ~210 MB/s a core against the
    #: 300 MB/s of 2 x 5 MP x 30 fps) is written whole rather than dropped, and compression
    #: resumes when the writer has caught up (a station's frames fit below it and are
    #: compressed during the robot's next move).
    uncompressed_above_queue_share: float = 0.5
    file: FileSettings = field(default_factory=FileSettings)

    def __post_init__(self) -> None:
        if self.frames not in FRAME_POLICIES:
            raise ValueError(f"frames must be one of {list(FRAME_POLICIES)}, got {self.frames!r}")
        if not 0 <= self.uncompressed_above_queue_share <= 1:
            raise ValueError(f"uncompressed_above_queue_share must be in [0, 1], got "
                             f"{self.uncompressed_above_queue_share!r}")

    @classmethod
    def from_mapping(cls, m: dict[str, Any]) -> RecorderSettings:
        """From a config table; raises ValueError naming the offending key."""
        file_keys = {f.name for f in fields(FileSettings)}
        own = {f.name for f in fields(cls)} - {"file", "enabled"}
        kw: dict[str, Any] = {}
        fkw: dict[str, Any] = {}
        for key, value in m.items():
            if key == "enabled":
                continue
            if key in file_keys:
                fkw[key] = value
            elif key in own:
                kw[key] = tuple(value) if key in ("topics", "exclude") else value
            else:
                raise ValueError(f"unknown key {key!r}; expected one of "
                                 f"{sorted(own | file_keys | {'enabled'})}")
        for key in ("queue_bytes", "split_bytes"):
            if key in kw and (not isinstance(kw[key], int) or kw[key] <= 0):
                raise ValueError(f"{key} must be a positive integer, got {kw[key]!r}")
        for key in ("split_s", "job_linger_s", "job_max_linger_s", "status_period_s", "retry_s"):
            if key in kw and (not isinstance(kw[key], int | float) or kw[key] <= 0):
                raise ValueError(f"{key} must be a positive number of seconds, got {kw[key]!r}")
        return cls(**kw, file=FileSettings(**fkw))


@dataclass
class _Session:
    name: str
    file: SessionFile
    job_id: str | None
    opened: float
    ended: float | None = None  # monotonic time the job ended, or of its last sample after that
    first_ended: float | None = None
    #: scans whose frames are in the file and whose result is not (yet)
    open_scans: set[str] = field(default_factory=set)
    #: answers a live worker owes the ended job, not (yet) in the file
    awaited: set[OwedAnswer] = field(default_factory=set)

    def may_close(self, now: float, linger_s: float, max_linger_s: float) -> bool:
        if self.ended is None or now - self.ended < linger_s:
            return False
        return ((not self.open_scans and not self.awaited)
                or now - (self.first_ended or self.ended) >= max_linger_s)


class Recorder:
    """Records one cell's bus. ``start()`` and ``stop()`` from any thread."""

    def __init__(self, bus: Bus, settings: RecorderSettings = RecorderSettings(),
                 cell_config: dict[str, Any] | None = None) -> None:
        self.bus = bus
        self.settings = settings
        self.cell_config = cell_config
        self.directory = Path(settings.directory)
        self._cond = threading.Condition()
        self._queue: deque[tuple[int, BusSample]] = deque()
        self._queued_bytes = 0
        self._stopping = False
        self._subs: list[Any] = []
        self._thread = threading.Thread(target=self._run, daemon=True, name="recorder")
        self.session: _Session | None = None
        #: Ended jobs' sessions still open for their linger (the current one is ``session``).
        self.lingering: list[_Session] = []
        self.latched: dict[str, BusSample] = {}
        self.dropped: dict[str, int] = {}
        self._drop_events: dict[str, int] = {}  # key -> drops not yet announced
        self.unrecordable: dict[str, str] = {}
        #: scan answers recorded (key and scan id), and second answers refused, per key
        self._answers = RecentIds(65536)
        self.duplicates: dict[str, int] = {}
        #: live workers' tokens per worker kind of :data:`ANSWERS`
        self._workers: dict[str, set[str]] = {a.worker_kind: set() for a in ANSWERS.values()}
        self.files: list[Path] = []
        self.total_messages = 0
        self.total_bytes = 0
        self.lost = 0
        #: camera frames the ``frames`` policy left out
        self.frames_skipped = 0
        self.error: str | None = None
        self._error_at = 0.0
        self._last_status = 0.0
        self.state = "idle"

    # ---------------------------------------------------------------- lifecycle
    def start(self) -> None:
        if self.cell_config is None:
            self.cell_config = self._fetch_config()
        prefix = self.bus.keys.prefix
        for s in self.bus.fetch_latched(f"{prefix}/calib/**", timeout_s=1.0):
            rel = self.bus.keys.relative(s.key)
            if rel in LATCHED:
                self.latched[rel] = s
        for kind in self._workers:
            self._subs.append(self.bus.watch_members(
                self.bus.keys.worker(kind, "*"),
                lambda key, present, kind=kind: self._on_worker(kind, key, present)))
        for pattern in self.settings.topics:
            self._subs.append(self.bus.subscribe(f"{prefix}/{pattern}", self._on_sample,
                                                 self._on_bad_sample))
        self._thread.start()
        log.info("recorder %r: recording %s of cell %r into %s", self.settings.name,
                 ", ".join(self.settings.topics), self.bus.keys.cell, self.directory)

    def stop(self) -> None:
        for s in self._subs:
            with contextlib.suppress(Exception):
                s.undeclare()
        self._subs.clear()
        with self._cond:
            self._stopping = True
            self._cond.notify()
        if self._thread.is_alive():
            self._thread.join(60)
        self.state = "stopped"
        with contextlib.suppress(Exception):
            self._announce_drops()  # drops after the writer's last tick are announced too
            self._publish_status(time.monotonic())

    def _announce_drops(self) -> dict[str, int]:
        """A ``dropped`` event per key for the drops not yet announced; returns them."""
        with self._cond:
            drops, self._drop_events = self._drop_events, {}
        for key, n in drops.items():
            self._event("dropped", key=key, messages=n,
                        message=f"{n} messages on {key} dropped: recorder queue full")
        return drops

    def _fetch_config(self) -> dict[str, Any] | None:
        try:
            return self.bus.call("config", timeout_s=2.0, connect_wait_s=0.5)["config"]
        except Exception as exc:  # no daemon (yet): the file says so
            log.info("recorder: no cell config from the daemon (%s)", exc)
            return None

    # ---------------------------------------------------------------- zenoh threads
    def _on_sample(self, sample: BusSample) -> None:
        rel = sample.key[len(self.bus.keys.prefix) + 1:]
        if self.settings.exclude and topic_matches(rel, list(self.settings.exclude)):
            return
        size = len(sample.payload)
        with self._cond:
            if self._queued_bytes + size > self.settings.queue_bytes:
                n = self.dropped.get(sample.key, 0)
                self.dropped[sample.key] = n + 1
                self._drop_events[sample.key] = self._drop_events.get(sample.key, 0) + 1
                first = n == 0
            else:
                self._queue.append((time.time_ns(), sample))
                self._queued_bytes += size
                self._cond.notify()
                return
        if first:
            log.error("recorder %r: queue full (%d MB), dropping messages on %s",
                      self.settings.name, self.settings.queue_bytes >> 20, sample.key)

    def _on_worker(self, kind: str, key: str, present: bool) -> None:
        with self._cond:
            (self._workers[kind].add if present else self._workers[kind].discard)(key)

    def _workers_live(self, kind: str) -> bool:
        with self._cond:
            return bool(self._workers[kind])

    def _on_bad_sample(self, key: str, exc: Exception) -> None:
        if key not in self.unrecordable:
            self.unrecordable[key] = str(exc)
            log.warning("recorder: cannot record %s: %s", key, exc)

    # ---------------------------------------------------------------- writer thread
    def _run(self) -> None:
        tick = min(self.settings.file.flush_interval_s / 2, self.settings.status_period_s)
        while True:
            with self._cond:
                if not self._queue and not self._stopping:
                    self._cond.wait(tick)
                batch = list(self._queue)
                self._queue.clear()
                stopping = self._stopping
            for recv_ns, sample in batch:
                self._handle(recv_ns, sample)
                with self._cond:  # the queue's bytes are held until written
                    self._queued_bytes -= len(sample.payload)
            self._housekeeping(time.monotonic())
            if stopping and not batch:
                break
        for s in list(self.lingering):
            self._close_lingering(s, "recorder stopped")
        self._close_session("recorder stopped")

    def _handle(self, recv_ns: int, sample: BusSample) -> None:
        rel = self.bus.keys.relative(sample.key)
        if self._second_answer(rel, sample):
            return
        if rel in LATCHED:
            self.latched[rel] = sample
        event = self._job_event(rel, sample)
        if event is not None and event.get("state") == "running":
            job_id = str(event.get("job_id"))
            if self.session is None or self.session.job_id != job_id:
                s = self.session
                if s is not None and s.job_id is not None and s.ended is not None:
                    self.lingering.append(s)  # the last job's file stays open for its linger
                    self.session = None
                else:
                    self._close_session(f"job {job_id} started")
                self._open_session(job_id, job_id)
        if self.session is None:
            self._open_session(f"idle-{time.strftime('%Y%m%dT%H%M%S')}", None)
        job = event.get("job_id") if event is not None else self._job_of(sample)
        owner = next((s for s in (self.session, *self.lingering)
                      if s is not None and job is not None and s.job_id == job), None)
        if owner is not None:
            self._write(recv_ns, sample, owner)
            if owner.ended is not None:  # a worker's late output: the linger starts again
                owner.ended = time.monotonic()
            meta = sample.attachment.meta
            if "scan_id" in meta and "periods" in meta:  # a fringe scan's frame: a cloud to come
                owner.open_scans.add(str(meta["scan_id"]))
        else:
            for s in (*self.lingering, self.session):
                self._write(recv_ns, sample, s)
        if rel.startswith("scan/") and rel.endswith("/result"):
            self._scan_result(sample)
        if owner is not None and owner.awaited:
            owner.awaited = {a for a in owner.awaited if a.key != rel}
        if event is not None and event.get("state") in TERMINAL_STATES and owner is not None:
            owner.ended = owner.first_ended = time.monotonic()
            owed = ANSWERS.get(str(event.get("kind")))
            if owed is not None and event["state"] in owed.states:
                if self._workers_live(owed.worker_kind):
                    owner.awaited.add(owed)
                    log.info("recorder %r: job %s ended; its file waits for %s (at most %g s)",
                             self.settings.name, owner.job_id, owed.key,
                             self.settings.job_max_linger_s)
                else:
                    log.info("recorder %r: job %s ended; no %s worker is live: its file closes "
                             "%g s after its last sample", self.settings.name, owner.job_id,
                             owed.worker_kind, self.settings.job_linger_s)

    def _second_answer(self, rel: str, sample: BusSample) -> bool:
        """A scan's cloud or result seen before (the same scan id on the same key): a worker
        that answered late or twice. It is counted, logged and announced, never written."""
        if not (rel.startswith("scan/") and rel.endswith(("/cloud", "/result"))):
            return False
        scan_id = sample.attachment.meta.get("scan_id")
        if scan_id is None and rel.endswith("/result"):
            scan_id = self._scan_id_of(sample)
        if scan_id is None:
            return False
        answer = f"{rel}\0{scan_id}"
        if answer not in self._answers:
            self._answers.add(answer)
            return False
        worker = sample.attachment.meta.get("worker", "?")
        self.duplicates[sample.key] = self.duplicates.get(sample.key, 0) + 1
        log.warning("recorder %r: a second %s for scan %s (worker %s): not recorded",
                    self.settings.name, rel, scan_id, worker)
        self._event("duplicate", key=sample.key, scan_id=str(scan_id), worker=str(worker),
                    message=f"a second {rel} for scan {scan_id} from worker {worker}: not "
                            f"recorded")
        return True

    @staticmethod
    def _scan_id_of(sample: BusSample) -> str | None:
        try:
            return str(json.loads(sample.payload)["scan_id"])
        except (ValueError, KeyError, TypeError):
            return None

    def _scan_result(self, sample: BusSample) -> None:
        scan_id = self._scan_id_of(sample)
        if scan_id is None:
            return
        for s in (self.session, *self.lingering):
            if s is not None:
                s.open_scans.discard(scan_id)

    @staticmethod
    def _job_event(rel: str, sample: BusSample) -> dict[str, Any] | None:
        if not (rel.startswith("job/") and rel.endswith("/event")
                and sample.schema == "scancell.JobEvent"):
            return None
        try:
            e = json.loads(sample.payload)
        except ValueError:
            return None
        return e if isinstance(e, dict) else None

    @staticmethod
    def _job_of(sample: BusSample) -> str | None:
        """The job a sample names: its attachment's ``job_id``, or a small JSON body's."""
        job = sample.attachment.meta.get("job_id")
        if job is None and sample.mime == "application/json" and len(sample.payload) < 65536:
            try:
                body = json.loads(sample.payload)
            except ValueError:
                return None
            job = body.get("job_id") if isinstance(body, dict) else None
        return str(job) if job is not None else None

    def _kept_frame(self, sample: BusSample) -> BusSample | None:
        """``sample`` as the ``frames`` policy writes it, or None if it leaves it out."""
        policy = self.settings.frames
        if policy == "all" or sample.schema not in IMAGE_SCHEMAS:
            return sample
        meta = sample.attachment.meta
        if policy == "none" or int(meta.get("exposure_index", 0)) > 0:
            self.frames_skipped += 1
            return None
        if int(meta.get("exposures", 1)) == 1:
            return sample
        att = replace(sample.attachment, meta={**meta, "exposures": 1,
                                               "exposures_taken": int(meta["exposures"])})
        return replace(sample, attachment=att)

    def _write(self, recv_ns: int, sample: BusSample, session: _Session | None) -> None:
        if session is None:
            self.lost += 1  # after a write error, until the retry: counted in the status
            return
        kept = self._kept_frame(sample)
        if kept is None:
            return
        st = self.settings
        behind = self._queued_bytes - len(sample.payload)  # what waits behind this sample
        hurry = behind > st.uncompressed_above_queue_share * st.queue_bytes
        try:
            session.file.write(kept.key, kept.mime, kept.schema, kept.payload, kept.attachment,
                               recv_ns, hurry)
        except EncodingError as exc:
            if sample.key not in self.unrecordable:
                self.unrecordable[sample.key] = str(exc)
                log.warning("recorder: cannot record %s: %s", sample.key, exc)
            return
        except OSError as exc:
            if session is self.session:
                self._fail(exc)
            else:
                self._close_lingering(session, f"write failed: {exc.strerror or exc}")
            return
        if session is self.session:
            self.total_messages += 1
            self.total_bytes += len(sample.payload)

    def _housekeeping(self, now: float) -> None:
        s = self.session
        if s is not None:
            try:
                s.file.maybe_flush(now)
            except OSError as exc:
                self._fail(exc)
            s = self.session
        st = self.settings
        for ls in (s, *self.lingering):  # no live worker of a kind left: its answer will not come
            if ls is not None and ls.awaited:
                ls.awaited = {a for a in ls.awaited if self._workers_live(a.worker_kind)}
        for ls in list(self.lingering):
            if ls.may_close(now, st.job_linger_s, st.job_max_linger_s):
                self._close_lingering(ls, f"job {ls.job_id} ended")
            else:
                with contextlib.suppress(OSError):
                    ls.file.maybe_flush(now)
        if s is not None:
            if s.may_close(now, st.job_linger_s, st.job_max_linger_s):
                self._close_session(f"job {s.job_id} ended")
            elif s.job_id is None and (now - s.opened >= self.settings.split_s
                                       or s.file.bytes >= self.settings.split_bytes):
                self._close_session("split")
        drops = self._announce_drops()
        if drops or now - self._last_status >= self.settings.status_period_s:
            self._publish_status(now)

    # ---------------------------------------------------------------- sessions
    def _open_session(self, name: str, job_id: str | None) -> None:
        if (job_id is None and self.error is not None
                and time.monotonic() - self._error_at < self.settings.retry_s):
            return
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            path = self._free_path(name)
            f = SessionFile(path, self.settings.file)
        except OSError as exc:
            self._fail(exc, f"cannot open a session file in {self.directory}")
            return
        self.session = _Session(name, f, job_id, time.monotonic())
        self.error = None
        self.state = "recording"
        self.files.append(path)
        try:
            self._write_header(f, name, job_id)
        except OSError as exc:
            self._fail(exc)
            return
        self._event("opened", message=f"recording session {name} to {path}")
        log.info("recorder: session %s -> %s", name, path)

    def _free_path(self, name: str) -> Path:
        path = self.directory / f"{name}.mcap"
        n = 1
        while path.exists():
            path = self.directory / f"{name}-{n}.mcap"
            n += 1
        return path

    def _write_header(self, f: SessionFile, name: str, job_id: str | None) -> None:
        import scancell

        f.metadata("scancell.session", {
            "cell": self.bus.keys.cell, "session": name, "job_id": job_id or "",
            "recorder": self.settings.name, "version": scancell.__version__,
            "host": socket.gethostname(), "pid": str(os.getpid()),
            "started_ns": str(time.time_ns())})
        f.metadata("scancell.config", {"config": self.cell_config} if self.cell_config
                   else {"config": "unknown: no daemon answered cmd/config"})
        f.metadata("scancell.calibration", {rel: s.payload.decode(errors="replace")
                                            for rel, s in sorted(self.latched.items())}
                   or {"none": "no calibration was on the bus when the session opened"})
        for rel, s in sorted(self.latched.items()):
            f.write(s.key, s.mime, s.schema, s.payload, s.attachment, time.time_ns())
            f.attach(f"{rel}.json", "application/json", s.payload)

    def _close_lingering(self, s: _Session, why: str) -> None:
        self.lingering.remove(s)
        current, self.session = self.session, s
        try:
            self._close_session(why)
        finally:
            self.session = current
            if current is not None and self.error is None:
                self.state = "recording"

    def _close_session(self, why: str) -> None:
        s, self.session = self.session, None
        if s is None:
            return
        with self._cond:
            dropped = dict(self.dropped)
        try:
            s.file.metadata("scancell.recorder", {
                "closed": why, "messages": str(s.file.messages), "bytes": str(s.file.bytes),
                "dropped_total": str(sum(dropped.values())), "dropped": dropped,
                "duplicates": dict(self.duplicates), "unrecordable": self.unrecordable,
                "frames_policy": self.settings.frames, "frames_skipped": str(self.frames_skipped),
                "image_compression": s.file.settings.image_compression,
                "image_bytes": str(s.file.image_bytes),
                "image_bytes_uncompressed_under_load": str(s.file.image_bytes_hurried)})
            s.file.close()
        except OSError as exc:
            s.file.abandon()
            self._fail(exc)
            return
        self.state = "idle" if self.error is None else "error"
        self._event("closed", file=str(s.file.path), session=s.name, messages=s.file.messages,
                    bytes=s.file.bytes, message=f"session {s.name} closed ({why})")
        log.info("recorder: session %s closed (%s): %d messages, %.1f MB", s.name, why,
                 s.file.messages, s.file.bytes / 1e6)

    def _fail(self, exc: OSError, what: str = "write failed") -> None:
        s, self.session = self.session, None
        where = s.file.path if s is not None else self.directory
        self.error = f"{what}: {where}: {exc.strerror or exc}"
        self._error_at = time.monotonic()
        self.state = "error"
        if s is not None:
            try:  # a summary needs disk space too; the chunks already written stay readable
                s.file.close()
            except OSError:
                s.file.abandon()
            if not s.file.messages:  # a retry on a full disk: no empty file every retry_s
                s.file.path.unlink(missing_ok=True)
                if self.files and self.files[-1] == s.file.path:
                    self.files.pop()
        log.error("recorder %r: %s; data up to the last chunk is kept, retrying in %.0f s",
                  self.settings.name, self.error, self.settings.retry_s)
        self._event("error", file=str(where), message=self.error)
        self._publish_status(time.monotonic())

    # ---------------------------------------------------------------- bus outputs
    def _event(self, event: str, **body: Any) -> None:
        s = self.session
        msg = {"recorder": self.settings.name, "event": event,
               "file": str(s.file.path) if s else None, "session": s.name if s else None,
               "stamp_ns": messages.now_ns(), **body}
        with contextlib.suppress(Exception):
            self.bus.publish_json(self.bus.keys.recorder_event(self.settings.name), msg,
                                  "scancell.RecorderEvent")

    def status(self) -> dict[str, Any]:
        s = self.session
        with self._cond:
            dropped = dict(self.dropped)
            queued = self._queued_bytes
        return {"recorder": self.settings.name, "state": self.state,
                "file": str(s.file.path) if s else None, "session": s.name if s else None,
                "messages": s.file.messages if s else 0, "bytes": s.file.bytes if s else 0,
                "total_messages": self.total_messages, "total_bytes": self.total_bytes,
                "queue_bytes": queued, "queue_limit_bytes": self.settings.queue_bytes,
                "dropped": dropped, "dropped_total": sum(dropped.values()),
                "duplicates": dict(self.duplicates), "lost_after_error": self.lost, "error": self.error,
                "frames_policy": self.settings.frames, "frames_skipped": self.frames_skipped,
                "image_bytes": s.file.image_bytes if s else 0,
                "image_bytes_uncompressed_under_load": s.file.image_bytes_hurried if s else 0,
                "stamp_ns": messages.now_ns()}

    def _publish_status(self, now: float) -> None:
        self._last_status = now
        with contextlib.suppress(Exception):
            self.bus.publish_json(self.bus.keys.recorder_status(self.settings.name),
                                  self.status(), "scancell.RecorderStatus")


def settings_with(settings: RecorderSettings, **changes: Any) -> RecorderSettings:
    """``settings`` with some fields (and FileSettings fields) changed."""
    file_keys = {f.name for f in fields(FileSettings)}
    fchanges = {k: changes.pop(k) for k in list(changes) if k in file_keys}
    return replace(settings, file=replace(settings.file, **fchanges), **changes)
