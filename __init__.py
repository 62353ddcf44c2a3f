"""scancell: software for robot-integrated fringe-projection 3D scanning cells.

Units everywhere are mm, radians and seconds; timestamps are int nanoseconds (UTC, host clock).
"""

__version__ = "0.1.0"
