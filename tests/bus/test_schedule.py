"""The bus's scheduling rules on the pure core (``motorbus.bus.schedule``): plain numbers,
no event loop, no clock.  The same guarantees are checked over ptys and simulators in
tests/bus/test_bus_guarantees.py."""

from __future__ import annotations

from dataclasses import dataclass

import pytest

from motorbus.bus.occupancy import BusTiming, command_occupancy
from motorbus.bus.schedule import (
    WRITE_COST_MAX_S,
    WRITE_COST_MIN_S,
    Job,
    Priority,
    ReservationSource,
    Scheduler,
    Wait,
)
from motorbus.protocol import la
from motorbus.protocol.base import Command
from motorbus.protocol.families import DEFAULT_TURNAROUND

SPACING = 1e-3


def timing(baud: int = 115200) -> BusTiming:
    return BusTiming(baud, SPACING, 2e-3, DEFAULT_TURNAROUND)


def status(ident: int = 1) -> Command[object]:
    return la.Control(ident, la.ControlAction.QUERY_STATUS)


def make_job(
    sched: Scheduler[Job],
    cmd: Command[object] | None = None,
    *,
    priority: Priority = Priority.NORMAL,
    reserved: bool = False,
    timeout: float | None = None,
    baud: int = 115200,
) -> Job:
    cmd = status() if cmd is None else cmd
    raw = cmd.encode()
    occ = command_occupancy(timing(baud), cmd, len(raw))
    return Job(
        cmd=cmd,
        raw=raw,
        priority=int(priority),
        seq=sched.next_seq(),
        timeout=occ.budget if timeout is None else timeout,
        key=cmd.device_key,
        after_write=occ.after_write,
        answered=occ.answered,
        reserved=reserved,
    )


def send(sched: Scheduler[Job], now: float, took: float = 0.0) -> Job:
    """Poll at ``now``: a job must be due; its write takes ``took``."""
    decision = sched.poll(now)
    assert isinstance(decision, Job), f"expected a job at {now}, got {decision!r}"
    sched.wrote(decision, now, now + took)
    return decision


# -- spacing, from the completed write ------------------------------------------------


@pytest.mark.parametrize(
    ("write_began", "write_took"),
    [(0.0, 0.0), (10.0, 5e-6), (10.0, 400e-6), (10.0, 3e-3), (123.456, 0.8e-3)],
)
def test_the_next_write_waits_min_spacing_from_the_completed_write(
    write_began: float, write_took: float
) -> None:
    sched: Scheduler[Job] = Scheduler()
    sched.push(make_job(sched))
    first = send(sched, write_began, write_took)
    completed = write_began + write_took
    sched.push(make_job(sched))
    # Anything sooner than the completed write plus the spacing is a wait, and the wait
    # is until exactly then: counted from the end of the write, not from its start.
    for now in (write_began, completed, completed + first.after_write / 2):
        decision = sched.poll(now)
        assert decision == Wait(completed + first.after_write, True)
    assert first.after_write >= SPACING
    assert sched.next_tx == completed + first.after_write
    assert isinstance(sched.poll(completed + first.after_write), Job)


@pytest.mark.parametrize(("baud", "expect_wire"), [(921600, False), (115200, True), (9600, True)])
def test_a_long_frame_holds_the_bus_for_its_wire_time_when_that_is_longer(
    baud: int, expect_wire: bool
) -> None:
    # A 7-entry broadcast, 27 bytes: 28 ms at 9600 bit/s, 2.3 ms at 115200, 0.3 ms at 921600.
    broadcast = la.Broadcast(la.BroadcastMode.POSITION, tuple((i, 1000) for i in range(1, 8)))
    sched: Scheduler[Job] = Scheduler()
    sched.push(make_job(sched, broadcast, baud=baud))
    job = send(sched, 0.0)
    wire = len(job.raw) * 10 / baud
    assert job.after_write == max(SPACING, wire)
    assert (job.after_write > SPACING) is expect_wire
    sched.push(make_job(sched, baud=baud))
    assert sched.poll(0.0) == Wait(job.after_write, True)


