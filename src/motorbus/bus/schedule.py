"""When the next frame may start: the bus's queue and its timing rules, without I/O.

Pure (no asyncio, no clock, no futures, no timer handles): the time is passed in, as in
the simulators, and the answer is a decision.  ``BusEngine`` (``motorbus.bus.engine``)
is the asyncio shell that writes the frame or sets its timer; table tests drive this module
with plain numbers (tests/bus/test_schedule.py).

The rules, for each queued job (in queue order: lowest priority value, then the order
it was queued in; the first that may start goes):

* spacing: not before ``next_tx``, which is the completed write of the previous frame
  plus its ``after_write`` (``max(min_spacing, its wire time)``, ``motorbus.bus.
  occupancy``).  The anchor is the moment the write call came back, not a timestamp
  taken before it: a process preempted between reading the clock and writing would
  otherwise write later than its timestamp says;
* late guard: after a timeout, the next request to that device waits until its guard
  ends, so that the late answer cannot be taken for the reply to a newer question
  (requests to other devices are not held);
* reservations: a frame that is not ``reserved`` (a stream tick's) nor an emergency is
  not started if it could still hold the bus when a reserved window begins; it waits
  until the window ends;
* order: a job held by the guard or a window holds the jobs behind it only if they
  reach a common device (``keeps_order``); a stream tick's frame is held by none.
  Before 2026-12-03 a held job held the whole queue: a status poll's retry waiting out
  its 20 ms guard made every stream tick behind it 20 ms late.

Whether a reply is still owed (the pending request) is the matcher's business
(``motorbus.bus.matching``): the shell asks this module only while nothing is pending.
"""

from __future__ import annotations

import enum
import heapq
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Generic, TypeVar

from motorbus.protocol.base import Command

__all__ = [
    "WRITE_COST_DECAY",
    "WRITE_COST_MAX_S",
    "WRITE_COST_MIN_S",
    "Job",
    "Priority",
    "ReservationSource",
    "Scheduler",
    "Wait",
    "keeps_order",
]

#: What a write is assumed to take when a request is fitted before a reserved stream
#: tick: the largest recent write duration, decaying by this factor a write, within
#: these bounds (seconds).  A write that takes longer only slips the tick (counted).
WRITE_COST_DECAY = 0.99
WRITE_COST_MIN_S = 50e-6
WRITE_COST_MAX_S = 500e-6

#: A source of reserved bus windows: given the time now, the earliest (start, end) window
#: that ends after now, or None.
ReservationSource = Callable[[float], "tuple[float, float] | None"]


class Priority(enum.IntEnum):
    """Queue order; lower goes first."""

    EMERGENCY = 0  # e-stop, stop-all: jump the queue
    HIGH = 1
    NORMAL = 2
    BACKGROUND = 3  # status polling that yields to everything else


@dataclass(slots=True, eq=False)
class Job:
    """One request travelling through the bus: what scheduling and matching need.

    The shell subclasses it to keep its future and timer handles beside these fields;
    ``gone()`` tells the queue that nobody awaits the job any more (cancelled or
    expired while queued), and the queue drops it unsent.
    """

    cmd: Command[object]
    raw: bytes
    priority: int
    seq: int
    timeout: float  # completed write to the reply's deadline
    key: str  # the device (``Command.device_key``): late guards are per device
    retries_left: int = 0
    after_write: float = 0.0  # completed write to the earliest next write (Occupancy)
    answered: float = 0.0  # what it holds when its device answers in time (Occupancy)
    reserved: bool = False  # a stream tick's frame: it owns the reserved window
    tx_start: float = 0.0  # when the write was issued (a stream tick's lateness)
    tx_time: float = 0.0  # when the write returned
    rx_mark: int = 0  # stream offset of the first received byte that may be its reply
    earliest: float = 0.0  # wire floor (wire_floor=True only)
    deadline: float = 0.0
    attempts: int = 0

    def __lt__(self, other: Job) -> bool:
        return (self.priority, self.seq) < (other.priority, other.seq)

    def gone(self) -> bool:
        """True if nobody awaits this job any more: drop it unsent."""
        return False

    @property
    def hold(self) -> float:
        """What the job may hold the bus from its completed write: its spacing, or its
        whole reply budget (its own timeout, which ``request(timeout=...)`` may set)."""
        return max(self.after_write, self.timeout if self.cmd.expects_reply else 0.0)


@dataclass(frozen=True, slots=True)
class Wait:
    """Nothing may start before ``at``; ``precise``: worth the timer's last microseconds
    (a tick's frame or a user's request; not a background poll, since the spacing rule
    is a minimum and a late poll breaks nothing)."""

    at: float
    precise: bool


def keeps_order(ahead: Job, job: Job) -> bool:
    """True if ``job`` may not be written before ``ahead``, queued before it.

    Requests that reach a common device keep their queue order (a pause must not
    overtake the move queued before it; a broadcast reaches every device of its family).
    A stream tick's frame (``reserved``) is kept back by no other frame: it owns its
    window and its actuators (their lease), and it is rebuilt at its write from the
    streams still sending.  Its own device rules (spacing, a late guard) still apply.
    """
    if job.reserved and not ahead.reserved:
        return False
    return ahead.cmd.reaches(job.key) or job.cmd.reaches(ahead.key)


def _precise(job: Job) -> bool:
    """Whether a wait for ``job`` is worth the timer's last microseconds (``Wait``)."""
    return job.reserved or job.priority < Priority.BACKGROUND


#: The job record a shell keeps (``Job`` or a subclass of it).
J = TypeVar("J", bound=Job)


