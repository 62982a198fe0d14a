"""A stop from anyone ends the stream that drives the actuator (a new user's report).

A pause or an e-stop of a streamed actuator, sent by another task, another client or a
dashboard, used to be undone by the stream's next tick (a follow target resumes a
paused LA, manual 3.5.4), and the stream ran on as if nothing had happened.  Now the
stop ends the stream (``StreamEnded``, naming the actuator and the stop), no target of
it follows the stop on the wire, and the stream's own safe action goes out as at any
end: the device may have been enabled again since the stop.

The witness is the simulated devices' own log of the frames they received, on the fake
clock.
"""

from __future__ import annotations

import asyncio
import math

import pytest

from motorbus.devices.la import InspireLA
from motorbus.errors import ReplyTimeoutError
from motorbus.protocol import la
from motorbus.sim.la import LAModel, PowerState
from motorbus.streams import StreamEnded, Streamer
from tests.fakeclock import Rig, rig
from tests.waiting import eventually

IDS = (1, 2, 3)


def _frames(r: Rig) -> list[bytes]:
    """The request frames the simulated devices received, in order."""
    return [bytes.fromhex(str(x["hex"])) for x in r.log if x["dir"] == "rx"]


def _is_follow(frame: bytes) -> bool:
    return frame[:2] == b"\x55\xaa" and frame[4] == la.CMD_BROADCAST_FOLLOW


def _control(frame: bytes, ident: int, action: la.ControlAction) -> bool:
    return frame == la.Control(ident, action).encode()


def _targets(t: float, _statuses: object) -> list[float]:
    return [1000 + 300 * math.sin(6 * t + i) for i in range(len(IDS))]


async def _started(r: Rig, safe_action: str) -> tuple[Streamer, object]:
    streamer = Streamer(r.bus)
    actuators = [InspireLA(r.bus, i) for i in IDS]
    for a in actuators:
        await a.enable()
    stream = streamer.follow(actuators, _targets, period=0.01, safe_action=safe_action)
    await eventually(lambda: sum(map(_is_follow, _frames(r))) >= 5, "5 ticks at the devices")
    return streamer, stream


async def _ended_by_the_estop_of_la1(r: Rig, stream: object) -> list[bytes]:
    """The stream ended on la:1's e-stop, and no target of it followed: the frames after
    the first e-stop to la:1."""
    with pytest.raises(StreamEnded, match=r"la:1 \(ESTOP\) stopped"):
        await asyncio.wait_for(stream.wait(), 5)  # type: ignore[attr-defined]
    frames = _frames(r)
    stop = min(n for n, f in enumerate(frames) if _control(f, 1, la.ControlAction.ESTOP))
    after = frames[stop + 1 :]
    assert not any(_is_follow(f) for f in after), "a target after the e-stop"
    return after


@pytest.mark.parametrize("safe_action", ["hold", "pause", "estop"])
async def test_a_pause_from_another_task_ends_the_stream_and_no_target_follows_it(
    safe_action: str,
) -> None:
    async with rig(range(1, 4)) as r:
        streamer, stream = await _started(r, safe_action)

        async def other_program() -> None:  # its own task: the bus's implicit lease
            await InspireLA(r.bus, 2).pause()

        await asyncio.create_task(other_program())
        with pytest.raises(StreamEnded, match=r"la:2 \(PAUSE\) stopped while the stream"):
            await asyncio.wait_for(stream.wait(), 5)  # type: ignore[attr-defined]
        await asyncio.sleep(0.1)  # ten periods: a stream still running would send
        frames = _frames(r)
        stop = max(n for n, f in enumerate(frames) if _control(f, 2, la.ControlAction.PAUSE))
        assert not any(_is_follow(f) for f in frames[stop:]), "a target after the pause"
        want = {
            "hold": PowerState.WORKING,
            "pause": PowerState.PAUSED,
            "estop": PowerState.ESTOPPED,
        }[safe_action]
        # Each gets the stream's own safe action, as at any end (la:2 after its pause).
        stopped = PowerState.ESTOPPED if safe_action == "estop" else PowerState.PAUSED
        states = [m.power_state for m in r.sim.models]  # type: ignore[attr-defined]
        assert states == [want, stopped, want], safe_action
        await streamer.close()


async def test_an_estop_from_outside_ends_the_stream_and_its_latch_holds() -> None:
    async with rig(range(1, 4)) as r:
        streamer, stream = await _started(r, "pause")
        await InspireLA(r.bus, 1).estop()
        after = await _ended_by_the_estop_of_la1(r, stream)
        # The stream's safe action, a pause, goes to la:1 as an e-stop: a pause would lift
        # the latch (a position command would then move it without a "work").
        assert not any(_control(f, 1, la.ControlAction.PAUSE) for f in after)
        assert any(_control(f, 1, la.ControlAction.ESTOP) for f in after)
        assert all(any(_control(f, i, la.ControlAction.PAUSE) for f in after) for i in (2, 3))
        states = [m.power_state for m in r.sim.models]  # type: ignore[attr-defined]
        assert states == [PowerState.ESTOPPED, PowerState.PAUSED, PowerState.PAUSED], states
        await streamer.close()