def test_a_reconnect_forgets_the_previous_write() -> None:
    sched: Scheduler[Job] = Scheduler()
    sched.push(make_job(sched))
    send(sched, 5.0)
    sched.restart()
    sched.push(make_job(sched))
    assert isinstance(sched.poll(5.0), Job)


@pytest.mark.parametrize(
    ("took", "before", "expect"),
    [
        (0.0, WRITE_COST_MIN_S, WRITE_COST_MIN_S),  # never below the floor
        (300e-6, WRITE_COST_MIN_S, 300e-6),  # a slow write raises it at once
        (10e-3, WRITE_COST_MIN_S, WRITE_COST_MAX_S),  # within the ceiling
        (0.0, 400e-6, 400e-6 * 0.99),  # and it decays a write at a time
    ],
)
def test_the_assumed_write_cost_follows_the_largest_recent_write(
    took: float, before: float, expect: float
) -> None:
    sched: Scheduler[Job] = Scheduler(write_cost=before)
    sched.push(make_job(sched))
    send(sched, 1.0, took)
    assert sched.write_cost == pytest.approx(expect)


# -- queue order --------------------------------------------------------------------------


def test_priority_order_then_the_order_of_queuing() -> None:
    sched: Scheduler[Job] = Scheduler()
    queued = [
        ("normal-1", Priority.NORMAL),
        ("background", Priority.BACKGROUND),
        ("high", Priority.HIGH),
        ("normal-2", Priority.NORMAL),
        ("emergency", Priority.EMERGENCY),
    ]
    names = {}
    for name, priority in queued:
        job = make_job(sched, priority=priority)
        names[id(job)] = name
        sched.push(job)
    order = []
    now = 0.0
    while len(sched):
        job = send(sched, now)
        order.append(names[id(job)])
        now = sched.next_tx
    assert order == ["emergency", "high", "normal-1", "normal-2", "background"]


def test_a_retry_goes_ahead_of_normal_traffic_but_not_of_an_emergency() -> None:
    sched: Scheduler[Job] = Scheduler()
    retried = make_job(sched, priority=Priority.BACKGROUND)
    normal = make_job(sched)
    emergency = make_job(sched, priority=Priority.EMERGENCY)
    sched.push(normal)
    sched.push(emergency)
    sched.requeue(retried)
    assert retried.priority == Priority.HIGH
    assert [send(sched, t) for t in (0.0, 1.0, 2.0)] == [emergency, retried, normal]
    # A retry never lowers a job's priority.
    sched.requeue(emergency)
    assert emergency.priority == Priority.EMERGENCY


@dataclass(slots=True, eq=False)
class _Droppable(Job):
    dropped: bool = False

    def gone(self) -> bool:
        return self.dropped


def test_jobs_nobody_awaits_are_dropped_unsent() -> None:
    sched: Scheduler[Job] = Scheduler()
    raw = status().encode()
    jobs = [
        _Droppable(cmd=status(), raw=raw, priority=2, seq=sched.next_seq(), timeout=0.0, key="la:1")
        for _ in range(3)
    ]
    for job in jobs:
        sched.push(job)
    jobs[0].dropped = jobs[1].dropped = True
    assert sched.poll(0.0) is jobs[2]
    assert sched.poll(1.0) is None and len(sched) == 0


@pytest.mark.parametrize(
    ("priority", "reserved", "precise"),
    [
        (Priority.NORMAL, False, True),
        (Priority.EMERGENCY, False, True),
        (Priority.BACKGROUND, False, False),  # a late poll breaks nothing: no spinning
        (Priority.BACKGROUND, True, True),  # a tick's frame is worth it
    ],
)
def test_which_waits_are_worth_a_precise_timer(
    priority: Priority, reserved: bool, precise: bool
) -> None:
    sched: Scheduler[Job] = Scheduler(next_tx=1.0)
    sched.push(make_job(sched, priority=priority, reserved=reserved))
    assert sched.poll(0.5) == Wait(1.0, precise)


# -- late guards ------------------------------------------------------------------------


