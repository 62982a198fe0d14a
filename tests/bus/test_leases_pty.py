"""Leases over a real pseudo-terminal: every motion has one owner and a safe end.

``PtySim`` logs every frame the simulated devices receive.  A program that moves a device
and closes its bus must leave the device's safe action as the last frame it received
(an LA pause, a stepper stop), unless the program released it with ``hold``; a second
owner is refused with nothing written; a bus used from another event loop raises at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import threading
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator, Sequence
from contextlib import asynccontextmanager, contextmanager

import pytest

from motorbus import BusManager
from motorbus.bus.bus import Bus
from motorbus.devices.la import InspireLA
from motorbus.devices.project_stepper import ProjectStepper
from motorbus.devices.quad_stepper import QuadStepper
from motorbus.errors import LeaseConflictError, ReplyTimeoutError, WrongLoopError
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import Family
from motorbus.sim.bus import LogRecord, Pacing
from motorbus.sim.la import LAModel
from motorbus.sim.model import DeviceModel
from motorbus.sim.project_stepper import ProjectStepperModel
from motorbus.sim.pty import PtySim
from motorbus.sim.quad_stepper import QuadStepperModel
from motorbus.streams import Streamer
from motorbus.transport.serial import SerialTransport
from tests.helpers import LOADED_HOST_MARGIN_MS, PACINGS

LA_BAUD = 921600
STEPPER_BAUD = 9600
HOST_MARGIN_S = LOADED_HOST_MARGIN_MS / 1e3  # frames, not timing (50 ms timed out, 6 workers)

PAUSE_1 = la.Control(1, la.ControlAction.PAUSE).encode()
PAUSE_2 = la.Control(2, la.ControlAction.PAUSE).encode()


class Recorder:
    """The frames the simulator received, in order (thread-safe append)."""

    def __init__(self) -> None:
        self.records: list[LogRecord] = []

    def __call__(self, record: LogRecord) -> None:
        self.records.append(record)

    @property
    def frames(self) -> list[bytes]:
        return [
            bytes.fromhex(str(r["hex"]))
            for r in list(self.records)
            if r["dir"] == "rx" and r["fault"] is None
        ]


def to_la(ident: int, frames: Sequence[bytes]) -> list[bytes]:
    """Frames addressed to LA ``ident`` (byte 3 of a request)."""
    return [f for f in frames if f[:2] == b"\x55\xaa" and f[3] == ident]


@contextmanager
def pty_sim(
    models: Sequence[DeviceModel], baud: int, pacing: Pacing
) -> Iterator[tuple[PtySim, Recorder]]:
    recorder = Recorder()
    with PtySim(models, baud=baud, pacing=pacing, log=recorder) as sim:
        yield sim, recorder
        assert sim.error is None, f"the simulator thread failed: {sim.error!r}"


def open_bus(sim: PtySim, families: Sequence[Family], **options: object) -> Bus:
    transport = SerialTransport(sim.path, baudrate=sim.bus.baud)
    return Bus(transport, name="pty", families=families, host_margin=HOST_MARGIN_S, **options)  # type: ignore[arg-type]


@asynccontextmanager
async def la_bus(pacing: Pacing, **options: object) -> AsyncIterator[tuple[Bus, Recorder]]:
    with pty_sim([LAModel(1), LAModel(2)], LA_BAUD, pacing) as (sim, recorder):
        bus = open_bus(sim, [Family.LA], **options)
        await bus.open()
        try:
            yield bus, recorder
        finally:
            await bus.close()
        # Everything the bus wrote has reached the simulator before the port closed:
        # a last query would be answered only after them, but the port is closed, so wait
        # for the simulator's reader to drain what is in flight.
        await asyncio.sleep(0.05)


@pytest.mark.parametrize("pacing", PACINGS)
async def test_a_move_then_close_ends_with_the_pause(pacing: Pacing) -> None:
    async with la_bus(pacing) as (bus, recorder):
        await InspireLA(bus, 1).move_to(1500)
        await InspireLA(bus, 2).status()  # queried, never moved: not stopped
    one = to_la(1, recorder.frames)
    assert one[0] == la.MoveTo(1, 1500).encode()
    assert one[-1] == PAUSE_1, "the last frame la:1 received is its safe action"
    assert PAUSE_2 not in recorder.frames


@pytest.mark.parametrize("pacing", PACINGS)
async def test_a_move_released_with_hold_sends_no_safe_frame(pacing: Pacing) -> None:
    async with la_bus(pacing) as (bus, recorder):
        actuator = InspireLA(bus, 1)
        await actuator.move_to(1500)
        await actuator.release(hold=True)
        assert bus.leases == ()
    assert to_la(1, recorder.frames) == [la.MoveTo(1, 1500).encode()]


async def test_the_bus_safe_action_estop_and_hold() -> None:
    async with la_bus("prompt", safe_action="estop") as (bus, recorder):
        await InspireLA(bus, 1).move_to(700, reply=False)
    assert to_la(1, recorder.frames)[-1] == la.Control(1, la.ControlAction.ESTOP).encode()
    async with la_bus("prompt", safe_action="hold") as (bus, recorder):
        await InspireLA(bus, 1).move_to(700, reply=False)
    assert to_la(1, recorder.frames) == [la.MoveTo(1, 700, False).encode()]


async def outside_the_lease(fn: Callable[[], Awaitable[object]]) -> object:
    """Run ``fn()`` in a task that does not hold the running task's leases."""
    return await asyncio.get_running_loop().create_task(fn(), context=contextvars.Context())  # type: ignore[arg-type]


