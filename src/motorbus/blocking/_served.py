"""Served buses without ``await``: ``motorbus.blocking.connect(ENDPOINT)``.

``connect`` opens a connection to a ``motorbus serve`` before it returns (as ``Bus``
opens its port); ``site.bus(name)`` is a :class:`ServedBus`, which the blocking
devices, streamers, group reads, leases and events take as they take a local
:class:`~motorbus.blocking.Bus`.  Behind it is the asyncio served client
(``motorbus.serve.client``), on the blocking runner's loop, unchanged: the requests,
the leases and the deadman are its own.

Closing the connection (``site.close()`` or ``bus.close()``, the end of either's
``with`` block however it is left, Ctrl-C in a blocking call, SIGTERM, the
interpreter's exit) is the served client's normal close: the server ends this
client's streams and leases with their safe actions.  A process killed outright gets
the server's deadman, as any client does.

What a served bus cannot do, and why, fails at the call with nothing sent: ``stats``
(the counters live in the server: ``fetch_stats()`` fetches them).
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Iterable
from types import TracebackType
from typing import Any, cast

from motorbus.blocking._bus import BusView, Lease
from motorbus.blocking._proxy import Closing, Proxy, coroutine
from motorbus.blocking._runner import runner
from motorbus.bus.jobs import BusState
from motorbus.bus.leases import LeaseInfo
from motorbus.errors import LocalProtocolError, ReplyTimeoutError, WrongLoopError
from motorbus.protocol.base import Command, Family
from motorbus.serve import client as _client
from motorbus.serve.tools_client import ServedScan
from motorbus.serve.zconf import zenoh

__all__ = ["FrameFeed", "ServedBus", "ServedSite", "connect"]

_STATES = {"open": BusState.OPEN, "lost": BusState.LOST, "closed": BusState.CLOSED}


def connect(
    endpoint: str, *, config_file: str | os.PathLike[str] | None = None, name: str = ""
) -> ServedSite:
    """The buses a ``motorbus serve`` serves at ``endpoint``, connected now:
    ``with mb.connect("tcp/127.0.0.1:7447") as site: bus = site.bus("arm")``, then
    ``mb.InspireLA(bus, 3)`` as on a local bus (``motorbus.connect`` without ``await``).

    Args:
        endpoint: the server's Zenoh endpoint (``PROTOCOL/ADDRESS``).
        config_file: a Zenoh configuration file (TLS, user/password).
        name: a label for this client in the server's lease owners and logs.

    Raises:
        ServeUnavailable: Eclipse Zenoh is not installed (``pip install 'motorbus[serve]'``).
        LocalProtocolError: a bad endpoint, configuration file or name (nothing sent).
        BusClosedError: no server answers there.
    """
    return ServedSite(endpoint, config_file=config_file, name=name)


class ServedSite(Closing, Proxy[_client.ServedSite]):
    """A connection to a ``motorbus serve``: :class:`motorbus.serve.ServedSite` without
    ``await``, opened before the constructor returns (``connect`` makes one).

    Use it as a context manager, or ``close()`` it: closing ends this client's
    streams and leases on the server with their safe actions.
    """

    _views: dict[str, ServedBus]

    def __init__(
        self,
        endpoint: str,
        *,
        config_file: str | os.PathLike[str] | None = None,
        name: str = "",
    ) -> None:
        zenoh()  # ServeUnavailable, naming the extra, before anything else
        aio = _client.connect(endpoint, config_file=config_file, name=name)  # checks them
        self._runner = runner()
        self._aio = aio
        self._views = {}
        self._runner.track(aio)  # closed with the buses on Ctrl-C, SIGTERM, at exit
        try:
            self._runner.call(aio.open())
        except BaseException:
            self._runner.untrack(aio)
            raise
        self._runner.opened()

    @property
    def endpoint(self) -> str:
        """The server's Zenoh endpoint."""
        return self._aio.endpoint

    @property
    def client_id(self) -> str:
        """This client's ID on the server (in its lease owners and logs)."""
        return self._aio.client_id

    @property
    def state(self) -> str:
        """``"open"``, ``"lost"`` (the server went away; it reconnects on its own when
        the server is back) or ``"closed"``."""
        return self._aio.state

    @property
    def closed(self) -> bool:
        """True once this connection is closed."""
        return self._aio.state == "closed"

    @property
    def buses(self) -> tuple[str, ...]:
        """The names of the buses the server serves."""
        return tuple(self._aio.buses)

    def bus(self, name: str | None = None) -> ServedBus:
        """The served bus ``name`` (may be left out when the server serves one).

        Raises:
            LocalProtocolError: no such bus (the message lists the served ones).
        """
        aio = self._aio.bus(name)
        view = self._views.get(aio.name)
        if view is None:
            view = self._views[aio.name] = ServedBus._of(aio, self._runner)
            view._site = self
        return view

    def close(self) -> None:
        """Leave the server (idempotent): it ends this client's streams and leases with
        their safe actions.  A Ctrl-C meanwhile is raised once it is done."""
        self._runner.untrack(self._aio)
        self._runner.finish(self._aio.close())


