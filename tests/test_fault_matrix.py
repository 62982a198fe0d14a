"""Every simulated fault against every kind of traffic: the bus's invariants hold.

Faults (``FaultConfig``): drop, flip, garbage, late, duplicate, silent, disconnect.
Traffic: LA request/reply (status, move, register read), quad stepper request/reply,
and an LA follow stream with status polling.  In every cell:

* no reply is ever given to a request it does not answer (the status ID, the register
  value, the MoveTo target: every MoveTo to a device asks for a new target, so a stale
  status would show the old one; the quad ack's address and command echo);
* every request resolves (a value, ``ReplyTimeoutError`` or ``BusClosedError``) within
  its deadline plus a generous slack (``asyncio.wait_for``);
* no task leaks (``sim_bus`` checks);
* the counters account for what happened (garbage bytes, late replies, reconnects);
* traffic goes on after the fault window: models keep receiving frames.

Every cell runs against a wire-paced and a prompt simulator (``pacing``): replies at the
emulated wire time, and replies the moment a request is complete.

Known limitation, not hidden: a reply later than the bus's ``late_guard`` (20 ms) after
its request's deadline can be taken for the answer to a later request of identical shape
to the same device (the bus cannot tell two identical status frames apart).  The late
delays below are chosen inside the guard, and ``test_late_reply_inside_the_guard_is_never_matched``
asserts on exactly that.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import pytest

from motorbus.bus.bus import DEFAULT_LATE_GUARD_S, Bus, BusState
from motorbus.devices.la import InspireLA
from motorbus.devices.project_stepper import ProjectStepper, ProjectVerifyError
from motorbus.errors import (
    BusClosedError,
    LocalProtocolError,
    RemoteProtocolError,
    ReplyTimeoutError,
)
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import Family
from motorbus.sim.bus import Pacing
from motorbus.sim.faults import FaultConfig
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from motorbus.sim.project_stepper import ProjectStepperModel
from motorbus.sim.quad_stepper import QuadStepperModel
from motorbus.streams import Streamer
from tests.bus.test_bus_faults import eventually
from tests.helpers import PACINGS, sim_bus

#: How long each cell drives traffic, seconds of simulator time, at least: a cell goes
#: on past it until traffic has resumed after the fault window (a reconnect's back-off
#: on a loaded machine can take most of ``RUN_S``), up to ``RESUME_CAP_S``.
RUN_S = 0.3
#: Past this, a cell whose traffic has not resumed stops, and its assertions fail.
RESUME_CAP_S = RUN_S + 5.0
#: The fault window of the windowed faults (silent, disconnect), seconds after the epoch.
WINDOW = (0.08, 0.16)
#: Host margin of the buses here.  ``sim_bus`` defaults to 50 ms (behaviour tests on a
#: loaded machine); the late cells need a deadline well short of the late guard.
MATRIX_HOST_MARGIN_S = 5e-3
#: Late delays: past the reply deadline, inside the 20 ms late guard that follows it.  The
#: LA deadline is ~5.5 ms at 921600 bit/s with this margin; the quad stepper's ~36 ms (30 ms
#: turnaround allowance) and its model answers within a few ms, so 15 ms and 40 ms land
#: between the deadline and the end of the guard.
LA_LATE_DELAY_S = 0.015
#: The late guard of the test of late replies inside it (see there), seconds.
LATE_GUARD_WIDE_S = 0.1
QUAD_LATE_DELAY_S = 0.04
#: Generous bound on any one request: every attempt's deadline, the late guard, and
#: scheduling slack on a loaded two-core machine.  Not a timing assertion: a hang guard.
RESOLVE_BOUND_S = 2.0
QUAD_BAUD = 115200
STREAM_PERIOD_S = 0.01


def fault_config(kind: str, late_delay: float) -> FaultConfig:
    """One fault kind at a rate high enough to hit a few hundred frames several times."""
    start, end = WINDOW
    return {
        "drop": FaultConfig(drop_byte_rate=0.01),
        "flip": FaultConfig(bit_flip_rate=0.01),
        "garbage": FaultConfig(garbage_rate=0.2),
        "late": FaultConfig(late_reply_rate=0.1, late_reply_delay_s=late_delay),
        "duplicate": FaultConfig(duplicate_reply_rate=0.2),
        "silent": FaultConfig(silent_windows=((start, end),)),
        "disconnect": FaultConfig(
            disconnect_after_s=start, reconnect_after_s=end - start, disconnect_count=1
        ),
    }[kind]


FAULTS = ("drop", "flip", "garbage", "late", "duplicate", "silent", "disconnect")


@dataclass
class Tally:
    """What the traffic saw."""

    ok: int = 0
    timeouts: int = 0
    closed: int = 0
    mismatches: list[str] = field(default_factory=list)


async def resolve(bus: Bus, cmd: Any, tally: Tally) -> Any:
    """Send ``cmd``; return its value or None after a typed error; fail on a hang."""
    try:
        value = await asyncio.wait_for(bus.request(cmd), RESOLVE_BOUND_S)
    except ReplyTimeoutError:
        tally.timeouts += 1
        return None
    except BusClosedError:
        tally.closed += 1
        await bus.wait_state(BusState.OPEN, timeout=RESOLVE_BOUND_S)
        return None
    tally.ok += 1
    return value


async def drive_until(
    sim: MemorySim,
    bus: Bus,
    until_s: float,
    step: Callable[[int], Any],
    resumed: Callable[[], bool],
) -> None:
    """Call ``step(k)`` (awaitable) until ``until_s`` seconds after the simulator's epoch
    and ``resumed()`` (traffic reached the devices after the fault window), or until
    ``RESUME_CAP_S``.  The end is a condition, not a time: how long a reconnect takes
    depends on the machine, and the cells assert what happened, not when."""
    k = 0
    while True:
        elapsed = bus.timer.now() - sim.bus.epoch
        if elapsed >= RESUME_CAP_S or (elapsed >= until_s and resumed()):
            return
        await step(k)
        k += 1


def after_window(sim: MemorySim) -> float:
    """The bus time at which the fault window ends."""
    return sim.bus.epoch + WINDOW[1]


def check_counters(kind: str, bus: Bus, sim: MemorySim) -> None:
    injected = sim.bus.stats.faults_injected
    if kind in ("drop", "flip", "garbage"):
        assert injected[kind] > 0
        assert bus.stats.garbage_bytes > 0 and bus.stats.resyncs > 0
    if kind in ("late", "duplicate", "silent"):
        # Whole frames only: nothing is garbage.  A stepper reply has no length and no
        # checksum, so a late or duplicated one that arrives while another reply is
        # awaited does not fit the awaited shape and is discarded as such (counted).
        if Family.LA in bus.families:
            assert bus.stats.garbage_bytes == 0
        else:  # whole 6-byte stepper replies were dropped, never a partial one
            assert bus.stats.garbage_bytes % 6 == 0, bus.stats.discarded_by_reason
    if kind == "silent":
        assert injected["silent"] > 0 and bus.stats.timeouts > 0
    if kind == "disconnect":
        assert injected["disconnect"] == 1
        assert (bus.stats.disconnects, bus.stats.reconnects) == (1, 1)


async def late_counted(kind: str, bus: Bus, sim: MemorySim) -> None:
    if kind == "late":
        assert sim.bus.stats.faults_injected["late"] > 0
        await eventually(lambda: bus.stats.late_replies > 0, "late replies counted")


# -- LA request/reply --------------------------------------------------------------------------


@pytest.mark.parametrize("kind", FAULTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_la_requests_under_fault(kind: str, pacing: Pacing) -> None:
    models = [LAModel(i) for i in (1, 2, 3)]
    faults = fault_config(kind, LA_LATE_DELAY_S)
    async with sim_bus(
        models, faults=faults, seed=7, host_margin=MATRIX_HOST_MARGIN_S, pacing=pacing
    ) as (
        bus,
        sim,
    ):
        tally = Tally()
        targets: dict[int, int] = {}

        async def step(k: int) -> None:
            ident = 1 + k % 3
            what = (k // 3) % 3
            if what == 0:
                # A new target each time: a stale status would carry the previous one.
                target = (targets.get(ident, 0) + 37 + k) % 2001
                targets[ident] = target
                status = await resolve(bus, la.MoveTo(ident, target), tally)
                if status is not None and (status.id, status.target) != (ident, target):
                    tally.mismatches.append(f"MoveTo({ident}, {target}) got {status}")
            elif what == 1:
                status = await resolve(bus, la.Control(ident, la.ControlAction.QUERY_STATUS), tally)
                if status is not None and status.id != ident:
                    tally.mismatches.append(f"status of {ident} got id {status.id}")
            else:
                value = await resolve(bus, la.ReadRegister(ident, la.Register.TARGET), tally)
                if value is not None and value != models[ident - 1].target:
                    tally.mismatches.append(
                        f"TARGET of {ident}: {value} != {models[ident - 1].target}"
                    )

        def resumed() -> bool:
            """Traffic went on after the fault window: the models took new targets."""
            after = after_window(sim)
            return any(t > after for m in models for t, _, _ in m.received)

        await drive_until(sim, bus, RUN_S, step, resumed)
        assert tally.mismatches == []
        assert tally.ok > 0
        check_counters(kind, bus, sim)
        await late_counted(kind, bus, sim)
        assert resumed()
        # The bus still answers.  Byte faults go on after the window, so one query may be
        # hit twice (with its retry); one of a few must get through.
        query = la.Control(1, la.ControlAction.QUERY_STATUS)
        answers = [await resolve(bus, query, Tally()) for _ in range(5)]
        assert any(a is not None for a in answers)


# -- quad stepper request/reply ----------------------------------------------------------------


def quad_command(k: int) -> q.QuadCommand:
    motor = 1 + k % 4
    choice = (k // 4) % 3
    if choice == 0:
        return q.RunPulses(motor, 100 + k)
    if choice == 1:
        return q.MotorSetup(motor, 1 + k % 16, 180)
    return q.Stop(motor)


@pytest.mark.parametrize("kind", FAULTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_quad_requests_under_fault(kind: str, pacing: Pacing) -> None:
    model = QuadStepperModel()
    faults = fault_config(kind, QUAD_LATE_DELAY_S)
    async with sim_bus(
        [model],
        baud=QUAD_BAUD,
        faults=faults,
        seed=3,
        host_margin=MATRIX_HOST_MARGIN_S,
        pacing=pacing,
    ) as (bus, sim):
        tally = Tally()
        before_window = 0

        async def step(k: int) -> None:
            nonlocal before_window
            cmd = quad_command(k)
            raw = cmd.encode()
            ack = await resolve(bus, cmd, tally)
            if ack is not None and (ack.address, ack.command) != (raw[2], raw[3]):
                tally.mismatches.append(f"{cmd} got {ack}")
            if bus.timer.now() - sim.bus.epoch < WINDOW[1]:
                before_window = sim.bus.stats.requests

        def resumed() -> bool:
            """Requests reached the model after the fault window."""
            return sim.bus.stats.requests > before_window

        await drive_until(sim, bus, RUN_S, step, resumed)
        assert tally.mismatches == []
        assert tally.ok > 0
        check_counters(kind, bus, sim)
        await late_counted(kind, bus, sim)
        assert resumed()


# -- LA follow stream with polling -------------------------------------------------------------


@pytest.mark.parametrize("kind", FAULTS)
@pytest.mark.parametrize("pacing", PACINGS)
async def test_follow_stream_under_fault(kind: str, pacing: Pacing) -> None:
    ids = (1, 2, 3, 4)
    models = [LAModel(i) for i in ids]
    faults = fault_config(kind, LA_LATE_DELAY_S)
    ticks = round(RUN_S / STREAM_PERIOD_S)
    last_tick = 0

    def resumed() -> bool:
        """Every model took a target after the fault window."""
        after = after_window(sim)
        return all(any(t > after for t, _, _ in m.received) for m in models)

    def faulted() -> bool:
        """A late reply was injected, if that is the fault (it delays 1 reply in 10; a
        loaded machine skips polls, and with them the replies it could delay)."""
        return kind != "late" or sim.bus.stats.faults_injected["late"] > 0

    def targets(t: float, statuses: object) -> list[int] | None:
        """Target of actuator i at tick k: 100 + 4k + i, so every received value is
        traceable.  The stream ends after ``ticks`` ticks once traffic has resumed after
        the window (a reconnect may take longer on a loaded machine) and the fault was
        injected, or at the cap."""
        nonlocal last_tick
        k = round(t / STREAM_PERIOD_S)
        if k * STREAM_PERIOD_S >= RESUME_CAP_S or (k >= ticks and resumed() and faulted()):
            return None
        last_tick = max(last_tick, k)
        return [100 + 4 * k + i for i in ids]

    async with sim_bus(
        models, faults=faults, seed=5, host_margin=MATRIX_HOST_MARGIN_S, pacing=pacing
    ) as (
        bus,
        sim,
    ):
        streamer = Streamer(bus)
        actuators = [InspireLA(bus, i) for i in ids]
        stream = streamer.follow(actuators, targets, period=STREAM_PERIOD_S, poll_status=True)
        await asyncio.wait_for(stream.wait(), RESUME_CAP_S + 5.0)
        await streamer.close(safe=False)
        assert stream.error is None
        assert stream.stats.ticks > 0
        for ident, status in stream.statuses.items():
            assert status.id == ident
        # After the outage, or after the host stalled (a loaded machine: the stream fell
        # GAP_TICKS behind, a gap too), the stream ramps from where the actuators are to
        # the trajectory: steps in between, between the actuators' start (0: an outage
        # before one reached the trajectory ramps from below it, seen under load) and
        # the trajectory's end.
        ramped = kind == "disconnect" or stream.stats.gaps > 0
        for model in models:
            for _, _, target in model.received:
                if ramped:
                    assert 0 <= target <= 100 + 4 * last_tick + model.id, (model.id, target)
                else:
                    assert (target - 100 - model.id) % 4 == 0, (model.id, target)
        if kind == "disconnect":
            assert stream.stats.gaps >= 1
        assert resumed()
        check_stream_counters(kind, bus, sim, stream.stats.skipped)
        await late_counted(kind, bus, sim)


def check_stream_counters(kind: str, bus: Bus, sim: MemorySim, skipped: int) -> None:
    injected = sim.bus.stats.faults_injected
    if kind in ("drop", "flip", "garbage") and injected[kind]:
        assert bus.stats.garbage_bytes > 0
    if kind == "disconnect":
        assert (bus.stats.disconnects, bus.stats.reconnects) == (1, 1)
        assert skipped > 0  # ticks skipped while the port was gone, then resumed


# -- the documented limit ----------------------------------------------------------------------


@pytest.mark.parametrize("pacing", PACINGS)
async def test_late_reply_inside_the_guard_is_never_matched(pacing: Pacing) -> None:
    """Late replies inside the guard are counted as late, never given to a newer request.

    Past ``late_guard`` after the deadline the bus no longer holds the device, and a
    stale status could be taken for the answer to a same-shaped later request: that is
    the known limit, and why every late delay in this file stays inside the guard.
    """
    assert LA_LATE_DELAY_S < DEFAULT_LATE_GUARD_S
    faults = FaultConfig(late_reply_rate=0.5, late_reply_delay_s=LA_LATE_DELAY_S)
    # The bus judges a reply by when it reads it: a loop stalled by a loaded machine
    # (a full suite on two cores) read a 15 ms-late reply past the default 20 ms guard,
    # outside what this test is about.  A wider guard keeps every late reply inside it.
    async with sim_bus(
        [LAModel(1)],
        faults=faults,
        seed=1,
        host_margin=MATRIX_HOST_MARGIN_S,
        pacing=pacing,
        late_guard=LATE_GUARD_WIDE_S,
    ) as (
        bus,
        sim,
    ):
        tally = Tally()
        for k in range(30):
            status = await resolve(bus, la.MoveTo(1, 10 + k), tally)
            if status is not None:
                assert status.target == 10 + k
        assert tally.timeouts > 0
        # Every request that gave up had its reply, which came later, counted as late.
        # (Not every reply the simulator delayed need be late: on a stalled host one can
        # still come before its deadline, and is then that request's answer; a fresh-
        # clone CI run saw it.)
        await eventually(
            lambda: bus.stats.late_replies >= tally.timeouts,
            "every late reply counted",
        )
        assert bus.stats.late_replies <= sim.bus.stats.faults_injected["late"]
        assert bus.stats.unexpected_frames == 0


@pytest.mark.parametrize("pacing", PACINGS)
async def test_corrupted_project_read_back_is_a_verify_error_not_local(pacing: Pacing) -> None:
    """The 0x3E dump has no checksum: a flipped bit can make a field no project can hold.

    ``upload(verify=True)`` must report that as ``ProjectVerifyError`` (the device's or
    the line's fault), never as ``LocalProtocolError`` (which says the caller erred).
    The soak run found this: one upload in ~100 under 1 % faults raised the latter.
    """
    project = ps.Project(
        number=1,
        subdivision=1,
        step_angle_x100=180,
        distance_per_rev=200,
        steps=(ps.StepSpec(run_distance=40, start_hz=2000, speed_rpm=600),),
    )
    faults = FaultConfig(bit_flip_rate=0.004)
    outcomes: dict[str, int] = {}
    async with sim_bus(
        [ProjectStepperModel()],
        baud=QUAD_BAUD,
        faults=faults,
        seed=2,
        host_margin=MATRIX_HOST_MARGIN_S,
        pacing=pacing,
    ) as (bus, sim):
        device = ProjectStepper(bus)
        for _ in range(12):
            try:
                await asyncio.wait_for(device.upload(project, save=False), 10 * RESOLVE_BOUND_S)
            except LocalProtocolError as err:  # pragma: no cover - the bug this guards
                pytest.fail(f"a corrupted read-back surfaced as LocalProtocolError: {err}")
            except (ProjectVerifyError, ReplyTimeoutError, RemoteProtocolError) as err:
                name = type(err).__name__
            else:
                name = "ok"
            outcomes[name] = outcomes.get(name, 0) + 1
        assert sim.bus.stats.faults_injected["flip"] > 0
        assert outcomes.get("ok", 0) > 0, outcomes
