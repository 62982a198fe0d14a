"""The bus's guarantees, checked on a fake clock, so they hold however slow the host is.

* Spacing: the next write starts >= ``min_spacing`` after the previous write RETURNED, on
  every path (requests, retries, polls, stream ticks, broadcasts, safe stops), even when
  writes take hundreds of microseconds (a preempted process).
* Streams never starve: while three loops of user requests keep the bus busy, a
  ``poll_status=True`` stream still sends a tick every period; polls that find no slot
  are skipped and counted, never holding a tick.
* Stop means stop: after a stream's safe action begins, nothing more of that stream is
  written, with the bus left open and in use afterwards.
* A late guard holds its device only: a retry waiting out its guard holds neither the
  stream's ticks nor other devices' requests, nor the other actuators' safe stops.

The clock (tests/fakeclock.py) only moves when the event loop is idle, so these are
behaviour tests: the same outcome on a loaded CI machine as on an idle one.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools

import pytest

from motorbus.bus.bus import Bus
from motorbus.bus.events import QuadDone
from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError, MotorbusError, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import Family
from motorbus.sim.bus import LogRecord, Pacing
from motorbus.streams import Streamer
from motorbus.transport.memory import memory_pair
from tests.fakeclock import AutojumpTimer, TimedTransport, preempted_writes, rig
from tests.helpers import PACINGS

MIN_SPACING_S = 1e-3
PERIOD_S = 0.01


def gaps_from_completed_write(wire: TimedTransport) -> list[float]:
    """Start of each write minus the moment the previous write returned."""
    return [b.before - a.after for a, b in itertools.pairwise(wire.writes)]


async def request_loop(actuator: InspireLA, stop: asyncio.Event, done: list[int]) -> None:
    while not stop.is_set():
        with contextlib.suppress(MotorbusError):
            await actuator.status()
        done[0] += 1


async def run_for(timer: AutojumpTimer, seconds: float) -> None:
    await timer.sleep_until(timer.now() + seconds)


# -- spacing -----------------------------------------------------------------------------


@pytest.mark.parametrize("pacing", PACINGS)
@pytest.mark.parametrize("seed", [1, 2, 3])
async def test_spacing_counts_from_the_completed_write_on_every_path(
    seed: int, pacing: Pacing
) -> None:
    """Ticks, polls, user requests, retries and safe stops; writes that take up to 400 us."""
    async with rig(write_time=preempted_writes(seed), pacing=pacing) as r:
        actuators = [InspireLA(r.bus, i) for i in range(1, 16)]
        stop = asyncio.Event()
        counts = [0]
        loops = [asyncio.create_task(request_loop(actuators[i], stop, counts)) for i in range(3)]
        # A request to an absent ID: timeouts and a retry in the mix.
        missing = asyncio.create_task(r.bus.request(la.Control(99, la.ControlAction.QUERY_STATUS)))
        streamer = Streamer(r.bus)
        stream = streamer.follow(
            actuators,
            lambda t, s: [1000] * 15,
            period=PERIOD_S,
            poll_status=True,
            safe_action="pause",
        )
        await run_for(r.timer, 0.5)
        await stream.stop(safe=True)
        stop.set()
        await asyncio.gather(*loops)
        with pytest.raises(ReplyTimeoutError):
            await missing
        await streamer.close()
        assert len(r.wire.writes) > 250
        kinds = {w.data[4] for w in r.wire.writes}  # CMD byte: 0x04 control, 0xF3 ...
        assert {0x04, 0xF3} <= kinds
        gaps = gaps_from_completed_write(r.wire)
        assert min(gaps) >= MIN_SPACING_S - 1e-9, min(gaps)
        assert r.bus.stats.retries >= 1


async def test_spacing_holds_for_back_to_back_requests_with_slow_writes() -> None:
    async with rig(range(1, 4), write_time=lambda: 300e-6) as r:
        for k in range(50):
            await r.bus.request(la.Control(1 + k % 3, la.ControlAction.QUERY_STATUS))
        gaps = gaps_from_completed_write(r.wire)
        assert len(gaps) == 49
        assert min(gaps) >= MIN_SPACING_S - 1e-9


# -- streams never starve ----------------------------------------------------------------


@pytest.mark.parametrize("pacing", PACINGS)
async def test_polling_stream_keeps_its_ticks_while_three_request_loops_run(
    pacing: Pacing,
) -> None:
    async with rig(pacing=pacing) as r:
        actuators = [InspireLA(r.bus, i) for i in range(1, 16)]
        stop = asyncio.Event()
        counts = [0]
        loops = [asyncio.create_task(request_loop(actuators[i], stop, counts)) for i in range(3)]
        streamer = Streamer(r.bus)
        seconds = 2.0
        ticks = round(seconds / PERIOD_S)
        stream = streamer.follow(
            actuators,
            [[1000 + k % 100] * 15 for k in range(ticks)],
            period=PERIOD_S,
            poll_status=True,
        )
        await stream.wait()
        stop.set()
        await asyncio.gather(*loops)
        await streamer.close()
        stats = stream.stats
        # (A skip past the end still sends the last row, a tick later.)
        assert stats.ticks + stats.skipped in (ticks, ticks + 1)
        assert stats.ticks >= 0.99 * ticks, stats.summary()
        assert counts[0] > 100  # the user loops were served too
        # Polls that found no free slot are counted, not silent.
        assert stats.polls + stats.polls_skipped > 0
        # The ticks stayed on their grid: broadcasts one period apart.
        sent = [w.before for w in r.wire.writes if w.data[4] == 0xF3]
        assert len(sent) == stats.ticks
        assert all(abs(b - a - PERIOD_S) < 1.5e-3 for a, b in itertools.pairwise(sent))


@pytest.mark.parametrize("pacing", PACINGS)
async def test_stream_ticks_are_not_held_behind_a_retry_waiting_out_its_late_guard(
    pacing: Pacing,
) -> None:
    """A device that does not answer: each request to it times out, and its retry waits
    out the device's 20 ms late guard at the head of the queue.  The stream's ticks,
    queued behind it, still leave on their deadlines, and the other devices' requests
    go on meanwhile."""
    async with rig(pacing=pacing) as r:
        actuators = [InspireLA(r.bus, i) for i in range(1, 16)]
        stop = asyncio.Event()
        absent, present = [0], [0]
        loops = [
            asyncio.create_task(request_loop(InspireLA(r.bus, 99), stop, absent)),
            asyncio.create_task(request_loop(actuators[0], stop, present)),
        ]
        streamer = Streamer(r.bus)
        ticks = 50
        stream = streamer.follow(
            actuators, [[1000 + k] * 15 for k in range(ticks)], period=PERIOD_S
        )
        await stream.wait()
        stop.set()
        await asyncio.gather(*loops)
        await streamer.close()
        stats = r.bus.stats
        assert stats.device("la:99").retries >= 5, stats.device("la:99")
        assert stream.stats.ticks == ticks, stream.stats.summary()
        assert stream.stats.late == 0 and stream.stats.slipped == 0, stream.stats.summary()
        sent = [w.before for w in r.wire.writes if w.data[4] == 0xF3]
        assert len(sent) == ticks
        assert all(abs(b - a - PERIOD_S) < 1.5e-3 for a, b in itertools.pairwise(sent))
        # la:1 was asked many times while la:99's retries waited out their guards.
        assert present[0] > 5 * absent[0]


# -- stop means stop ---------------------------------------------------------------------


def follow_frames_after_first_pause(records: list[LogRecord], ids: set[int]) -> list[str]:
    """Hex of every follow target for ``ids`` the devices received after the first pause."""
    frames = [bytes.fromhex(str(rec["hex"])) for rec in records if rec["dir"] == "rx"]
    pause = la.ControlAction.PAUSE.value
    first = next(
        (
            i
            for i, f in enumerate(frames)
            if f[4] == la.CMD_CONTROL and f[3] in ids and f[6] == pause
        ),
        None,
    )
    assert first is not None, "no pause was sent"
    after = []
    for f in frames[first:]:
        broadcast = f[4] == 0xF3 and any(f[i] in ids for i in range(5, len(f) - 1, 3))
        if broadcast or (f[4] in (0x19, 0x20) and f[3] in ids):
            after.append(f.hex(" "))
    return after


@pytest.mark.parametrize("pacing", PACINGS)
@pytest.mark.parametrize("offset_ms", [0.0, 0.3, 1.0, 2.5, 5.0, 7.5, 9.0, 9.7])
@pytest.mark.parametrize("how", ["stop", "exception"])
async def test_nothing_of_a_stream_is_sent_after_its_safe_stop(
    offset_ms: float, how: str, pacing: Pacing
) -> None:
    async with rig(pacing=pacing) as r:
        actuators = [InspireLA(r.bus, i) for i in range(1, 16)]
        streamer = Streamer(r.bus)
        other = [asyncio.create_task(actuators[0].status())]

        async def targets(t: float, statuses: object) -> list[int]:
            await asyncio.sleep(0)  # an async source: the tick is built across loop turns
            return [900 + int(t * 100) % 200] * 15

        stream = streamer.follow(
            actuators, targets, period=PERIOD_S, poll_status=True, safe_action="pause"
        )
        await run_for(r.timer, 0.1 + offset_ms / 1e3)
        if how == "stop":
            await stream.stop(safe=True)
        else:
            with contextlib.suppress(RuntimeError):
                async with stream:
                    raise RuntimeError("user code failed")
        # The bus stays open and in use: whatever follows is inspected.
        for i in range(1, 16):
            await actuators[i - 1].status()
        await run_for(r.timer, 0.05)
        await asyncio.gather(*other)
        await streamer.close()
        assert follow_frames_after_first_pause(r.log, set(range(1, 16))) == []
        paused = {
            bytes.fromhex(str(rec["hex"]))[3]
            for rec in r.log
            if rec["dir"] == "rx"
            and bytes.fromhex(str(rec["hex"]))[4] == la.CMD_CONTROL
            and bytes.fromhex(str(rec["hex"]))[6] == la.ControlAction.PAUSE.value
        }
        assert paused == set(range(1, 16))


def pause_writes(wire: TimedTransport) -> list[tuple[int, float]]:
    """(ID, when the write began) of every LA pause written, in order."""
    return [
        (w.data[3], w.before)
        for w in wire.writes
        if w.data[4] == la.CMD_CONTROL and w.data[6] == la.ControlAction.PAUSE.value
    ]


def assert_la1_held_up_no_other_pause(wire: TimedTransport) -> dict[int, float]:
    """Actuators 1-15 each got a pause, la:1's (unanswered) was retried, and every
    other's first pause was written before that retry.  Returns each first pause."""
    pauses = pause_writes(wire)
    first: dict[int, float] = {}
    for ident, at in pauses:
        first.setdefault(ident, at)
    assert set(first) == set(range(1, 16)), pauses
    attempts_to_1 = [at for ident, at in pauses if ident == 1]
    assert len(attempts_to_1) >= 2, pauses  # la:1's pause was retried
    assert max(first[i] for i in range(2, 16)) < attempts_to_1[1], pauses
    return first


