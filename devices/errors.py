"""Typed device errors. Every driver raises only these (or subclasses) to its caller."""

from __future__ import annotations


class DeviceError(Exception):
    """Base of all device errors; ``code`` is the command error code it maps to."""

    code = "device_fault"


class ConnectionLost(DeviceError):
    """The link to the device is down or dropped during an operation."""

    code = "connection_lost"


class Timeout(DeviceError):
    """The device did not answer within the allowed time."""

    code = "timeout"


class DeviceFault(DeviceError):
    """The device answered, and what it said is a fault (alarm, beam break, limit)."""

    code = "device_fault"


class BadReply(DeviceError):
    """The device answered with bytes that could not be parsed or do not fit the protocol."""

    code = "bad_reply"


class BeamBroken(DeviceFault):
    """A laser tracker lost its beam (occlusion, reflector moved too fast)."""
