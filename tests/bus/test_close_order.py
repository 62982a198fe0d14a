"""Nothing moves after the bus's closing safe stops: motion queued or submitted while
the bus closes is dropped or refused, never written after the pause."""

from __future__ import annotations

import asyncio

import pytest

from motorbus.devices.la import InspireLA
from motorbus.errors import BusClosedError
from motorbus.protocol import la
from motorbus.protocol.base import Family
from tests.bus.test_leases_pty import (
    LA_BAUD,
    PAUSE_1,
    Recorder,
    la_bus,
    open_bus,
    pty_sim,
    to_la,
)

pytestmark = pytest.mark.asyncio


@pytest.mark.parametrize("pacing", ["wire", "prompt"])
async def test_queued_motion_is_not_written_after_the_closing_pause(pacing: str) -> None:
    async with la_bus(pacing) as (bus, rec):
        futures = [bus.submit(la.MoveTo(1, 500 + (i % 2) * 500), retries=0) for i in range(20)]
        await asyncio.sleep(0.003)
    frames = to_la(1, rec.frames)
    assert frames[-1] == PAUSE_1, [f.hex() for f in frames[-3:]]
    assert frames.count(PAUSE_1) == 1
    assert bus.leases == ()
    dropped = [f for f in futures if f.done() and f.exception() is not None]
    assert dropped, "some of the 20 moves were still queued at close"
    assert all(isinstance(f.exception(), BusClosedError) for f in dropped)


@pytest.mark.parametrize("pacing", ["wire", "prompt"])
async def test_motion_submitted_while_the_bus_closes_is_refused(pacing: str) -> None:
    refused: list[BaseException] = []

    async def mover(actuator: InspireLA) -> None:
        i = 0
        while True:
            try:
                await actuator.move_to(500 + (i % 2) * 500)
            except BusClosedError as err:
                refused.append(err)
                return
            i += 1

    async with la_bus(pacing) as (bus, rec):
        task = asyncio.get_running_loop().create_task(mover(InspireLA(bus, 1)))
        await asyncio.sleep(0.05)
    await asyncio.wait_for(task, 5)
    frames = to_la(1, rec.frames)
    assert frames[-1] == PAUSE_1, [f.hex() for f in frames[-3:]]
    assert refused and ("closing" in str(refused[0]) or "closed" in str(refused[0]))
    assert bus.leases == ()


async def test_a_second_cancellation_does_not_cut_a_lease_s_safe_stop() -> None:
    from motorbus.errors import MotorbusError

    async with la_bus("wire") as (bus, rec):

        async def worker() -> None:
            async with bus.lease(["la:1"], owner="w"):
                await InspireLA(bus, 1).move_to(1500)
                await asyncio.sleep(10)

        async def poller() -> None:  # keeps the bus busy, so the pause has to queue
            while True:
                try:
                    await InspireLA(bus, 2).status()
                except MotorbusError:
                    return

        task = asyncio.get_running_loop().create_task(worker())
        busy = asyncio.get_running_loop().create_task(poller())
        await asyncio.sleep(0.05)
        task.cancel()
        await asyncio.sleep(0)  # the worker is in __aexit__: its pause is in flight
        task.cancel()  # a second cancellation (a timeout, a task group)
        with pytest.raises(asyncio.CancelledError):
            await task
        assert bus.leases == ()
    await busy
    frames = to_la(1, rec.frames)
    assert frames[-1] == PAUSE_1, [f.hex() for f in frames]


async def test_a_safe_action_owed_while_the_port_is_lost_goes_out_when_it_is_back() -> None:
    from motorbus.bus.bus import BusState
    from motorbus.sim.la import LAModel, PowerState
    from tests.helpers import sim_bus

    model = LAModel(1)
    async with sim_bus([model], pacing="prompt") as (bus, sim):
        lease = bus.lease(["la:1"], owner="me")
        await InspireLA(bus, 1).move_to(1500)
        sim.peer.unplug()
        await bus.wait_state(BusState.LOST, timeout=2)
        await lease.release()  # owed: the port is lost
        assert model.power_state is PowerState.WORKING
        sim.peer.plug()
        await bus.wait_state(BusState.OPEN, timeout=5)
        await asyncio.sleep(0.05)
        assert model.power_state is PowerState.PAUSED


class _Stop(BaseException):
    """Not an Exception: a hook's ``BaseException`` is raised, once the port closed."""


async def test_close_hooks_run_together_and_a_failing_one_stops_nothing(
    caplog: pytest.LogCaptureFixture,
) -> None:
    started: list[str] = []
    release = asyncio.Event()

    async def slow() -> None:
        started.append("slow")
        await release.wait()

    async def failing() -> None:
        started.append("failing")
        release.set()  # runs while "slow" waits: the hooks run together
        raise RuntimeError("hook broke")

    async def interrupted() -> None:
        started.append("interrupted")
        raise _Stop

    with pytest.raises(_Stop):
        async with la_bus("wire") as (bus, rec):
            await InspireLA(bus, 1).move_to(800)  # the implicit lease: a pause owed
            for hook in (slow, failing, interrupted):
                bus.add_close_hook(hook)
    assert started == ["slow", "failing", "interrupted"]
    assert "a close hook failed: hook broke" in caplog.text
    # The leases still ended and the port still closed before _Stop came out.
    assert to_la(1, rec.frames)[-1] == PAUSE_1
    assert bus.leases == ()
    assert bus.state.value == "closed"


async def test_stop_everything_closes_the_buses_together() -> None:
    """The way out of ``motorbus.run`` (a signal): two buses, and la:1 on bus A does not
    answer, so its pause is retried after a long late guard (0.5 s).  Bus B's pause
    does not wait for bus A's retries."""
    from motorbus.errors import ReplyTimeoutError
    from motorbus.runtime import shutdown
    from motorbus.sim.la import LAModel

    with (
        pty_sim([LAModel(2)], LA_BAUD, "prompt") as (sim_a, rec_a),
        pty_sim([LAModel(1)], LA_BAUD, "prompt") as (sim_b, rec_b),
    ):
        a = open_bus(sim_a, [Family.LA], late_guard=0.5)
        b = open_bus(sim_b, [Family.LA])
        await a.open()
        await b.open()
        try:
            with pytest.raises(ReplyTimeoutError):
                await a.request(la.MoveTo(1, 500))  # written: la:1 on A owes a pause
            await InspireLA(b, 1).move_to(500)
            await shutdown.stop_everything()
        finally:
            await a.close()
            await b.close()
        await asyncio.sleep(0.05)  # what was written reaches the simulators

    def pauses(rec: Recorder, epoch: float) -> list[float]:
        return [
            epoch + float(r["t"])
            for r in list(rec.records)
            if r["dir"] == "rx" and bytes.fromhex(str(r["hex"])) == PAUSE_1
        ]

    on_a, on_b = pauses(rec_a, sim_a.bus.epoch), pauses(rec_b, sim_b.bus.epoch)
    assert len(on_a) >= 2 and len(on_b) == 1, (on_a, on_b)
    assert on_b[0] < on_a[1]  # bus B's pause came before bus A's retry