@pytest.mark.parametrize("pacing", PACINGS)
async def test_a_second_owner_is_refused_with_nothing_sent(pacing: Pacing) -> None:
    async with la_bus(pacing) as (bus, recorder):
        lease = bus.lease(["la:1"], owner="stream")
        before = len(recorder.frames)
        with pytest.raises(LeaseConflictError, match="la:1 is leased by 'stream'"):
            await outside_the_lease(lambda: InspireLA(bus, 1).move_to(100))
        with pytest.raises(LeaseConflictError):  # a broadcast naming it
            await outside_the_lease(
                lambda: bus.send(la.Broadcast(la.BroadcastMode.POSITION, ((2, 10), (1, 10))))
            )
        with pytest.raises(LeaseConflictError):
            bus.lease(["la:2", "la:1"], owner="rig")
        await InspireLA(bus, 2).status()  # the bus still works, and flushes the line
        assert to_la(1, recorder.frames[before:]) == []
        assert to_la(2, recorder.frames[before:]) == [
            la.Control(2, la.ControlAction.QUERY_STATUS).encode()
        ]
        assert [(i.key, i.owner) for i in bus.leases] == [("la:1", "stream")]
        # The owner's task moves it, and ends on purpose: nothing more is sent.
        await InspireLA(bus, 1).move_to(200)
        await lease.release(hold=True)
        assert bus.leases == ()
    assert to_la(1, recorder.frames)[-1] == la.MoveTo(1, 200).encode()


@pytest.mark.parametrize("pacing", PACINGS)
async def test_a_lease_block_left_by_an_error_applies_the_safe_action(pacing: Pacing) -> None:
    async with la_bus(pacing) as (bus, recorder):
        with pytest.raises(RuntimeError, match="user code"):
            async with bus.lease(["la:1", "la:2"], owner="rig", safe_action="pause"):
                await InspireLA(bus, 1).move_to(300)
                await InspireLA(bus, 2).move_to(400)
                raise RuntimeError("user code failed")
        assert bus.leases == ()
        frames = list(recorder.frames)
        await InspireLA(bus, 1).status()  # lease over: anyone may use it again
    assert frames[-2:] in ([PAUSE_1, PAUSE_2], [PAUSE_2, PAUSE_1])
    assert to_la(1, recorder.frames).count(PAUSE_1) == 1  # closing sent no second one


async def test_a_device_stopped_by_its_owner_is_not_stopped_again_at_close() -> None:
    async with la_bus("prompt") as (bus, recorder):
        actuator = InspireLA(bus, 1)
        await actuator.move_to(900)
        await actuator.pause()
    assert to_la(1, recorder.frames).count(PAUSE_1) == 1


async def test_a_bus_manager_stops_each_device_once() -> None:
    with pty_sim([LAModel(1), LAModel(2)], LA_BAUD, "prompt") as (sim, recorder):
        mgr = BusManager()
        mgr.add_bus("arm", sim.path, baud=LA_BAUD, devices=["la:1"], host_margin_ms=50)
        async with mgr:
            await mgr.la("arm", 1).move_to(900)
            await mgr.la("arm", 2).move_to(800)  # not in the bus file: its lease stops it
        await asyncio.sleep(0.05)
    assert to_la(1, recorder.frames).count(PAUSE_1) == 1
    assert to_la(2, recorder.frames)[-1] == PAUSE_2


async def long_quad_run(quad: QuadStepper, motor: int) -> None:
    """Configure ``motor`` for a run far longer than any test, and start it."""
    await quad.configure(
        motor, subdivision=8, step_angle_x100=180, pulses=16777215,
        start_hz=10, accel_hz=0, speed_rpm=1,
    )  # fmt: skip
    await quad.run(motor, wait=False)


@pytest.mark.parametrize("pacing", PACINGS)
async def test_stepper_motion_then_close_ends_with_their_stops(pacing: Pacing) -> None:
    models = [ProjectStepperModel(), QuadStepperModel()]
    with pty_sim(models, STEPPER_BAUD, pacing) as (sim, recorder):
        bus = open_bus(sim, [Family.PROJECT_STEPPER, Family.QUAD_STEPPER])
        async with bus:
            await ProjectStepper(bus).jog()
            await long_quad_run(QuadStepper(bus), 2)
            assert {i.key for i in bus.leases} == {"project_stepper", "quad_stepper"}
        await asyncio.sleep(0.1)
    frames = recorder.frames
    jog = frames.index(ps.JogForward(motor=ps.DEFAULT_MOTOR).encode())
    run = frames.index(q.Run(2).encode())
    # What ends each motion, after both, and nothing else.
    assert sorted(frames[max(jog, run) + 1 :]) == sorted(
        [ps.ManualStop(motor=ps.DEFAULT_MOTOR).encode(), q.Stop(2).encode()]
    )


