"""The Dask cluster the batch commands share: a scheduler's address, or a local cluster."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from typing import Any

#: how long a command tries to reach a scheduler before it gives up (s)
CONNECT_TIMEOUT_S = 10.0


class SchedulerUnreachable(OSError):
    """The scheduler named could not be reached; nothing was submitted or written."""


def connect(scheduler: str | None, workers: int | None) -> Any:
    """A Dask client: of the scheduler at ``scheduler`` (tcp://HOST:PORT), or of a new local
    cluster of ``workers`` worker processes (default: one per core), one thread each (a task
    uses its cores through numba, numpy and Open3D itself)."""
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
        except (OSError, TimeoutError) as exc:
            raise SchedulerUnreachable(f"scheduler {scheduler}: cannot be reached ({exc})") from None
    # distributed sets its workers' OMP/OPENBLAS/MKL_NUM_THREADS=1 and MALLOC_TRIM_THRESHOLD_
    # in this process's environment too, where every process started after would inherit them
    # (a BLAS with one thread rounds some sums differently: a reprocess then differed from the
    # live run in the 16th digit)
    saved = dict(os.environ)
    try:
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               dashboard_address=":0")
    finally:
        os.environ.clear()
        os.environ.update(saved)
    return Client(cluster)


def close(client: Any) -> None:
    """Close ``client`` and, if it started one, its local cluster."""
    from distributed import LocalCluster

    cluster = getattr(client, "cluster", None)
    client.close()
    if isinstance(cluster, LocalCluster):
        cluster.close()


@contextlib.contextmanager
def session(scheduler: str, workers: int | None, what: str) -> Iterator[Any]:
    """A client of ``scheduler`` (tcp://HOST:PORT, or ``local``) for the length of the block,
    after printing where ``what`` runs and its dashboard's link (its progress); closed after.
    Raises SchedulerUnreachable before anything is submitted."""
    client = connect(None if scheduler == "local" else scheduler, workers)
    try:
        n = len(client.scheduler_info()["workers"])
        print(f"{what} on {scheduler} ({n} workers); progress: {client.dashboard_link}",
              file=sys.stderr, flush=True)
        yield client
    finally:
        close(client)
