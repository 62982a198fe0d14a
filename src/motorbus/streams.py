"""Fixed-rate follow-mode streams to LA actuators, coalesced into broadcasts.

A stream sends one target per actuator every ``period`` seconds (10..50 ms, LA manual
3.5.3: "send at a fixed interval of 10-50 ms").  Ticks are scheduled on absolute
deadlines, ``origin + k * period``, on the bus's high-resolution timer, so a stream
never drifts; a tick that cannot be served on time is skipped, never burst.

Per bus, one :class:`Streamer` serves every stream in one task:

* without feedback, the targets of every actuator whose tick falls due together are
  packed into 0xF3 broadcast frames of at most 15 entries (``la.split_broadcast``),
  so 15 actuators at 10 ms cost one frame a tick (15 addressed frames cannot fit: the
  1 ms spacing allows 10 in 10 ms);
* with feedback, each actuator gets a 0x20 frame and its status reply;
* the slots left in a tick poll the status of streamed actuators round-robin
  (``poll_status=True``), without ever delaying the next tick: a poll that cannot
  start in time is dropped unsent and counted (``polls_skipped``).

Ticks never wait behind user requests: each streamer reserves its tick windows on the
bus (``Bus.add_reservation_source``), and the bus does not start a request that could
still hold the line when a tick is due.  A tick whose frame must still wait (a reply
owed, or the 1 ms spacing from the previous write) slips by the time needed and is
counted (``slipped``).

Stop means stop: once a stream starts stopping (``stop``, the end of its ``async with``
block, an error), nothing more of it is written.  Its frames are built at the moment
they are written (``Bus.submit(refresh=...)``), from the streams still running, so a
tick queued or being built when the stop began is dropped, not sent after the safe
action's pause (a follow target would resume a paused actuator, LA manual 3.5.4).

Every end is a safe end: however a stream ends (its targets run out, ``stop()``, the end
of its ``async with`` block, an error, a gap it was told to stop on, the bus closing),
its safe action (``safe_action``: "pause" or "estop") goes to its actuators, unless the
owner ends it explicitly with ``stop(hold=True)`` (the actuators then hold their last
target).

After a gap, a ramp: when the bus comes back after losing its port, or the stream fell
``GAP_TICKS`` or more ticks behind (a stalled host), the targets have moved on while the
actuators have not.  With ``on_gap="ramp"`` (the default) the stream reads where each
actuator is and ramps from there to the trajectory at its ``max_speed``; with
``on_gap="stop"`` it applies its safe action and ends with an error.  Either way the gap
is a ``StreamGap`` event (``stream.gaps``, or ``bus.events``) and a count
(``stats.gaps``).

All the streamers of one bus share one time budget: a set of streams that cannot fit
the bus is refused when it starts, with an error that says what would fit, and an
actuator can be streamed by one stream at a time.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import inspect
import itertools
import logging
import math
import weakref
from collections.abc import AsyncIterator, Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, TypeAlias

from motorbus import realtime
from motorbus.bus.bus import Bus, BusState, Priority
from motorbus.bus.events import BusEvent, Subscription
from motorbus.bus.occupancy import occupancy
from motorbus.bus.stats import LatencyHistogram
from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError, MotorbusError, NotSentError, StreamEnded
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_flag
from motorbus.shutdown import deferred_interrupts
from motorbus.validation import PHASE_MAX_S, check_number, is_scalar, target_id, target_position

__all__ = [
    "PERIOD_MAX_S",
    "PERIOD_MIN_S",
    "GapPolicy",
    "SafeAction",
    "Stream",
    "StreamEnded",
    "StreamGap",
    "StreamStats",
    "Streamer",
]

log = logging.getLogger("motorbus.streams")

#: Follow-mode targets must come at a fixed interval of 10..50 ms (LA manual 3.5.3).
PERIOD_MIN_S = 0.010
PERIOD_MAX_S = 0.050
#: Share of each tick that streams may plan to use; the rest absorbs host jitter and
#: the user's own requests.
TICK_BUDGET_SHARE = 0.8
#: A tick sent later than this after its deadline counts as late (it is still sent).
LATE_AFTER_S = 1e-3
#: Ticks within this of each other are served together (and coalesced).
COALESCE_WINDOW_S = 200e-6
#: A tick's targets are computed as soon as the previous tick's frames, feedback and
#: polls are done, at most this long before its deadline; its frames then leave from
#: a timer callback at the deadline itself.  One timer wake-up a tick (each costs
#: 180-600 us of CPU on this VM, benchmarks/bench_wakeups.py): the preparation rides
#: on the previous tick's.
PLAN_AHEAD_S = 0.050
#: Polls stop this long before the next tick, to leave time to prepare it.
PREPARE_S = 1e-3
#: A stream this many ticks behind (or more) has had a gap: its actuators are no longer
#: where its trajectory is (``on_gap``).  Fewer are skipped and counted, nothing more.
GAP_TICKS = 3
#: Default ``max_speed`` (position units per second) of the ramp after a gap: the full
#: 0..2000 stroke in 4 s.
DEFAULT_MAX_SPEED = 500.0
#: Largest ``max_speed``: the full stroke in 0.1 s, beyond what an LA can do.
MAX_SPEED_LIMIT = 20_000.0

Targets: TypeAlias = Mapping[int, int]
TargetSource: TypeAlias = Any  # sequence, iterator, async iterator or callable; see Stream


class SafeAction(enum.Enum):
    """What a stream does to its actuators when it ends (unless ended with ``hold``)."""

    HOLD = "hold"  # nothing: each actuator holds its last target
    PAUSE = "pause"  # CMD_MC pause: power stage off, the next target resumes
    ESTOP = "estop"  # CMD_MC e-stop: power stage off, "work" needed to move again


class GapPolicy(enum.Enum):
    """What a stream does after a gap (the bus was lost, or the stream fell behind)."""

    RAMP = "ramp"  # read each position, ramp from there to the trajectory at max_speed
    STOP = "stop"  # apply the safe action and end the stream with an error


@dataclass(frozen=True, slots=True)
class StreamGap(BusEvent):
    """A stream had a gap: its targets stopped reaching its actuators for a while.

    Attributes:
        stream: the stream's ``number`` (``Stream.number``).
        ids: the stream's actuators.
        cause: ``"outage"`` (the bus lost its port and came back) or ``"behind"`` (the
            stream fell ``GAP_TICKS`` or more ticks behind).
        missed: ticks not sent since the last tick that was.
        positions: where each actuator reported it was after the gap (``"ramp"``).
        action: ``"ramp"`` (ramping from ``positions``) or ``"stop"`` (safe action
            applied, stream ended; also when a position could not be read).
    """

    stream: int
    ids: tuple[int, ...]
    cause: str
    missed: int
    positions: Mapping[int, int]
    action: str


@dataclass(slots=True)
class StreamStats:
    """Timing and counts of one stream (durations in seconds)."""

    ticks: int = 0  # ticks served (frames sent)
    late: int = 0  # ticks sent more than LATE_AFTER_S after their deadline
    skipped: int = 0  # ticks dropped because the stream fell a whole period behind
    #: Ticks whose first frame could not be written at the deadline itself (a reply
    #: was still owed, or the 1 ms spacing from the previous write): sent that much later.
    slipped: int = 0
    frames: int = 0  # frames sent for this stream (broadcasts shared count once each)
    feedback_timeouts: int = 0
    polls: int = 0
    #: Polls that could not get a slot before the next tick (dropped unsent), and ticks
    #: whose free slots held no poll at all.
    polls_skipped: int = 0
    gaps: int = 0  # gaps handled (``StreamGap`` events)
    #: Lateness of each tick's first frame against its absolute deadline.
    jitter: LatencyHistogram = field(default_factory=LatencyHistogram)

    def summary(self) -> dict[str, float]:
        """Counts plus jitter p50/p99/max in microseconds."""
        j = self.jitter.summary()
        return {
            "ticks": self.ticks,
            "late": self.late,
            "skipped": self.skipped,
            "slipped": self.slipped,
            "frames": self.frames,
            "feedback_timeouts": self.feedback_timeouts,
            "polls": self.polls,
            "polls_skipped": self.polls_skipped,
            "gaps": self.gaps,
            "jitter_p50_us": j["p50_us"],
            "jitter_p99_us": j["p99_us"],
            "jitter_max_us": j["max_us"],
        }


class Stream:
    """A running (or finished) follow-mode stream; create it with ``Streamer.follow``.

    Targets, per tick ``k`` at time ``t = k * period`` since the stream started, come
    from ``source``, one of:

    * a sequence (list, tuple, array): item ``k`` each tick; the stream ends after the
      last item;
    * an iterator or generator: the next item each tick, ending with it;
    * an async iterator: awaited each tick;
    * a callable ``f(t, statuses)``, where ``statuses`` maps ID to the latest
      ``la.Status`` (feedback replies and polls): its return value each tick; return
      ``None`` to end the stream.

    An item is a position 0..2000 for a single actuator, a sequence with one position
    per actuator (in the order given), or a mapping ``{id: position}``.

    However the stream ends, its ``safe_action`` goes to its actuators once, unless it
    is ended with ``stop(hold=True)``.  ``gaps`` queues its ``StreamGap`` events
    (``await stream.gaps.next(timeout)``); it closes when the stream ends.
    """

    _numbers = itertools.count(1)

    def __init__(
        self,
        streamer: Streamer,
        actuators: Sequence[InspireLA],
        source: TargetSource,
        *,
        period: float,
        feedback: bool,
        poll_status: bool,
        safe_action: SafeAction,
        on_gap: GapPolicy = GapPolicy.RAMP,
        max_speed: float = DEFAULT_MAX_SPEED,
    ) -> None:
        self.streamer = streamer
        self.actuators = tuple(actuators)
        self.ids = tuple(a.id for a in self.actuators)
        self.number = next(Stream._numbers)
        self.period = period
        self.feedback = feedback
        self.poll_status = poll_status
        self.safe_action = safe_action
        self.on_gap = on_gap
        self.max_speed = max_speed
        #: True once the safe action was sent (or ``hold`` chose to send none).
        self.safe_applied = False
        self.gaps: Subscription[StreamGap] = streamer.bus.events.subscribe(
            StreamGap, lambda e: e.stream == self.number
        )
        #: While ramping after a gap: the position each ramping actuator was last sent.
        self.ramp: dict[int, float] | None = None
        #: The bus's disconnect count when this stream last had it up (an outage since?).
        self.disconnects_seen = streamer.bus.stats.disconnects
        #: ``stats.skipped`` when the last tick went out (the ticks a gap missed).
        self.skipped_mark = 0
        self.stats = StreamStats()
        self.statuses: dict[int, la.Status] = {}
        self.last_targets: dict[int, int] = {}
        self.error: BaseException | None = None
        self.origin = 0.0
        self.next_tick = 0
        self.paused = False
        #: True from the moment the stream starts to stop: nothing more of it is written.
        self.stopping = False
        self.done = False
        self._source = source
        self._sequence: Sequence[Any] | None = None
        self._iterator: Iterator[Any] | None = None
        self._aiterator: AsyncIterator[Any] | None = None
        self._callable: Callable[..., Any] | None = None
        self._finished = asyncio.get_running_loop().create_future()
        self._poll_cursor = 0
        self._bind(source)

    # -- control ----------------------------------------------------------------

    def _bind(self, source: TargetSource) -> None:
        self._sequence = self._iterator = self._aiterator = self._callable = None
        if isinstance(source, (str, bytes, bytearray)):
            # Strings are sequences: "1500" would stream the targets 1, 5, 0, 0.
            raise LocalProtocolError(
                f"targets must be positions, not text: got {source!r}", field="targets"
            )
        if isinstance(source, Sequence):
            self._sequence = source
        elif hasattr(source, "__len__") and hasattr(source, "__getitem__"):
            self._sequence = source  # numpy arrays and the like
        elif hasattr(source, "__anext__"):
            self._aiterator = source
        elif hasattr(source, "__next__") or (hasattr(source, "__iter__") and not callable(source)):
            self._iterator = iter(source)
        elif callable(source):
            self._callable = source
        else:
            raise LocalProtocolError(
                f"targets must be a sequence, an iterator, an async iterator or a callable "
                f"f(t, statuses); got {type(source).__name__}",
                field="targets",
            )

    def set_targets(self, source: TargetSource) -> None:
        """Replace the target source on the fly; it starts at its own index 0 next tick."""
        self._bind(source)
        self._index_base = self.next_tick

    _index_base = 0

    def pause(self) -> None:
        """Stop sending targets (the tick grid keeps running, so resume is on the grid)."""
        self.paused = True

    def resume(self) -> None:
        """Send targets again from the next tick."""
        self.paused = False

    @property
    def sending(self) -> bool:
        """True while the stream may still write targets (not paused, stopping or done)."""
        return not (self.paused or self.stopping or self.done)

    async def stop(self, *, hold: bool = False, safe: bool | None = None) -> None:
        """End the stream and apply its safe action; with ``hold``, send none.  Idempotent.

        From the moment this is called, nothing more of the stream is written: a tick
        being built or queued is dropped, so the safe action is the last word.  A stream
        that already ended (its targets ran out, an error) applied its safe action then;
        one ended with ``hold`` gets it now.  ``hold=True`` leaves the actuators holding
        their last target: say so where you rely on it.  ``safe=False`` is the older
        spelling of ``hold=True`` (``safe=True`` is the default).
        """
        hold = _hold_flag(hold, safe)
        self.stopping = True
        try:
            if not hold:
                with deferred_interrupts():
                    await self.apply_safe_action()
        finally:
            self._finish(None)

    async def wait(self) -> None:
        """Wait until the stream ends; raises ``StreamEnded`` if it ended on an error."""
        await asyncio.shield(self._finished)
        if self.error is not None:
            raise StreamEnded(f"stream to {list(self.ids)} ended: {self.error}") from self.error

    async def apply_safe_action(self) -> None:
        """Bring every actuator of the stream to the configured safe state, once.

        The stream stops sending first (``stopping``), so no target follows the stop.
        """
        self.stopping = True
        if self.safe_applied:
            return
        self.safe_applied = True
        if self.safe_action is SafeAction.HOLD:
            return
        action = (
            la.ControlAction.ESTOP
            if self.safe_action is SafeAction.ESTOP
            else la.ControlAction.PAUSE
        )
        for ident in self.ids:
            try:
                await self.streamer.bus.request(
                    la.Control(ident, action), priority=Priority.EMERGENCY
                )
            except MotorbusError as err:
                log.warning("safe action %s on la:%d failed: %s", action.name, ident, err)

    async def _end(self, error: BaseException | None) -> None:
        """End from the tick loop (targets ran out, a failure, a gap): safe action, then done."""
        self.stopping = True
        try:
            with deferred_interrupts():
                await self.apply_safe_action()
        finally:
            self._finish(error)

    def _finish(self, error: BaseException | None) -> None:
        if self.done:
            return
        self.stopping = True
        self.done = True
        self.error = error
        self.gaps.close()
        if not self._finished.done():
            self._finished.set_result(None)
        self.streamer._remove(self)

    async def __aenter__(self) -> Stream:
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        # However the block is left, the safe action goes out (a ``stop(hold=True)``
        # inside the block is the way to leave the actuators holding).
        await self.stop()

    # -- targets ------------------------------------------------------------------

    async def _targets(self, k: int, t: float) -> Targets | None:
        """The targets of tick ``k`` (time ``t`` since start), or None when exhausted."""
        item: Any
        i = k - self._index_base
        if self._sequence is not None:
            if i >= len(self._sequence):
                return None
            item = self._sequence[i]
        elif self._iterator is not None:
            try:
                item = next(self._iterator)
            except StopIteration:
                return None
        elif self._aiterator is not None:
            try:
                item = await self._aiterator.__anext__()
            except StopAsyncIteration:
                return None
        else:
            assert self._callable is not None
            item = self._callable(t, self.statuses)
            if inspect.isawaitable(item):
                item = await item
        if item is None:
            return None
        return self._normalise(item)

    def _normalise(self, item: Any) -> Targets:
        kind = type(item)
        if kind is list or kind is tuple:  # the common case first: no ABC checks
            return self._normalise_values(item)
        if kind is float or kind is int:
            return self._normalise_scalar(item)
        if isinstance(item, Mapping):
            targets = {target_id(i): _position(v, f"targets[{i}]") for i, v in item.items()}
            unknown = set(targets) - set(self.ids)
            if unknown:
                raise LocalProtocolError(
                    f"targets name ids {sorted(unknown)} that this stream does not drive "
                    f"(it drives {list(self.ids)})",
                    field="targets",
                )
            return targets
        if isinstance(item, (int, float)) or _is_scalar(item):
            return self._normalise_scalar(item)
        if isinstance(item, str | bytes):  # a sequence, but of characters
            raise LocalProtocolError(
                f"targets must be positions, not text: got {item!r}", field="targets"
            )
        # A numpy row (a 1-D array, or a row of a 2-D array of ticks x actuators):
        # tolist() gives plain floats/ints, which take the fast path below.
        tolist = getattr(item, "tolist", None)
        values = tolist() if callable(tolist) else list(item)
        return self._normalise_values(values)

    def _normalise_scalar(self, item: Any) -> Targets:
        if len(self.ids) != 1:
            raise LocalProtocolError(
                f"a single target was given for {len(self.ids)} actuators; give one "
                "per actuator or a mapping {id: position}",
                field="targets",
            )
        return {self.ids[0]: _position(item, "target")}

    def _normalise_values(self, values: Sequence[Any]) -> Targets:
        if len(values) != len(self.ids):
            raise LocalProtocolError(
                f"targets has {len(values)} values for {len(self.ids)} actuators",
                field="targets",
            )
        # The common case, once a tick per bus: plain numbers all in range.  Anything
        # else (a bool, NaN, a string, out of range) takes the checking path below,
        # which names the offending value.
        if all(type(v) in _PLAIN_NUMBERS for v in values):
            try:
                if min(values) >= la.POSITION_MIN and max(values) <= la.POSITION_MAX:
                    return dict(zip(self.ids, map(round, values), strict=True))
            except (ValueError, OverflowError):  # NaN or infinity: round() refuses them
                pass
        return {i: _position(v, f"targets[{i}]") for i, v in zip(self.ids, values, strict=True)}


def _hold_flag(hold: object, safe: object) -> bool:
    """``hold`` from ``stop``/``close``'s ``hold`` and older ``safe`` arguments."""
    held = check_flag("hold", hold)
    if safe is None:
        return held
    if check_flag("safe", safe) and held:
        raise LocalProtocolError(
            "hold=True and safe=True contradict each other: hold sends no safe action",
            field="hold",
            value=hold,
        )
    return held or not safe