async def test_a_finished_quad_run_is_not_stopped_at_close() -> None:
    with pty_sim([QuadStepperModel()], STEPPER_BAUD, "prompt") as (sim, recorder):
        bus = open_bus(sim, [Family.QUAD_STEPPER])
        async with bus:
            quad = QuadStepper(bus)
            await quad.configure(
                1, subdivision=1, step_angle_x100=180, pulses=10,
                start_hz=1000, accel_hz=0, speed_rpm=600,
            )  # fmt: skip
            await quad.run(1, wait=True, timeout=5)  # its done reply came
        await asyncio.sleep(0.1)
    assert recorder.frames[-1] == q.Run(1).encode()


async def test_a_stepper_run_released_with_hold_keeps_running() -> None:
    with pty_sim([QuadStepperModel()], STEPPER_BAUD, "prompt") as (sim, recorder):
        bus = open_bus(sim, [Family.QUAD_STEPPER])
        async with bus:
            quad = QuadStepper(bus)
            await long_quad_run(quad, 1)
            await quad.release(hold=True)
        await asyncio.sleep(0.1)
    assert recorder.frames[-1] == q.Run(1).encode()


async def test_a_bus_used_from_another_loop_raises_at_once() -> None:
    async with la_bus("prompt") as (bus, recorder):
        actuator = InspireLA(bus, 1)
        outcome: list[BaseException] = []

        def other_thread() -> None:
            async def use() -> None:
                await asyncio.wait_for(actuator.move_to(100), timeout=5)

            try:
                asyncio.run(use())
            except BaseException as err:
                outcome.append(err)

        before = len(recorder.frames)
        thread = threading.Thread(target=other_thread)
        thread.start()
        await asyncio.to_thread(thread.join)
        assert len(outcome) == 1 and isinstance(outcome[0], WrongLoopError), outcome
        assert "another event loop" in str(outcome[0])
        assert (await actuator.status()).id == 1  # its own loop still works
        assert recorder.frames[before:] == [la.Control(1, la.ControlAction.QUERY_STATUS).encode()]
        assert bus.leases == ()


@pytest.mark.parametrize("pacing", PACINGS)
async def test_a_stream_that_ends_normally_ends_with_the_pause_at_close(pacing: Pacing) -> None:
    # Issue 19 case 1: the targets end, the stream stops, the bus closes: the last frame
    # each actuator received must be its pause, not an F3 target.
    async with la_bus(pacing) as (bus, recorder):
        streamer = Streamer(bus)
        ramp = [{1: 100 + 10 * k, 2: 200 + 10 * k} for k in range(5)]
        stream = streamer.follow(
            [InspireLA(bus, 1), InspireLA(bus, 2)], ramp, period=0.01, safe_action="pause"
        )
        await asyncio.wait_for(stream.wait(), timeout=10)
        await stream.stop(safe=True)
    frames = recorder.frames
    assert any(f[3] == la.BROADCAST_ID and f[4] == la.CMD_BROADCAST_FOLLOW for f in frames)
    last_broadcast = max(i for i, f in enumerate(frames) if f[3] == la.BROADCAST_ID)
    assert sorted(frames[last_broadcast + 1 :]) == sorted([PAUSE_1, PAUSE_2])


async def test_an_unbound_lease_owns_only_what_is_submitted_with_it() -> None:
    # A streamer's lease: its frames name it; the program's own task is another owner.
    async with la_bus("prompt") as (bus, recorder):
        lease = bus.lease(["la:1"], owner="streams", bind=False)
        with pytest.raises(LeaseConflictError):
            await InspireLA(bus, 1).move_to(100)
        await bus.submit(la.MoveTo(1, 300), lease=lease)
        assert [(i.key, i.owner) for i in bus.leases] == [("la:1", "streams")]
    assert to_la(1, recorder.frames) == [la.MoveTo(1, 300).encode(), PAUSE_1]


async def test_a_move_to_every_actuator_pauses_those_that_answered() -> None:
    # ID 255 names every LA that answered, not every ID that was asked (a scan asks 254).
    async with la_bus("prompt") as (bus, recorder):
        for ident in (1, 2, 7):
            with contextlib.suppress(ReplyTimeoutError):
                await bus.request(la.Control(ident, la.ControlAction.QUERY_STATUS), timeout=0.05)
        await bus.send(la.MoveTo(la.BROADCAST_ID, 1000, False))
        assert [i.key for i in bus.leases] == ["la:1", "la:2"]
    frames = recorder.frames
    after = frames[frames.index(la.MoveTo(la.BROADCAST_ID, 1000, False).encode()) + 1 :]
    assert sorted(after) == sorted([PAUSE_1, PAUSE_2])
