"""The server side of a served bus: real ``Bus`` objects behind Zenoh queries.

One ``BusServer`` serves open buses (``motorbus serve`` opens them with a
``BusManager``, so every key of the bus file is honoured).  What must stay next to the
wire stays on the bus: spacing, deadlines, matching, retries, leases and their safe
ends.  A client sends a request frame; the server decodes it into its ``Command``
(refusing any frame that is not a request of the bus's families), submits it on the
bus and answers with the reply frame (``motorbus.serve.keys`` has the payloads).

Leases: each client's motion belongs to a lease of that client (owner ``"client ID"``
for motion outside the client's own leases), so a client moving a device another
client holds is refused (``LeaseConflictError`` naming the holder).  The deadman: a
client's leases end with their safe actions (the bus's lease machinery sends them)
when its Zenoh liveliness token goes (it closed, crashed, was killed: its link
closes) or when its heartbeat stops for ``liveness`` seconds (it froze, or its host
lost the network without a reset).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
import uuid
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from motorbus.bus.bus import Bus, Priority
from motorbus.bus.events import (
    BusEvent,
    FaultChanged,
    Subscription,
)
from motorbus.bus.leases import Lease, LeaseInfo
from motorbus.errors import (
    LeaseConflictError,
    LocalProtocolError,
    ServedRefusal,
)
from motorbus.protocol import safety
from motorbus.protocol.base import Command
from motorbus.serve import keys as k
from motorbus.serve.streams_server import StreamService
from motorbus.serve.tap import raw_reply, reply_mark, tapped
from motorbus.serve.tools_server import ToolsService
from motorbus.serve.zconf import (
    any_port,
    bound_endpoint,
    on_zenoh_thread,
    server_config,
    zenoh,
)

__all__ = ["BusServer"]

log = logging.getLogger("motorbus.serve")

#: Events a bus server remembers after publishing them (``BusServer._own_fault``).
RECENT_EVENTS = 64

_PRIORITY = {
    "normal": Priority.NORMAL,
    "high": Priority.HIGH,
    "emergency": Priority.EMERGENCY,
    "background": Priority.BACKGROUND,  # a dashboard's status polls: after everything else
}
_LEASE_OPS = ("acquire", "add", "hand_over", "release", "release_implicit")
#: The fields each query payload may carry (docs/serve.md); any other is refused.
_READ_FIELDS = frozenset({"client"})
_REQUEST_FIELDS = frozenset({"client", "frame", "timeout", "retries", "priority", "lease"})
_LEASE_FIELDS = frozenset(
    {"client", "op", "keys", "owner", "safe_action", "safe_commands", "lease", "hold"}
)
#: How often the heartbeat check runs, as a share of the liveness timeout.
_CHECKS_PER_LIVENESS = 10
#: How long a client whose Zenoh session ended is remembered (seconds): a query it sent
#: before it ended may reach the server after its end did, and must not move anything.
_GONE_KEEP_S = 60.0


@dataclass
class _Client:
    """What the server knows of one client."""

    id: str
    last_seen: float
    #: bus name -> the lease of the client's motion outside its own leases.
    implicit: dict[str, Lease] = field(default_factory=dict)
    #: lease number -> (bus name, lease) of the leases the client took.
    explicit: dict[int, tuple[str, Lease]] = field(default_factory=dict)
    ended: str = ""  # why its leases were ended (told once to its next motion)
    #: When its Zenoh session ended (``time.monotonic``), 0.0 while it lives: its
    #: queries are refused from then on (``BusServer._client``).
    gone: float = 0.0


class BusServer:
    """Serve ``buses`` (open ``Bus`` objects by name) on a Zenoh endpoint.

    Args:
        buses: the buses to serve, by name (each one key chunk).
        listen: the Zenoh endpoint (default loopback, ``tcp/127.0.0.1:7447``); port 0
            takes any free port, which ``endpoint`` names once started.
        liveness: seconds without a client's heartbeat before its leases end
            (``keys.LIVENESS_MIN_S``..``LIVENESS_MAX_S``, default 1).
        zenoh_config: a Zenoh configuration file (TLS, access control, routers).
        watch_only: refuse every motion and lease: clients may only watch and query.
        devices: the device keys each bus declares, by bus name (its ``devices`` query).
    """

    def __init__(
        self,
        buses: Mapping[str, Bus],
        *,
        listen: str = "tcp/127.0.0.1:7447",
        liveness: float = k.LIVENESS_DEFAULT_S,
        zenoh_config: str | None = None,
        watch_only: bool = False,
        devices: Mapping[str, Sequence[str]] | None = None,
    ) -> None:
        if not buses:
            raise LocalProtocolError("a server needs at least one bus", field="buses")
        for name in buses:
            k.check_chunk("bus", name)
        self.liveness = k.check_liveness(liveness)
        self.buses = dict(buses)
        self.listen = listen
        #: Where clients connect: ``listen``, with the port it was given once started.
        self.endpoint = listen
        self.watch_only = watch_only
        self.instance = uuid.uuid4().hex[:12]
        self._config = server_config(listen, zenoh_config)
        self._session: Any = None
        self._declared: list[Any] = []
        self._publishers: dict[str, Any] = {}
        # Per bus: events published so far (the last one's ``seq``), and the forwarder's
        # subscription (events taken off the bus but not yet published).
        self._events_out: dict[str, int] = {}
        self._event_subs: dict[str, Subscription[BusEvent]] = {}
        #: Per bus: the last events published, by ``seq`` (``_own_fault``).
        self._recent: dict[str, deque[tuple[int, BusEvent]]] = {}
        self._clients: dict[str, _Client] = {}
        self._lease_numbers = 0
        self._tasks: set[asyncio.Task[Any]] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._listeners: list[tuple[Bus, Callable[[tuple[LeaseInfo, ...]], None]]] = []
        #: Deadman ends so far: (client id, seconds from noticing to the last safe frame).
        self.deadman_ends: list[tuple[str, float]] = []
        #: Served streams (``motorbus.serve.streams_server``): the ``stream`` keys.
        self._streams = StreamService(self)
        self.tools = ToolsService(self.buses, devices or {})

    # -- life cycle --------------------------------------------------------------------

    async def start(self) -> None:
        """Open the Zenoh session and declare every key; raises if ``listen`` is taken."""
        z = zenoh()
        self._loop = asyncio.get_running_loop()
        self._session = await asyncio.to_thread(z.open, self._config)
        session = self._session
        if any_port(self.listen):
            self.endpoint = await asyncio.to_thread(bound_endpoint, session, self.listen)
        self._declare(session.declare_queryable(f"{k.PREFIX}/info", self._on_query(self._info)))
        for name, bus in self.buses.items():
            self._declare(
                session.declare_queryable(
                    k.bus_key(name, "request"),
                    self._on_query(self._request, name, exact=k.bus_key(name, "request")),
                )
            )
            self._declare(
                session.declare_queryable(
                    k.bus_key(name, "watch"),
                    self._on_query(self._watch, name, exact=k.bus_key(name, "watch")),
                )
            )
            self._declare(
                session.declare_queryable(
                    k.bus_key(name, "lease"),
                    self._on_query(self._lease, name, exact=k.bus_key(name, "lease")),
                )
            )
            self._declare(
                session.declare_queryable(
                    k.bus_key(name, "leases"), self._on_query(self._leases, name)
                )
            )
            self._declare(
                session.declare_queryable(
                    k.bus_key(name, "stats"), self._on_query(self._stats, name)
                )
            )
            self._publishers[name] = session.declare_publisher(k.bus_key(name, "leases"))
            self._streams.declare(session, name)
            self._spawn(self._forward_events(name, bus))
            self._watch_leases(name, bus)
        self._declare(
            session.liveliness().declare_subscriber(
                f"{k.CLIENT_PREFIX}/*", self._threadsafe(self._on_token), history=True
            )
        )
        self._declare(
            session.declare_subscriber(
                f"{k.CLIENT_PREFIX}/*/alive", self._threadsafe(self._on_heartbeat)
            )
        )
        self._declared += self.tools.start(session, self._on_query, self._threadsafe)
        self._declare(session.liveliness().declare_token(k.server_key(self.instance)))
        self._spawn(self._check_heartbeats())

    async def close(self) -> None:
        """End every client's leases (safe actions), stop serving, close the session."""
        for client in list(self._clients.values()):
            await self._end_client(client, "the server is closing")
        for task in list(self._tasks):
            task.cancel()
        for task in list(self._tasks):
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        for bus, fn in self._listeners:
            bus.remove_lease_listener(fn)
        self._listeners.clear()
        self.tools.close()
        session, self._session = self._session, None
        if session is not None:
            await asyncio.to_thread(session.close)

    async def __aenter__(self) -> BusServer:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    def _declare(self, entity: Any) -> None:
        self._declared.append(entity)

    def _spawn(self, coro: Any) -> None:
        task = asyncio.ensure_future(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _threadsafe(self, fn: Callable[[Any], None]) -> Any:
        """A Zenoh callback (a Zenoh thread) that runs ``fn`` on the server's loop."""
        loop = self._loop
        assert loop is not None

        def callback(sample: Any) -> None:
            with contextlib.suppress(RuntimeError):  # the loop closed: nothing to do
                loop.call_soon_threadsafe(fn, sample)

        return on_zenoh_thread(callback)

    # -- queries -----------------------------------------------------------------------

    def _on_query(self, handler: Callable[..., Any], *args: Any, exact: str | None = None) -> Any:
        """A Zenoh handler answering queries with ``handler``.  ``exact``: answer only
        a query naming this key (a request or lease query with a wildcard,
        ``motorbus/v1/bus/*/request``, would act on every bus)."""

        def run(query: Any) -> None:
            self._spawn(self._answer(query, handler, args, exact))

        return self._threadsafe(run)

    async def _answer(
        self, query: Any, handler: Callable[..., Any], args: tuple[Any, ...], exact: str | None
    ) -> None:
        try:
            try:
                if exact is not None and str(query.key_expr) != exact:
                    raise k.PayloadError(
                        f"key={str(query.key_expr)!r}: a request or lease query names one "
                        f"bus, without wildcards ({exact}); nothing sent",
                        field="key",
                        value=str(query.key_expr),
                    )
                raw = b"" if query.payload is None else query.payload.to_bytes()
                payload = k.decode_json(raw) if raw else {}
                result = await handler(*args, payload)
                query.reply(query.key_expr, k.encode_json({"ok": True, **result}))
            except ServedRefusal as err:
                query.reply_err(k.encode_json(err.payload))
            except k.PayloadError as err:
                query.reply_err(
                    k.encode_json(
                        k.error_payload("bad_payload", str(err), field=err.field, value=err.value)
                    )
                )
            except asyncio.CancelledError:
                query.reply_err(k.encode_json(k.error_payload("closed", "the server is closing")))
                raise
            except Exception as err:  # every other error goes back to that client only
                query.reply_err(k.encode_json(k.error_of(err)))
        except Exception as err:  # the client went away: nothing to answer
            log.debug("could not answer a query: %s", err)
        finally:
            with contextlib.suppress(Exception):
                query.drop()

    async def _info(self, payload: dict[str, Any]) -> dict[str, Any]:
        k.only_fields(payload, _READ_FIELDS)
        return {
            "version": k.VERSION,
            "instance": self.instance,
            "pid": os.getpid(),
            "liveness_s": self.liveness,
            "watch_only": self.watch_only,
            "buses": {
                name: {
                    "families": sorted(f.value for f in bus.families),
                    "baud": bus.baudrate,
                    "safe_action": bus.safe_action,
                    "state": bus.state.value,
                    "watch": True,  # reads and stops also on .../watch
                }
                for name, bus in self.buses.items()
            },
        }

    def _bus(self, name: str) -> Bus:
        return self.buses[name]

    def _client(self, payload: dict[str, Any]) -> _Client:
        cid = k.check_chunk("client", k.field_of(payload, "client", str))
        client = self._clients.get(cid)
        if client is None:
            client = self._clients[cid] = _Client(cid, time.monotonic())
        elif client.gone:
            # A query sent before its client ended that arrived after the end did (they
            # travel apart): nothing of a client that has ended reaches the wire.
            raise ServedRefusal(
                k.error_payload(
                    "lease_gone",
                    f"client {client.id}: its Zenoh session ended and its leases with it; "
                    "nothing sent",
                )
            )
        return client

    async def _watch(self, name: str, payload: dict[str, Any]) -> dict[str, Any]:
        """``.../watch``: a request that may only read or stop (``safety.watch_allowed``),
        so that access control can let a user watch a bus and not move it."""
        return await self._request(name, payload, watch=True)

    async def _request(
        self, name: str, payload: dict[str, Any], *, watch: bool = False
    ) -> dict[str, Any]:
        k.only_fields(payload, _REQUEST_FIELDS)
        bus = self._bus(name)
        client = self._client(payload)
        cmd = k.decode_frame(k.hex_field(payload, "frame"), sorted(bus.families, key=str))
        timeout = k.field_of(payload, "timeout", (int, float), optional=True)
        retries = k.field_of(payload, "retries", int, optional=True)
        priority_name = k.field_of(payload, "priority", str, optional=True, default="normal")
        if priority_name not in _PRIORITY:
            raise k.PayloadError(
                f"priority={priority_name!r}: allowed {', '.join(k.PRIORITIES)}",
                field="priority",
                value=priority_name,
            )
        if watch and not safety.watch_allowed(cmd):
            raise ServedRefusal(
                k.error_payload(
                    "refused",
                    f"{k.bus_key(name, 'watch')} carries reads and stops only, not "
                    f"{type(cmd).__name__}: send it on {k.bus_key(name, 'request')} (nothing sent)",
                )
            )
        if self.watch_only and not safety.watch_allowed(cmd):
            raise ServedRefusal(
                k.error_payload(
                    "refused",
                    f"this server lets clients only watch: client {client.id} may read and "
                    f"stop devices, not send {type(cmd).__name__} (nothing sent)",
                )
            )
        lease = None
        if cmd.starts_motion:
            lease = self._motion_lease(client, name, bus, cmd, payload.get("lease"))
        # The events count as the reply came off the wire (an EE DD right behind a
        # start's acknowledgement is after it, however soon this handler runs again).
        sent = tapped(cmd, marker=lambda: self._events_so_far(name))
        future = bus.submit(
            sent, timeout=timeout, retries=retries, priority=_PRIORITY[priority_name], lease=lease
        )
        try:
            await future
        except asyncio.CancelledError:
            future.cancel()
            raise
        raw = raw_reply(sent)
        events = reply_mark(sent)
        if events is None:  # no reply (a command that expects none): the count now
            events = self._events_so_far(name)
        elif self._own_fault(name, events + 1, future.result()):
            events += 1  # the reply's own fault event, published as it was taken: before it
        return {"reply": None if raw is None else raw.hex(), "events": events}

    def _events_so_far(self, name: str) -> int:
        """The ``seq`` of the bus's last event before now: published, or taken off the bus
        and about to be (a reply carries it, so that the client can tell the events that
        came before the reply from those after, whatever order they arrive in)."""
        return self._events_out.get(name, 0) + len(self._queued_events(name))

    def _queued_events(self, name: str) -> list[BusEvent]:
        """The bus's events taken off it and not yet published that will be (in order)."""
        sub = self._event_subs.get(name)
        return [] if sub is None else [e for e in sub.queued() if k.event_payload(e) is not None]

    def _own_fault(self, name: str, seq: int, status: object) -> bool:
        """Is the bus's event ``seq`` the fault change of the reply ``status`` (the bus
        publishes it as it takes the reply, as on a local bus)?"""
        out = self._events_out.get(name, 0)
        if seq > out:
            queued = self._queued_events(name)
            event = queued[seq - out - 1] if seq - out <= len(queued) else None
        else:
            event = next((e for n, e in self._recent.get(name, ()) if n == seq), None)
        return isinstance(event, FaultChanged) and event.status is status

    def _motion_lease(
        self, client: _Client, name: str, bus: Bus, cmd: Command[object], number: object
    ) -> Lease:
        """The lease a client's motion command belongs to (its own, or its implicit one)."""
        self._check_control(client)
        if number is not None:
            return self._explicit(client, name, number)
        lease = client.implicit.get(name)
        if lease is None or not lease.active:
            lease = bus.lease(
                safety.motion_keys(cmd),
                owner=f"client {client.id}",
                safe_action=bus.safe_action,
                bind=False,
            )
            client.implicit[name] = lease
        return lease

    def _check_control(self, client: _Client) -> None:
        if self.watch_only:
            raise ServedRefusal(
                k.error_payload(
                    "refused",
                    f"this server lets clients only watch: client {client.id} may not move "
                    "devices or take leases (nothing sent)",
                )
            )
        if client.ended:
            why, client.ended = client.ended, ""
            raise ServedRefusal(
                k.error_payload(
                    "lease_gone",
                    f"client {client.id}: {why}; nothing sent (send again to go on)",
                )
            )

    def _explicit(self, client: _Client, name: str, number: object) -> Lease:
        if isinstance(number, bool) or not isinstance(number, int):
            raise k.PayloadError(f"lease={number!r} must be an int", field="lease", value=number)
        held = client.explicit.get(number)
        if held is None or held[0] != name or not held[1].active:
            raise ServedRefusal(
                k.error_payload(
                    "lease_gone",
                    f"lease {number} of client {client.id} is not held on bus {name} "
                    f"(server instance {self.instance}: it ended, or the server restarted)",
                )
            )
        return held[1]

    async def _lease(self, name: str, payload: dict[str, Any]) -> dict[str, Any]:
        k.only_fields(payload, _LEASE_FIELDS)
        bus = self._bus(name)
        client = self._client(payload)
        op = k.field_of(payload, "op", str)
        if op not in _LEASE_OPS:
            raise k.PayloadError(
                f"op={op!r}: allowed {', '.join(_LEASE_OPS)}", field="op", value=op
            )
        if op == "release_implicit":
            lease = client.implicit.get(name)
            wanted = k.field_of(payload, "keys", list, optional=True)
            hold = k.field_of(payload, "hold", bool, optional=True, default=False)
            held = lease.keys if lease is not None and lease.active else frozenset()
            for key in [] if wanted is None else bus_keys(wanted):
                owner = _owner_of(bus, key)
                if owner is not None and key not in held:
                    raise LeaseConflictError(key, owner, f"client {client.id}")
            to_end = held if wanted is None else frozenset(bus_keys(wanted)) & held
            if lease is not None and to_end:
                await lease.release(hold=hold, keys=to_end)
            return {}
        self._check_control(client)
        if op == "acquire":
            wanted_keys = bus_keys(k.field_of(payload, "keys", list))
            owner = k.field_of(payload, "owner", str)
            action = k.field_of(payload, "safe_action", str, optional=True, default="pause")
            frames = k.field_of(payload, "safe_commands", list, optional=True, default=[])
            safe = [
                k.decode_frame(_hex_item(f, "safe_commands"), sorted(bus.families, key=str))
                for f in frames
            ]
            lease = bus.lease(
                wanted_keys,
                owner=f"{owner} (client {client.id})",
                safe_action=action,
                bind=False,
                safe_commands=safe,
            )
            self._lease_numbers += 1
            client.explicit[self._lease_numbers] = (name, lease)
            return {"lease": self._lease_numbers}
        lease = self._explicit(client, name, payload.get("lease"))
        if op == "add":
            lease.add(bus_keys(k.field_of(payload, "keys", list)))
            return {}
        if op == "hand_over":
            # The devices pass to the client's own implicit lease, nothing sent.
            passed = bus_keys(k.field_of(payload, "keys", list))
            await lease.release(hold=True, keys=passed)
            implicit = client.implicit.get(name)
            if implicit is None or not implicit.active:
                client.implicit[name] = bus.lease(
                    passed, owner=f"client {client.id}", safe_action=bus.safe_action, bind=False
                )
            else:
                implicit.add(passed)
            return {"active": lease.active}
        if op == "release":
            wanted = k.field_of(payload, "keys", list, optional=True)
            hold = k.field_of(payload, "hold", bool, optional=True, default=False)
            if wanted is None:  # its streams stop first, with their safe actions
                await self._streams.end_lease(client, payload["lease"])
            await lease.release(hold=hold, keys=None if wanted is None else bus_keys(wanted))
            if not lease.active:
                client.explicit.pop(payload["lease"], None)
            return {"active": lease.active}
        raise k.PayloadError(
            f"op={op!r}: allowed acquire, add, hand_over, release, release_implicit",
            field="op",
            value=op,
        )

    async def _leases(self, name: str, payload: dict[str, Any]) -> dict[str, Any]:
        k.only_fields(payload, _READ_FIELDS)
        return {"leases": _lease_rows(self._bus(name).leases)}

    async def _stats(self, name: str, payload: dict[str, Any]) -> dict[str, Any]:
        k.only_fields(payload, _READ_FIELDS)
        return {"stats": self._bus(name).stats.as_dict()}

    # -- publications --------------------------------------------------------------------

    def _watch_leases(self, name: str, bus: Bus) -> None:
        publisher = self._publishers[name]

        def changed(infos: tuple[LeaseInfo, ...]) -> None:
            with contextlib.suppress(Exception):
                publisher.put(k.encode_json({"leases": _lease_rows(infos)}))

        bus.add_lease_listener(changed)
        self._listeners.append((bus, changed))

    async def _forward_events(self, name: str, bus: Bus) -> None:
        session = self._session
        with bus.events.subscribe(BusEvent) as sub:
            self._event_subs[name] = sub
            async for event in sub:
                body = k.event_payload(event)
                if body is None:
                    continue
                body["seq"] = self._events_out[name] = self._events_out.get(name, 0) + 1
                self._recent.setdefault(name, deque(maxlen=RECENT_EVENTS)).append(
                    (body["seq"], event)
                )
                with contextlib.suppress(Exception):
                    session.put(k.bus_key(name, f"event/{body['kind']}"), k.encode_json(body))

    # -- the deadman -----------------------------------------------------------------------

    def _on_token(self, sample: Any) -> None:
        cid = str(sample.key_expr).rsplit("/", 1)[-1]
        client = self._clients.get(cid)
        if str(sample.kind).endswith("DELETE"):
            # Kept, marked gone: a motion query of its that arrives after this (another
            # channel than the token's) is refused, not served under a fresh lease.
            if client is not None and not client.gone:
                client.gone = time.monotonic()
                self._spawn(self._end_client(client, "its Zenoh session ended", keep=True))
        elif client is None:
            self._clients[cid] = _Client(cid, time.monotonic())
        elif client.gone:  # its session came back (a link lost and found again): its
            # next motion hears once that its leases ended (``_end_client``, ``keep``)
            client.gone, client.last_seen = 0.0, time.monotonic()

    def _on_heartbeat(self, sample: Any) -> None:
        cid = str(sample.key_expr).split("/")[-2]
        client = self._clients.get(cid)
        if client is not None:
            client.last_seen = time.monotonic()

    async def _check_heartbeats(self) -> None:
        while True:
            await asyncio.sleep(self.liveness / _CHECKS_PER_LIVENESS)
            now = time.monotonic()
            for client in list(self._clients.values()):
                if client.gone:
                    if now - client.gone > _GONE_KEEP_S:
                        del self._clients[client.id]
                    continue
                streams = self._streams.holds(client.id)
                if now - client.last_seen > self.liveness and (_holds(client) or streams):
                    silent = now - client.last_seen
                    self._spawn(
                        self._end_client(client, f"no heartbeat for {silent:.2f} s", keep=True)
                    )

    async def _end_client(self, client: _Client, why: str, *, keep: bool = False) -> None:
        """End every lease of ``client`` with its safe action (the bus sends it)."""
        await self._streams.end_client(client, why)  # its streams first, safely
        leases = [lease for lease in client.implicit.values() if lease.active]
        leases += [lease for _, lease in client.explicit.values() if lease.active]
        client.implicit.clear()
        client.explicit.clear()
        if not leases:
            return
        if keep:
            client.ended = f"its leases were ended ({why})"
        log.warning("client %s: %s; ending its %d lease(s)", client.id, why, len(leases))
        start = time.monotonic()
        results = await asyncio.gather(
            *(lease.release(hold=False) for lease in leases), return_exceptions=True
        )
        for result in results:
            if isinstance(result, BaseException):
                log.error("client %s: a safe end failed: %s", client.id, result)
        self.deadman_ends.append((client.id, time.monotonic() - start))


def _holds(client: _Client) -> bool:
    return any(lease.active for lease in client.implicit.values()) or any(
        lease.active for _, lease in client.explicit.values()
    )


def bus_keys(values: list[Any]) -> list[str]:
    """Device keys from a payload (each checked as ``safety.check_key`` checks it)."""
    out = []
    for value in values:
        if not isinstance(value, str):
            raise k.PayloadError(f"keys: {value!r} is not a device key", field="keys", value=value)
        out.append(safety.check_key(value))
    return out


def _hex_item(value: object, name: str) -> bytes:
    return k.hex_field({name: value}, name)


def _owner_of(bus: Bus, key: str) -> str | None:
    for info in bus.leases:
        if info.key == key:
            return info.owner
    return None


def _lease_rows(infos: tuple[LeaseInfo, ...]) -> list[dict[str, Any]]:
    return [
        {"key": i.key, "owner": i.owner, "safe_frames": [f.hex() for f in i.safe_frames]}
        for i in infos
    ]