_PLAIN_NUMBERS = (int, float)
_is_scalar = is_scalar
_position = target_position


class Streamer:
    """Serves every stream of one bus from one task, on absolute tick deadlines.

    Args:
        bus: an open bus carrying LA actuators.
        phase: offset of this bus's tick grid in seconds (the manager spreads buses so
            that they do not all wake at once).
    """

    def __init__(self, bus: Bus, *, phase: float = 0.0) -> None:
        if not isinstance(bus, Bus):
            raise LocalProtocolError(f"bus must be a Bus, got {bus!r}", field="bus", value=bus)
        phase = check_number("phase", phase, 0.0, PHASE_MAX_S, "s")
        self.bus = bus
        self.phase = phase
        self.streams: list[Stream] = []
        self._task: asyncio.Task[None] | None = None
        self._wake: asyncio.Future[None] | None = None
        #: Planned bus time of one tick of this streamer's streams (s), kept current.
        self._tick_cost_s = 0.0
        #: The window of a tick prepared or in progress: (deadline, end of its frames).
        self._active: tuple[float, float] | None = None
        _streamers_of(bus).add(self)
        bus.add_reservation_source(self._reservation)
        # Whatever ends the program closes the bus: the streams stop safely first.
        bus.add_close_hook(self._on_bus_close)

    async def _on_bus_close(self) -> None:
        await self.close(safe=True)

    def _bus_streams(self) -> list[Stream]:
        """Every running stream on this streamer's bus, whichever streamer serves it."""
        return [st for streamer in _streamers_of(self.bus) for st in streamer.streams]

    def _reservation(self, now: float) -> tuple[float, float] | None:
        """The next window this streamer's ticks need (see ``Bus.add_reservation_source``)."""
        active = self._active
        if active is not None and active[1] > now:
            return active
        sending = [s for s in self.streams if s.sending]  # a paused stream needs no slot
        if not sending:
            return None
        deadline = min(s.origin + s.next_tick * s.period for s in sending)
        return deadline, deadline + self._tick_cost_s

    def _update_tick_cost(self) -> None:
        self._tick_cost_s = sum(self.tick_cost(self.streams).values())

    # -- planning -------------------------------------------------------------------

    def slot_cost(self, *, reply_bytes: int, request_bytes: int) -> float:
        """Bus time one frame occupies when the device answers in time
        (``Occupancy.answered``): the spacing, or its round trip if longer."""
        return occupancy(
            self.bus.timing, Family.LA, request_bytes=request_bytes, reply_bytes=reply_bytes
        ).answered

    def tick_cost(self, streams: Iterable[Stream]) -> dict[float, float]:
        """Planned bus time per tick, per period, for a set of streams."""
        by_period: dict[float, tuple[int, int]] = {}
        for s in streams:
            broadcast, feedback = by_period.get(s.period, (0, 0))
            if s.feedback:
                feedback += len(s.ids)
            else:
                broadcast += len(s.ids)
            by_period[s.period] = (broadcast, feedback)
        follow_bytes = len(la.Follow(1, 0).encode())
        costs: dict[float, float] = {}
        for period, (broadcast, feedback) in by_period.items():
            frames = math.ceil(broadcast / la.MAX_BROADCAST_ENTRIES)
            cost = 0.0
            if frames:
                full, rest = divmod(broadcast, la.MAX_BROADCAST_ENTRIES)
                sizes = [la.MAX_BROADCAST_ENTRIES] * full + ([rest] if rest else [])
                cost += sum(self.slot_cost(request_bytes=6 + 3 * n, reply_bytes=0) for n in sizes)
            cost += feedback * self.slot_cost(
                request_bytes=follow_bytes, reply_bytes=la.STATUS_FRAME_SIZE
            )
            costs[period] = cost
        return costs

    def check_budget(self, extra: Stream) -> None:
        """Refuse ``extra`` if the streams of this bus would no longer fit their ticks.

        The budget is the bus's, shared by every streamer on it.
        """
        streams = [*self._bus_streams(), extra]
        costs = self.tick_cost(streams)
        load = sum(cost / period for period, cost in costs.items())
        if load <= TICK_BUDGET_SHARE:
            return
        poll = self.slot_cost(
            request_bytes=len(la.Control(1, la.ControlAction.QUERY_STATUS).encode()),
            reply_bytes=la.STATUS_FRAME_SIZE,
        )
        usable = extra.period * TICK_BUDGET_SHARE
        others = load - costs.get(extra.period, 0.0) / extra.period
        free_ms = max(0.0, (TICK_BUDGET_SHARE - others) * extra.period) * 1e3
        fit_feedback = int(max(0.0, usable - 0.0) // poll)
        raise LocalProtocolError(
            f"streams on bus {self.bus.name} would need {load * 100:.0f} % of the bus "
            f"(limit {TICK_BUDGET_SHARE * 100:.0f} %): a {extra.period * 1e3:.0f} ms tick has "
            f"{usable * 1e3:.1f} ms usable, {free_ms:.1f} ms still free. What fits per tick: "
            f"at most {fit_feedback} actuators with feedback (one {poll * 1e3:.2f} ms round "
            f"trip each), or {la.MAX_BROADCAST_ENTRIES} actuators per broadcast frame without "
            "feedback; or use a longer period",
            field="streams",
        )

    # -- starting and stopping --------------------------------------------------------

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
    ) -> Stream:
        """Start streaming follow-mode targets; returns the running ``Stream``.

        Args:
            actuators: one actuator or several, all on this streamer's bus.
            targets: where targets come from; see :class:`Stream`.
            period: seconds between ticks, 0.010..0.050 (LA manual 3.5.3).
            feedback: send 0x20 per actuator and decode each status (else 0x19, coalesced
                into 0xF3 broadcasts with the other no-feedback streams of the bus).
            poll_status: in the slots a tick leaves free, query the status of this
                stream's actuators round-robin (no-feedback streams).
            safe_action: "hold", "pause" or "estop"; applied however the stream ends (its
                targets run out, ``stop()``, the end of its ``async with`` block, an
                error, the bus closing), unless it is ended with ``stop(hold=True)``.
            on_gap: after a gap (the bus lost its port and came back, or the stream
                fell ``GAP_TICKS`` ticks behind): "ramp" (default) reads each actuator's
                position and ramps from there to the trajectory at ``max_speed``;
                "stop" applies the safe action and ends the stream with an error.
            max_speed: the stream's speed limit in position units per second, for the
                ramp after a gap (default 500: the full stroke in 4 s).

        Raises:
            LocalProtocolError: a bad period, option, an empty or foreign actuator list,
                an actuator already streamed, or a load that does not fit the bus.
        """
        if isinstance(actuators, InspireLA):
            group = [actuators]
        elif isinstance(actuators, Sequence) and all(isinstance(a, InspireLA) for a in actuators):
            group = list(actuators)
        else:
            raise LocalProtocolError(
                f"actuators must be an InspireLA or a sequence of them, got {actuators!r}",
                field="actuators",
            )
        if not group:
            raise LocalProtocolError("actuators must name at least one actuator", field="actuators")
        # 10..50 ms (LA manual 3.5.3); the slack admits a float32 0.01 (0.00999999978).
        period = check_number("period", period, PERIOD_MIN_S, PERIOD_MAX_S, "s", slack=1e-9)
        check_flag("feedback", feedback)
        check_flag("poll_status", poll_status)
        try:
            action = SafeAction(safe_action)
        except ValueError:
            raise LocalProtocolError(
                f"safe_action={safe_action!r} is not allowed: choose hold, pause or estop",
                field="safe_action",
            ) from None
        try:
            gap_policy = GapPolicy(on_gap)
        except ValueError:
            raise LocalProtocolError(
                f"on_gap={on_gap!r} is not allowed: choose ramp or stop",
                field="on_gap",
                value=on_gap,
            ) from None
        max_speed = check_number("max_speed", max_speed, 1.0, MAX_SPEED_LIMIT, "units/s")
        busy = {i for s in self._bus_streams() for i in s.ids}
        for a in group:
            if a.bus is not self.bus:
                raise LocalProtocolError(
                    f"actuator la:{a.id} is on bus {a.bus.name}, not {self.bus.name}",
                    field="actuators",
                )
            if a.id in busy:
                raise LocalProtocolError(
                    f"actuator la:{a.id} is already streamed on bus {self.bus.name}",
                    field="actuators",
                )
        if len({a.id for a in group}) != len(group):
            raise LocalProtocolError("actuators lists an id twice", field="actuators")
        stream = Stream(
            self,
            group,
            targets,
            period=float(period),
            feedback=feedback,
            poll_status=poll_status,
            safe_action=action,
            on_gap=gap_policy,
            max_speed=max_speed,
        )
        self.check_budget(stream)
        now = self.bus.timer.now()
        # Align the origin to this bus's grid so streams of one period coalesce.
        grid = self.phase + math.ceil((now + 0.002 - self.phase) / stream.period) * stream.period
        stream.origin = grid
        self.streams.append(stream)
        self._update_tick_cost()
        if self._task is None or self._task.done():
            self._task = asyncio.get_running_loop().create_task(
                self._run(), name=f"motorbus streams {self.bus.name}"
            )
        else:
            self._ring()
        return stream

    def _remove(self, stream: Stream) -> None:
        if stream in self.streams:
            self.streams.remove(stream)
            self._update_tick_cost()
            self._ring()

    async def close(self, *, hold: bool = False, safe: bool | None = None) -> None:
        """End every stream with its safe action (none with ``hold``) and stop the task.

        Every stream stops sending at once, before the first safe action is sent.
        ``safe=False`` is the older spelling of ``hold=True``.
        """
        hold = _hold_flag(hold, safe)
        streams = list(self.streams)
        for s in streams:
            s.stopping = True
        with deferred_interrupts():
            for s in streams:
                await s.stop(hold=hold)
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None

    # -- the tick loop -------------------------------------------------------------------

    def _ring(self) -> None:
        if self._wake is not None and not self._wake.done():
            self._wake.set_result(None)

    async def _sleep_until(self, deadline: float) -> None:
        wake: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._wake = wake

        def ring() -> None:
            if not wake.done():
                wake.set_result(None)

        # Only the preparation wakes here; the frames go out from a precise callback.
        handle = self.bus.timer.call_at(deadline, ring, precise=False)
        try:
            await wake
        finally:
            handle.cancel()
            self._wake = None

    async def _run(self) -> None:
        timer = self.bus.timer
        while self.streams:
            deadline = min(s.origin + s.next_tick * s.period for s in self.streams)
            if deadline - PLAN_AHEAD_S > timer.now():
                await self._sleep_until(deadline - PLAN_AHEAD_S)
                continue  # re-check: streams may have changed while asleep
            due = [
                s
                for s in self.streams
                if s.origin + s.next_tick * s.period <= deadline + COALESCE_WINDOW_S
            ]
            await self._serve_tick(due, deadline)
            if self.streams:
                # Idle time until the next tick: where real-time mode runs the garbage
                # collector's full collections (a no-op otherwise; motorbus.realtime).
                upcoming = min(s.origin + s.next_tick * s.period for s in self.streams)
                idle = upcoming - PREPARE_S - timer.now()
                if idle > 0:
                    realtime.idle_hook(idle)

    async def _serve_tick(self, due: list[Stream], deadline: float) -> None:
        """Prepare the tick's frames ahead of ``deadline``, send them at it, then
        do the feedback round trips and polls."""
        timer = self.bus.timer
        now = timer.now()
        feedback: list[tuple[Stream, int, int]] = []
        served: list[Stream] = []
        bus_up = self.bus.state is BusState.OPEN
        for s in due:
            k = s.next_tick
            behind = int((now - (s.origin + k * s.period)) // s.period)
            if behind >= 1:  # overrun: skip to the current slot instead of bursting
                s.stats.skipped += behind
                k += behind
            s.next_tick = k + 1
            if not bus_up:  # the port is gone: the grid runs on, the ticks are skipped
                s.stats.skipped += 1
                continue
            if not s.sending:
                continue
            cause = self._gap_cause(s, behind)
            if cause is not None:
                await self._gap(s, cause)
                continue  # the ramp (or nothing, after a stop) starts next tick
            try:
                targets = await s._targets(k, k * s.period)
            except Exception as err:  # the user's target source failed: end that stream
                log.warning("stream to %s: target source failed: %s", list(s.ids), err)
                await s._end(err)
                continue
            if targets is None:  # a normal end: still a safe one
                await s._end(None)
                continue
            if s.ramp is not None:
                targets = ramp_step(s.ramp, targets, s.max_speed * s.period)
                if not s.ramp:
                    s.ramp = None  # every actuator is back on the trajectory
            s.skipped_mark = s.stats.skipped
            s.last_targets.update(targets)
            served.append(s)
            if s.feedback:
                feedback.extend((s, i, p) for i, p in targets.items())
        if not served:
            return
        self._active = (deadline, deadline + self._tick_cost_s)
        try:
            parts = [(s, s.last_targets) for s in served if not s.feedback]
            sent_at, frames, slipped = await self._send_at(deadline, parts)
            for s in served:
                if not s.feedback:
                    s.stats.frames += frames
            if feedback and timer.now() < deadline:
                # Feedback frames are round trips, sent one after another from this task:
                # the first leaves at the deadline (the tick was prepared a period ahead).
                await timer.sleep_until(deadline)
            for s, ident, pos in feedback:
                if sent_at is None:
                    sent_at = timer.now()
                    slipped = sent_at - deadline > LATE_AFTER_S / 10
                if not s.sending:
                    continue
                follow = la.Follow(ident, pos, True)
                try:
                    status = await self.bus.submit(
                        follow,
                        priority=Priority.HIGH,
                        reserved=True,
                        refresh=_while_sending(s, follow),
                    )
                except MotorbusError:
                    s.stats.feedback_timeouts += 1
                else:
                    if status is not None:
                        s.statuses[ident] = status
                s.stats.frames += 1
        finally:
            self._active = None
        if sent_at is None:
            return  # the port went away before anything left
        for s in served:
            lateness = max(0.0, sent_at - (s.origin + (s.next_tick - 1) * s.period))
            s.stats.ticks += 1
            s.stats.jitter.record(lateness)
            if slipped:
                s.stats.slipped += 1
            if lateness > LATE_AFTER_S:
                s.stats.late += 1
        await self._poll(served)

    def _gap_cause(self, s: Stream, behind: int) -> str | None:
        """Why ``s`` has a gap to handle before its next targets, or None."""
        if self.bus.stats.disconnects != s.disconnects_seen:
            return "outage"
        if behind >= GAP_TICKS:
            return "behind"
        return None

    async def _gap(self, s: Stream, cause: str) -> None:
        """Handle a gap of ``s`` by its ``on_gap``: read where each actuator is and ramp
        from there, or apply the safe action and end it.  Publishes ``StreamGap``.

        An actuator whose position cannot be read cannot be ramped: that ends the
        stream as "stop" does.
        """
        bus = self.bus
        s.disconnects_seen = bus.stats.disconnects
        s.stats.gaps += 1
        missed = s.stats.skipped - s.skipped_mark
        s.skipped_mark = s.stats.skipped
        positions: dict[int, int] = {}
        unread: list[int] = []
        if s.on_gap is GapPolicy.RAMP:
            for ident in s.ids:
                try:
                    status = await bus.request(
                        la.Control(ident, la.ControlAction.QUERY_STATUS), priority=Priority.HIGH
                    )
                except MotorbusError as err:
                    log.warning("stream to %s: la:%d position unread: %s", list(s.ids), ident, err)
                    unread.append(ident)
                    continue
                s.statuses[ident] = status
                positions[ident] = min(max(status.position, la.POSITION_MIN), la.POSITION_MAX)
        ramp = s.on_gap is GapPolicy.RAMP and not unread and s.sending
        action = "ramp" if ramp else "stop"
        bus.events.publish(
            StreamGap(bus.name, bus.timer.now(), s.number, s.ids, cause, missed, positions, action)
        )
        log.warning(
            "stream to %s: gap (%s, %d ticks missed): %s",
            list(s.ids),
            cause,
            missed,
            f"ramping from {positions}" if ramp else "safe action, stream ended",
        )
        if not ramp:
            if s.sending:
                why = f"la:{', la:'.join(map(str, unread))} unread" if unread else 'on_gap="stop"'
                await s._end(StreamEnded(f"gap ({cause}, {missed} ticks missed; {why})"))
            return
        s.ramp = {i: float(p) for i, p in positions.items()}
        # The reads took time: the stream goes on from the next slot still ahead.
        upcoming = math.ceil((bus.timer.now() - s.origin) / s.period)
        if upcoming > s.next_tick:
            s.stats.skipped += upcoming - s.next_tick
            s.next_tick = upcoming
        s.skipped_mark = s.stats.skipped

    async def _send_at(
        self, deadline: float, parts: list[tuple[Stream, dict[int, int]]]
    ) -> tuple[float | None, int, bool]:
        """Send the broadcast targets of ``parts`` at ``deadline`` exactly.

        The frames are queued from a timer callback at the deadline: a task woken then
        would send one event-loop step late (~55 us here, bench_wakeups.py).  Each frame
        is built at the moment it is written, from the streams still sending then
        (``Bus.submit(refresh=...)``), so a stream stopped or paused since its targets
        were computed sends nothing more, even from a frame that had to wait its turn.
        Returns (when the first frame left, or None if nothing left; frames sent; whether
        the tick slipped: its first frame could not be written at the deadline itself).
        """
        if not parts:
            return None, 0, False
        loop = asyncio.get_running_loop()
        fired: asyncio.Future[list[asyncio.Future[Any]]] = loop.create_future()
        sent: list[float] = []
        step = la.MAX_BROADCAST_ENTRIES
        # IDs were checked when the streams started (distinct across streams) and every
        # position by _position, so the frames are built without re-checking.
        entries = [(s, pair) for s, targets in parts for pair in targets.items()]
        chunks = [entries[i : i + step] for i in range(0, len(entries), step)]

        def fire() -> None:
            if fired.done():
                return
            futures = []
            try:
                for chunk in chunks:
                    build = _broadcast_builder(chunk)
                    first = build()
                    if first is None:
                        continue
                    futures.append(
                        self.bus.submit(first, priority=Priority.HIGH, reserved=True, refresh=build)
                    )
            except MotorbusError as err:
                fired.set_exception(err)
                return
            if futures and futures[0].done():  # an idle bus wrote it inside submit()
                sent.append(self.bus.timer.now())
            fired.set_result(futures)

        handle = self.bus.timer.call_at(deadline, fire)
        slipped = False
        try:
            futures = await fired
            for f in futures:
                await f
                if not sent:  # it waited its turn (a reply owed, or the spacing)
                    sent.append(self.bus.timer.now())
                    slipped = True
        except MotorbusError as err:
            log.debug("stream tick on bus %s not sent: %s", self.bus.name, err)
            return None, 0, False
        finally:
            handle.cancel()
        return (sent[0] if sent else None), len(futures), slipped

    async def _poll(self, due: list[Stream]) -> None:
        """Use the slots left before the next tick to poll statuses round-robin.

        A poll is queued only if even its timeout would end before the next tick, with
        a ``start_by`` past which it is dropped unsent: user requests take the slot
        first (they queue ahead of polls), and a poll that cannot get one is counted in
        ``polls_skipped``; it never holds the next tick.
        """
        pollers = [s for s in due if s.poll_status and s.sending]
        if not pollers or not self.streams:
            return
        timer = self.bus.timer
        poll = self.bus.occupancy(la.Control(1, la.ControlAction.QUERY_STATUS))
        next_deadline = min(s.origin + s.next_tick * s.period for s in self.streams)
        # A poll starts only if even its timeout, and the spacing after it, would end
        # before the next tick.
        worst = poll.worst + poll.spacing
        start_by = next_deadline - PREPARE_S - worst
        for s in pollers:
            polled = 0
            for _ in range(len(s.ids)):
                # No room left in this tick (the spacing alone would pass start_by): the
                # round robin goes on next tick; that is not a skipped poll.
                if max(timer.now(), self.bus.next_write_at) > start_by or not s.sending:
                    break
                ident = s.ids[s._poll_cursor % len(s.ids)]
                try:
                    status = await self.bus.submit(
                        la.Control(ident, la.ControlAction.QUERY_STATUS),
                        retries=0,
                        priority=Priority.BACKGROUND,
                        start_by=start_by,
                    )
                except NotSentError:
                    s.stats.polls_skipped += 1
                    polled = -1  # counted already
                    break
                except MotorbusError:
                    s._poll_cursor += 1
                    s.stats.feedback_timeouts += 1
                    continue
                s._poll_cursor += 1
                polled += 1
                s.statuses[ident] = status
                s.stats.polls += 1
            if polled == 0:
                s.stats.polls_skipped += 1


def ramp_step(ramp: dict[int, float], targets: Targets, step: float) -> dict[int, int]:
    """One tick of the ramp after a gap: move each ramping actuator at most ``step``
    from where it was last sent (``ramp``) toward its target.

    ``ramp`` is updated in place; an actuator that reaches its target leaves it (from
    then on it follows the targets as they come).  Actuators not ramping pass through.
    """
    out = dict(targets)
    for ident, goal in targets.items():
        at = ramp.get(ident)
        if at is None:
            continue
        if abs(goal - at) <= step:
            del ramp[ident]
            continue
        at += step if goal > at else -step
        ramp[ident] = at
        out[ident] = round(at)
    return out


def _while_sending(stream: Stream, cmd: la.Follow) -> Callable[[], la.Follow | None]:
    """A ``refresh`` for one feedback frame: drop it if its stream no longer sends."""
    return lambda: cmd if stream.sending else None


def _broadcast_builder(
    chunk: list[tuple[Stream, tuple[int, int]]],
) -> Callable[[], la.Broadcast | None]:
    """A ``refresh`` that builds one 0xF3 frame from the entries still sending.

    While every stream of the chunk still sends, the frame built first is reused (it is
    built once a tick, at the deadline, on the hot path).
    """
    streams = tuple({s: None for s, _ in chunk})
    built: list[la.Broadcast] = []

    def build() -> la.Broadcast | None:
        if all(s.sending for s in streams):
            if not built:
                built.append(
                    la.Broadcast.prevalidated(la.BroadcastMode.FOLLOW, tuple(p for _, p in chunk))
                )
            return built[0]
        pairs = tuple(pair for s, pair in chunk if s.sending)
        if not pairs:
            return None
        return la.Broadcast.prevalidated(la.BroadcastMode.FOLLOW, pairs)

    return build


_STREAMERS: weakref.WeakKeyDictionary[Bus, weakref.WeakSet[Streamer]] = weakref.WeakKeyDictionary()


def _streamers_of(bus: Bus) -> weakref.WeakSet[Streamer]:
    """The streamers of ``bus`` (they share its budget and its actuators)."""
    found = _STREAMERS.get(bus)
    if found is None:
        found = _STREAMERS[bus] = weakref.WeakSet()
    return found
