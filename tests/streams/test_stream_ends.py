"""How streams end, over a pty against the simulators: every end is a safe end, and a
gap (a lost port, a stalled host) is followed by a ramp from where the actuators are.

The simulator's own log of the frames it received is the witness: for each actuator,
what came last, and what came first after an outage.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import threading
import time
from collections.abc import AsyncIterator, Sequence
from contextlib import asynccontextmanager
from typing import Any

import pytest

from motorbus.bus.bus import Bus, BusState
from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError, StreamEnded
from motorbus.protocol import la
from motorbus.protocol.base import Family
from motorbus.sim.bus import LogRecord, Pacing
from motorbus.sim.faults import FaultConfig
from motorbus.sim.la import LAModel
from motorbus.sim.pty import PtySim
from motorbus.streaming.model import GAP_TICKS
from motorbus.streaming.targets import ramp_step
from motorbus.streams import Streamer, StreamGap
from motorbus.transport.serial import SerialTransport
from tests.bus.test_bus_faults import eventually
from tests.helpers import PACINGS, sim_bus

LA_BAUD = 921600
PERIOD_S = 0.01
#: Generous: tests assert behaviour, not speed (a loaded machine answers late).
PTY_HOST_MARGIN_S = 0.05
#: Hang guard for waiting on an event, not a timing claim.
BOUND_S = 5.0
PAUSE = ("control", la.ControlAction.PAUSE.value)
#: The ramp's step per tick at the default ``max_speed`` (500 units/s) and PERIOD_S.
STEP = 5.0


class FrameLog:
    """What the simulator received, per actuator: ``(t, "target", pos)``, ``(t, "control",
    sub)``, and ``(t, "link", what)`` for every actuator when the link changed."""

    def __init__(self, ids: Sequence[int]) -> None:
        self.ids = tuple(ids)
        self._lock = threading.Lock()
        self.events: dict[int, list[tuple[float, str, int | str]]] = {i: [] for i in ids}

    def __call__(self, record: LogRecord) -> None:  # called from the sim thread
        t = float(record["t"])  # type: ignore[arg-type]
        with self._lock:
            if record["dir"] == "link":
                for events in self.events.values():
                    events.append((t, "link", str(record["fault"])))
                return
            if record["dir"] != "rx" or record["fault"] is not None:
                return
            raw = bytes.fromhex(str(record["hex"]))
            ident, cmd = raw[3], raw[4]
            if cmd == la.CMD_BROADCAST_FOLLOW:
                body = raw[5:-1]
                for k in range(0, len(body), 3):
                    self._add(body[k], t, "target", body[k + 1] | body[k + 2] << 8)
            elif cmd in (la.CMD_FOLLOW, la.CMD_FOLLOW_NO_REPLY):
                self._add(ident, t, "target", raw[6] | raw[7] << 8)
            elif cmd == la.CMD_CONTROL and raw[6] != la.ControlAction.QUERY_STATUS:
                self._add(ident, t, "control", raw[6])

    def _add(self, ident: int, t: float, kind: str, value: int) -> None:
        if ident in self.events:
            self.events[ident].append((t, kind, value))

    def of(self, ident: int) -> list[tuple[str, int | str]]:
        with self._lock:
            return [(kind, value) for _, kind, value in self.events[ident]]


@asynccontextmanager
async def pty_bus(
    ids: Sequence[int], pacing: Pacing, faults: FaultConfig | None = None, **sim: Any
) -> AsyncIterator[tuple[Bus, FrameLog, PtySim]]:
    frames = FrameLog(ids)
    models = [LAModel(i) for i in ids]
    with PtySim(models, baud=LA_BAUD, log=frames, pacing=pacing, faults=faults, **sim) as ptysim:
        transport = SerialTransport(sim.get("link", ptysim.path), baudrate=LA_BAUD)
        bus = Bus(transport, name="pty", families={Family.LA}, host_margin=PTY_HOST_MARGIN_S)
        async with bus:
            yield bus, frames, ptysim
        assert ptysim.error is None


def ends_targets(ticks: int) -> Any:
    """A target function that returns None (the normal end) after ``ticks`` ticks."""

    def targets(t: float, statuses: object) -> list[int] | None:
        return None if t >= ticks * PERIOD_S - 1e-9 else [1000 + round(t * 1000)] * 3

    return targets


# -- every end is a safe end ----------------------------------------------------------------


@pytest.mark.parametrize("pacing", PACINGS)
async def test_a_stream_that_ends_normally_pauses_its_actuators(pacing: Pacing) -> None:
    """The issue's case: targets run out, ``stop(safe=True)``, the bus closes."""
    ids = (1, 2, 3)
    async with pty_bus(ids, pacing) as (bus, frames, _):
        streamer = Streamer(bus)
        actuators = [InspireLA(bus, i) for i in ids]
        stream = streamer.follow(actuators, ends_targets(10), period=PERIOD_S, safe_action="pause")
        await asyncio.wait_for(stream.wait(), BOUND_S)
        await stream.stop(safe=True)
    for i in ids:
        got = frames.of(i)
        assert ("target", 1000) in got, got
        assert got[-1] == PAUSE, f"la:{i} last received {got[-3:]}"
        assert got.count(PAUSE) == 1, got  # once, not again by stop() or the close


