"""Reading a pyserial byte stream (``socket://``, a serial port, ``loop://``) without waiting.

pyserial's ``read(n)`` returns when n bytes have come or the timeout has passed: a reader asking
for 4096 bytes got every 60-byte reply only at the end of its timeout (50 ms), a tracker shot
or a robot's state 50 ms late. :func:`read_available` waits for the first byte only.
"""

from __future__ import annotations

import serial

#: the most one call returns; the rest waits for the next call
CHUNK_BYTES = 4096
#: how long a reader waits for a first byte before it looks again (is the link closing, has a
#: reply's deadline passed) (s); also the read timeout the drivers open their ports with
READ_WAIT_S = 0.05


def read_available(port: serial.SerialBase, wait_s: float = READ_WAIT_S) -> bytes:
    """The bytes the port holds, as soon as there is one: waits up to ``wait_s`` for the first
    byte (b"" if none came), then takes what else has already arrived without waiting. Sets the
    port's read timeout (the writer's is its own)."""
    port.timeout = wait_s
    first = port.read(1)
    if not first:
        return first
    port.timeout = 0
    return first + port.read(CHUNK_BYTES - 1)
