"""The bus's reply matching on the pure core (``motorbus.bus.matching``): plain numbers
and frames, no event loop, no clock.  The same guarantees are checked over ptys and
simulators in tests/bus/test_bus_guarantees.py."""

from __future__ import annotations

import pytest

from motorbus.bus.matching import (
    LATE_WINDOW_S,
    MAX_DONE_WATCHES,
    WIRE_FLOOR_FACTOR,
    DoneWatch,
    Matcher,
    TimedOut,
    Verdict,
)
from motorbus.bus.occupancy import BusTiming, command_occupancy
from motorbus.bus.schedule import Job
from motorbus.protocol import la
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import LA_REPLY_HEADER, Command, Family, FrameShape
from motorbus.protocol.families import DEFAULT_TURNAROUND
from motorbus.protocol.la.wire import build_frame

BAUD = 115200
TIMING = BusTiming(BAUD, 1e-3, 2e-3, DEFAULT_TURNAROUND)
#: The LA status reply of ID 1 (tests/bus/test_bus_guarantees.py), its body reused for others.
_STATUS_1 = bytes.fromhex("AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 00 01 08 07 0A 07 94")


def status(ident: int = 1) -> Command[object]:
    return la.Control(ident, la.ControlAction.QUERY_STATUS)


def status_reply(ident: int = 1) -> bytes:
    return build_frame(LA_REPLY_HEADER, bytes((ident,)) + _STATUS_1[4:-1])


def quad(*body: int) -> bytes:
    """A quad stepper reply ``FF AA b2..b5``."""
    return bytes((0xFF, 0xAA, *body))


def make_job(cmd: Command[object], seq: int = 0) -> Job:
    raw = cmd.encode()
    occ = command_occupancy(TIMING, cmd, len(raw))
    return Job(cmd=cmd, raw=raw, priority=2, seq=seq, timeout=occ.budget, key=cmd.device_key)


def sent(
    matcher: Matcher[Job], cmd: Command[object], *, mark: int, at: float, took: float = 0.0
) -> Job:
    """``cmd`` written at ``at`` (returning ``took`` later) with ``mark`` bytes received."""
    job = make_job(cmd)
    job.rx_mark = mark
    matcher.sent(job)
    matcher.written(job, at, at + took, BAUD)
    return job


def test_the_frames_are_what_the_commands_say() -> None:
    # The fixtures themselves, so that a wrong frame cannot make a test pass.
    assert status(1).matches_reply(status_reply(1)) and status_reply(1) == _STATUS_1
    assert status(2).matches_reply(status_reply(2)) and not status(1).matches_reply(status_reply(2))
    assert q.Run(2).matches_reply(quad(0x02, 0x09, 0x00, 0x00))
    assert q.Run(2).matches_done(quad(0x02, 0x09, 0x01, 0x00))


# -- causality ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("start", "verdict"),
    [
        (0, Verdict.UNEXPECTED),  # buffered long before the write
        (99, Verdict.UNEXPECTED),  # its first byte was already in before the write
        (100, Verdict.ACCEPTED),  # the first byte after the write
        (5000, Verdict.ACCEPTED),
    ],
)
def test_a_frame_that_began_before_the_write_is_never_the_reply(
    start: int, verdict: Verdict
) -> None:
    matcher: Matcher[Job] = Matcher({Family.LA})
    job = sent(matcher, status(1), mark=100, at=1.0)
    assert matcher.classify(status_reply(1), start, 1.0 + 1e-6) == (verdict, None)
    assert matcher.pending is job  # classifying decides, the shell releases


def test_however_soon_a_caused_frame_arrives_it_is_accepted_without_wire_floor() -> None:
    matcher: Matcher[Job] = Matcher({Family.LA})
    sent(matcher, status(1), mark=0, at=1.0)
    assert matcher.classify(status_reply(1), 0, 1.0)[0] is Verdict.ACCEPTED


def test_another_devices_reply_is_not_the_pending_ones() -> None:
    matcher: Matcher[Job] = Matcher({Family.LA})
    sent(matcher, status(1), mark=0, at=1.0)
    assert matcher.classify(status_reply(2), 0, 1.001)[0] is Verdict.UNEXPECTED


# -- deadlines: never early, decided by the shell, after it read what the OS holds -------


@pytest.mark.parametrize("took", [0.0, 200e-6, 5e-3])
def test_the_deadline_counts_from_the_completed_write(took: float) -> None:
    matcher: Matcher[Job] = Matcher({Family.LA})
    job = sent(matcher, status(1), mark=0, at=1.0, took=took)
    budget = command_occupancy(TIMING, status(1)).budget
    assert job.deadline == 1.0 + took + budget  # never counted from the write's start