async def test_a_hold_stream_estopped_from_outside_keeps_the_latch_at_the_bus_close() -> None:
    """A "hold" stream (the default) passes its actuators to the bus's implicit lease,
    which pauses them at the close: la:1, e-stopped from outside, gets an e-stop there
    (a reviewer's finding: the pause lifted the latch)."""
    async with rig(range(1, 4)) as r:
        streamer, stream = await _started(r, "hold")
        await InspireLA(r.bus, 1).estop()
        with pytest.raises(StreamEnded, match=r"la:1 \(ESTOP\) stopped"):
            await asyncio.wait_for(stream.wait(), 5)  # type: ignore[attr-defined]
        await streamer.close()
        estop = len(_frames(r))
        await r.bus.close()
        after = _frames(r)[estop:]
        assert not any(_control(f, 1, la.ControlAction.PAUSE) for f in after), after
        states = [m.power_state for m in r.sim.models]  # type: ignore[attr-defined]
        assert states == [PowerState.ESTOPPED, PowerState.PAUSED, PowerState.PAUSED], states


async def test_a_stop_then_an_enable_from_outside_still_ends_on_the_streams_pause() -> None:
    """The device enabled again after the stop, before the stream ended: the stream's
    safe action is what it gets last (a reviewer's finding against a first version,
    which skipped the safe action a stop had covered)."""
    async with rig(range(1, 4)) as r:
        streamer, stream = await _started(r, "pause")
        la2 = InspireLA(r.bus, 2)
        await la2.pause()
        await la2.enable()
        with pytest.raises(StreamEnded, match=r"la:2 \(PAUSE\) stopped"):
            await asyncio.wait_for(stream.wait(), 5)  # type: ignore[attr-defined]
        frames = _frames(r)
        enabled = max(n for n, f in enumerate(frames) if _control(f, 2, la.ControlAction.WORK))
        assert any(_control(f, 2, la.ControlAction.PAUSE) for f in frames[enabled + 1 :])
        states = [m.power_state for m in r.sim.models]  # type: ignore[attr-defined]
        assert states == [PowerState.PAUSED] * 3, states
        await streamer.close()


async def test_a_broadcast_estop_stops_every_stream_and_a_new_stream_runs_after_it() -> None:
    async with rig(range(1, 4)) as r:
        streamer, stream = await _started(r, "pause")
        await r.bus.request(la.Control(la.BROADCAST_ID, la.ControlAction.ESTOP))
        with pytest.raises(StreamEnded, match=r"la:1 \(ESTOP\), la:2 \(ESTOP\), la:3"):
            await asyncio.wait_for(stream.wait(), 5)  # type: ignore[attr-defined]
        frames = _frames(r)
        stop = frames.index(la.Control(la.BROADCAST_ID, la.ControlAction.ESTOP).encode())
        assert not any(_is_follow(f) for f in frames[stop + 1 :]), "a target after the e-stop"
        states = [m.power_state for m in r.sim.models]  # type: ignore[attr-defined]
        assert PowerState.WORKING not in states, states
        # The stop ended that stream, not the streamer: a new stream on the same
        # actuators (enabled again) runs, and the old stop does not end it.
        actuators = [InspireLA(r.bus, i) for i in IDS]
        for a in actuators:
            await a.enable()
        count = sum(map(_is_follow, _frames(r)))
        again = streamer.follow(actuators, _targets, period=0.01, safe_action="pause")
        await asyncio.sleep(0.1)
        assert not again.done, again.error
        assert sum(map(_is_follow, _frames(r))) >= count + 5
        await again.stop()
        await streamer.close()


async def test_a_status_query_or_an_enable_does_not_end_a_stream() -> None:
    async with rig(range(1, 4)) as r:
        streamer, stream = await _started(r, "pause")
        await InspireLA(r.bus, 2).status()
        await InspireLA(r.bus, 3).enable()
        count = sum(map(_is_follow, _frames(r)))
        await asyncio.sleep(0.1)
        assert not stream.done, stream.error  # type: ignore[attr-defined]
        assert sum(map(_is_follow, _frames(r))) >= count + 5
        await streamer.close()


async def test_an_estop_whose_answer_never_came_still_ends_the_stream_and_keeps_the_latch() -> None:
    """The device heard the e-stop but its answer was lost (a reviewer's probe): the
    stop may have taken effect, so it counts; before, the stream ran on and its pause at
    the end lifted the latch."""
    models = [LAModel(i, turnaround_typical=120e-6, turnaround_max=120e-6) for i in IDS]
    async with rig(models=models) as r:
        streamer, stream = await _started(r, "pause")
        models[0]._silent_left = 10  # it hears from here on, and answers nothing
        with pytest.raises(ReplyTimeoutError):
            await InspireLA(r.bus, 1).estop()
        after = await _ended_by_the_estop_of_la1(r, stream)
        assert not any(_control(f, 1, la.ControlAction.PAUSE) for f in after)
        assert models[0].power_state is PowerState.ESTOPPED
        await streamer.close()
