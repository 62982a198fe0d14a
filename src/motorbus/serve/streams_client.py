"""Served streams, the client side: ``Streamer(served_bus)`` streams on the server.

``motorbus.Streamer(bus)`` on a ``ServedBus`` (``motorbus.connect``) gives a
:class:`ServedStreamer`, with the calls of the local one: ``follow`` (same arguments,
same checks, same errors, raised at once) returns a :class:`ServedStream` with
``stop``, ``wait``, ``pause``, ``resume``, ``set_targets``, ``stats``, ``statuses``,
``gaps`` and ``async with``.  The ticks are the server's (``motorbus.serve.
streams_server``): the stream runs on the server's bus timer, and this side only
keeps the server supplied with targets ahead of their ticks.

What differs, and why: a target source here is run ``lead`` seconds (default
``LEAD_S``) ahead of its ticks, since its targets must cross the network before they
are due; a callable ``f(t, statuses)`` therefore sees statuses that are ``lead`` plus
up to ``STATS_EVERY_S`` older than on a local bus.  A sequence's rows go ahead in
batches.  ``stream.stats`` and ``stream.statuses`` are the server's, as last published
(every ``STATS_EVERY_S``, and at the end); ``stats.as_dict()`` has one count more,
``held``: ticks the server prepared with no target from this client.

Whose motion: a stream started by a task that holds a lease (``bus.lease``, bound to
the task) of all its actuators runs under that lease on the server (no second owner:
the rig's lease is its stream's); else under a lease of the stream's own, as on a local
bus.  Either way its end applies its safe action.

Clocks: ``stream.origin`` is tick 0 on this host's clock (``time.monotonic``, the
clock of ``ServedBus.timer``): the server's tick 0 as its open reply told it (the
server's ``starts_in``, from when the reply came).  Tick ``k`` is due at ``origin + k *
period`` on this clock, late by the reply's way from the server, as every reply this
client stamps is (docs/serve.md, Clocks).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import TYPE_CHECKING, Any

from motorbus.bus.events import Subscription
from motorbus.devices.la import InspireLA
from motorbus.errors import BusClosedError, LocalProtocolError, MotorbusError, StreamEnded
from motorbus.protocol import la
from motorbus.serve import keys as k
from motorbus.serve.streams_server import START_IN_DEFAULT_S, stream_key
from motorbus.streaming.model import (
    DEFAULT_MAX_SPEED,
    GapPolicy,
    SafeAction,
    StreamStats,
    check_follow_options,
    hold_flag,
)
from motorbus.streaming.stream import StreamGap, actuator_group
from motorbus.streaming.targets import TargetAdapter, TargetSource
from motorbus.validation import LEAD_MAX_S, PHASE_MAX_S, check_number

if TYPE_CHECKING:
    from motorbus.serve.client import ServedBus

__all__ = ["LEAD_S", "ServedStream", "ServedStreamStats", "ServedStreamer"]

log = logging.getLogger("motorbus.serve")

#: How far ahead of its ticks a source is run and its targets published (seconds).
LEAD_S = START_IN_DEFAULT_S
#: A sequence's rows go out this far ahead at a time (seconds of ticks a publication).
BATCH_S = 0.05


@dataclass(slots=True)
class ServedStreamStats(StreamStats):
    """``StreamStats`` as the server last published them (counts and tick jitter)."""

    held: int = 0
    """Ticks the server prepared with no target from this client (it held them)."""
    figures: dict[str, float] = field(default_factory=dict)

    def update(self, figures: dict[str, Any]) -> None:
        for name in (
            "ticks", "late", "skipped", "slipped", "frames", "feedback_timeouts", "polls",
            "polls_skipped", "poll_timeouts", "gaps", "held",
        ):  # fmt: skip
            value = figures.get(name)
            if isinstance(value, int) and not isinstance(value, bool):
                setattr(self, name, value)
        self.figures = {n: v for n, v in figures.items() if isinstance(v, int | float)}

    def as_dict(self) -> dict[str, float]:
        out = StreamStats.as_dict(self)
        for name in ("jitter_p50_us", "jitter_p99_us", "jitter_max_us"):
            out[name] = self.figures.get(name, math.nan)
        out["held"] = self.held
        return out


class ServedStreamer:
    """``Streamer`` for a served bus (``motorbus.Streamer(served_bus)`` makes one)."""

    def __init__(self, bus: ServedBus, *, phase: float = 0.0, lead: float = LEAD_S) -> None:
        self.bus = bus
        self.phase = check_number("phase", phase, 0.0, PHASE_MAX_S, "s")
        self.lead = check_number("lead", lead, 0.0, LEAD_MAX_S, "s")
        self.streams: list[ServedStream] = []

    def follow(
        self,
        actuators: InspireLA | Sequence[InspireLA],
        targets: TargetSource,
        *,
        period: float = 0.02,
        feedback: bool = False,
        poll_status: bool = False,
        safe_action: SafeAction | str = SafeAction.HOLD,
        on_gap: GapPolicy | str = GapPolicy.RAMP,
        max_speed: float = DEFAULT_MAX_SPEED,
        max_missed: int | None = None,
    ) -> ServedStream:
        """``Streamer.follow`` on the server (see there); the stream's tick 0 is
        ``lead`` seconds from now.  Raises what it raises, at once."""
        group = actuator_group(actuators, self.bus)
        options = check_follow_options(
            period=period,
            feedback=feedback,
            poll_status=poll_status,
            safe_action=safe_action,
            on_gap=on_gap,
            max_speed=max_speed,
            max_missed=max_missed,
        )
        ids = tuple(a.id for a in group)
        if len(set(ids)) != len(ids):
            raise LocalProtocolError("actuators lists an id twice", field="actuators")
        adapter = TargetAdapter(ids, targets)  # refuses a source of no known kind
        self.bus.site._check_open(self.bus.name)
        body: dict[str, Any] = {}
        lease = self.bus._bound_lease()
        if lease is not None and {f"la:{i}" for i in ids} <= lease.keys:
            body["lease"] = lease.number  # the task's lease: the stream runs under it
        elif lease is not None and not lease.active:
            raise BusClosedError(f"{lease!r} has ended ({lease.ended}): the stream not started")
        opened = self.bus.site._query_blocking(
            k.bus_key(self.bus.name, "stream"),
            {
                **body,
                "op": "open",
                "ids": list(ids),
                "period": options.period,
                "feedback": options.feedback,
                "poll_status": options.poll_status,
                "safe_action": options.safe_action.value,
                "on_gap": options.on_gap.value,
                "max_speed": options.max_speed,
                "max_missed": options.max_missed,
                "phase": self.phase,
                "start_in": self.lead,
            },
        )
        stream = ServedStream(self, group, adapter, opened, options.period)
        stream.feedback, stream.poll_status = options.feedback, options.poll_status
        stream.safe_action, stream.on_gap = options.safe_action, options.on_gap
        stream.max_speed, stream.max_missed = options.max_speed, options.max_missed
        self.streams.append(stream)
        return stream

    async def close(self, *, hold: bool = False, safe: bool | None = None) -> None:
        """End every stream with its safe action (none with ``hold``)."""
        hold = hold_flag(hold, safe)
        streams, self.streams = list(self.streams), []
        outcomes = await asyncio.gather(
            *(s.stop(hold=hold) for s in streams), return_exceptions=True
        )
        for outcome in outcomes:
            if isinstance(outcome, BaseException):
                raise outcome


class ServedStream:
    """A stream running on the server; the handle of ``ServedStreamer.follow``
    (the members of ``motorbus.Stream``)."""

    #: Its frames are written by the server: this host's bus observers never see them.
    remote = True

    def __init__(
        self,
        streamer: ServedStreamer,
        actuators: list[InspireLA],
        adapter: TargetAdapter,
        opened: dict[str, Any],
        period: float,
    ) -> None:
        bus = streamer.bus
        self.streamer = streamer
        self.actuators = tuple(actuators)
        self.ids = adapter.ids
        self.number = int(opened["stream"])
        self.period = period
        self.feedback = False
        self.poll_status = False
        self.safe_action = SafeAction.HOLD
        self.on_gap = GapPolicy.RAMP
        self.max_speed = DEFAULT_MAX_SPEED
        self.max_missed: int | None = None
        self.stats = ServedStreamStats()
        self.statuses: dict[int, la.Status] = {}
        self.last_targets: dict[int, int] = {}
        #: Once it ended: the ticks whose target from this client the server did not
        #: write as sent (it skipped the tick, the target came after it, or it ramped
        #: back after a gap), as it said.
        self.unwritten: frozenset[int] = frozenset()
        self.error: BaseException | None = None
        self.paused = False
        self.stopping = False
        self.done = False
        self.source = adapter
        self.gaps: Subscription[StreamGap] = bus.events.subscribe(
            StreamGap, lambda e: e.stream == self.number
        )
        self._key = stream_key(bus.name, self.number, "targets")
        self._finished = asyncio.get_running_loop().create_future()
        #: Tick 0 on this host's clock (the server's start, as it told us).
        self._t0 = time.monotonic() + float(opened.get("starts_in", streamer.lead))
        self._next = 0  # the next tick whose target this side publishes
        self._base = 0  # the tick where the current source started
        self._instance = bus.site.instance
        session = bus.site._session
        self._stats_sub = session.declare_subscriber(
            stream_key(bus.name, self.number, "stats"), bus.site._threadsafe(self._on_stats)
        )
        self._ops: set[asyncio.Future[None]] = set()
        self._feeder = asyncio.ensure_future(self._feed())

    def __repr__(self) -> str:
        state = "done" if self.done else "running"
        return f"ServedStream({self.number} to {list(self.ids)} on {self.streamer.bus!r}, {state})"

    @property
    def sending(self) -> bool:
        return not (self.paused or self.stopping or self.done)

    @property
    def origin(self) -> float:
        """Tick 0 on this host's clock (``time.monotonic``; module docstring, Clocks)."""
        return self._t0

    # -- control -----------------------------------------------------------------------

    def set_targets(self, source: TargetSource) -> None:
        """Replace the target source; it starts at its own index 0 at the first tick
        still ``lead`` ahead (the rows published before that stay)."""
        self.source.bind(source)
        self._next = max(self._next, self._tick_now() + 1)
        self._base = self._next
        self._feeder.cancel()
        self._feeder = asyncio.ensure_future(self._feed())

    def pause(self) -> None:
        """Stop sending targets (the server's tick grid keeps running)."""
        self.paused = True
        self._op_later("pause")

    def resume(self) -> None:
        """Send targets again from the next tick."""
        self.paused = False
        self._op_later("resume")

    async def stop(self, *, hold: bool = False, safe: bool | None = None) -> None:
        """End the stream and apply its safe action on the server; with ``hold``, none."""
        hold = hold_flag(hold, safe)
        self.stopping = True
        self._feeder.cancel()
        try:
            if not self.done:
                state = await self._op("stop", hold=hold)
                self._take(state)
        finally:
            self._finish(self.error)

    async def wait(self) -> None:
        """Wait until the stream ends; raises ``StreamEnded`` if it ended on an error."""
        await asyncio.shield(self._finished)
        if self.error is not None:
            raise StreamEnded(f"stream to {list(self.ids)} ended: {self.error}") from self.error

    async def __aenter__(self) -> ServedStream:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()

    # -- the server ------------------------------------------------------------------------

    async def _op(self, op: str, **extra: Any) -> dict[str, Any]:
        bus = self.streamer.bus
        return await bus._query("stream", {"op": op, "stream": self.number, **extra})

    def _op_later(self, op: str) -> None:
        async def send() -> None:
            try:
                self._take(await self._op(op))
            except MotorbusError as err:
                log.warning("stream %d: %s not sent: %s", self.number, op, err)

        task = asyncio.ensure_future(send())
        self._ops.add(task)
        task.add_done_callback(self._ops.discard)

    def _on_stats(self, sample: Any) -> None:
        with contextlib.suppress(MotorbusError, ValueError, KeyError, TypeError):
            self._take(k.decode_json(sample.payload.to_bytes()))

    def _take(self, state: dict[str, Any]) -> None:
        """The server's state of this stream: counters, statuses, gaps, its end."""
        self.stats.update(state.get("stats", {}))
        for ident, raw in state.get("statuses", {}).items():
            status = la.decode_reply(bytes.fromhex(raw))
            if isinstance(status, la.Status):
                self.statuses[int(ident)] = status
        bus = self.streamer.bus
        for gap in state.get("gaps", []):
            positions = {int(i): int(p) for i, p in gap.get("positions", {}).items()}
            bus.events.publish(
                StreamGap(
                    bus.name, time.monotonic(), self.number, self.ids, str(gap["cause"]),
                    int(gap["missed"]), positions, str(gap["action"]),
                )
            )  # fmt: skip
        if state.get("done"):
            unwritten = state.get("unwritten", [])
            self.unwritten = frozenset(t for t in unwritten if isinstance(t, int))
            error = state.get("error")
            if error and self.error is None:
                self.error = StreamEnded(str(error))
            self._finish(self.error)

    def _finish(self, error: BaseException | None) -> None:
        if self.done:
            return
        self.stopping = self.done = True
        self.error = error
        self._feeder.cancel()
        with contextlib.suppress(Exception):
            self._stats_sub.undeclare()
        self.gaps.close()
        if not self._finished.done():
            self._finished.set_result(None)
        with contextlib.suppress(ValueError):
            self.streamer.streams.remove(self)

    # -- feeding the server ------------------------------------------------------------------

    def _tick_now(self) -> int:
        return math.floor((time.monotonic() - self._t0) / self.period)

    async def _feed(self) -> None:
        """Publish targets ``lead`` ahead of their ticks until the source ends."""
        site = self.streamer.bus.site
        ahead = max(1, math.ceil(self.streamer.lead / self.period))
        batch = max(1, round(BATCH_S / self.period)) if self.source.sequence is not None else 1
        try:
            while not self.stopping:
                horizon = self._tick_now() + ahead + batch
                first, rows, end = self._next, [], False
                while self._next < horizon:
                    targets = await self.source.next(
                        self._next * self.period, self.statuses, self._next - self._base
                    )
                    if targets is None:
                        end = True
                        break
                    rows.append({str(i): p for i, p in targets.items()})
                    self.last_targets.update(targets)
                    self._next += 1
                if self.stopping:
                    return
                session = site._session
                if session is None or site.state != "open" or site.instance != self._instance:
                    # The server went away (or restarted): the stream ended with it.
                    self._finish(BusClosedError(f"the server of {self!r} went away"))
                    return
                payload = {"client": site.client_id, "tick": first}
                session.put(self._key, k.encode_json({**payload, "rows": rows, "end": end}))
                if end:
                    return
                wake = self._t0 + (self._next - ahead) * self.period
                await asyncio.sleep(max(0.0, wake - time.monotonic()))
        except asyncio.CancelledError:
            raise
        except Exception as err:  # the source failed: the stream ends with its safe action
            log.warning("stream to %s: target source failed: %s", list(self.ids), err)
            self.error = err
            with contextlib.suppress(MotorbusError):
                self._take(await self._op("stop"))
            self._finish(err)
