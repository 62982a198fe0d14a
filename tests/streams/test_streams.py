"""Follow-mode streams against simulated actuators: targets, coalescing, budgets, safety."""

from __future__ import annotations

import asyncio
import gc
import itertools
import math

import pytest

from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.runtime import realtime
from motorbus.sim.bus import Pacing
from motorbus.sim.la import LAModel, PowerState
from motorbus.streams import SafeAction, StreamEnded, Streamer
from tests.fakeclock import rig
from tests.helpers import PACINGS, sim_bus
from tests.waiting import eventually


def trajectory(n: int, k: int, i: int) -> int:
    return round(1000 + 500 * math.sin(0.3 * k + i))


@pytest.mark.parametrize("pacing", PACINGS)
async def test_fifteen_actuators_one_broadcast_per_tick(pacing: Pacing) -> None:
    models = [LAModel(i) for i in range(1, 16)]
    ticks = 25
    rows = [[trajectory(15, k, i) for i in range(15)] for k in range(ticks)]
    async with rig(models=models, pacing=pacing) as r:  # fake time: no tick is skipped
        bus = r.bus
        actuators = [InspireLA(bus, i) for i in range(1, 16)]
        streamer = Streamer(bus)
        stream = streamer.follow(actuators, rows, period=0.01)
        await asyncio.wait_for(stream.wait(), 5)
        assert stream.stats.ticks == ticks
        assert bus.stats.no_reply_frames == ticks  # 15 targets, one 0xF3 frame a tick
        assert bus.stats.requests == ticks
        for i, model in enumerate(models):
            got = [target for _, cmd, target in model.received if cmd == la.CMD_BROADCAST_FOLLOW]
            assert got == [row[i] for row in rows]
        await streamer.close()


@pytest.mark.parametrize("rows", [[700], [700, 800, 900]], ids=["one-row", "three-rows"])
async def test_ticks_skipped_past_the_end_of_the_rows_still_send_the_last_row(
    rows: list[int],
) -> None:
    # A first tick two periods late skips the rows of the ticks it missed (the skip
    # rule keeps a stream on its time grid).  A one-row stream once skipped its only
    # row and ended having sent nothing; the last row is where the trajectory ends, so
    # it goes out, once.
    model = LAModel(1)
    async with rig(models=[model]) as r:
        streamer = Streamer(r.bus)
        stream = streamer.follow(InspireLA(r.bus, 1), rows, period=0.01)
        r.timer.advance(0.035)  # fake time: the first tick's deadline passes unserved
        await asyncio.wait_for(stream.wait(), 5)
        assert [t for _, _, t in model.received] == [rows[-1]]
        assert (stream.stats.ticks, stream.stats.skipped) == (1, 2)
        await streamer.close()