@dataclass(slots=True)
class Scheduler(Generic[J]):
    """The queue of jobs and the times the bus's rules allow them to start."""

    #: Completed write of the last frame plus its ``after_write``: the earliest next write.
    next_tx: float = 0.0
    #: The write duration assumed when fitting a request before a reserved window.
    write_cost: float = WRITE_COST_MIN_S
    #: Per device key: no request to it before then (after a timeout).
    guard_until: dict[str, float] = field(default_factory=dict)
    reservation_sources: list[ReservationSource] = field(default_factory=list)
    heap: list[J] = field(default_factory=list)
    _seq: int = 0

    def __len__(self) -> int:
        return len(self.heap)

    def next_seq(self) -> int:
        """The queue order of a new job among jobs of its priority."""
        self._seq += 1
        return self._seq

    def push(self, job: J) -> None:
        """Queue ``job``."""
        heapq.heappush(self.heap, job)

    def requeue(self, job: J, priority: int = Priority.HIGH) -> None:
        """Queue a job again (a retry), at ``priority`` or better."""
        job.priority = min(job.priority, int(priority))
        heapq.heappush(self.heap, job)

    def drain(self) -> Iterator[J]:
        """Take every queued job out, in queue order (the port is gone)."""
        heap = self.heap
        while heap:
            yield heapq.heappop(heap)

    # -- the decision ----------------------------------------------------------------

    def poll(self, now: float) -> J | Wait | None:
        """What to do at ``now`` with no reply owed: the job to write now (taken off the
        queue), the time to look again, or None with nothing queued.  Jobs nobody
        awaits any more are dropped on the way.

        The first job in queue order that may start now goes.  A job held by a rule of
        its own (its device's late guard, a reserved window it may not use) does not
        hold the jobs behind it, except those that must keep their order with it
        (``keeps_order``); the spacing holds every job alike.
        """
        heap = self.heap
        while heap:
            job = heap[0]
            if job.gone():
                heapq.heappop(heap)
                continue
            start = self.start_at(job, now)
            if start <= now:
                return heapq.heappop(heap)
            if start <= self.next_tx:  # held by the spacing alone, and so is every job
                return Wait(start, job.reserved or job.priority < Priority.BACKGROUND)  # _precise
            return self._past_the_held(now)
        return None

    def _past_the_held(self, now: float) -> J | Wait:
        """``poll`` when the head is held by a rule of its own: the first job behind it
        that may start now, else the earliest time one may."""
        heap = self.heap
        held: list[J] = []  # live jobs taken off to look behind them, put back below
        wait: Wait | None = None
        try:
            while heap:
                job = heap[0]
                if job.gone():
                    heapq.heappop(heap)
                    continue
                if not any(keeps_order(ahead, job) for ahead in held):
                    start = self.start_at(job, now)
                    if start <= now:
                        return heapq.heappop(heap)
                    if wait is None or start < wait.at:
                        wait = Wait(start, _precise(job))
                    elif start == wait.at and _precise(job):
                        wait = Wait(start, True)
                    if start <= self.next_tx:
                        break  # held by the spacing alone: nothing behind starts sooner
                held.append(heapq.heappop(heap))
        finally:
            for job in held:
                heapq.heappush(heap, job)
        assert wait is not None  # the head itself was held, not taken
        return wait

    def start_at(self, job: Job, now: float) -> float:
        """The earliest time ``job`` may start, seen at ``now``."""
        # The latest of the spacing, the device's late guard and now (comparisons, not
        # max() and get(): this runs for every frame, once or more).
        start = self.next_tx if self.next_tx > now else now
        guards = self.guard_until
        if guards and job.key in guards and guards[job.key] > start:
            start = guards[job.key]
        if not self.reservation_sources or job.reserved:
            return start  # nothing to look up (held_by_reservation's own first test)
        held = self.held_by_reservation(job, start)
        return start if held is None else held

    def held_by_reservation(self, job: Job, start: float) -> float | None:
        """End of the reserved window ``job`` would overlap if started at ``start``."""
        if job.reserved or job.priority == Priority.EMERGENCY or not self.reservation_sources:
            return None
        occupancy = self.write_cost + job.hold
        for source in self.reservation_sources:
            window = source(start)
            if window is None:
                continue
            begin, end = window
            if start >= end or start + occupancy <= begin:
                continue  # after the window, or done before it begins
            if start >= begin:
                return end  # inside the window: wait for its end
            following = source(end + 1e-9)
            gap = math.inf if following is None else following[0] - end
            if occupancy <= gap:
                return end  # the next gap holds its whole budget
            # No gap holds its whole budget (a long timeout, a large host margin): it is
            # fitted by what it holds when its device answers in time, so a tick waits
            # only for a reply that is really late; if even that fits no gap, it goes now.
            answered = self.write_cost + max(job.after_write, job.answered)
            if answered <= gap and start + answered > begin:
                return end
        return None

    # -- what happened ---------------------------------------------------------------

    def wrote(self, job: Job, before: float, after: float) -> None:
        """``job``'s write was called at ``before`` and returned at ``after``: the
        spacing counts from ``after``; the write's duration feeds ``write_cost``."""
        self.next_tx = after + job.after_write
        # min(MAX, max(MIN, this write's, the last cost decayed)), without the calls.
        cost = self.write_cost * WRITE_COST_DECAY
        if after - before > cost:
            cost = after - before
        if cost < WRITE_COST_MIN_S:
            cost = WRITE_COST_MIN_S
        self.write_cost = cost if cost < WRITE_COST_MAX_S else WRITE_COST_MAX_S

    def guard(self, key: str, until: float) -> None:
        """Hold requests to device ``key`` until ``until`` (a timeout's late guard)."""
        self.guard_until[key] = until

    def restart(self) -> None:
        """A new port (reconnected): no previous write to keep apart from."""
        self.next_tx = 0.0