@pytest.mark.parametrize("pacing", PACINGS)
async def test_leaving_the_block_and_closing_the_bus_pause_too(pacing: Pacing) -> None:
    ids = (1, 2)
    async with pty_bus(ids, pacing) as (bus, frames, _):
        streamer = Streamer(bus)
        async with streamer.follow(
            [InspireLA(bus, i) for i in ids],
            lambda t, s: [700, 700],
            period=PERIOD_S,
            safe_action="pause",
        ):
            await eventually(lambda: ("target", 700) in frames.of(2), "targets to arrive")
        assert all(frames.of(i)[-1] == PAUSE for i in ids)
        endless = streamer.follow(
            [InspireLA(bus, i) for i in ids],
            lambda t, s: [900, 900],
            period=PERIOD_S,
            safe_action="pause",
        )
        await eventually(lambda: ("target", 900) in frames.of(2), "targets to arrive")
    assert endless.done and endless.error is None
    for i in ids:
        assert frames.of(i)[-1] == PAUSE, frames.of(i)[-3:]


@pytest.mark.parametrize("pacing", PACINGS)
async def test_stop_hold_ends_with_the_actuators_holding(pacing: Pacing) -> None:
    ids = (1,)
    async with pty_bus(ids, pacing) as (bus, frames, _):
        streamer = Streamer(bus)
        stream = streamer.follow(
            InspireLA(bus, 1), lambda t, s: 800, period=PERIOD_S, safe_action="estop"
        )
        await eventually(lambda: ("target", 800) in frames.of(1), "targets to arrive")
        await stream.stop(hold=True)
        await stream.stop(hold=True)  # idempotent
        with pytest.raises(LocalProtocolError, match="hold=True and safe=True"):
            await stream.stop(hold=True, safe=True)
    assert frames.of(1)[-1] == ("target", 800)
    assert all(kind == "target" for kind, _ in frames.of(1))


# -- after a gap, a ramp ---------------------------------------------------------------------


def test_ramp_step_moves_at_most_a_step_and_lets_go_on_arrival() -> None:
    ramp = {1: 500.0, 2: 1000.0}
    assert ramp_step(ramp, {1: 600, 2: 990, 3: 5}, 20.0) == {1: 520, 2: 990, 3: 5}
    assert ramp == {1: 520.0}  # la:2 was within a step: it follows from now on
    assert ramp_step(ramp, {1: 400}, 20.0) == {1: 500}
    assert ramp_step(ramp, {1: 505}, 20.0) == {1: 505} and ramp == {}


def sweep(t: float, statuses: object) -> dict[int, int]:
    """A 300 units/s sweep from 100, then back (the issue's trajectory)."""
    return {1: 100 + round(300 * t) % 1800, 2: 1900 - round(300 * t) % 1800}


