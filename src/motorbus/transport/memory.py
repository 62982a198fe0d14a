"""An in-memory serial link: the host side is a :class:`Transport`, the device side a peer.

Simulators attach to :class:`MemoryPeer`; the bus drives :class:`MemoryTransport` exactly
as it would a serial port.  Bytes travel through ``loop.call_soon`` in both directions, so
nothing is delivered re-entrantly inside ``write`` or ``send`` and order is preserved.
Peer-to-host data can be split like a real UART splits it: whole, byte by byte, or at
random (seeded) points, which is how the bus's reassembly is tested against every split.

A small registry maps ``memory://NAME`` URLs to host transports, so code that only takes a
URL (the CLI, :func:`motorbus.transport.open_transport`) can be pointed at a simulator.
"""

from __future__ import annotations

import asyncio
import collections
import itertools
import logging
import random
from collections.abc import Callable
from typing import Literal

from motorbus.errors import BusClosedError, LocalProtocolError
from motorbus.transport.base import CountingTransport, DataCallback, LostCallback, Transport

__all__ = [
    "DELIVERY_MODES",
    "MEMORY_SCHEME",
    "Delivery",
    "MemoryPeer",
    "MemoryTransport",
    "lookup_memory_link",
    "memory_pair",
    "register_memory_link",
    "registered_memory_links",
    "unregister_memory_link",
]

_log = logging.getLogger("motorbus.transport")

#: URL scheme of in-memory links.
MEMORY_SCHEME = "memory://"
#: How peer-to-host bytes are cut into ``on_data`` chunks.
Delivery = Literal["whole", "bytewise", "random"]
#: Every delivery mode, in the order tests parametrise them.
DELIVERY_MODES: tuple[Delivery, ...] = ("whole", "bytewise", "random")
#: Default line speed of a memory link; only used by the bus to compute wire time.
DEFAULT_MEMORY_BAUDRATE = 115200
#: Largest chunk the "random" mode cuts; small enough to split every frame of the three
#: protocols (the longest, an LA status reply, is 22 bytes) in several places.
RANDOM_CHUNK_MAX = 8

_pair_numbers = itertools.count(1)


class MemoryTransport(CountingTransport):
    """Host side of an in-memory link (create it with :func:`memory_pair`)."""

    def __init__(
        self,
        url: str,
        *,
        baudrate: int = DEFAULT_MEMORY_BAUDRATE,
        remove_echo: bool = False,
    ) -> None:
        """Create the host side; use :func:`memory_pair`, which also builds the peer."""
        super().__init__(url, baudrate, remove_echo=remove_echo)
        self._peer: MemoryPeer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._on_data: DataCallback | None = None
        self._on_lost: LostCallback | None = None
        # Bumped on every open and close, so deliveries queued for an earlier session
        # are dropped instead of reaching a later one.
        self._session = 0
        # Chunks sent by the peer and not yet delivered (what a kernel would hold), and
        # how many queued delivery callbacks ``drain_input`` has already done the work of.
        self._inflight: collections.deque[tuple[int, bytes]] = collections.deque()
        self._drained = 0

    @property
    def peer(self) -> MemoryPeer:
        """The device side of this link."""
        if self._peer is None:  # pragma: no cover - memory_pair always attaches one
            raise BusClosedError(f"{self.url}: no peer attached")
        return self._peer

    @property
    def is_open(self) -> bool:
        """True while open and not lost."""
        return self._on_data is not None

    async def open(self, on_data: DataCallback, on_lost: LostCallback) -> None:
        """Open the link.

        Raises:
            LocalProtocolError: already open.
            BusClosedError: the peer is unplugged (a ``ConnectionError``, so an ``OSError``).
        """
        self._refuse_if_open()
        if not self.peer.connected:
            raise BusClosedError(f"{self.url}: the device side is unplugged")
        self._loop = asyncio.get_running_loop()
        self._session += 1
        self._echo.reset()
        self._on_data = on_data
        self._on_lost = on_lost

    def write(self, data: bytes) -> None:
        """Queue ``data`` for the peer's receiver (delivered with ``call_soon``).

        Raises:
            BusClosedError: not open.
        """
        data = self._outgoing(data)
        if data and self._loop is not None:
            self._loop.call_soon(self.peer._receive, data)

    async def close(self) -> None:
        """Close the link; queued deliveries are dropped and ``on_lost`` is not called."""
        self._detach()

    def _detach(self) -> None:
        self._session += 1
        self._on_data = None
        self._on_lost = None
        self._echo.reset()

    def drain_input(self) -> None:
        """Deliver now every chunk the peer has sent and the loop has not delivered yet."""
        while self._inflight:
            self._drained += 1
            self._deliver(*self._inflight.popleft())

    def _schedule(self, chunks: list[bytes]) -> bool:
        """Queue peer-to-host chunks; return False if nobody is listening."""
        if self._loop is None or not self.is_open:
            return False
        for chunk in chunks:
            self._inflight.append((self._session, chunk))
            self._loop.call_soon(self._deliver_next)
        return True

    def _deliver_next(self) -> None:
        if self._drained:
            self._drained -= 1  # ``drain_input`` delivered this callback's chunk
            return
        self._deliver(*self._inflight.popleft())

    def _deliver(self, session: int, chunk: bytes) -> None:
        if session != self._session or self._on_data is None:
            self.peer.dropped_bytes += len(chunk)
            return
        chunk = self._incoming(chunk)
        if chunk:
            self._on_data(chunk)

    def _schedule_lost(self, exc: BaseException) -> None:
        if self._loop is None or not self.is_open:
            return
        self._loop.call_soon(self._lose, self._session, exc)

    def _lose(self, session: int, exc: BaseException) -> None:
        if session != self._session or self._on_lost is None:
            return
        on_lost = self._on_lost
        self._detach()
        on_lost(exc)


