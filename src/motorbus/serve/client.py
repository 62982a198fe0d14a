"""The client side of a served bus: ``motorbus.connect(ENDPOINT)``.

``ServedBus`` has the members of ``Bus`` that the device classes use (``request``,
``submit``, ``send``, ``lease``, ``leases``, ``release``, ``hand_over``, ``events``,
``timer``, ``name``), so ``InspireLA(bus, 3)``, ``ProjectStepper(bus)`` and
``QuadStepper(bus)`` work on it unchanged.  Each request travels as its encoded frame
in a Zenoh query; the server puts it on its real bus (spacing, deadlines, matching,
retries stay next to the wire) and answers with the reply frame, which the client
decodes with the same command.

The deadman: the client holds a liveliness token and publishes a heartbeat from its own
thread; when either stops (the program ended, however it ended, or froze, or its host
left the network) the server ends the client's leases with their safe actions.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import os
import re
import socket
import threading
import time
import uuid
from collections.abc import Iterable
from contextlib import AbstractAsyncContextManager
from types import TracebackType
from typing import TYPE_CHECKING, Any, TypeVar

from motorbus.bus.events import (
    BusStateChanged,
    EventHub,
)
from motorbus.bus.lease_shell import SafeStopper
from motorbus.bus.leases import PROGRAM, LeaseInfo
from motorbus.bus.schedule import Priority
from motorbus.bus.timer import Timer, default_timer
from motorbus.errors import (
    BusClosedError,
    LeaseConflictError,
    LocalProtocolError,
    MotorbusError,
    NotSentError,
    RemoteProtocolError,
    ReplyTimeoutError,
    ServeRefused,
)
from motorbus.protocol import safety
from motorbus.protocol.base import Command, Family, check_flag
from motorbus.serve import keys as k
from motorbus.serve.event_order import EventOrder
from motorbus.serve.zconf import client_config, on_zenoh_thread, zenoh, zenoh_error_text

if TYPE_CHECKING:
    from motorbus.serve.tools_client import ServedDevices, ServedScan

__all__ = ["ServeRefused", "ServedBus", "ServedLease", "ServedSite", "connect"]

R = TypeVar("R")

#: Longest wait for the server to answer a query beyond the request's own time (the
#: server bounds every request by its deadlines; this only catches a vanished server).
QUERY_SLACK_S = 30.0
#: Longest wait for a lease operation or the first contact.
CONTACT_TIMEOUT_S = 5.0

_PRIORITY_NAMES = {
    Priority.NORMAL: "normal",
    Priority.HIGH: "high",
    Priority.EMERGENCY: "emergency",
    Priority.BACKGROUND: "background",
}
_bound: contextvars.ContextVar[tuple[ServedLease, ...]] = contextvars.ContextVar(
    "motorbus_served_leases", default=()
)


def error_from(payload: dict[str, Any]) -> Exception:
    """The exception an error reply stands for (``keys.ERROR_KINDS``)."""
    kind = payload.get("error")
    message = str(payload.get("message", "error"))
    if kind == "lease_conflict":
        err = LeaseConflictError(
            str(payload.get("key")), str(payload.get("owner")), str(payload.get("refused"))
        )
        return err
    if kind in ("bad_payload", "unknown_key"):
        return LocalProtocolError(message, field=payload.get("field"), value=payload.get("value"))
    if kind in ("lease_gone", "closed"):
        return BusClosedError(message)
    if kind == "timeout":
        return ReplyTimeoutError(message)
    if kind == "not_sent":
        return NotSentError(message)
    if kind == "remote":
        raw = payload.get("raw", "")
        return RemoteProtocolError(message, raw=bytes.fromhex(str(raw).replace(" ", "")))
    if kind == "refused":
        return ServeRefused(message)
    return MotorbusError(message)


class ServedLease:
    """A lease held on the server (``ServedBus.lease``); the same use as ``Lease``."""

    def __init__(self, bus: ServedBus, number: int, owner: str, keys: Iterable[str], action: str):
        self.bus = bus
        self.number = number
        self.owner = owner
        self.safe_action = action
        self.implicit = False
        self.active = True
        self.ended = ""  # why it ended without a release (the server went away)
        self._keys = frozenset(keys)

    def __repr__(self) -> str:
        state = "held" if self.active else "released"
        return f"ServedLease(owner={self.owner!r}, keys={sorted(self._keys)}, {state})"

    @property
    def keys(self) -> frozenset[str]:
        return self._keys if self.active else frozenset()

    def add(self, keys: Iterable[str] | str) -> None:
        keys = [keys] if isinstance(keys, str) else list(keys)
        self.bus._lease_op_blocking({"op": "add", "lease": self.number, "keys": keys})
        self._keys |= frozenset(keys)

    async def release(self, *, hold: bool = False, keys: Iterable[str] | None = None) -> None:
        if not self.active:
            return
        check_flag("hold", hold)
        body: dict[str, Any] = {"op": "release", "lease": self.number, "hold": hold}
        if keys is not None:
            keys = body["keys"] = list(
                safety.check_lease_keys(keys, self.bus.families, self.bus.name)
            )
        result = await self.bus._query("lease", body)
        self.active = bool(result.get("active", False))
        if keys is not None:
            self._keys -= frozenset(keys)

    async def __aenter__(self) -> ServedLease:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.release(hold=False)


class ServedBus:
    """One bus of a server, used as a ``Bus`` is (see the module docstring)."""

    def __init__(self, site: ServedSite, name: str, info: dict[str, Any]) -> None:
        self.site = site
        self.name = name
        self.families = frozenset(Family(f) for f in info.get("families", []))
        self.baudrate = int(info.get("baud", 0))
        self.safe_action = str(info.get("safe_action", "pause"))
        self._watch_key = info.get("watch") is True  # reads and stops go on .../watch
        self.events = EventHub()
        self._timer: Timer | None = None
        self._leases: list[ServedLease] = []
        # Events travel apart from replies: put back in the server's order around them.
        self._order = EventOrder(self.events.publish)
        #: The one sender of safe actions, as ``Bus.lease_keeper`` (``stop``,
        #: ``stop_soon``, ``stop_shielded``, ``safe_commands``): emergency requests
        #: through the server.
        self.lease_keeper = SafeStopper(name, self.families, self.request)

    def __repr__(self) -> str:
        return f"ServedBus({self.name!r} at {self.site.endpoint})"

    @property
    def timer(self) -> Timer:
        """The local timer (waits between polls; the bus's own timing is the server's)."""
        if self._timer is None:
            self._timer = default_timer()
        return self._timer

    @property
    def state(self) -> str:
        return self.site.state

    # -- requests ------------------------------------------------------------------------

    async def request(
        self,
        cmd: Command[R],
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
    ) -> R:
        """``Bus.request`` through the server: the decoded reply."""
        future = self.submit(cmd, timeout=timeout, retries=retries, priority=priority)
        try:
            return await future
        except asyncio.CancelledError:
            future.cancel()
            raise

    def submit(
        self,
        cmd: Command[R],
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
        refresh: Any = None,
        lease: ServedLease | None = None,
    ) -> asyncio.Future[R]:
        """``Bus.submit`` through the server.  ``refresh`` runs just before the frame
        leaves this client (None: dropped unsent, the future gives None)."""
        if not isinstance(cmd, Command):
            raise LocalProtocolError(
                f"cmd must be a motorbus Command, got {type(cmd).__name__}", field="cmd"
            )
        if cmd.family not in self.families:
            raise LocalProtocolError(
                f"cmd is a {cmd.family.value} command; bus {self.name} carries "
                f"{', '.join(sorted(f.value for f in self.families))}",
                field="cmd",
            )
        if priority not in _PRIORITY_NAMES:
            raise LocalProtocolError(
                f"priority={priority!r}: allowed {', '.join(p.name for p in _PRIORITY_NAMES)}",
                field="priority",
                value=priority,
            )
        self.site._check_open(self.name)
        return asyncio.ensure_future(self._send(cmd, timeout, retries, priority, refresh, lease))

    async def _send(
        self,
        cmd: Command[Any],
        timeout: float | None,
        retries: int | None,
        priority: Priority,
        refresh: Any,
        lease: ServedLease | None,
    ) -> Any:
        if refresh is not None:
            cmd = refresh()
            if cmd is None:
                return None
        body: dict[str, Any] = {"frame": cmd.encode().hex(), "priority": _PRIORITY_NAMES[priority]}
        if timeout is not None:
            body["timeout"] = timeout
        if retries is not None:
            body["retries"] = retries
        if cmd.starts_motion:
            held = lease if lease is not None else self._bound_lease()
            if held is not None:
                if not held.active:
                    raise BusClosedError(
                        f"{held!r} has ended ({held.ended or 'released'}): "
                        f"{type(cmd).__name__} not sent"
                    )
                body["lease"] = held.number
        # An e-stop also travels first on the link (Zenoh's real-time lane, not batched).
        urgent = priority is Priority.EMERGENCY
        self._order.begin()
        try:
            what = "watch" if self._watch_key and safety.watch_allowed(cmd) else "request"
            result = await self._query(what, body, extra=timeout or 0.0, urgent=urgent)
        except BaseException:
            self._order.fail()
            raise
        before = result.get("events")
        await self._order.end(before if type(before) is int else None)
        reply = result.get("reply")
        return None if reply is None else cmd.decode_reply(bytes.fromhex(reply))

    def _bound_lease(self) -> ServedLease | None:
        """The running task's lease on this bus: the newest that is held, or one that
        ended with the server (its motion is refused: the server holds no lease of
        this client any more, and nothing moves on its own after a restart)."""
        for lease in reversed(_bound.get()):
            if lease.bus is self and (lease.active or lease.ended):
                return lease
        return None

    async def send(self, cmd: Command[object], *, priority: Priority = Priority.NORMAL) -> None:
        """Send a command that expects no reply."""
        await self.request(cmd, priority=priority)

    async def _query(
        self, what: str, body: dict[str, Any], extra: float = 0.0, urgent: bool = False
    ) -> dict[str, Any]:
        key = k.bus_key(self.name, what)
        return await self.site._query(key, body, QUERY_SLACK_S + extra, urgent=urgent)

    # -- leases ------------------------------------------------------------------------------

    def lease(
        self,
        keys: Iterable[str] | str,
        *,
        owner: str,
        safe_action: str = "pause",
        bind: bool = True,
        safe_commands: Iterable[Command[object]] = (),
    ) -> ServedLease:
        """``Bus.lease`` on the server (one round trip; errors raised here; a bad key
        or safe action before it, with nothing sent)."""
        keys = list(safety.check_lease_keys(keys, self.families, self.name))
        safe_action = safety.check_safe_action(safe_action)
        check_flag("bind", bind)
        result = self._lease_op_blocking(
            {
                "op": "acquire",
                "keys": keys,
                "owner": owner,
                "safe_action": safe_action,
                "safe_commands": [c.encode().hex() for c in safe_commands],
            }
        )
        lease = ServedLease(self, int(result["lease"]), owner, keys, safe_action)
        self._leases.append(lease)
        if bind:
            _bound.set((*_bound.get(), lease))
        return lease

    def hand_over(self, lease: ServedLease, keys: Iterable[str]) -> None:
        """``Bus.hand_over``: the devices pass to this client's implicit lease."""
        self._lease_op_blocking({"op": "hand_over", "lease": lease.number, "keys": list(keys)})

    async def release(self, keys: Iterable[str] | None = None, *, hold: bool = False) -> None:
        """``Bus.release``: end this client's motion outside its leases on ``keys``."""
        body: dict[str, Any] = {"op": "release_implicit", "hold": check_flag("hold", hold)}
        if keys is not None:
            body["keys"] = list(safety.check_lease_keys(keys, self.families, self.name))
        await self._query("lease", body)

    @property
    def leases(self) -> tuple[LeaseInfo, ...]:
        """Every leased device now (one round trip); this client's motion outside its
        leases shows as owner ``"program"``, as on a local bus."""
        result = self.site._query_blocking(k.bus_key(self.name, "leases"), {})
        mine = f"client {self.site.client_id}"
        suffix = f" (client {self.site.client_id})"
        out = []
        for row in result.get("leases", []):
            owner = str(row["owner"])
            owner = PROGRAM if owner == mine else owner.removesuffix(suffix)
            frames = tuple(bytes.fromhex(f) for f in row.get("safe_frames", []))
            out.append(LeaseInfo(str(row["key"]), owner, frames))
        return tuple(out)

    def _lease_op_blocking(self, body: dict[str, Any]) -> dict[str, Any]:
        return self.site._query_blocking(k.bus_key(self.name, "lease"), body)

    def served_streamer(self, *, phase: float = 0.0, lead: float | None = None) -> Any:
        """What ``motorbus.Streamer(bus)`` makes of this bus: streams on the server's
        timer (``motorbus.serve.streams_client``); ``lead``: how far ahead of their
        ticks the targets go (default ``LEAD_S``)."""
        from motorbus.serve.streams_client import LEAD_S, ServedStreamer

        return ServedStreamer(self, phase=phase, lead=LEAD_S if lead is None else lead)

    async def fetch_stats(self) -> dict[str, Any]:
        """The server bus's counters (``BusStats.as_dict``)."""
        result = await self._query("stats", {})
        stats: dict[str, Any] = result["stats"]
        return stats

    # -- what the tools ask (motorbus.serve.tools_client) ---------------------------------

    async def fetch_devices(self) -> ServedDevices:
        """What the server's bus declares, what answered it, and its timing (nothing
        is sent on the bus)."""
        from motorbus.serve.tools_client import fetch_devices

        return await fetch_devices(self)

    async def scan(
        self, ids: Iterable[int] | None = None, *, timeout: float | None = None, passes: int = 2
    ) -> ServedScan:
        """Status queries through the server to ``ids`` (default: the LA IDs it knows)."""
        from motorbus.serve.tools_client import scan_served

        return await scan_served(
            self, None if ids is None else list(ids), timeout=timeout, passes=passes
        )

    def frames(self) -> AbstractAsyncContextManager[asyncio.Queue[dict[str, Any]]]:
        """``async with bus.frames() as batches``: the frames the server's bus writes and
        reads, as the server publishes them (it taps its bus only while subscribed)."""
        from motorbus.serve.tools_client import frame_batches

        return frame_batches(self)

    def _lost(self, why: str) -> None:
        for lease in self._leases:
            if lease.active:
                lease.active = False
                lease.ended = why
        self._leases.clear()