@pytest.mark.parametrize("pacing", PACINGS)
async def test_after_an_outage_the_stream_ramps_from_the_read_positions(
    pacing: Pacing, tmp_path: Any
) -> None:
    ids = (1, 2)
    faults = FaultConfig(disconnect_after_s=0.5, reconnect_after_s=0.5, disconnect_count=1)
    link = tmp_path / "ttyLA"
    loop = asyncio.get_running_loop()
    handled: list[dict[str, Any]] = []
    loop.set_exception_handler(lambda _loop, context: handled.append(context))
    try:
        async with pty_bus(ids, pacing, faults, link=str(link)) as (bus, frames, _):
            streamer = Streamer(bus)
            stream = streamer.follow(
                [InspireLA(bus, i) for i in ids], sweep, period=PERIOD_S, safe_action="pause"
            )
            await bus.wait_state(BusState.LOST, timeout=BOUND_S)
            await bus.wait_state(BusState.OPEN, timeout=BOUND_S)

            def resumed() -> bool:
                for i in ids:
                    got = frames.of(i)
                    if ("link", "disconnect") not in got:
                        return False
                    cut = got.index(("link", "disconnect"))
                    if sum(kind == "target" for kind, _ in got[cut:]) < 8:
                        return False
                return True

            await eventually(resumed, "targets after the outage")
            step = STEP
            for i in ids:
                got = frames.of(i)
                cut = got.index(("link", "disconnect"))
                before = [v for kind, v in got[:cut] if kind == "target"]
                after = [v for kind, v in got[cut:] if kind == "target"]
                assert isinstance(before[-1], int) and isinstance(after[0], int)
                # The sweep moved ~300 units during the outage; the actuator did not.
                assert abs(after[0] - before[-1]) <= step + 10, (i, before[-3:], after[:3])
            # A loaded host may also have stalled 3 ticks (a "behind" gap): look for the
            # outage among the gaps.
            gaps = [await stream.gaps.next(timeout=BOUND_S), *stream.gaps.pending()]
            assert all(isinstance(g, StreamGap) for g in gaps)
            assert stream.stats.gaps == len(gaps)
            (gap,) = [g for g in gaps if g.cause == "outage"]
            assert (gap.action, gap.ids) == ("ramp", ids)
            assert gap.missed > 0
            assert stream.max_speed * PERIOD_S == STEP
            for i in ids:
                after = [v for kind, v in frames.of(i)[cut:] if kind == "target"]
                assert isinstance(after[0], int)
                assert abs(after[0] - gap.positions[i]) <= math.ceil(step), (i, gap, after[:3])
                steps = [abs(b - a) for a, b in itertools.pairwise(after)]
                assert max(steps[:5]) <= math.ceil(step) + 1, after[:6]
            assert stream.error is None and not stream.done
            await stream.stop()
            # Stopped after the reconnect, with the bus still open: the pause comes last.
            for i in ids:
                assert frames.of(i)[-1] == PAUSE, f"la:{i} last received {frames.of(i)[-3:]}"
    finally:
        loop.set_exception_handler(None)
    assert not [c for c in handled if "Fatal" in str(c.get("message"))], handled


#: A period at which only a host stalled 150 ms falls 3 ticks behind (a "behind" gap
#: would end an on_gap="stop" stream before the outage the test makes).
SLOW_S = 0.05


@pytest.mark.parametrize("pacing", PACINGS)
async def test_on_gap_stop_pauses_and_ends_the_stream_with_an_error(pacing: Pacing) -> None:
    models = [LAModel(1)]
    async with sim_bus(models, pacing=pacing) as (bus, sim):
        streamer = Streamer(bus)
        stream = streamer.follow(
            InspireLA(bus, 1), sweep_one, period=SLOW_S, safe_action="pause", on_gap="stop"
        )
        await eventually(lambda: len(models[0].received) >= 3, "targets to arrive")
        sim.peer.unplug()
        await bus.wait_state(BusState.LOST, timeout=BOUND_S)
        sent = len(models[0].received)
        sim.peer.plug()
        with pytest.raises(StreamEnded, match=r"gap \(outage"):
            await asyncio.wait_for(stream.wait(), BOUND_S)
        assert len(models[0].received) == sent  # no target after the outage
        assert models[0].power_state.value == "paused"
        gap = await stream.gaps.next(timeout=BOUND_S)
        assert (gap.cause, gap.action, gap.positions) == ("outage", "stop", {})
        await streamer.close()


def sweep_one(t: float, statuses: object) -> int:
    return 100 + round(300 * t) % 1800