def test_a_reply_read_past_the_deadline_before_it_is_decided_is_accepted() -> None:
    """The host stalled: data and deadline due at once.  The reply was in when the bus
    looked, so it is the pending request's, whichever callback the loop runs first."""
    matcher: Matcher[Job] = Matcher({Family.LA})
    job = sent(matcher, status(1), mark=0, at=1.0)
    seen = job.deadline + 5e-3
    assert matcher.classify(status_reply(1), 0, seen) == (Verdict.ACCEPTED, None)


def test_a_reply_after_the_deadline_was_decided_is_the_late_reply_of_its_request() -> None:
    matcher: Matcher[Job] = Matcher({Family.LA})
    job = sent(matcher, status(1), mark=0, at=1.0)
    decided = job.deadline + 5e-3
    # The shell found nothing in: it times the request out, then asks again.
    matcher.timed_out(job, decided)
    assert matcher.release(job) and matcher.pending is None
    verdict, about = matcher.classify(status_reply(1), 0, decided + 1e-3)
    assert verdict is Verdict.LATE
    assert isinstance(about, TimedOut)
    assert (about.key, about.deadline, about.until) == (
        "la:1",
        job.deadline,
        decided + LATE_WINDOW_S,
    )


@pytest.mark.parametrize(
    ("seen_after_write", "verdict"),
    [(0.0, Verdict.EARLY), (2e-3, Verdict.EARLY), (3e-3, Verdict.ACCEPTED)],
)
def test_wire_floor_refuses_a_reply_sooner_than_the_wire(
    seen_after_write: float, verdict: Verdict
) -> None:
    matcher: Matcher[Job] = Matcher({Family.LA}, wire_floor=True)
    job = sent(matcher, status(1), mark=0, at=1.0)
    wire = (len(job.raw) + len(status_reply(1))) * 10 / BAUD  # ~2.5 ms at 115200
    assert job.earliest == pytest.approx(1.0 + WIRE_FLOOR_FACTOR * wire)
    assert matcher.classify(status_reply(1), 0, 1.0 + seen_after_write)[0] is verdict


# -- late replies are never given to a later request ---------------------------------------


def test_a_late_reply_is_not_given_to_the_next_request_to_that_device() -> None:
    matcher: Matcher[Job] = Matcher({Family.LA})
    first = sent(matcher, status(1), mark=0, at=1.0)
    matcher.timed_out(first, first.deadline)
    matcher.release(first)
    # The late guard held the next request; the same question is asked again after it,
    # with 40 more bytes received in between.  The first's late answer began before it.
    second = sent(matcher, status(1), mark=40, at=first.deadline + 20e-3)
    late = status_reply(1)
    verdict, about = matcher.classify(late, 20, second.tx_time + 1e-4)
    assert verdict is Verdict.LATE and isinstance(about, TimedOut)
    assert matcher.pending is second
    # Its own reply (bytes after its write) is still its reply.
    assert matcher.classify(late, 40 + len(late), second.tx_time + 2e-4)[0] is Verdict.ACCEPTED


def test_the_newest_timed_out_request_is_credited_and_old_ones_are_forgotten() -> None:
    matcher: Matcher[Job] = Matcher({Family.LA})
    deadlines = []
    for at in (1.0, 1.5):  # the same question to la:1 timed out twice
        job = sent(matcher, status(1), mark=0, at=at)
        matcher.timed_out(job, at + 0.01)
        matcher.release(job)
        deadlines.append(job.deadline)
    verdict, about = matcher.classify(status_reply(1), 0, 1.6)
    assert verdict is Verdict.LATE and isinstance(about, TimedOut)
    assert about.deadline == deadlines[1]
    # Past the first's window only the second is remembered; past both, nobody's.
    verdict, about = matcher.classify(status_reply(1), 0, 1.01 + LATE_WINDOW_S + 1e-3)
    assert verdict is Verdict.LATE and isinstance(about, TimedOut)
    assert [t.deadline for t in matcher.timeouts] == [deadlines[1]]
    assert matcher.classify(status_reply(1), 0, 1.51 + LATE_WINDOW_S + 1e-3)[0] is (
        Verdict.UNEXPECTED
    )
    assert not matcher.timeouts