def test_a_late_guard_holds_only_its_own_device() -> None:
    sched: Scheduler[Job] = Scheduler()
    sched.guard("la:1", 5.0)
    sched.push(make_job(sched, status(2)))
    assert send(sched, 4.0).key == "la:2"  # another device is not held
    sched.push(make_job(sched, status(1)))
    assert sched.poll(4.5) == Wait(5.0, True)  # past the spacing, still guarded
    assert send(sched, 5.0).key == "la:1"


def test_a_guarded_retry_does_not_hold_the_jobs_queued_behind_it() -> None:
    # The retry of a timed-out poll goes ahead of normal traffic (HIGH, queued first),
    # then waits out its device's guard: other devices' requests go meanwhile.
    sched: Scheduler[Job] = Scheduler()
    sched.guard("la:1", 5.0)
    sched.requeue(make_job(sched, status(1)))
    other = make_job(sched, status(2))
    sched.push(other)
    assert send(sched, 4.0) is other
    assert sched.poll(4.5) == Wait(5.0, True)  # the retry alone is left, still guarded
    assert send(sched, 5.0).key == "la:1"


def test_a_stream_tick_is_not_held_behind_a_guarded_retry() -> None:
    sched: Scheduler[Job] = Scheduler()
    sched.guard("la:3", 5.0)
    sched.requeue(make_job(sched, status(3)))
    entries = [(i, 1000) for i in range(1, 16)]
    tick = make_job(
        sched, la.Broadcast(la.BroadcastMode.FOLLOW, entries), priority=Priority.HIGH, reserved=True
    )
    sched.push(tick)
    assert send(sched, 4.0) is tick


def test_requests_that_reach_one_device_keep_their_order() -> None:
    # Behind a guarded request to la:1: another to la:1, a request to la:2, and a
    # broadcast (it reaches la:1 too).  Only the request to la:2 overtakes it.
    sched: Scheduler[Job] = Scheduler()
    sched.guard("la:1", 5.0)
    first = make_job(sched, status(1))
    again = make_job(sched, la.Control(1, la.ControlAction.PAUSE))
    other = make_job(sched, status(2))
    broadcast = make_job(sched, la.Broadcast(la.BroadcastMode.FOLLOW, [(1, 1000), (2, 1000)]))
    for job in (first, again, other, broadcast):
        sched.push(job)
    assert send(sched, 4.0) is other
    assert sched.poll(4.5) == Wait(5.0, True)
    assert [send(sched, t) for t in (5.0, 6.0, 7.0)] == [first, again, broadcast]


def test_a_held_broadcast_holds_every_actuator_behind_it() -> None:
    sched: Scheduler[Job] = Scheduler()
    sched.reservation_sources.append(windows((1.0, 1.001)))
    broadcast = make_job(sched, la.Broadcast(la.BroadcastMode.POSITION, [(1, 1000)]), timeout=HOLD)
    pause = make_job(sched, la.Control(7, la.ControlAction.PAUSE))
    sched.push(broadcast)
    sched.push(pause)
    assert sched.poll(0.9995) == Wait(1.001, True)  # the pause does not overtake it
    assert [send(sched, t) for t in (1.001, 1.002)] == [broadcast, pause]


def test_a_job_held_by_the_spacing_holds_all_and_the_earliest_wait_is_given() -> None:
    sched: Scheduler[Job] = Scheduler(next_tx=2.0)
    sched.guard("la:1", 5.0)
    sched.push(make_job(sched, status(1)))
    sched.push(make_job(sched, status(2), priority=Priority.BACKGROUND))
    sched.push(make_job(sched, status(3), priority=Priority.BACKGROUND))
    # la:1 waits for its guard; la:2 for the spacing, and la:3 cannot start sooner.
    assert sched.poll(1.0) == Wait(2.0, False)
    assert len(sched) == 3  # everything looked at is put back
    assert send(sched, 2.0).key == "la:2"


def test_the_later_of_spacing_and_guard_wins() -> None:
    sched: Scheduler[Job] = Scheduler(next_tx=7.0)
    sched.guard("la:1", 5.0)
    sched.push(make_job(sched, status(1)))
    assert sched.poll(4.0) == Wait(7.0, True)