@pytest.mark.parametrize("pacing", PACINGS)
async def test_a_stalled_host_is_a_gap_too(pacing: Pacing) -> None:
    models = [LAModel(1)]
    stalled: list[float] = []

    def stalls_once(t: float, statuses: object) -> int:
        if t >= 0.05 and not stalled:
            stalled.append(t)
            time.sleep(0.2)  # the whole loop stalls: 20 ticks go by
        return sweep_one(t, statuses)

    async with sim_bus(models, pacing=pacing) as (bus, _):
        streamer = Streamer(bus)
        with bus.events.subscribe(StreamGap) as gaps:
            stream = streamer.follow(InspireLA(bus, 1), stalls_once, period=PERIOD_S)
            await eventually(lambda: len(models[0].received) >= 40, "40 ticks")
            # The sweep (3 units a tick) moved 60 units during the stall; the targets
            # never jump.  Up to GAP_TICKS - 1 ticks skipped on a loaded machine are no
            # gap: 9 units at most.
            targets = [p for _, _, p in models[0].received]
            jumps = [abs(b - a) for a, b in itertools.pairwise(targets)]
            assert max(jumps) <= 3 * GAP_TICKS, targets
            gap = await gaps.next(timeout=BOUND_S)
        assert (gap.cause, gap.action) == ("behind", "ramp") and gap.missed >= 3
        assert stream.stats.gaps >= 1  # more if the machine stalled again
        await streamer.close()


async def test_bad_gap_options_are_refused() -> None:
    async with sim_bus([LAModel(1)]) as (bus, _):
        streamer = Streamer(bus)
        with pytest.raises(LocalProtocolError, match="on_gap='jump' is not allowed"):
            streamer.follow(InspireLA(bus, 1), [1], on_gap="jump")
        with pytest.raises(LocalProtocolError, match="max_speed"):
            streamer.follow(InspireLA(bus, 1), [1], max_speed=0)
        assert bus.stats.requests == 0


# -- the budget is the bus's ----------------------------------------------------------------


async def test_the_streams_of_a_bus_share_the_budget_the_bus_holds() -> None:
    from motorbus.streaming.budget import StreamBudget, stream_budget, tick_cost

    models = [LAModel(i) for i in range(1, 21)]
    async with sim_bus(models) as (bus, _):
        first, second = Streamer(bus), Streamer(bus)
        assert isinstance(stream_budget(bus), StreamBudget)
        assert first.budget is second.budget is stream_budget(bus)
        stream = first.follow(InspireLA(bus, 1), lambda t, s: 500, period=PERIOD_S)
        with pytest.raises(LocalProtocolError, match="la:1 is already streamed on bus sim"):
            second.follow(InspireLA(bus, 1), [500], period=PERIOD_S)
        # 5 feedback round trips a 10 ms tick fit beside la:1's broadcast, but not beside
        # 12 more every 50 ms that the other streamer serves: the budget is the bus's.
        fb = first.follow(
            [InspireLA(bus, i) for i in range(2, 14)],
            lambda t, s: [500] * 12,
            period=0.05,
            feedback=True,
        )
        five = [InspireLA(bus, i) for i in range(14, 19)]
        with pytest.raises(LocalProtocolError, match=r"would need \d+ % of the bus"):
            second.follow(five, lambda t, s: [500] * 5, period=PERIOD_S, feedback=True)
        assert stream_budget(bus).streams == [stream, fb]
        assert set(tick_cost(bus.timing, stream_budget(bus).streams)) == {PERIOD_S, 0.05}
        await fb.stop()
        assert stream_budget(bus).streams == [stream]
        late = second.follow(five, lambda t, s: [500] * 5, period=PERIOD_S, feedback=True)
        await first.close()
        await second.close()
        assert stream_budget(bus).streams == [] and late.done


def test_fifteen_broadcast_actuators_cost_one_frame_a_tick() -> None:
    from motorbus.bus.occupancy import BusTiming
    from motorbus.streaming.budget import slot_cost, tick_cost

    timing = BusTiming(LA_BAUD, 0.001, 0.0005, {Family.LA: 0.0008})

    class Planned:
        def __init__(self, n: int, feedback: bool) -> None:
            self.ids = tuple(range(1, n + 1))
            self.period = PERIOD_S
            self.feedback = feedback

    one_frame = slot_cost(timing, request_bytes=6 + 3 * 15, reply_bytes=0)
    assert tick_cost(timing, [Planned(15, False)]) == {PERIOD_S: one_frame}
    assert tick_cost(timing, [Planned(16, False)])[PERIOD_S] > one_frame
    assert tick_cost(timing, [Planned(2, True)])[PERIOD_S] > 2 * 0.001
