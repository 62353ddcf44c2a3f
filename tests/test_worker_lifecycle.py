"""The queue-driven worker's stop: what is being handled finishes before the worker closes
what it holds, and what is queued behind it is left."""

from __future__ import annotations

import threading

import pytest
from scancell.workers.base import ThreadedWorker


class SlowWorker(ThreadedWorker[int]):
    join_timeout_s = 10.0

    def __init__(self) -> None:
        super().__init__(bus=None)  # no subscriptions: items come by submit
        self.started = threading.Event()
        self.release = threading.Event()
        self.log: list[str] = []

    def handle(self, item: int) -> None:
        self.log.append(f"start {item}")
        self.started.set()
        self.release.wait(5.0)
        self.log.append(f"done {item}")

    def on_stop(self) -> None:
        self.log.append("closed")


@pytest.mark.unit
def test_stop_closes_after_the_item_being_handled_and_leaves_the_queued_ones():
    w = SlowWorker()
    w.start()
    for item in (1, 2, 3):
        w.submit(item)
    assert w.started.wait(5.0)
    stopper = threading.Thread(target=w.stop)
    stopper.start()
    stopper.join(0.3)
    assert stopper.is_alive() and w.log == ["start 1"]  # not closed under item 1
    w.release.set()
    stopper.join(5.0)
    assert not stopper.is_alive()
    assert w.log == ["start 1", "done 1", "closed"]