class ServedBus(BusView[_client.ServedBus]):
    """One bus of a server, used as a blocking :class:`~motorbus.blocking.Bus` is:
    ``mb.InspireLA(bus, 1)``, ``mb.Streamer(bus).follow(...)``, ``bus.lease(...)``,
    ``bus.events``, ``bus.read_statuses(...)``.  Made by ``site.bus(name)``.

    ``close()`` (and the end of its ``with`` block) closes the connection it belongs
    to, as closing a local bus ends the program's use of it: so
    ``with mb.connect(EP).bus() as bus:`` stands where ``with mb.Bus(...) as bus:`` did.
    """

    _site: ServedSite

    @property
    def site(self) -> ServedSite:
        """The connection this bus belongs to."""
        return self._site

    @property
    def families(self) -> frozenset[Family]:
        """The device families the server's bus carries."""
        return self._aio.families

    @property
    def baudrate(self) -> int:
        """The server bus's rate in bit/s."""
        return self._aio.baudrate

    @property
    def safe_action(self) -> str:
        """The server bus's safe action for motion outside any lease."""
        return self._aio.safe_action

    @property
    def state(self) -> BusState:
        """``BusState.OPEN``, ``LOST`` (the server went away) or ``CLOSED``, as a local
        bus says it."""
        return _STATES.get(self._aio.state, BusState.LOST)

    @property
    def closed(self) -> bool:
        """True once the connection is closed."""
        return self._site.closed

    @property
    def stats(self) -> Any:
        """Not on a served bus: a local bus's live counters are its own; a served bus's
        are the server's.  ``fetch_stats()`` fetches them (``BusStats.as_dict``)."""
        raise AttributeError(
            f"bus.stats: the counters of served bus {self.name!r} live in the server at "
            f"{self._site.endpoint}, not in this process; bus.fetch_stats() fetches them "
            "(a dict, as BusStats.as_dict gives)"
        )

    fetch_stats = coroutine(_client.ServedBus.fetch_stats)
    fetch_devices = coroutine(_client.ServedBus.fetch_devices)
    release = coroutine(_client.ServedBus.release)

    def scan(
        self, ids: Iterable[int] | None = None, *, timeout: float | None = None, passes: int = 2
    ) -> ServedScan:
        """Status queries through the server to ``ids`` (default: the LA IDs it knows)."""
        wanted = None if ids is None else list(ids)
        return self._runner.call(self._aio.scan(wanted, timeout=timeout, passes=passes))

    @property
    def leases(self) -> tuple[LeaseInfo, ...]:
        """Every leased device now (one round trip, from this thread); this client's
        motion outside its leases shows as owner ``"program"``, as on a local bus."""
        self._not_on_the_loop("bus.leases")
        return self._aio.leases

    def lease(
        self,
        keys: Iterable[str] | str,
        *,
        owner: str,
        safe_action: str = "pause",
        safe_commands: Iterable[Command[object]] = (),
    ) -> Lease:
        """Hold ``keys`` for ``owner`` on the server from now on (one round trip).

        As on a local bus, the lease belongs to the calling thread: the motion it sends
        from now on is the lease's.  ``with bus.lease(...):`` releases it with its
        safe action however the block is left; so does closing the connection.

        Raises:
            LeaseConflictError: another owner (another client, too) holds a device.
            LocalProtocolError: a bad key or action (nothing sent), or owner.
        """
        self._not_on_the_loop("bus.lease")
        # The keys and the action are checked by the served bus's lease, before it
        # sends anything (safety.check_lease_keys, as a local bus's).
        # Taken from this thread, bound in its context: every later call from this
        # thread carries it (the runner runs each call in a copy of that context).
        held = self._aio.lease(
            keys,
            owner=owner,
            safe_action=safe_action,
            bind=True,
            safe_commands=tuple(safe_commands),
        )
        return Lease._of(cast(Any, held), self._runner)

    def frames(self) -> FrameFeed:
        """``with bus.frames() as feed: feed.next(timeout=1.0)``: the frames the server's
        bus writes and reads, batch by batch, as it publishes them."""
        return FrameFeed(self)

    def _not_on_the_loop(self, what: str) -> None:
        # Both wait for the server's answer in the calling thread: on the bus's thread
        # (a target callback) that would stall every stream of the process meanwhile.
        if self._runner.in_loop_thread():
            raise WrongLoopError(
                f"{what} from the bus thread itself (a target callback or an event "
                "handler) would stall it for a round trip: use the asyncio API there"
            )

    def close(self) -> None:
        """Close the connection this bus belongs to (``site.close()``): the server ends
        this client's streams and leases with their safe actions, on every bus."""
        self._site.close()


class FrameFeed:
    """The server bus's frames, batch by batch (``ServedBus.frames``): each batch is
    ``{"time", "frames": [[t, "tx" | "rx", HEX], ...]}`` on the server bus's clock.
    The server taps its bus only while the ``with`` block lasts."""

    def __init__(self, bus: ServedBus) -> None:
        self._bus = bus
        self._runner = bus._runner
        self._context = bus._aio.frames()
        self._queue: asyncio.Queue[dict[str, Any]] | None = None

    def __enter__(self) -> FrameFeed:
        self._queue = self._runner.call(self._context.__aenter__())
        return self

    def next(self, timeout: float | None = None) -> dict[str, Any]:
        """The next batch, waiting up to ``timeout`` seconds (None: no limit).

        Raises:
            ReplyTimeoutError: none came within ``timeout``.
            LocalProtocolError: called outside the ``with`` block.
        """
        queue = self._queue
        if queue is None:
            raise LocalProtocolError("use the feed inside `with bus.frames() as feed:`")

        async def take() -> dict[str, Any]:
            async with asyncio.timeout(timeout):
                return await queue.get()

        try:
            return self._runner.call(take())
        except TimeoutError:
            raise ReplyTimeoutError(f"no frames from {self._bus.name} within {timeout} s") from None

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self._queue = None
        self._runner.finish(self._context.__aexit__(None, None, None))
