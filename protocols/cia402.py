"""CiA 402 (CANopen drives and motion control): the objects and bits scancell uses.

Pure definitions, no I/O: the object indices, the controlword commands and the statusword bits
of CiA 402 part 2. The object dictionary built from them, as python-canopen wants it, is in
``devices/cia402_dictionary.py``.
"""

from __future__ import annotations

# ---- objects (index, subindex)
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
DEVICE_NAME = 0x1008
ERROR_CODE = 0x603F
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
VELOCITY_ACTUAL = 0x606C
TARGET_POSITION = 0x607A
HOME_OFFSET = 0x607C
SOFTWARE_POSITION_LIMIT = 0x607D  # sub 1 min, sub 2 max
PROFILE_VELOCITY = 0x6081
PROFILE_ACCELERATION = 0x6083
PROFILE_DECELERATION = 0x6084
HOMING_METHOD = 0x6098
SUPPORTED_DRIVE_MODES = 0x6502

#: 0x1000 for a CiA 402 servo drive: profile 402 in the low word, "servo drive" type bits.
DEVICE_TYPE_402_SERVO = 0x00020192

# ---- modes of operation (0x6060 / 0x6061)
MODE_PROFILE_POSITION = 1
MODE_HOMING = 6
SUPPORTED_MODES_BITS = 0x21  # bit 0 profile position, bit 5 homing

# ---- controlword bits (0x6040)
CW_SWITCH_ON = 1 << 0
CW_ENABLE_VOLTAGE = 1 << 1
CW_QUICK_STOP = 1 << 2  # active low
CW_ENABLE_OPERATION = 1 << 3
CW_NEW_SET_POINT = 1 << 4  # profile position; "homing operation start" in homing mode
CW_CHANGE_IMMEDIATELY = 1 << 5
CW_RELATIVE = 1 << 6
CW_FAULT_RESET = 1 << 7  # rising edge
CW_HALT = 1 << 8

# ---- statusword bits (0x6041)
SW_READY_TO_SWITCH_ON = 1 << 0
SW_SWITCHED_ON = 1 << 1
SW_OPERATION_ENABLED = 1 << 2
SW_FAULT = 1 << 3
SW_VOLTAGE_ENABLED = 1 << 4
SW_QUICK_STOP = 1 << 5  # active low
SW_SWITCH_ON_DISABLED = 1 << 6
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
SW_SET_POINT_ACK = 1 << 12  # profile position; "homing attained" in homing mode
SW_FOLLOWING_ERROR = 1 << 13  # profile position; "homing error" in homing mode

#: State name -> (statusword mask, value), as CiA 402 table 30 (and canopen's State402).
STATES: dict[str, tuple[int, int]] = {
    "NOT READY TO SWITCH ON": (0x4F, 0x00),
    "SWITCH ON DISABLED": (0x4F, 0x40),
    "READY TO SWITCH ON": (0x6F, 0x21),
    "SWITCHED ON": (0x6F, 0x23),
    "OPERATION ENABLED": (0x6F, 0x27),
    "QUICK STOP ACTIVE": (0x6F, 0x07),
    "FAULT REACTION ACTIVE": (0x4F, 0x0F),
    "FAULT": (0x4F, 0x08),
}

#: Emergency error codes the simulated drive raises (CiA 301 / 402).
ERROR_FOLLOWING = 0x8611
ERROR_SOFTWARE_LIMIT = 0x8612  # manufacturer use within 0x86xx "positioning controller"
ERROR_GENERIC = 0x1000


def state_of(statusword: int) -> str:
    """The CiA 402 state encoded in a statusword (``"UNKNOWN"`` if none matches)."""
    for name, (mask, value) in STATES.items():
        if statusword & mask == value:
            return name
    return "UNKNOWN"
