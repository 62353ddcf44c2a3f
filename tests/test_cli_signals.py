"""The CLI's long-running commands stop on a SIGTERM that the kernel hands to another thread
(zenoh's native threads take process signals too)."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent("""
    import signal, sys, threading
    from scancell.cli._common import stop_on_signals, wait_for

    stop = stop_on_signals()
    threading.Thread(target=threading.Event().wait, daemon=True).start()
    # the main thread blocks SIGTERM (the other thread started before): the kernel must deliver
    # it to the other thread
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})
    print("ready", flush=True)
    wait_for(stop)
    print("stopped", flush=True)
""")


@pytest.mark.unit
def test_a_sigterm_taken_by_another_thread_stops_the_wait():
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert proc.returncode == 0 and "stopped" in out, err