@pytest.mark.parametrize("path", ["stream-stop", "bus-close"])
async def test_a_silent_actuator_does_not_delay_the_others_safe_stop(path: str) -> None:
    """la:1 does not answer: its pause times out and its retries wait out its late guard
    (20 ms each).  The other 14 actuators' pauses go meanwhile, each right after the
    one before, not behind la:1's retries.  Two paths: a stream's own safe action, and
    the bus's leases ended as it closes (a stream that held its targets)."""
    async with rig(range(2, 16)) as r:
        actuators = [InspireLA(r.bus, i) for i in range(1, 16)]
        streamer = Streamer(r.bus)
        stream = streamer.follow(
            actuators,
            [[1000 + k] * 15 for k in range(100)],
            period=PERIOD_S,
            safe_action="pause" if path == "stream-stop" else "hold",
        )
        await run_for(r.timer, 0.05)
        await stream.stop()
        await streamer.close()
        if path == "bus-close":
            assert pause_writes(r.wire) == []  # held: the pauses are the bus's, at close
            await r.bus.close()
        first = assert_la1_held_up_no_other_pause(r.wire)
        assert max(first.values()) - first[1] < r.bus.config.late_guard, first


@pytest.mark.parametrize("how", ["two-streams-one-streamer", "two-streamers-bus-close"])
async def test_a_silent_actuator_of_one_stream_does_not_delay_another_streams_stop(
    how: str,
) -> None:
    """Two streams stopped together: by their streamer's close, or (one streamer each)
    by the bus's close hooks.  la:1, in the first, does not answer; the second
    stream's pauses do not wait for la:1's retries."""
    async with rig(range(2, 16)) as r:
        shared = Streamer(r.bus) if how == "two-streams-one-streamer" else None
        for ids in (range(1, 8), range(8, 16)):
            owner = shared if shared is not None else Streamer(r.bus)
            owner.follow(
                [InspireLA(r.bus, i) for i in ids],
                [[1000] * len(ids)] * 100,
                period=PERIOD_S,
                safe_action="pause",
            )
        await run_for(r.timer, 0.05)
        if shared is not None:
            await shared.close()
        else:
            await r.bus.close()
        assert_la1_held_up_no_other_pause(r.wire)


