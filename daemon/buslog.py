"""A logging handler that publishes records as foxglove.Log on ``<cell>/daemon/log``."""

from __future__ import annotations

import logging

from scancell.bus import Bus
from scancell.protocols import foxglove_schemas as fg


class BusLogHandler(logging.Handler):
    def __init__(self, bus: Bus, level: int = logging.INFO) -> None:
        super().__init__(level)
        self.bus = bus

    def emit(self, record: logging.LogRecord) -> None:
        try:
            msg = fg.log_message(record.levelname, self.format(record), record.name,
                                       int(record.created * 1e9))
            self.bus.publish(self.bus.keys.daemon_log, fg.encode_proto(msg))
        except Exception:  # the bus may be closing; never let logging raise
            self.handleError(record)