# -- reservations -------------------------------------------------------------------------


def windows(*spans: tuple[float, float]) -> ReservationSource:
    """A source of fixed reserved windows."""

    def source(now: float) -> tuple[float, float] | None:
        return next(((b, e) for b, e in spans if e > now), None)

    return source


HOLD = 10e-3  # the job's timeout in these tests: it may hold the bus 10 ms
#: What a status query holds at 115200 baud when its device answers in time (write,
#: reply, turnaround): about 3.4 ms; the gaps of 4 ms below hold it, those of 0.5 ms not.


@pytest.mark.parametrize(
    ("now", "spans", "priority", "reserved", "expect"),
    [
        # done well before the window: goes now
        (0.0, [(1.0, 1.001)], Priority.NORMAL, False, None),
        # would still hold the bus when the window begins: waits for its end
        (0.995, [(1.0, 1.001)], Priority.NORMAL, False, 1.001),
        # inside the window: waits for its end
        (1.0005, [(1.0, 1.001)], Priority.NORMAL, False, 1.001),
        # after the window: goes now
        (1.002, [(1.0, 1.001)], Priority.NORMAL, False, None),
        # the window's own frame is not held by it
        (1.0005, [(1.0, 1.001)], Priority.NORMAL, True, None),
        # nor is an emergency
        (1.0005, [(1.0, 1.001)], Priority.EMERGENCY, False, None),
        (0.995, [(1.0, 1.001)], Priority.EMERGENCY, False, None),
        # windows so close that no gap fits the job, even answered in time: it goes now
        # rather than never
        (0.995, [(1.0, 1.001), (1.0015, 1.002), (1.0025, 1.003)], Priority.NORMAL, False, None),
        # no gap fits its whole budget, but one fits it answered in time (3.4 ms): it
        # is not started where even that would run into the window ...
        (0.9995, [(1.0, 1.001), (1.005, 1.006), (1.01, 1.011)], Priority.NORMAL, False, 1.001),
        # ... and goes where that fits
        (0.99, [(1.0, 1.001), (1.005, 1.006), (1.01, 1.011)], Priority.NORMAL, False, None),
        # a gap that fits it: it waits for that gap
        (0.995, [(1.0, 1.001), (1.5, 1.501)], Priority.NORMAL, False, 1.001),
    ],
)
def test_reservations_hold_frames_that_are_not_theirs(
    now: float,
    spans: list[tuple[float, float]],
    priority: Priority,
    reserved: bool,
    expect: float | None,
) -> None:
    sched: Scheduler[Job] = Scheduler()
    sched.reservation_sources.append(windows(*spans))
    sched.push(make_job(sched, priority=priority, reserved=reserved, timeout=HOLD))
    decision = sched.poll(now)
    if expect is None:
        assert isinstance(decision, Job)
    else:
        assert decision == Wait(expect, True)


def test_a_frame_without_reply_holds_only_its_spacing_before_a_window() -> None:
    # 1 ms spacing + write cost: fits 1.2 ms before the window, not 0.5 ms before it.
    no_reply = la.Control(255, la.ControlAction.PAUSE)
    assert not no_reply.expects_reply
    for now, sent in ((0.9988, True), (0.9995, False)):
        sched: Scheduler[Job] = Scheduler()
        sched.reservation_sources.append(windows((1.0, 1.001)))
        sched.push(make_job(sched, no_reply, timeout=HOLD))
        assert isinstance(sched.poll(now), Job) is sent


def test_a_held_frame_goes_in_the_window_it_was_held_for_ends() -> None:
    sched: Scheduler[Job] = Scheduler()
    sched.reservation_sources.append(windows((1.0, 1.001), (1.5, 1.501)))
    user = make_job(sched, timeout=HOLD)
    sched.push(user)
    assert sched.poll(0.995) == Wait(1.001, True)
    tick = make_job(sched, priority=Priority.HIGH, reserved=True)  # as streams send them
    sched.push(tick)
    assert send(sched, 1.0) is tick  # the tick's frame goes at its time
    assert sched.poll(1.0) == Wait(1.001, True)
    assert send(sched, 1.001) is user