# -- one budget per bus ------------------------------------------------------------------


async def test_two_streamers_on_one_bus_share_its_actuators_and_its_budget() -> None:
    async with rig() as r:
        actuators = [InspireLA(r.bus, i) for i in range(1, 16)]
        first, second = Streamer(r.bus), Streamer(r.bus)
        stream = first.follow(actuators[0], lambda t, s: 500, period=PERIOD_S)
        # The same actuator from another streamer of the same bus: refused.
        with pytest.raises(LocalProtocolError, match="already streamed"):
            second.follow(actuators[0], lambda t, s: 1500, period=PERIOD_S)
        # Feedback round trips: one streamer allows at most what the bus allows, and a
        # second streamer cannot add more on top of the first's.
        fits = first.follow(actuators[1:7], lambda t, s: [1000] * 6, period=PERIOD_S, feedback=True)
        with pytest.raises(LocalProtocolError, match="would need"):
            second.follow(actuators[7:9], lambda t, s: [1000] * 2, period=PERIOD_S, feedback=True)
        await stream.stop()
        await fits.stop()
        await first.close()
        await second.close()


# -- deadlines decided by time, not by callback order -------------------------------------


STATUS_REPLY_1 = bytes.fromhex("AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 00 01 08 07 0A 07 94")


@pytest.mark.parametrize(
    "order",
    ["data-callback-first", "deadline-first", "reply-after-the-decision"],
)
async def test_a_reply_already_in_when_a_late_loop_decides_the_deadline_is_taken(
    order: str,
) -> None:
    """After a host stall both callbacks are due at once: the outcome must not depend on
    which the loop runs first (it once did).  The deadline callback reads what the OS
    holds before it decides, so a reply that was in when the bus looked is taken either
    way, and counted as read past its deadline; only one that comes after the decision
    is a timeout (and its late reply)."""
    loop = asyncio.get_running_loop()
    timer = AutojumpTimer(loop)
    timer.start()
    host, peer = memory_pair(baudrate=921600)
    peer.set_receiver(lambda data: None)
    try:
        async with Bus(host, families={Family.LA}, timer=timer, retries=0) as bus:
            request = asyncio.ensure_future(
                bus.request(la.Control(1, la.ControlAction.QUERY_STATUS))
            )
            await asyncio.sleep(0)
            assert bus.stats.requests == 1
            deadline = bus._core.matcher.pending.deadline  # type: ignore[union-attr]
            # The host stalls for 5 ms past the deadline; then both become due.
            timer.t = deadline + 5e-3
            if order == "data-callback-first":
                peer.send(STATUS_REPLY_1)  # delivered by call_soon, before the timer wakes
            elif order == "deadline-first":
                peer.send(STATUS_REPLY_1)  # in (queued), but the deadline callback runs first
                timer._wake()
            else:
                timer._wake()  # decided with nothing in: a timeout
                peer.send(STATUS_REPLY_1)
            if order == "reply-after-the-decision":
                with pytest.raises(ReplyTimeoutError):
                    await request
            else:
                status = await request
                assert status.position == 990  # type: ignore[attr-defined]
            for _ in range(5):
                await asyncio.sleep(0)
            stats = bus.stats
            if order == "reply-after-the-decision":
                assert (stats.timeouts, stats.late_replies, stats.replies) == (1, 1, 0)
                assert stats.timeouts_in_host_stall == 1
            else:
                assert (stats.timeouts, stats.late_replies, stats.replies) == (0, 0, 1)
                assert stats.replies_past_deadline == 1
    finally:
        await timer.stop()