class ServedSite:
    """A connection to a ``motorbus serve``: its buses by name (``site.bus(name)``).

    Use as ``async with motorbus.connect("tcp/127.0.0.1:7447") as site:``.
    """

    def __init__(self, endpoint: str, *, config_file: str | None = None, name: str = "") -> None:
        self.endpoint = endpoint
        self.config_file = config_file
        raw = f"{name or 'client'}-{socket.gethostname()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"
        self.client_id = re.sub(r"[^A-Za-z0-9_.\-]", "-", raw)[:128]
        self.buses: dict[str, ServedBus] = {}
        self.instance = ""
        self.liveness = k.LIVENESS_DEFAULT_S
        self.state = "closed"
        self._session: Any = None
        self._entities: list[Any] = []
        self._pending: set[asyncio.Future[Any]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop = threading.Event()
        self._beat: threading.Thread | None = None

    def bus(self, name: str | None = None) -> ServedBus:
        """The served bus ``name`` (may be left out when the server serves one)."""
        if name is None and len(self.buses) == 1:
            return next(iter(self.buses.values()))
        if name not in self.buses:
            raise LocalProtocolError(
                f"bus={name!r}: the server at {self.endpoint} serves "
                f"{', '.join(sorted(self.buses)) or 'no bus'}",
                field="bus",
                value=name,
            )
        return self.buses[name]

    async def open(self) -> None:
        """Connect, learn the buses, hold the token and start the heartbeat."""
        z = zenoh()
        self._loop = asyncio.get_running_loop()
        config = client_config(self.endpoint, self.config_file)
        try:
            self._session = await asyncio.to_thread(z.open, config)
        except Exception as err:
            raise BusClosedError(
                f"cannot reach a motorbus server at {self.endpoint}: {zenoh_error_text(err)}"
            ) from None
        try:
            info = await self._query(f"{k.PREFIX}/info", {}, CONTACT_TIMEOUT_S)
        except BaseException:
            await asyncio.to_thread(self._session.close)
            raise
        self.instance = str(info["instance"])
        self.liveness = float(info.get("liveness_s", k.LIVENESS_DEFAULT_S))
        for name, bus_info in info.get("buses", {}).items():
            self.buses[name] = ServedBus(self, name, bus_info)
        session = self._session
        self._entities.append(session.liveliness().declare_token(k.client_key(self.client_id)))
        self._entities.append(
            session.liveliness().declare_subscriber(
                f"{k.PREFIX}/server/*", self._threadsafe(self._on_server), history=True
            )
        )
        for name, bus in self.buses.items():
            self._entities.append(
                session.declare_subscriber(
                    k.bus_key(name, "event/*"), self._threadsafe(self._event_handler(bus))
                )
            )
        self.state = "open"
        self._beat = threading.Thread(target=self._heartbeat, name="motorbus-serve-heartbeat")
        self._beat.daemon = True
        self._beat.start()

    async def close(self) -> None:
        """Leave the server: it ends this client's leases with their safe actions."""
        self._stop.set()
        if self._beat is not None:
            await asyncio.to_thread(self._beat.join, 2.0)
        self._fail_pending(BusClosedError(f"the connection to {self.endpoint} was closed"))
        session, self._session = self._session, None
        self.state = "closed"
        if session is not None:
            await asyncio.to_thread(session.close)

    async def __aenter__(self) -> ServedSite:
        await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    def _heartbeat(self) -> None:
        key = f"{k.client_key(self.client_id)}/alive"
        period = self.liveness / 4
        while not self._stop.wait(period):
            session = self._session
            if session is None:
                return
            with contextlib.suppress(Exception):
                session.put(key, b"")

    def _threadsafe(self, fn: Any) -> Any:
        loop = self._loop
        assert loop is not None

        def callback(sample: Any) -> None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(fn, sample)

        return on_zenoh_thread(callback)

    def _on_server(self, sample: Any) -> None:
        instance = str(sample.key_expr).rsplit("/", 1)[-1]
        if str(sample.kind).endswith("DELETE"):
            if instance == self.instance and self.state == "open":
                why = f"the server at {self.endpoint} (instance {instance}) went away"
                self.state = "lost"
                self._fail_pending(BusClosedError(why))
                for bus in self.buses.values():
                    bus._lost(f"{why}: its leases ended with it")
                    bus.events.publish(BusStateChanged(bus.name, time.monotonic(), "lost", why))
        elif instance != self.instance or self.state != "open":
            # A (restarted) server: a new instance holds none of our leases.
            old, self.instance = self.instance, instance
            self.state = "open"
            for bus in self.buses.values():
                bus._lost(f"the server restarted (instance {old} -> {instance})")
                bus.events.publish(
                    BusStateChanged(bus.name, time.monotonic(), "reconnected", instance)
                )

    def _event_handler(self, bus: ServedBus) -> Any:
        def handle(sample: Any) -> None:
            try:
                body = k.decode_json(sample.payload.to_bytes())
                event = k.event_from(bus.name, body)
            except (LocalProtocolError, KeyError, ValueError, TypeError):
                return
            if event is not None:
                seq = body.get("seq")
                bus._order.deliver(seq if isinstance(seq, int) else None, event)

        return handle

    def _check_open(self, bus: str) -> None:
        if self.state != "open":
            raise BusClosedError(f"bus {bus} at {self.endpoint} is {self.state}")

    def _fail_pending(self, err: Exception) -> None:
        for future in list(self._pending):
            if not future.done():
                future.set_exception(err)
        self._pending.clear()

    async def _query(
        self, key: str, body: dict[str, Any], timeout: float, urgent: bool = False
    ) -> dict[str, Any]:
        session = self._session
        if session is None:
            raise BusClosedError(f"the connection to {self.endpoint} is closed")
        loop = asyncio.get_running_loop()
        future: asyncio.Future[dict[str, Any]] = loop.create_future()
        self._pending.add(future)

        def settle(value: dict[str, Any] | None, err: Exception | None) -> None:
            self._pending.discard(future)
            if future.done():
                return
            if err is not None:
                future.set_exception(err)
            elif value is not None:
                future.set_result(value)

        def on_reply(reply: Any) -> None:
            value, err = _reply_value(reply)
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(settle, value, err)

        def on_done() -> None:
            err = BusClosedError(self._unanswered(key))
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(settle, None, err)

        z = zenoh()
        payload = k.encode_json({"client": self.client_id, **body})
        lane: dict[str, Any] = {"priority": z.Priority.REAL_TIME, "express": True} if urgent else {}
        handler = on_zenoh_thread(on_reply, on_done)
        session.get(key, handler, payload=payload, timeout=timeout, **lane)
        return await future

    def _query_blocking(self, key: str, body: dict[str, Any]) -> dict[str, Any]:
        """A query answered before this returns (for ``Bus``'s synchronous members)."""
        session = self._session
        if session is None or self.state != "open":
            raise BusClosedError(f"the connection to {self.endpoint} is {self.state}")
        payload = k.encode_json({"client": self.client_id, **body})
        replies = session.get(key, payload=payload, timeout=CONTACT_TIMEOUT_S)
        for reply in replies:
            value, err = _reply_value(reply)
            if err is not None:
                raise err
            assert value is not None
            return value
        raise BusClosedError(self._unanswered(key))

    def _unanswered(self, key: str) -> str:
        return (
            f"no motorbus server answered {key} at {self.endpoint}: none serves it, or the "
            "server's access control does not let this client use that key"
        )


def _reply_value(reply: Any) -> tuple[dict[str, Any] | None, Exception | None]:
    try:
        if reply.ok is not None:
            return k.decode_json(reply.ok.payload.to_bytes()), None
        payload = k.decode_json(reply.err.payload.to_bytes())
        return None, error_from(payload)
    except LocalProtocolError as err:
        return None, MotorbusError(f"the server's answer did not decode: {err}")


def connect(
    endpoint: str, *, config_file: str | os.PathLike[str] | None = None, name: str = ""
) -> ServedSite:
    """The buses a ``motorbus serve`` serves at ``endpoint`` (a Zenoh endpoint such as
    ``tcp/127.0.0.1:7447``): ``async with motorbus.connect(EP) as site: bus =
    site.bus("arm")``, then ``InspireLA(bus, 3)`` as on a local bus.

    Args:
        endpoint: the server's Zenoh endpoint.
        config_file: a Zenoh configuration file (TLS, user/password).
        name: a label for this client in the server's lease owners and logs.

    Raises:
        LocalProtocolError: a bad endpoint, ``config_file`` (not an existing file) or
            ``name`` (at once, nothing sent).

    Raises (on ``open``/``async with``):
        ServeUnavailable: Eclipse Zenoh is not installed (``pip install 'motorbus[serve]'``).
        BusClosedError: no server answers there.
    """
    from motorbus.serve.zconf import check_client_name, check_config_file, check_endpoint

    return ServedSite(
        check_endpoint("endpoint", endpoint),
        config_file=check_config_file(config_file),
        name=check_client_name(name),
    )
