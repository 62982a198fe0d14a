"""Served streams, the server side: the real ``Streamer`` on the server's bus timer.

A client opens a stream with a query to ``motorbus/v1/bus/{bus}/stream`` carrying the
options ``Streamer.follow`` takes (checked here by the same checks, so a bad one is
refused naming its field, before anything is sent).  The server starts the stream on
its own bus, in a ``Streamer`` of that client, ``start_in`` seconds ahead, and the
client publishes its targets ahead of their ticks on
``motorbus/v1/bus/{bus}/stream/{n}/targets``: rows for ticks ``tick, tick + 1, ...``
(tick ``k`` is ``k * period`` after the stream's start), a sequence's rows well ahead or
a callable's one row per tick as it goes.  The stream's target source here is the
buffer of those rows (:class:`TargetFeed`).

A client that falls silent (no row for a tick when the tick is prepared) gets the
stream's gap policy: the actuators hold their last target meanwhile; after
``GAP_TICKS`` missing ticks it is a gap (``StreamGap``, cause ``"client"``):
``on_gap="stop"`` applies the safe action and ends the stream; ``"ramp"`` holds until
rows come again and ramps from the last target sent to them at ``max_speed``.

Whose motion: the stream's actuators are the client's (taken over from its implicit
lease if it moved them before).  An open that names one of the client's explicit leases
(``lease``: its number; ``ServedStreamer.follow`` sends the lease the calling task
holds) runs the stream under that lease, which must hold every actuator of it: no
second owner.  The stream's end still applies its safe action; the actuators stay in
the lease, whose owner ends it (releasing it stops its streams first).  When the
client dies (its token goes, or its heartbeat stops: the deadman) its streams stop
with their safe actions before its leases end; a stream of its own lease whose safe
action is ``"hold"`` passes its actuators to the client's implicit lease, whose end
(the client's, at the latest) then pauses them, as a local bus's close does.  The
server publishes each stream's counters, latest statuses and gaps on
``motorbus/v1/bus/{bus}/stream/{n}/stats`` every ``STATS_EVERY_S`` and when it ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from motorbus.bus.bus import Bus
from motorbus.devices.la import InspireLA
from motorbus.errors import BusClosedError, LocalProtocolError, MotorbusError, StreamEnded
from motorbus.protocol import la
from motorbus.protocol.base import Family
from motorbus.serve import keys as k
from motorbus.streaming.model import GAP_TICKS, GapPolicy, SafeAction, check_follow_options
from motorbus.streaming.stream import Stream, StreamGap
from motorbus.streaming.targets import TargetAdapter, Targets
from motorbus.streams import Streamer
from motorbus.validation import LEAD_MAX_S

if TYPE_CHECKING:
    from motorbus.serve.server import BusServer, _Client

__all__ = [
    "MAX_ROWS",
    "START_IN_DEFAULT_S",
    "START_IN_MAX_S",
    "STATS_EVERY_S",
    "STREAM_OPS",
    "StreamService",
    "TargetFeed",
    "stream_key",
]

log = logging.getLogger("motorbus.serve")

#: The operations of ``motorbus/v1/bus/{bus}/stream``.
STREAM_OPS = ("open", "stop", "pause", "resume", "stats")
#: Default and largest ``start_in``: seconds from the open to the stream's tick 0, the
#: time the client has to get its first targets there.
START_IN_DEFAULT_S = 0.1
START_IN_MAX_S = LEAD_MAX_S
#: Most rows in one targets publication.
MAX_ROWS = 10_000
#: How often a running stream's counters and statuses are published (seconds).
STATS_EVERY_S = 0.1


def stream_key(bus: str, number: int, what: str) -> str:
    """``motorbus/v1/bus/{bus}/stream/{number}/{what}`` (``targets`` or ``stats``)."""
    return k.bus_key(bus, f"stream/{number}/{what}")


class TargetFeed:
    """The rows a client sent ahead for one served stream, by tick: its target source.

    ``source(t, statuses)`` is what the server's ``Stream`` calls at each tick ``k``
    (``t = k * period``): the row of tick ``k``; ``{}`` (nothing new: the actuators hold
    their last target) if the client has not sent it; ``None`` after the last row of a
    source that ended.  Missing rows are the gap policy's (module docstring).
    """

    def __init__(self, ids: tuple[int, ...], period: float, on_gap: GapPolicy) -> None:
        self.adapter = TargetAdapter(ids, [])
        self.ids = ids
        self.period = period
        self.on_gap = on_gap
        self.rows: dict[int, Targets] = {}
        #: No row below this tick is buffered (the ticks before it were served).
        self.low = 0
        #: One past the highest tick buffered.
        self.top = 0
        #: The tick after the last row, once the client's source has ended.
        self.end: int | None = None
        self.stream: Stream | None = None
        #: Ticks with no row from the client since the last one that had one.
        self.missed = 0
        #: Every tick prepared without a row from the client (after its first row).
        self.held = 0
        self.started = False
        self.sent: dict[int, int] = {}
        #: The ticks whose row was not written as sent: skipped, prepared with no row,
        #: or ramped after a gap (the first ``MAX_ROWS``; published when the stream
        #: ends, ``unwritten``).
        self.unwritten: list[int] = []

    def row(self, item: object, where: str) -> Targets:
        """One row of a payload as ``{id: position}`` (a list in ``ids`` order, a
        position for one actuator, or an object ``{"ID": position}``)."""
        if isinstance(item, dict):
            converted: dict[int, object] = {}
            for key, value in item.items():
                if not (isinstance(key, str) and key.isdigit()):
                    raise k.PayloadError(
                        f"{where}: {key!r} is not an actuator id", field="rows", value=key
                    )
                converted[int(key)] = value
            item = converted
        if isinstance(item, bool) or not isinstance(item, int | float | list | dict):
            raise k.PayloadError(
                f"{where}: {item!r} is not a position, a list or an object",
                field="rows",
                value=repr(item),
            )
        try:
            return self.adapter.normalise(item)
        except LocalProtocolError as err:
            raise k.PayloadError(f"{where}: {err}", field="rows", value=err.value) from None

    def put(self, tick: int, rows: list[Targets], end: bool) -> None:
        """Rows for ticks ``tick, tick + 1, ...``: they replace any sent before for those
        ticks and later; ``end`` says the source ends after them."""
        for later in range(max(tick, self.low), self.top):  # only what is replaced
            self.rows.pop(later, None)
        for n, targets in enumerate(rows):
            if tick + n >= self.low:  # a row for a tick already served is dropped
                self.rows[tick + n] = targets
        self.top = max(self.low, tick + len(rows))
        self.end = tick + len(rows) if end else None

    def source(self, t: float, statuses: Mapping[int, la.Status]) -> Targets | None:
        k_now = round(t / self.period)
        targets = None
        for stale in range(self.low, k_now):  # one a tick, however many are buffered
            row = self.rows.pop(stale, None)
            if row is not None and stale + 1 == self.end:
                # Skipped past the end: the last row, where the trajectory ends, still
                # goes out (now), as a local stream's does.
                targets = row
            elif self.end is None or stale < self.end:
                self._unwritten(stale)  # a tick the stream skipped (past the end: no row)
        if targets is None:
            targets = self.rows.pop(k_now, None)
        self.low = max(self.low, k_now + 1)
        if targets is not None:
            self._resume()
            if self.stream is not None and self.stream.ramp is not None:
                self._unwritten(k_now)  # ramped back after a gap: not the row as sent
            self.started = True
            self.sent.update(targets)
            return targets
        if self.end is not None and k_now >= self.end:
            return None  # the client's source ended: a normal (safe) end
        self._unwritten(k_now)  # no row for it (yet): its row is dropped when it comes
        if not self.started:
            return {}  # no row yet: nothing is sent
        self.missed += 1
        self.held += 1
        if self.missed == GAP_TICKS and self.on_gap is GapPolicy.STOP:
            self._publish(self.missed, "stop")
            raise StreamEnded(f'gap (client silent, {self.missed} ticks missed; on_gap="stop")')
        return {}

    def _unwritten(self, tick: int) -> None:
        if len(self.unwritten) < MAX_ROWS:
            self.unwritten.append(tick)

    def _last_sent(self) -> dict[int, float]:
        """Where each actuator was last sent: its last row's target, but for an actuator
        still ramping after an earlier gap, where the ramp had brought it (its rows were
        not sent as such)."""
        last = {i: float(p) for i, p in self.sent.items()}
        if self.stream is not None and self.stream.ramp:
            last.update(self.stream.ramp)
        return last

    def _resume(self) -> None:
        """Rows again after missing ones: ramp from the positions last sent.  (From the
        last rows instead, a gap during a ramp made the actuators jump to their targets:
        500, 520, then 1500 at a ramp of 20 a tick.)"""
        stream = self.stream
        if self.missed and stream is not None and self.sent:
            stream.ramp = self._last_sent()
            if self.missed >= GAP_TICKS:
                self._publish(self.missed, "ramp")
        self.missed = 0

    def _publish(self, missed: int, action: str) -> None:
        stream = self.stream
        if stream is None:
            return
        bus = stream.streamer.bus
        stream.stats.gaps += 1
        bus.events.publish(
            StreamGap(
                bus.name, bus.timer.now(), stream.number, stream.ids, "client", missed,
                {i: round(p) for i, p in self._last_sent().items()}, action,
            )
        )  # fmt: skip


@dataclass
class _Served:
    """One served stream: its client, bus, server-side ``Stream`` and feed."""

    client: _Client
    bus: str
    stream: Stream
    feed: TargetFeed
    streamer: Streamer
    held_on_purpose: bool = False
    finished: bool = False
    #: The client's explicit lease the stream runs under (the open's ``lease``), if any.
    lease: int | None = None


class StreamService:
    """The served streams of one ``BusServer`` (its ``stream`` keys)."""

    def __init__(self, server: BusServer) -> None:
        self.server = server
        self.streams: dict[int, _Served] = {}
        #: One streamer per client, bus and lease (0: the streamer's own lease, which
        #: holds that client's streams only; else a lease of the client's, by number).
        self.streamers: dict[tuple[str, str, int], Streamer] = {}

    def declare(self, session: Any, name: str) -> None:
        """Declare the stream keys of bus ``name`` (``BusServer.start``)."""
        server = self.server
        server._declare(
            session.declare_queryable(k.bus_key(name, "stream"), server._on_query(self.query, name))
        )
        server._declare(
            session.declare_subscriber(
                k.bus_key(name, "stream/*/targets"),
                server._threadsafe(lambda sample: self.on_targets(name, sample)),
            )
        )

    def holds(self, cid: str) -> bool:
        """Whether client ``cid`` has a stream running."""
        return any(s.client.id == cid and not s.stream.done for s in self.streams.values())

    async def end_lease(self, client: _Client, number: int) -> None:
        """The client releases its lease ``number``: the streams under it stop first,
        with their safe actions."""
        for served in [s for s in self.streams.values() if s.client.id == client.id]:
            if served.lease == number and not served.stream.done:
                await served.stream.stop()
                await self._finished(served)

    async def end_client(self, client: _Client, why: str) -> None:
        """The client is gone: stop its streams with their safe actions (the deadman)."""
        mine = [s for s in self.streams.values() if s.client is client or s.client.id == client.id]
        for served in mine:
            if not served.stream.done:
                log.warning(
                    "client %s: %s; stopping stream %d", client.id, why, served.stream.number
                )
                try:  # with its safe action, and why: the client's wait() raises it
                    await served.stream.end(BusClosedError(why))
                except MotorbusError as err:
                    log.error("client %s: a stream's safe action failed: %s", client.id, err)
            await self._finished(served)

    # -- the query -----------------------------------------------------------------------

    async def query(self, name: str, payload: dict[str, Any]) -> dict[str, Any]:
        op = k.field_of(payload, "op", str)
        if op not in STREAM_OPS:
            raise k.PayloadError(
                f"op={op!r}: allowed {', '.join(STREAM_OPS)}", field="op", value=op
            )
        client = self.server._client(payload)
        if op == "open":
            return await self._open(name, client, payload)
        served = self._own(name, client, payload)
        stream = served.stream
        if op == "stop":
            hold = k.field_of(payload, "hold", bool, optional=True, default=False)
            if not stream.done:
                served.held_on_purpose = hold
            await stream.stop(hold=hold)
            await self._finished(served)
        elif op == "pause":
            stream.pause()
        elif op == "resume":
            stream.resume()
        return self.state(served)

    def _own(self, name: str, client: _Client, payload: dict[str, Any]) -> _Served:
        number = k.field_of(payload, "stream", int)
        served = self.streams.get(number)
        if served is None or served.client.id != client.id or served.bus != name:
            raise LocalProtocolError(
                f"stream={number}: client {client.id} has no such stream on bus {name}",
                field="stream",
                value=number,
            )
        return served

    async def _open(self, name: str, client: _Client, payload: dict[str, Any]) -> dict[str, Any]:
        bus = self.server._bus(name)
        if Family.LA not in bus.families:
            raise LocalProtocolError(f"bus {name} carries no LA actuators", field="bus", value=name)
        ids = _ids(payload)
        options = check_follow_options(
            period=payload.get("period", 0.02),
            feedback=payload.get("feedback", False),
            poll_status=payload.get("poll_status", False),
            safe_action=payload.get("safe_action", "hold"),
            on_gap=payload.get("on_gap", "ramp"),
            max_speed=payload.get("max_speed", 500.0),
            max_missed=payload.get("max_missed"),
        )
        start_in = k.field_of(payload, "start_in", (int, float), optional=True)
        start_in = START_IN_DEFAULT_S if start_in is None else start_in
        if not 0 <= start_in <= START_IN_MAX_S:
            raise k.PayloadError(
                f"start_in={start_in!r} is out of range: allowed 0..{START_IN_MAX_S:g} s",
                field="start_in",
                value=start_in,
            )
        phase = k.field_of(payload, "phase", (int, float), optional=True, default=0.0)
        self.server._check_control(client)
        number = k.field_of(payload, "lease", int, optional=True)
        under = None if number is None else self.server._explicit(client, name, number)
        feed = TargetFeed(ids, options.period, options.on_gap)
        slot = (client.id, name, number or 0)
        streamer = self.streamers.get(slot)
        if streamer is None and under is not None:
            streamer = Streamer.borrowing(bus, under, phase=phase)
        elif streamer is None:
            streamer = Streamer(bus, phase=phase)
        keys = [f"la:{i}" for i in ids]
        # The client's own earlier motion of these actuators passes to its stream (to
        # the lease it names, which holds them already: then nothing passes).
        implicit = client.implicit.get(name)
        moved = [key for key in keys if implicit is not None and key in implicit.keys]
        if implicit is not None and moved and under is None:
            bus.hand_over(implicit, moved)
        else:
            moved = []
        created = under is None and (streamer.lease is None or not streamer.lease.active)
        try:
            if created:  # the streamer's lease, named for its client (else Streamer makes it)
                streamer.lease = bus.lease(keys, owner=f"stream of client {client.id}", bind=False)
            stream = streamer.follow(
                [InspireLA(bus, i) for i in ids],
                feed.source,
                period=options.period,
                feedback=options.feedback,
                poll_status=options.poll_status,
                safe_action=options.safe_action,
                on_gap=options.on_gap,
                max_speed=options.max_speed,
                max_missed=options.max_missed,
            )
        except BaseException:
            if created and streamer.lease is not None:
                await streamer.lease.release(hold=True)  # nothing was sent
            if moved:
                self._to_client(client, name, bus, moved)
            raise
        # Tick 0 comes ``start_in`` later, on the streamer's grid (nothing ran yet).
        stream.origin += math.ceil(start_in / stream.period - 1e-9) * stream.period
        feed.stream = stream
        self.streamers[slot] = streamer
        served = self.streams[stream.number] = _Served(client, name, stream, feed, streamer)
        served.lease = slot[2] or None
        self.server._spawn(self._publish(served))
        return {**self.state(served), "starts_in": stream.origin - bus.timer.now()}

    # -- targets ---------------------------------------------------------------------------

    def on_targets(self, name: str, sample: Any) -> None:
        """A targets publication (on the server's loop)."""
        try:
            number = int(str(sample.key_expr).split("/")[-2])
            payload = k.decode_json(sample.payload.to_bytes())
        except (ValueError, LocalProtocolError) as err:
            log.warning("bus %s: a targets publication did not decode: %s", name, err)
            return
        served = self.streams.get(number)
        if served is None or served.bus != name or served.stream.done:
            return
        if payload.get("client") != served.client.id:
            log.warning("bus %s: stream %d: targets from another client ignored", name, number)
            return
        try:
            tick = k.field_of(payload, "tick", int)
            if tick < 0:
                raise k.PayloadError(f"tick={tick} must be >= 0", field="tick", value=tick)
            items = k.field_of(payload, "rows", list)
            if len(items) > MAX_ROWS:
                raise k.PayloadError(
                    f"rows: {len(items)} rows, at most {MAX_ROWS} a publication",
                    field="rows",
                    value=len(items),
                )
            end = k.field_of(payload, "end", bool, optional=True, default=False)
            rows = [served.feed.row(item, f"rows[{n}]") for n, item in enumerate(items)]
        except LocalProtocolError as err:
            # A bad target ends the stream (with its safe action), as a failing target
            # source does on a local bus; the client learns why from the stats.
            log.warning("bus %s: stream %d: bad targets: %s", name, number, err)
            self.server._spawn(served.stream.end(err))
            return
        served.feed.put(tick, rows, end)

    # -- state -------------------------------------------------------------------------------

    def state(self, served: _Served) -> dict[str, Any]:
        """The ``stats`` payload of a served stream (at its end, with ``unwritten``:
        the ticks whose row from the client was not written as sent, ``TargetFeed``)."""
        stream = served.stream
        end = {"unwritten": served.feed.unwritten} if stream.done else {}
        return {
            **end,
            "stream": stream.number,
            "ids": list(stream.ids),
            "done": stream.done,
            "error": None if stream.error is None else str(stream.error),
            "paused": stream.paused,
            "tick": stream.next_tick,
            "stats": {**stream.stats.as_dict(), "held": served.feed.held},
            "statuses": {str(i): s.encode().hex() for i, s in stream.statuses.items()},
            "gaps": [
                {"cause": g.cause, "missed": g.missed, "action": g.action,
                 "positions": {str(i): p for i, p in g.positions.items()}}
                for g in stream.gaps.pending()
            ],
        }  # fmt: skip

    async def _publish(self, served: _Served) -> None:
        session = self.server._session
        key = stream_key(served.bus, served.stream.number, "stats")
        stream = served.stream
        while not stream.done:
            with contextlib.suppress(TimeoutError, StreamEnded):
                await asyncio.wait_for(stream.wait(), STATS_EVERY_S)
            with contextlib.suppress(Exception):
                session.put(key, k.encode_json(self.state(served)))
        await self._finished(served)
        with contextlib.suppress(Exception):
            session.put(key, k.encode_json(self.state(served)))

    async def _finished(self, served: _Served) -> None:
        """A stream ended: a "hold" stream's actuators pass to the client's implicit
        lease (the client's end pauses them); an idle streamer leaves the bus."""
        if served.finished:
            return
        served.finished = True
        stream = served.stream
        bus = stream.streamer.bus
        held = stream.safe_action is SafeAction.HOLD and not served.held_on_purpose
        if held and served.lease is None:  # under a lease, they stay in it
            self._to_client(served.client, served.bus, bus, [f"la:{i}" for i in stream.ids])
        streamer = served.streamer
        if not streamer.streams:
            self.streamers.pop((served.client.id, served.bus, served.lease or 0), None)
            with contextlib.suppress(MotorbusError):
                await streamer.close()

    def _to_client(self, client: _Client, name: str, bus: Bus, keys: list[str]) -> None:
        """``keys`` pass to ``client``'s implicit lease on bus ``name`` (nothing sent)."""
        lease = client.implicit.get(name)
        try:
            if lease is not None and lease.active:
                lease.add(keys)
            else:
                client.implicit[name] = bus.lease(
                    keys, owner=f"client {client.id}", safe_action=bus.safe_action, bind=False
                )
        except MotorbusError as err:
            log.warning("client %s: %s could not pass back to it: %s", client.id, keys, err)


def _ids(payload: Mapping[str, Any]) -> tuple[int, ...]:
    ids = k.field_of(payload, "ids", list)
    if not ids:
        raise k.PayloadError("ids must name at least one actuator", field="ids", value="[]")
    for i in ids:
        if isinstance(i, bool) or not isinstance(i, int) or not la.ID_MIN <= i <= la.ID_MAX:
            raise k.PayloadError(
                f"ids: {i!r} is not an actuator id: allowed {la.ID_MIN}..{la.ID_MAX}",
                field="ids",
                value=i if isinstance(i, int) else repr(i),
            )
    return tuple(ids)
