"""A stream started by a task that holds a lease on its actuators runs under that lease.

No second owner: the program that leased the actuators (a rig, an application's block)
streams them itself, as on a served bus.  The lease's end stops such a stream before
the lease's safe action is written, so nothing of the stream follows it; the wire tap
(every frame as the bus writes it) is the judge.
"""

from __future__ import annotations

import asyncio
import contextvars

import pytest

from motorbus import InspireLA, Streamer
from motorbus.bus.bus import Bus
from motorbus.errors import LeaseConflictError, LocalProtocolError
from motorbus.protocol import la
from motorbus.sim.la import LAModel, PowerState
from tests.helpers import sim_bus
from tests.waiting import eventually

pytestmark = pytest.mark.asyncio

PAUSE = {i: la.Control(i, la.ControlAction.PAUSE).encode() for i in (1, 2, 3)}


def is_follow_broadcast(frame: bytes) -> bool:
    return frame[3] == la.BROADCAST_ID and frame[4] == la.CMD_BROADCAST_FOLLOW


def written(bus: Bus) -> list[bytes]:
    """Every frame the bus writes from now on, in order."""
    frames: list[bytes] = []

    def tap(outgoing: bool, data: bytes, at: float) -> None:
        if outgoing:
            frames.append(data)

    bus.add_wire_tap(tap)
    return frames


async def test_a_stream_runs_under_the_lease_its_task_holds_and_stops_before_its_end() -> None:
    models = [LAModel(1), LAModel(2)]
    async with sim_bus(models, pacing="prompt") as (bus, _sim):
        frames = written(bus)
        async with bus.lease(["la:1", "la:2"], owner="app") as lease:
            stream = Streamer(bus).follow(
                [InspireLA(bus, 1), InspireLA(bus, 2)], lambda t, s: [700, 800], period=0.01
            )
            await eventually(lambda: stream.stats.ticks >= 3, "three ticks")
            assert lease.keys == {"la:1", "la:2"}  # no second owner
            assert [info.owner for info in bus.leases] == ["app", "app"]
            # A task that holds no lease (a fresh context) is refused, by the lease's name.
            other = asyncio.get_running_loop().create_task(
                InspireLA(bus, 1).move_to(100), context=contextvars.Context()
            )
            with pytest.raises(LeaseConflictError, match="la:1 is leased by 'app'"):
                await other
        # The block's end: the stream stopped, then the lease's safe action went.
        assert stream.done
        assert all(m.power_state is PowerState.PAUSED for m in models)
        last_follow = max(i for i, f in enumerate(frames) if is_follow_broadcast(f))
        pauses = [frames.index(PAUSE[1]), frames.index(PAUSE[2])]
        assert last_follow < min(pauses)
        count = len(frames)
        await asyncio.sleep(0.05)  # several periods: nothing more of the stream
        assert not any(is_follow_broadcast(f) for f in frames[count:])
        assert bus.leases == ()


async def test_release_with_hold_stops_the_stream_and_sends_nothing() -> None:
    model = LAModel(1)
    async with sim_bus([model], pacing="prompt") as (bus, _sim):
        frames = written(bus)
        lease = bus.lease(["la:1"], owner="app")
        stream = Streamer(bus).follow(
            InspireLA(bus, 1), lambda t, s: 900, period=0.01, safe_action="pause"
        )
        await eventually(lambda: stream.stats.ticks >= 3, "three ticks")
        await lease.release(hold=True)
        assert stream.done
        count = len(frames)
        await asyncio.sleep(0.05)
        assert frames[count:] == []
        assert PAUSE[1] not in frames  # hold: nothing sent, the stream's pause included
        assert model.power_state is PowerState.WORKING
        await bus.release(hold=True)


async def test_releasing_some_keys_stops_only_their_streams() -> None:
    async with sim_bus([LAModel(1), LAModel(2)], pacing="prompt") as (bus, _sim):
        lease = bus.lease(["la:1", "la:2"], owner="app")
        streamer = Streamer(bus)
        one = streamer.follow(InspireLA(bus, 1), lambda t, s: 700, period=0.01)
        two = streamer.follow(InspireLA(bus, 2), lambda t, s: 800, period=0.01)
        await eventually(lambda: two.stats.ticks >= 3, "three ticks")
        await lease.release(keys=["la:1"])
        assert one.done and not two.done
        ticks = two.stats.ticks
        await eventually(lambda: two.stats.ticks >= ticks + 3, "la:2 streams on")
        assert lease.keys == {"la:2"}
        await lease.release()
        assert two.done


