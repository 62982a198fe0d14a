"""The small interface every byte transport of motorbus implements.

The bus (``motorbus.bus``) sees a port only through :class:`Transport`: open it with two
callbacks, write bytes without blocking, close it.  Serial backends
(:mod:`motorbus.transport.serial`) and the in-memory link used by the simulators
(:mod:`motorbus.transport.memory`) both implement it, so the bus never knows which one it
drives.  :class:`EchoFilter` is shared by both: half-duplex adapters echo what we send.
"""

from __future__ import annotations

import abc
import logging
from collections.abc import Callable
from dataclasses import dataclass

from motorbus.errors import BusClosedError, LocalProtocolError

__all__ = [
    "ECHO_BUFFER_MAX",
    "CountingTransport",
    "DataCallback",
    "EchoFilter",
    "LostCallback",
    "Transport",
    "TransportStats",
]

_log = logging.getLogger("motorbus.transport")

#: Called from the event loop with each chunk of received bytes (never empty).
DataCallback = Callable[[bytes], None]
#: Called once per open when the port goes away on its own (not for a deliberate close).
LostCallback = Callable[[BaseException | None], None]

#: Most bytes of our own output kept for echo matching.  An echo arrives within one
#: frame's wire time, and the largest frame of the three protocols is far below this, so
#: only a port that never echoes could fill it; past this bound the oldest bytes go.
ECHO_BUFFER_MAX = 4096


@dataclass(slots=True)
class TransportStats:
    """Byte counters of one transport, cumulative over every open.

    ``bytes_in`` counts every byte read from the port, echo included;
    ``echo_bytes_removed`` counts the part of it that was our own echo and was dropped;
    ``bytes_out`` counts every byte handed to the port by :meth:`Transport.write`.
    """

    bytes_in: int = 0
    bytes_out: int = 0
    echo_bytes_removed: int = 0


class EchoFilter:
    """Drop the local echo of a half-duplex adapter from the received stream.

    Every written chunk is remembered (:meth:`expect`); received bytes that equal the
    remembered bytes, in order, are removed.  The first byte that does not match ends
    echo matching: the remembered bytes are forgotten and the rest of the data passes
    through unchanged, because a device reply can only start after our request ended.
    """

    __slots__ = ("_pending",)

    def __init__(self) -> None:
        self._pending = bytearray()

    @property
    def pending(self) -> int:
        """Number of written bytes whose echo has not arrived yet."""
        return len(self._pending)

    def expect(self, data: bytes) -> None:
        """Remember ``data`` (just written) as the echo to expect next."""
        self._pending += data
        overflow = len(self._pending) - ECHO_BUFFER_MAX
        if overflow > 0:
            _log.debug("echo filter: no echo for %d bytes, forgetting the oldest", overflow)
            del self._pending[:overflow]

    def reset(self) -> None:
        """Forget every expected byte (on open and close)."""
        self._pending.clear()

    def feed(self, data: bytes) -> tuple[bytes, int]:
        """Remove the expected echo from the start of ``data``.

        Args:
            data: bytes just received from the port.

        Returns:
            ``(rest, removed)``: the bytes to pass on (possibly empty) and how many echo
            bytes were dropped.
        """
        pending = self._pending
        if not pending:
            return data, 0
        n = 0
        limit = min(len(pending), len(data))
        while n < limit and data[n] == pending[n]:
            n += 1
        if n < len(data):
            if pending[n:]:
                _log.debug(
                    "echo filter: byte %d differs from our output, %d echo bytes dropped",
                    n,
                    len(pending) - n,
                )
            # A mismatch (or data past the whole echo) ends echo matching.
            pending.clear()
        else:
            del pending[:n]
        return data[n:], n


class Transport(abc.ABC):
    """A byte pipe to a bus: a serial port, a TCP serial server or an in-memory link.

    Attributes:
        url: where the transport connects (device path, ``socket://``, ``memory://``).
        baudrate: line speed in bits per second; the bus uses it to compute wire time.
        stats: cumulative byte counters.
    """

    url: str
    baudrate: int
    stats: TransportStats

    @abc.abstractmethod
    async def open(self, on_data: DataCallback, on_lost: LostCallback) -> None:
        """Open the port and start delivering received bytes.

        Args:
            on_data: called from the event loop with every received chunk (never empty).
            on_lost: called at most once per open, with the cause, when the port goes away
                on its own (pty closed, USB unplug, socket closed).  Never called for
                :meth:`close`.

        Raises:
            OSError: the port cannot be opened.
            BusClosedError: the link is unplugged (in-memory link).
            LocalProtocolError: the transport is already open.
        """

    @abc.abstractmethod
    def write(self, data: bytes) -> None:
        """Queue ``data`` for sending; never blocks.

        Raises:
            BusClosedError: the transport is not open.
        """

    @abc.abstractmethod
    async def close(self) -> None:
        """Close the port; idempotent.  ``on_lost`` is not called for a deliberate close."""

    def drain_input(self) -> None:
        """Deliver now, through ``on_data``, the bytes already received but not yet read.

        Never blocks.  The bus calls it right before writing a request: bytes that arrived
        before the write cannot be its reply, yet a lagging event loop would read them
        after it.  A transport that cannot tell does nothing (this default).
        """
        return None

    @property
    @abc.abstractmethod
    def is_open(self) -> bool:
        """True between a successful :meth:`open` and :meth:`close` or loss of the port."""


class CountingTransport(Transport):
    """A :class:`Transport` base that keeps :attr:`stats` and removes local echo.

    Subclasses call :meth:`_outgoing` on every write and :meth:`_incoming` on every
    received chunk, so byte counting and echo removal work the same on every transport.

    Attributes:
        remove_echo: drop our own echo from received bytes (half-duplex adapters).
    """

    def __init__(self, url: str, baudrate: int, *, remove_echo: bool = False) -> None:
        """Set the common attributes (see :class:`Transport`)."""
        self.url = url
        self.baudrate = baudrate
        self.remove_echo = remove_echo
        self.stats = TransportStats()
        self._echo = EchoFilter()

    def _refuse_if_open(self) -> None:
        if self.is_open:
            raise LocalProtocolError(f"{self.url} is already open", field="url", value=self.url)

    def _outgoing(self, data: bytes) -> bytes:
        """Check the port is open, count ``data`` and expect its echo; return it as bytes.

        Raises:
            BusClosedError: the transport is not open.
        """
        if not self.is_open:
            raise BusClosedError(f"{self.url} is not open")
        data = bytes(data)
        self.stats.bytes_out += len(data)
        if self.remove_echo and data:
            self._echo.expect(data)
        return data

    def _incoming(self, data: bytes) -> bytes:
        """Count received ``data`` and strip our echo; return what ``on_data`` should get."""
        self.stats.bytes_in += len(data)
        if self.remove_echo:
            data, removed = self._echo.feed(data)
            self.stats.echo_bytes_removed += removed
        return data


def check_transport(value: object) -> Transport:
    """``value`` if it is a :class:`Transport`; ``LocalProtocolError`` naming it otherwise
    (``Bus(None)`` failed with an ``AttributeError`` on the transport's URL)."""
    if not isinstance(value, Transport):
        raise LocalProtocolError(
            f"transport must be a motorbus Transport (motorbus.open_transport(url, "
            f"baudrate=...)), got {value!r}",
            field="transport",
            value=value,
        )
    return value
