"""The time budget of one bus's streams: what a tick costs, and what still fits.

Pure arithmetic over ``motorbus.bus.occupancy`` (no asyncio, no clock).  One
:class:`StreamBudget` per bus, kept here for the bus's life (``stream_budget(bus)``,
created by the first ``Streamer`` on it), so every streamer of the bus shares it: a set of
streams that cannot fit the bus is refused when it starts, with an error that says
what would fit, and an actuator can be streamed by one stream at a time.
"""

from __future__ import annotations

import weakref
from collections.abc import Iterable, Sequence
from typing import Protocol

from motorbus.bus.occupancy import BusTiming, occupancy
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import Family

__all__ = [
    "TICK_BUDGET_SHARE",
    "Planned",
    "StreamBudget",
    "slot_cost",
    "stream_budget",
    "tick_cost",
]

#: Share of each tick that streams may plan to use; the rest absorbs host jitter and
#: the user's own requests.
TICK_BUDGET_SHARE = 0.8
#: Bytes of one 0xF3 broadcast frame: header, Len, ID FF, F3, checksum, 3 per entry.
_BROADCAST_HEAD = 6
_BROADCAST_ENTRY = 3


class Planned(Protocol):
    """What the budget needs to know of a stream."""

    @property
    def ids(self) -> tuple[int, ...]: ...
    @property
    def period(self) -> float: ...
    @property
    def feedback(self) -> bool: ...


def slot_cost(timing: BusTiming, *, request_bytes: int, reply_bytes: int) -> float:
    """Bus time one LA frame occupies when the device answers in time
    (``Occupancy.answered``): the spacing, or its round trip if longer."""
    return occupancy(
        timing, Family.LA, request_bytes=request_bytes, reply_bytes=reply_bytes
    ).answered


def tick_cost(timing: BusTiming, streams: Iterable[Planned]) -> dict[float, float]:
    """Planned bus time per tick, per period, for a set of streams (seconds).

    Streams without feedback of one period share 0xF3 broadcasts of up to 15 entries;
    each actuator of a feedback stream costs a 0x20 round trip.
    """
    by_period: dict[float, tuple[int, int]] = {}
    for s in streams:
        broadcast, feedback = by_period.get(s.period, (0, 0))
        if s.feedback:
            feedback += len(s.ids)
        else:
            broadcast += len(s.ids)
        by_period[s.period] = (broadcast, feedback)
    costs: dict[float, float] = {}
    for period, (broadcast, feedback) in by_period.items():
        costs[period] = broadcast_tick(timing, broadcast)[0] + feedback * feedback_slot(timing)
    return costs


def broadcast_tick(timing: BusTiming, actuators: int) -> tuple[float, int]:
    """Bus time of the 0xF3 frames that carry ``actuators`` follow targets in one tick
    (up to 15 a frame), and how many frames that is."""
    full, rest = divmod(actuators, la.MAX_BROADCAST_ENTRIES)
    sizes = [la.MAX_BROADCAST_ENTRIES] * full + ([rest] if rest else [])
    cost = sum(
        slot_cost(timing, request_bytes=_BROADCAST_HEAD + _BROADCAST_ENTRY * n, reply_bytes=0)
        for n in sizes
    )
    return cost, len(sizes)


def feedback_slot(timing: BusTiming) -> float:
    """Bus time of one actuator streamed with feedback: a 0x20 follow and its status."""
    return slot_cost(
        timing, request_bytes=len(la.Follow(1, 0).encode()), reply_bytes=la.STATUS_FRAME_SIZE
    )


class StreamBudget:
    """The streams running on one bus, whichever streamer serves them, and their budget.

    Args:
        bus_name: for error messages.
    """

    def __init__(self, bus_name: str) -> None:
        self.bus_name = bus_name
        self.streams: list[Planned] = []

    def busy_ids(self) -> set[int]:
        """Every actuator some running stream of the bus drives."""
        return {i for s in self.streams for i in s.ids}

    def check_ids(self, ids: Sequence[int]) -> None:
        """Refuse actuators already streamed on this bus, or listed twice."""
        busy = self.busy_ids()
        for ident in ids:
            if ident in busy:
                raise LocalProtocolError(
                    f"actuator la:{ident} is already streamed on bus {self.bus_name}",
                    field="actuators",
                )
        if len(set(ids)) != len(ids):
            raise LocalProtocolError("actuators lists an id twice", field="actuators")

    def check_load(self, timing: BusTiming, extra: Planned) -> None:
        """Refuse ``extra`` if the streams of this bus would no longer fit their ticks."""
        costs = tick_cost(timing, [*self.streams, extra])
        load = sum(cost / period for period, cost in costs.items())
        if load <= TICK_BUDGET_SHARE:
            return
        poll = slot_cost(
            timing,
            request_bytes=len(la.Control(1, la.ControlAction.QUERY_STATUS).encode()),
            reply_bytes=la.STATUS_FRAME_SIZE,
        )
        usable = extra.period * TICK_BUDGET_SHARE
        others = load - costs.get(extra.period, 0.0) / extra.period
        free_ms = max(0.0, (TICK_BUDGET_SHARE - others) * extra.period) * 1e3
        fit_feedback = int(max(0.0, usable) // poll)
        raise LocalProtocolError(
            f"streams on bus {self.bus_name} would need {load * 100:.0f} % of the bus "
            f"(limit {TICK_BUDGET_SHARE * 100:.0f} %): a {extra.period * 1e3:.0f} ms tick has "
            f"{usable * 1e3:.1f} ms usable, {free_ms:.1f} ms still free. What fits per tick: "
            f"at most {fit_feedback} actuators with feedback (one {poll * 1e3:.2f} ms round "
            f"trip each), or {la.MAX_BROADCAST_ENTRIES} actuators per broadcast frame without "
            "feedback; or use a longer period",
            field="streams",
        )

    def admit(self, timing: BusTiming, stream: Planned) -> None:
        """Add ``stream`` if its actuators are free and the load fits; else raise
        ``LocalProtocolError`` and change nothing."""
        self.check_ids(stream.ids)
        self.check_load(timing, stream)
        self.streams.append(stream)

    def release(self, stream: Planned) -> None:
        """Forget an ended stream (unknown ones are ignored)."""
        if stream in self.streams:
            self.streams.remove(stream)


class _Named(Protocol):
    @property
    def name(self) -> str: ...


#: The budget of each bus's streams, shared by all its streamers; the streams layer
#: keeps it (the bus knows nothing of streams), for as long as the bus lives.
_BUDGETS: weakref.WeakKeyDictionary[_Named, StreamBudget] = weakref.WeakKeyDictionary()


def stream_budget(bus: _Named) -> StreamBudget:
    """The time budget ``bus``'s streams share (created on first use): every
    ``Streamer`` of a bus checks its streams against this one."""
    budget = _BUDGETS.get(bus)
    if budget is None:
        budget = _BUDGETS[bus] = StreamBudget(bus.name)
    return budget
