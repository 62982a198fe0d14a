"""Byte transports: serial ports through three asyncio backends, and an in-memory link.

The bus depends only on :class:`Transport`.  :func:`open_transport` turns a URL into a
transport: ``memory://NAME`` for a registered in-memory link, anything else for a serial
port or pyserial URL (``socket://host:port``).
"""

from motorbus.transport.base import (
    CountingTransport,
    DataCallback,
    EchoFilter,
    LostCallback,
    Transport,
    TransportStats,
)
from motorbus.transport.memory import (
    DELIVERY_MODES,
    Delivery,
    MemoryPeer,
    MemoryTransport,
    memory_pair,
    register_memory_link,
    registered_memory_links,
    unregister_memory_link,
)
from motorbus.transport.serial import (
    BACKENDS,
    DEFAULT_BACKEND,
    SerialTransport,
    available_backends,
    open_transport,
)

__all__ = [
    "BACKENDS",
    "DEFAULT_BACKEND",
    "DELIVERY_MODES",
    "CountingTransport",
    "DataCallback",
    "Delivery",
    "EchoFilter",
    "LostCallback",
    "MemoryPeer",
    "MemoryTransport",
    "SerialTransport",
    "Transport",
    "TransportStats",
    "available_backends",
    "memory_pair",
    "open_transport",
    "register_memory_link",
    "registered_memory_links",
    "unregister_memory_link",
]