@pytest.mark.parametrize("gc_controlled", [False, True], ids=["plain", "realtime-gc"])
async def test_a_starting_stream_collects_the_young_generations_first(
    gc_controlled: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The set-up's young objects would cost the collector's first pass mid-stream; the
    # start does that pass instead, once: a stream joining a running one does not.  Under
    # real-time mode's GC control too: its freeze at enable() leaves what the program set
    # up afterwards young, and a gen-1 pass of 1.2 ms over it was a late tick
    # (bench_late_ticks.py --realtime --hogs 2, 2026-12-04).
    monkeypatch.setattr(realtime._gc, "active", gc_controlled)
    assert realtime.gc_controlled() is gc_controlled
    collected: list[int] = []

    def note(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            collected.append(info["generation"])

    async with sim_bus([LAModel(1), LAModel(2)]) as (bus, _):
        streamer = Streamer(bus)
        was_enabled = gc.isenabled()
        gc.disable()  # only the collections asked for explicitly are seen
        gc.callbacks.append(note)
        try:
            first = streamer.follow([InspireLA(bus, 1)], [[1000]] * 50, period=0.01)
            started = list(collected)
            collected.clear()
            second = streamer.follow([InspireLA(bus, 2)], [[1000]] * 5, period=0.01)
        finally:
            gc.callbacks.remove(note)
            if was_enabled:
                gc.enable()
        assert started == [1]
        assert collected == []
        await asyncio.wait_for(asyncio.gather(first.wait(), second.wait()), 5)
        await streamer.close()


@pytest.mark.parametrize("pacing", PACINGS)
async def test_feedback_stream_decodes_every_status_and_callback_sees_them(pacing: Pacing) -> None:
    # On the fake clock (tests/fakeclock.py): the frame times below are the bus's own
    # behaviour, not the machine's speed.
    models = [LAModel(i) for i in (1, 2)]
    seen: list[int] = []

    def source(t: float, statuses: dict[int, la.Status]) -> list[int] | None:
        seen.append(len(statuses))
        return None if t >= 0.1 else [500 + round(t * 1000), 600]

    async with rig(models=models, pacing=pacing) as r:
        bus = r.bus
        streamer = Streamer(bus)
        stream = streamer.follow(
            [InspireLA(bus, 1), InspireLA(bus, 2)], source, period=0.01, feedback=True
        )
        await stream.wait()
        assert set(stream.statuses) == {1, 2}
        assert stream.statuses[2].target == 600
        assert seen[0] == 0 and seen[-1] == 2
        cmds = {cmd for _, cmd, _ in models[0].received}
        assert cmds == {la.CMD_FOLLOW}
        assert stream.stats.feedback_timeouts == 0
        # Each tick's 0x20 frames go out on the tick, not a period early: the model saw
        # one per actuator per tick, at the period apart.
        times = [t for t, cmd, _ in models[0].received if cmd == la.CMD_FOLLOW]
        gaps = [b - a for a, b in itertools.pairwise(times)]
        assert len(times) == stream.stats.ticks
        assert min(gaps) > 0.5 * 0.01  # never two ticks' frames back to back
        await streamer.close()


@pytest.mark.parametrize("pacing", PACINGS)
async def test_polling_uses_free_slots_round_robin(pacing: Pacing) -> None:
    models = [LAModel(i) for i in range(1, 16)]
    # Polls only start when even their timeout ends before the next tick: a margin that
    # leaves room for them in a 10 ms tick.
    async with sim_bus(models, host_margin=0.002, pacing=pacing) as (bus, _):
        streamer = Streamer(bus)
        actuators = [InspireLA(bus, i) for i in range(1, 16)]
        # 60 ticks: a few would do on a prompt machine; a loaded one (eight workers) skips
        # the polls of the ticks it starts late, and a late reply times out at 2 ms.
        stream = streamer.follow(actuators, [[1000] * 15] * 60, period=0.01, poll_status=True)
        await asyncio.wait_for(stream.wait(), 5)
        assert set(stream.statuses) == set(range(1, 16))  # every actuator read at least once
        assert stream.stats.polls >= 15
        await streamer.close()


@pytest.mark.parametrize("pacing", PACINGS)
async def test_infeasible_streams_are_refused_with_what_fits(pacing: Pacing) -> None:
    models = [LAModel(i) for i in range(1, 21)]
    async with sim_bus(models, pacing=pacing) as (bus, _):
        streamer = Streamer(bus)
        actuators = [InspireLA(bus, i) for i in range(1, 21)]
        with pytest.raises(LocalProtocolError, match="with feedback") as err:
            streamer.follow(actuators, [[1000] * 20], period=0.01, feedback=True)
        assert "broadcast" in str(err.value)
        assert bus.stats.requests == 0
        with pytest.raises(LocalProtocolError, match=r"period=0.005 s is out of range"):
            streamer.follow(actuators[:1], [1000], period=0.005)
        with pytest.raises(LocalProtocolError, match="safe_action"):
            streamer.follow(actuators[:1], [1000], period=0.01, safe_action="explode")
        await streamer.close()


@pytest.mark.parametrize("pacing", PACINGS)
async def test_bad_target_ends_the_stream_with_its_safe_action(pacing: Pacing) -> None:
    model = LAModel(1)
    async with sim_bus([model], pacing=pacing) as (bus, _):
        streamer = Streamer(bus)
        # An iterator: its items exist only at their ticks, so each is checked there (a
        # sequence is checked whole at follow: tests/test_bad_input.py).
        stream = streamer.follow(
            InspireLA(bus, 1), iter([1000, 1100, 2500, 1200]), period=0.01, safe_action="pause"
        )
        with pytest.raises(StreamEnded, match=r"targets?.*2500.*0\.\.2000|2500"):
            await asyncio.wait_for(stream.wait(), 5)
        # Every item before the bad one (an iterator skips none), nothing after it, and
        # the stream's safe action.
        assert [t for _, _, t in model.received] == [1000, 1100]
        assert stream.stats.ticks == 2
        assert model.power_state is PowerState.PAUSED
        await streamer.close()


@pytest.mark.parametrize("pacing", PACINGS)
async def test_cancelled_block_applies_estop(pacing: Pacing) -> None:
    model = LAModel(1)
    async with sim_bus([model], pacing=pacing) as (bus, _):
        streamer = Streamer(bus)

        async def run() -> None:
            async with streamer.follow(
                InspireLA(bus, 1), lambda t, s: 1000, period=0.01, safe_action=SafeAction.ESTOP
            ):
                await asyncio.sleep(10)

        task = asyncio.create_task(run())
        await eventually(lambda: len(model.received) >= 3, "3 targets at the model")
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        await InspireLA(bus, 1).move_to(200)
        assert model.target != 200  # e-stopped: moves need "work" first
        await streamer.close()


@pytest.mark.parametrize("pacing", PACINGS)
async def test_pause_resume_and_new_targets_on_the_fly(pacing: Pacing) -> None:
    model = LAModel(1)
    async with sim_bus([model], pacing=pacing) as (bus, _):
        streamer = Streamer(bus)
        stream = streamer.follow(InspireLA(bus, 1), lambda t, s: 700, period=0.01)
        await eventually(lambda: len(model.received) >= 2, "2 targets at the model")
        stream.pause()
        await asyncio.sleep(0.03)
        paused_count = len(model.received)
        await asyncio.sleep(0.03)
        assert len(model.received) == paused_count
        stream.set_targets([900, 901, 902])
        stream.resume()
        await asyncio.wait_for(stream.wait(), 5)
        targets = [t for _, _, t in model.received]
        new = targets[next(n for n, t in enumerate(targets) if t != 700) :]
        # The new rows in order, none of the old after them; a loaded machine may skip a
        # row's tick (seen: [900, 902]), but the last row always goes out.
        assert new == sorted(set(new)) and set(new) <= {900, 901, 902}, targets
        assert new[-1] == 902 and len(new) + stream.stats.skipped >= 3, targets
        await streamer.close()


def test_tick_timing_counts_missing_frames_not_rounding_artifacts() -> None:
    from motorbus.sim.analysis import tick_timing

    period = 0.01
    times = [k * period for k in range(100)]
    assert tick_timing(times, period).missed == 0
    assert tick_timing(times[:50] + times[51:], period).missed == 1
    jittery = list(times)
    jittery[50] += 0.0056  # late enough to round into its neighbour's slot
    assert tick_timing(jittery, period).missed == 0
    drifting = [k * period * 1.07 for k in range(100)]
    assert tick_timing(drifting, period, by_index=True).drift > 0.06


async def test_a_tick_frame_is_built_once_and_checked_once_at_its_deadline(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Issue 40: one path from deadline to wire.  A tick's frame is built when the tick
    is prepared and checked once at its deadline (``Bus.send_prepared``), which writes
    it on an idle bus: no fallback ``submit``, no third build at the write."""
    import motorbus.streams as streams_mod
    from motorbus.streaming import model

    builds: list[int] = []
    made = [0]
    real_builder = model.broadcast_builder
    real_prevalidated = la.Broadcast.prevalidated

    def counting_builder(chunk):  # type: ignore[no-untyped-def]
        build = real_builder(chunk)
        builds.append(0)
        index = len(builds) - 1

        def counted():  # type: ignore[no-untyped-def]
            builds[index] += 1
            return build()

        return counted

    def counting_prevalidated(*args, **kwargs):  # type: ignore[no-untyped-def]
        made[0] += 1
        return real_prevalidated(*args, **kwargs)

    monkeypatch.setattr(streams_mod, "broadcast_builder", counting_builder)
    monkeypatch.setattr(la.Broadcast, "prevalidated", counting_prevalidated)
    ticks = 10
    async with rig() as r:
        actuators = [InspireLA(r.bus, i) for i in range(1, 16)]
        streamer = Streamer(r.bus)
        stream = streamer.follow(actuators, [[1000 + k] * 15 for k in range(ticks)], period=0.01)
        await stream.wait()
        await streamer.close()
        assert stream.stats.ticks == ticks
        assert r.bus.stats.no_reply_frames == ticks
    assert builds == [2] * ticks  # built when prepared, checked once when sent
    assert made[0] == ticks  # one frame object a tick
