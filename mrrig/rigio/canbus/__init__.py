"""CAN contract in code: DBC-driven codec with AUTOSAR E2E and python-can buses."""

from mrrig.rigio.canbus.bus import BusError, find_free_port, open_bus, start_bridge, stop_bridge
from mrrig.rigio.canbus.codec import (
    DEFAULT_DBC_PATH,
    Codec,
    EncodeError,
    MessageStats,
    Packer,
    Parsed,
    Parser,
)
from mrrig.rigio.canbus.layout import CodecError, MessageLayout

__all__ = [
    "DEFAULT_DBC_PATH",
    "BusError",
    "Codec",
    "CodecError",
    "EncodeError",
    "MessageLayout",
    "MessageStats",
    "Packer",
    "Parsed",
    "Parser",
    "find_free_port",
    "open_bus",
    "start_bridge",
    "stop_bridge",
]