async def test_a_stream_that_ends_leaves_its_actuators_in_the_lease() -> None:
    model = LAModel(1)
    async with sim_bus([model], pacing="prompt") as (bus, _sim):
        frames = written(bus)
        async with bus.lease(["la:1"], owner="app") as lease:
            stream = Streamer(bus).follow(InspireLA(bus, 1), [[500]] * 3, period=0.01)
            await asyncio.wait_for(stream.wait(), 5)
            assert lease.keys == {"la:1"}  # still the lease's
            assert PAUSE[1] not in frames  # the stream's own end: "hold", by default
            await InspireLA(bus, 1).move_to(600)  # the lease's holder moves on
        assert frames[-1] == PAUSE[1]  # the lease's end pays the pause it owes


async def test_an_actuator_the_lease_does_not_hold_is_refused_with_nothing_sent() -> None:
    async with sim_bus([LAModel(1), LAModel(3)], pacing="prompt") as (bus, _sim):
        frames = written(bus)
        async with bus.lease(["la:1"], owner="app"):
            with pytest.raises(LocalProtocolError, match="la:3 not held by 'app'") as refused:
                Streamer(bus).follow(
                    [InspireLA(bus, 1), InspireLA(bus, 3)], lambda t, s: [1, 2], period=0.01
                )
            assert refused.value.field == "lease"
            await asyncio.sleep(0.03)
            assert frames == []
            # The refused follow freed its place: la:1 streams under the lease now.
            stream = Streamer(bus).follow(InspireLA(bus, 1), lambda t, s: 5, period=0.01)
            await eventually(lambda: stream.stats.ticks >= 2, "two ticks")


async def test_streams_of_the_streamer_s_own_lease_and_of_a_task_s_lease_run_side_by_side() -> None:
    models = [LAModel(1), LAModel(2)]
    async with sim_bus(models, pacing="prompt") as (bus, _sim):
        streamer = Streamer(bus)
        own = streamer.follow(InspireLA(bus, 2), lambda t, s: 400, period=0.01, safe_action="pause")
        async with bus.lease(["la:1"], owner="app"):
            under = streamer.follow(InspireLA(bus, 1), lambda t, s: 300, period=0.01)
            await eventually(lambda: own.stats.ticks >= 3 and under.stats.ticks >= 3, "both stream")
            owners = {info.key: info.owner for info in bus.leases}
            assert owners["la:1"] == "app" and owners["la:2"].startswith("stream on")
        assert under.done and not own.done
        assert models[0].power_state is PowerState.PAUSED
        # The streamer's close ends what is left, with its safe action.
        await streamer.close()
        assert own.done and models[1].power_state is PowerState.PAUSED


async def test_closing_the_streamer_stops_its_streams_under_a_lease() -> None:
    model = LAModel(1)
    async with sim_bus([model], pacing="prompt") as (bus, _sim):
        frames = written(bus)
        async with bus.lease(["la:1"], owner="app"):
            streamer = Streamer(bus)
            stream = streamer.follow(
                InspireLA(bus, 1), lambda t, s: 300, period=0.01, safe_action="pause"
            )
            await eventually(lambda: stream.stats.ticks >= 2, "two ticks")
            await streamer.close()
            assert stream.done
            assert frames[-1] == PAUSE[1]  # the stream's safe action
            count = len(frames)
            await asyncio.sleep(0.05)
            assert frames[count:] == []


async def test_a_lease_s_end_takes_its_streamer_off_the_bus() -> None:
    # A program that takes a lease and streams under it again and again leaves nothing
    # behind on the bus: no reservation source, no close hook per ended lease.
    async with sim_bus([LAModel(1)], pacing="prompt") as (bus, _sim):
        streamer = Streamer(bus)
        sources = bus._core.schedule.reservation_sources
        baseline = len(sources)
        for _ in range(5):
            async with bus.lease(["la:1"], owner="app"):
                stream = streamer.follow(InspireLA(bus, 1), lambda t, s: 300, period=0.01)
                await eventually(lambda st=stream: st.stats.ticks >= 1, "a tick")
                assert len(sources) == baseline + 1
            assert len(sources) == baseline
        assert len(streamer._under) <= 1
