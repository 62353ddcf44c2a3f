"""``scancell reprocess`` over a Dask cluster: one task per recording.

Each recording is one Dask task (:func:`reprocess_task`) that runs
:func:`scancell.workers.reprocess.reprocess` on a worker, exactly as a reprocess without Dask
does, into a fresh attempt folder ``.<name>-reprocessed.partial/<attempt>/`` beside its output.
This process (the batch's driver) is the only one that commits: when a task's result comes back
it moves that attempt into ``<name>-reprocessed/`` and deletes the partial folder. A worker that
dies mid-recording (killed, its machine lost) leaves an attempt nobody commits; Dask runs the
task again on another worker (up to ``distributed.scheduler.allowed-failures`` deaths), and the
driver commits the attempt whose result it receives, once. A recording a worker cannot read is
an error in its own result; the others go on.

The recordings and output folders must be at the same path on the workers as here (one machine,
or shared storage). The cluster is ``tcp://HOST:PORT`` (a ``dask scheduler``, see
``deploy/systemd/``) or a local one with a worker process per core.
"""

from __future__ import annotations

import json
import shutil
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class RecordingOutcome:
    file: Path
    out: Path
    ok: bool = False
    error: str | None = None
    worker: str | None = None  # the Dask worker whose attempt was committed
    truth: str | None = None  # what true errors were reported against, if anything
    result: dict[str, Any] = field(default_factory=dict)  # ReprocessResult.to_json()

    def to_json(self) -> dict[str, Any]:
        return {"file": str(self.file), "out": str(self.out), "ok": self.ok, "error": self.error,
                "worker": self.worker, "truth": self.truth, "result": self.result}


def partial_root(out: Path) -> Path:
    """Where the attempts at ``out`` are written before one is committed."""
    return out.with_name(f".{out.name}.partial")


def reprocess_task(file: str, out: str, calib: str | None, truth_cell: str | None
                   ) -> dict[str, Any]:
    """On a Dask worker: reprocess ``file`` into a new attempt folder under
    ``partial_root(out)``; returns ``{"ok", "attempt" | "error", "worker", ...}``. Errors of the
    recording itself are returned, not raised: they would fail the same way anywhere."""
    from distributed import get_worker
    from scancell.workers.reprocess import recording_truth, reprocess

    try:
        worker = get_worker().address
    except ValueError:  # run in this process (tests, no cluster)
        worker = "local"
    attempt = partial_root(Path(out)) / uuid.uuid4().hex
    try:
        truth, source = recording_truth(file, truth_cell)
        r = reprocess(file, attempt, calib, progress=False, truth=truth)
    except (ValueError, OSError) as exc:  # RecordingError, CalibrationError, a bad --truth-cell
        shutil.rmtree(attempt, ignore_errors=True)
        return {"ok": False, "error": str(exc), "worker": worker}
    return {"ok": True, "attempt": str(attempt), "worker": worker, "truth": source,
            "result": r.to_json()}


def commit(outcome: RecordingOutcome, answer: dict[str, Any]) -> RecordingOutcome:
    """Move the answered attempt into ``outcome.out`` (replacing an older output) and drop
    the other attempts; the paths in its ``reprocess.json`` follow."""
    outcome.worker, outcome.truth = answer.get("worker"), answer.get("truth")
    root = partial_root(outcome.out)
    if not answer.get("ok"):
        outcome.error = answer.get("error") or "failed"
        shutil.rmtree(root, ignore_errors=True)
        return outcome
    attempt = Path(answer["attempt"])
    if outcome.out.exists():
        shutil.rmtree(outcome.out)
    attempt.rename(outcome.out)
    shutil.rmtree(root, ignore_errors=True)
    text = json.dumps(answer["result"], indent=2).replace(str(attempt), str(outcome.out))
    (outcome.out / "reprocess.json").write_text(text)
    outcome.ok, outcome.result = True, json.loads(text)
    return outcome


def run(client: Any, files: list[Path], outs: list[Path], calib: str | None,
        truth_cell: str | None, on_done: Callable[[RecordingOutcome, int, int], None] | None = None
        ) -> list[RecordingOutcome]:
    """Reprocess ``files`` into ``outs`` on ``client``'s cluster; each outcome in the order
    given. ``on_done(outcome, done, total)`` as each finishes."""
    from distributed import as_completed

    batch = uuid.uuid4().hex[:8]
    outcomes = [RecordingOutcome(f.resolve(), o.resolve()) for f, o in zip(files, outs, strict=True)]
    futures = {}
    for i, oc in enumerate(outcomes):
        fut = client.submit(reprocess_task, str(oc.file), str(oc.out),
                            None if calib is None else str(Path(calib).resolve()), truth_cell,
                            key=f"reprocess-{batch}-{i}-{oc.file.name}", pure=False)
        futures[fut] = oc
    for done, fut in enumerate(as_completed(futures), 1):
        oc = futures[fut]
        try:
            answer = fut.result()
        except Exception as exc:  # KilledWorker after too many deaths, a worker-side crash
            answer = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        commit(oc, answer)
        if on_done is not None:
            on_done(oc, done, len(outcomes))
    return outcomes


def write_summary(folder: Path, outcomes: list[RecordingOutcome], scheduler: str,
                  seconds: float) -> Path:
    """``reprocess-batch-<time>.json`` in ``folder``: each recording's worker and result."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"reprocess-batch-{time.strftime('%Y%m%dT%H%M%S')}.json"
    path.write_text(json.dumps({"scheduler": scheduler, "seconds": round(seconds, 2),
                                "recordings": [o.to_json() for o in outcomes]}, indent=2))
    return path