async def test_a_reply_before_the_deadline_is_not_counted_as_read_past_it() -> None:
    """The count of replies read past their deadline is the host's lateness, not every
    reply's: a prompt loop reads a prompt reply before its deadline."""
    host, peer = memory_pair(baudrate=921600)
    peer.set_receiver(lambda data: peer.send(STATUS_REPLY_1))
    async with Bus(host, families={Family.LA}, retries=0) as bus:
        await bus.request(la.Control(1, la.ControlAction.QUERY_STATUS))
        assert bus.stats.replies == 1 and bus.stats.replies_past_deadline == 0


# -- a "done" reply in the same read as its ack ---------------------------------------------


async def test_a_done_reply_that_arrives_in_the_same_read_as_its_ack_is_the_done_event() -> None:
    """A quad stepper run answers twice: the ack, then "done" when the motor stops.  A
    short run on a late loop (or a USB adapter's latency timer) hands both to one read.
    The reassembler judges a read with the reply shapes expected when it came, and the
    done shape was only expected once the ack was taken: the done reply was discarded as
    "unexpected reply shape" and the run timed out (seen in CI, under load, over a pty)."""
    host, peer = memory_pair(baudrate=9600)
    ack, done = bytes.fromhex("FF AA 00 09 00 00"), bytes.fromhex("FF AA 00 09 01 00")

    received: list[bytes] = []

    def device(data: bytes) -> None:
        received.append(data)
        if data == q.Run(1).encode():
            peer.send(ack + done)  # one read: the run was that short

    peer.set_receiver(device)
    async with Bus(host, families={Family.QUAD_STEPPER}, retries=0) as bus:
        with bus.events.subscribe(QuadDone) as sub:
            await bus.request(q.Run(1))
            event = await sub.next(timeout=5)
        assert (event.kind, event.raw) == ("run", done)
        assert bus.stats.events == 1 and bus.stats.unexpected_frames == 0
        assert bus.stats.reassembler.discarded_bytes == 0
    # What the device got last: the run, not the stop a lost done reply used to send.
    assert received[-1] == q.Run(1).encode()
