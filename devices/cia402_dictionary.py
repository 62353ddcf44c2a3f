"""The CiA 402 object dictionary of a profile-position drive with homing and software limits,
as python-canopen wants it: shared by the ``canopen_axis`` driver and the simulated drive, and
replaceable by a vendor's EDS file."""

from __future__ import annotations

from canopen import objectdictionary as od
from canopen.objectdictionary import datatypes as dt
from scancell.protocols import cia402 as p


def _var(index: int, name: str, data_type: int, access: str, default: int | str = 0,
         subindex: int = 0) -> od.ODVariable:
    v = od.ODVariable(name, index, subindex)
    v.data_type = data_type
    v.access_type = access
    v.default = default
    return v


def drive_object_dictionary(name: str = "scancell CiA 402 axis") -> od.ObjectDictionary:
    """The object dictionary of a profile-position drive with homing and software limits."""
    d = od.ObjectDictionary()
    for var in (
        _var(p.DEVICE_TYPE, "Device type", dt.UNSIGNED32, "ro", p.DEVICE_TYPE_402_SERVO),
        _var(p.ERROR_REGISTER, "Error register", dt.UNSIGNED8, "ro"),
        _var(p.DEVICE_NAME, "Manufacturer device name", dt.VISIBLE_STRING, "const", name),
        _var(p.ERROR_CODE, "Error code", dt.UNSIGNED16, "ro"),
        _var(p.CONTROLWORD, "Controlword", dt.UNSIGNED16, "rw"),
        _var(p.STATUSWORD, "Statusword", dt.UNSIGNED16, "ro"),
        _var(p.MODES_OF_OPERATION, "Modes of operation", dt.INTEGER8, "rw"),
        _var(p.MODES_OF_OPERATION_DISPLAY, "Modes of operation display", dt.INTEGER8, "ro"),
        _var(p.POSITION_ACTUAL, "Position actual value", dt.INTEGER32, "ro"),
        _var(p.VELOCITY_ACTUAL, "Velocity actual value", dt.INTEGER32, "ro"),
        _var(p.TARGET_POSITION, "Target position", dt.INTEGER32, "rw"),
        _var(p.HOME_OFFSET, "Home offset", dt.INTEGER32, "rw"),
        _var(p.PROFILE_VELOCITY, "Profile velocity", dt.UNSIGNED32, "rw", 100_000),
        _var(p.PROFILE_ACCELERATION, "Profile acceleration", dt.UNSIGNED32, "rw", 500_000),
        _var(p.PROFILE_DECELERATION, "Profile deceleration", dt.UNSIGNED32, "rw", 500_000),
        _var(p.HOMING_METHOD, "Homing method", dt.INTEGER8, "rw", 35),
        _var(p.SUPPORTED_DRIVE_MODES, "Supported drive modes", dt.UNSIGNED32, "ro",
             p.SUPPORTED_MODES_BITS),
    ):
        d.add_object(var)
    limits = od.ODRecord("Software position limit", p.SOFTWARE_POSITION_LIMIT)
    limits.add_member(_var(p.SOFTWARE_POSITION_LIMIT, "Number of entries", dt.UNSIGNED8, "ro", 2, 0))
    limits.add_member(_var(p.SOFTWARE_POSITION_LIMIT, "Min position limit", dt.INTEGER32, "rw",
                           -(2**31), 1))
    limits.add_member(_var(p.SOFTWARE_POSITION_LIMIT, "Max position limit", dt.INTEGER32, "rw",
                           2**31 - 1, 2))
    d.add_object(limits)
    return d
