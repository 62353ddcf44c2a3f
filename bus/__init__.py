"""The message bus: zenoh sessions (``zenoh_bus``), an in-process bus for reprocessing
(``local``), and the ``BusLike`` protocol both implement."""

from scancell.bus.protocol import BusLike, BusSample, Latched, Subscription
from scancell.bus.zenoh_bus import (
    DEFAULT_ENDPOINT,
    ENV_CONNECT,
    AccessDenied,
    Bus,
    BusConfig,
    LatchedPublisher,
    NoDaemon,
    open_session,
    sample_from_zenoh,
)

__all__ = ["DEFAULT_ENDPOINT", "ENV_CONNECT", "AccessDenied", "Bus", "BusConfig", "BusLike",
           "BusSample", "Latched", "LatchedPublisher", "NoDaemon", "Subscription", "open_session",
           "sample_from_zenoh"]
