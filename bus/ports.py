"""Free loopback ports for the servers of one machine's simulated cell, its demo and its tests.

A port is checked by binding it and handed to the server that binds it later. In between, the
kernel may give the same port to an outgoing connection as its local port, if the port lies in
its ephemeral range (Linux: 32768-60999 by default): a clean-clone ``make test`` lost a daemon
to errno 98 that way, with three test processes opening zenoh links beside it. The ports
handed out here lie below that range, where the kernel never picks one by itself.
"""

from __future__ import annotations

import os
import random
import socket
from pathlib import Path

#: the lowest port handed out: above the registered services most hosts run
LOWEST = 20000
_GIVEN: set[int] = set()
_rng = random.Random(os.getpid() ^ int.from_bytes(os.urandom(4), "little"))


def ephemeral_range() -> tuple[int, int]:
    """The kernel's range of local ports for outgoing connections (Linux; the default
    elsewhere)."""
    try:
        lo, hi = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(lo), int(hi)
    except (OSError, ValueError):
        return 32768, 60999


def free_port(host: str = "127.0.0.1") -> int:
    """A port on ``host`` free now, below the ephemeral range, and not handed out before by
    this process. Random over the range, so that processes choosing side by side rarely try the
    same one; a port in use (a server, a connection in TIME_WAIT) is passed over."""
    high = ephemeral_range()[0]
    low = LOWEST if high - LOWEST >= 1000 else 1024
    for _ in range(4 * (high - low)):
        port = _rng.randrange(low, high)
        if port in _GIVEN:
            continue
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
        _GIVEN.add(port)
        return port
    raise OSError(f"no free port on {host} between {low} and {high}")