class MemoryPeer:
    """Device side of an in-memory link, driven by a simulator.

    Attributes:
        dropped_bytes: bytes sent while the host was not listening (closed or unplugged).
    """

    def __init__(self, host: MemoryTransport, *, delivery: Delivery, seed: int) -> None:
        """Create the peer of ``host``; use :func:`memory_pair`."""
        if delivery not in DELIVERY_MODES:
            raise LocalProtocolError(
                f"delivery={delivery!r} is not allowed: choose one of {', '.join(DELIVERY_MODES)}",
                field="delivery",
                value=delivery,
            )
        self._host = host
        self.delivery: Delivery = delivery
        self._rng = random.Random(seed)
        self._receiver: Callable[[bytes], None] | None = None
        self._connected = True
        self.dropped_bytes = 0

    @property
    def host(self) -> MemoryTransport:
        """The host side of this link."""
        return self._host

    @property
    def connected(self) -> bool:
        """False between :meth:`unplug` and :meth:`plug`."""
        return self._connected

    def set_receiver(self, cb: Callable[[bytes], None]) -> None:
        """Call ``cb`` with every chunk the host writes, as written."""
        self._receiver = cb

    def send(self, data: bytes) -> None:
        """Send ``data`` to the host, cut into chunks by the delivery mode.

        Bytes sent while unplugged or while the host is closed are dropped and counted in
        :attr:`dropped_bytes`, as a real port drops what nobody reads.
        """
        if not data:
            return
        data = bytes(data)
        if not self._connected or not self._host._schedule(self._split(data)):
            self.dropped_bytes += len(data)

    def unplug(self, exc: BaseException | None = None) -> None:
        """Disconnect the link as a USB unplug would.

        The host gets ``on_lost(exc)`` (a :class:`BusClosedError` if ``exc`` is None) after
        the bytes already queued for it, and :meth:`MemoryTransport.open` fails until
        :meth:`plug`.
        """
        if not self._connected:
            return
        self._connected = False
        self._host._schedule_lost(exc or BusClosedError(f"{self._host.url}: device unplugged"))

    def plug(self) -> None:
        """Reconnect the link; the host may open it again."""
        self._connected = True

    def _receive(self, data: bytes) -> None:
        if self._connected and self._receiver is not None:
            self._receiver(data)

    def _split(self, data: bytes) -> list[bytes]:
        if self.delivery == "whole":
            return [data]
        if self.delivery == "bytewise":
            return [data[i : i + 1] for i in range(len(data))]
        chunks = []
        i = 0
        while i < len(data):
            n = self._rng.randint(1, RANDOM_CHUNK_MAX)
            chunks.append(data[i : i + n])
            i += n
        return chunks


def memory_pair(
    *,
    delivery: Delivery = "whole",
    seed: int = 0,
    baudrate: int = DEFAULT_MEMORY_BAUDRATE,
    remove_echo: bool = False,
    name: str | None = None,
) -> tuple[MemoryTransport, MemoryPeer]:
    """Create a connected in-memory link.

    Args:
        delivery: how peer-to-host bytes are cut: ``"whole"`` (one chunk per
            :meth:`MemoryPeer.send`), ``"bytewise"`` (one byte per ``on_data``) or
            ``"random"`` (chunks of 1..``RANDOM_CHUNK_MAX`` bytes).
        seed: seed of the ``"random"`` cuts, so a failing split can be replayed.
        baudrate: line speed reported to the bus (bits per second).
        remove_echo: drop our own echo from received bytes (see :class:`EchoFilter`).
        name: name in the transport's ``memory://`` URL (not registered; see
            :func:`register_memory_link`); a unique one by default.

    Returns:
        ``(host_transport, device_peer)``.

    Raises:
        LocalProtocolError: unknown delivery mode.
    """
    url = MEMORY_SCHEME + (name if name is not None else f"pair-{next(_pair_numbers)}")
    host = MemoryTransport(url, baudrate=baudrate, remove_echo=remove_echo)
    peer = MemoryPeer(host, delivery=delivery, seed=seed)
    host._peer = peer
    return host, peer


_registry: dict[str, Transport] = {}


def _check_name(name: object) -> str:
    if not isinstance(name, str) or not name or "://" in name:
        raise LocalProtocolError(
            f"name={name!r} is not allowed: a non-empty string without '://'",
            field="name",
            value=name,
        )
    return name


def register_memory_link(name: str, transport: Transport) -> None:
    """Make ``memory://NAME`` resolve to ``transport`` in ``open_transport``.

    Registering a name again replaces the earlier transport.

    Raises:
        LocalProtocolError: ``name`` is empty or contains ``://``.
    """
    _registry[_check_name(name)] = transport


def unregister_memory_link(name: str) -> None:
    """Forget ``memory://NAME``; unknown names are ignored."""
    _registry.pop(name, None)


def registered_memory_links() -> list[str]:
    """Return the registered names, sorted."""
    return sorted(_registry)


def lookup_memory_link(url: str) -> Transport:
    """Return the transport registered for a ``memory://NAME`` URL.

    Raises:
        LocalProtocolError: the URL is not a ``memory://`` URL or its name is not registered.
    """
    if not url.startswith(MEMORY_SCHEME):
        raise LocalProtocolError(
            f"url={url!r} is not a {MEMORY_SCHEME}NAME URL", field="url", value=url
        )
    name = url[len(MEMORY_SCHEME) :]
    try:
        return _registry[name]
    except KeyError:
        known = ", ".join(registered_memory_links()) or "none"
        raise LocalProtocolError(
            f"url={url!r}: no memory link named {name!r} is registered (registered: {known})",
            field="url",
            value=url,
        ) from None