# -- done-watches --------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("frame", "expect"),
    [
        (quad(0x02, 0x09, 0x01, 0x00), "run 2"),  # names its motor: that run
        (quad(0x00, 0x09, 0x01, 0x00), "run 1"),  # address 00 (any motor): the oldest run
        (quad(0x00, 0x0C, 0x03, 0x01), "led 3"),
        (quad(0x03, 0x09, 0x01, 0x00), None),  # motor 3 runs nothing watched
        (quad(0x02, 0x09, 0x00, 0x00), None),  # an ack, not a done
        (quad(0x00, 0x0C, 0x04, 0x01), None),  # LED 4 was not switched
    ],
)
def test_a_done_reply_goes_to_the_command_it_completes(frame: bytes, expect: str | None) -> None:
    matcher: Matcher[Job] = Matcher({Family.QUAD_STEPPER})
    for cmd in (q.Run(1), q.Run(2), q.SetLed(3, True)):
        assert cmd.done_shapes()
        assert not matcher.watch_done(cmd)
    verdict, about = matcher.classify(frame, 0, 1.0)
    if expect is None:
        assert (verdict, about) == (Verdict.UNEXPECTED, None)
        assert len(matcher.done_watches) == 3
        return
    assert verdict is Verdict.DONE and isinstance(about, DoneWatch)
    kind, number = expect.split()
    assert about.kind == kind
    assert about.cmd == (q.Run(int(number)) if kind == "run" else q.SetLed(int(number), True))
    assert about.led == (int(number) if kind == "led" else None)
    assert about not in matcher.done_watches and len(matcher.done_watches) == 2
    # A done reply completes its command once: the same frame again is nobody's.
    again = matcher.classify(frame, 6, 1.1)[0]
    assert again is (Verdict.DONE if frame[2] == 0 and kind == "run" else Verdict.UNEXPECTED)


def test_a_pending_request_does_not_take_a_done_reply_and_its_ack_is_not_a_done() -> None:
    matcher: Matcher[Job] = Matcher({Family.QUAD_STEPPER})
    matcher.watch_done(q.Run(1))
    sent(matcher, q.Run(1), mark=0, at=2.0)
    assert matcher.classify(quad(0x01, 0x09, 0x01, 0x00), 0, 2.001)[0] is Verdict.DONE
    assert matcher.classify(quad(0x01, 0x09, 0x00, 0x00), 6, 2.001)[0] is Verdict.ACCEPTED


def test_done_watches_are_bounded_and_the_oldest_forgotten() -> None:
    matcher: Matcher[Job] = Matcher({Family.QUAD_STEPPER})
    assert not matcher.watch_done(q.SetLed(1, True))
    for _ in range(MAX_DONE_WATCHES - 1):
        assert not matcher.watch_done(q.Run(1))
    assert matcher.watch_done(q.Run(1))  # one too many: the oldest (the LED) goes
    assert len(matcher.done_watches) == MAX_DONE_WATCHES
    assert matcher.classify(quad(0x00, 0x0C, 0x01, 0x01), 0, 1.0)[0] is Verdict.UNEXPECTED


# -- the shapes the reassembler may cut ---------------------------------------------------


def test_the_reassembler_is_told_exactly_what_is_awaited() -> None:
    told: list[tuple[FrameShape, ...]] = []
    matcher: Matcher[Job] = Matcher({Family.QUAD_STEPPER}, on_shapes=told.append)
    matcher.update_shapes(force=True)
    assert told == [()]
    run = sent(matcher, q.Run(1), mark=0, at=1.0)
    # The ack, and the done reply, which may come in the same read as the ack.
    assert told[-1] == tuple(dict.fromkeys(q.Run(1).reply_shapes() + q.Run(1).done_shapes()))
    matcher.release(run)
    assert told[-1] == ()
    matcher.watch_done(q.Run(1))
    assert told[-1] == q.Run(1).done_shapes()
    # A timed-out request's reply stays expected for its late window, then not.
    led = sent(matcher, q.SetLed(2, True), mark=0, at=1.0)
    matcher.timed_out(led, 1.01)
    matcher.release(led)
    assert told[-1] == q.Run(1).done_shapes() + q.SetLed(2, True).reply_shapes()
    calls = len(told)
    matcher.update_shapes()  # nothing changed: not told again
    assert len(told) == calls
    matcher.classify(quad(0x01, 0x09, 0x01, 0x00), 0, 1.02)  # the done came
    assert told[-1] == q.SetLed(2, True).reply_shapes()
    matcher.classify(quad(0x07, 0x07, 0x07, 0x07), 6, 1.01 + LATE_WINDOW_S + 1.0)
    assert told[-1] == ()


def test_a_bus_of_las_only_tells_the_reassembler_nothing() -> None:
    told: list[tuple[FrameShape, ...]] = []
    matcher: Matcher[Job] = Matcher({Family.LA}, on_shapes=told.append)
    matcher.update_shapes(force=True)
    sent(matcher, status(1), mark=0, at=1.0)
    assert told == []
