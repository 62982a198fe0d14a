"""Blocking streams: targets set from the calling thread go out on the stream's ticks,
and however the stream ends its safe action follows its last target."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

import motorbus
import motorbus.blocking as mb
from motorbus.sim.process import SimProcess
from tests.blocking.frames import (
    BAUD,
    HOST_MARGIN_S,
    assert_paused_after,
    broadcast_targets,
    is_broadcast_follow,
    received,
)

IDS = [1, 2, 3]
#: Longest the test waits for the stream to send what was set (a bound, not a speed).
SEEN_TIMEOUT_S = 10.0


def open_bus(port: str) -> mb.Bus:
    transport = motorbus.open_transport(port, baudrate=BAUD)
    return mb.Bus(transport, families=[motorbus.Family.LA], host_margin=HOST_MARGIN_S)


def seen(sim: SimProcess, wanted: dict[int, int]) -> bool:
    return any(is_broadcast_follow(f) and broadcast_targets(f) == wanted for f in received(sim))


def eventually(condition: object, what: str) -> None:
    stop = threading.Event()
    timer = threading.Timer(SEEN_TIMEOUT_S, stop.set)
    timer.start()
    try:
        while not stop.wait(0.01):
            if condition():  # type: ignore[operator]
                return
        raise AssertionError(f"waited {SEEN_TIMEOUT_S:g} s for {what}; it never happened")
    finally:
        timer.cancel()


def test_targets_set_from_the_calling_thread_are_streamed_then_paused(tmp_path: Path) -> None:
    with SimProcess(["la:1-3"], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        with open_bus(sim.path) as bus:
            actuators = [bus.la(i) for i in IDS]
            for a in actuators:
                a.enable()
            setpoint = mb.Setpoint([500, 600, 700])
            with bus.streamer().follow(
                actuators, setpoint, period=0.02, safe_action="pause"
            ) as stream:
                eventually(lambda: seen(sim, {1: 500, 2: 600, 3: 700}), "the first targets")
                setpoint.set({2: 900})  # a mapping names some of them
                eventually(lambda: seen(sim, {1: 500, 2: 900, 3: 700}), "the second targets")
                setpoint.set([800, 900, 1000])
                eventually(lambda: seen(sim, {1: 800, 2: 900, 3: 1000}), "the third targets")
                assert stream.last_targets == {1: 800, 2: 900, 3: 1000}
                assert not stream.done
            assert stream.done
        frames = received(sim)
    broadcasts = [i for i, f in enumerate(frames) if is_broadcast_follow(f)]
    # The targets went out in the order they were set, and the pause came after.
    order = [broadcast_targets(frames[i]) for i in broadcasts]
    firsts = [order.index(t) for t in ({1: 500, 2: 600, 3: 700}, {1: 500, 2: 900, 3: 700})]
    assert firsts == sorted(firsts)
    assert order[-1] == {1: 800, 2: 900, 3: 1000}
    assert_paused_after(frames, broadcasts[-1], IDS)


def test_a_bad_target_is_refused_when_set_and_the_stream_keeps_its_own(tmp_path: Path) -> None:
    with SimProcess(["la:1-3"], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        with open_bus(sim.path) as bus:
            actuators = [bus.la(i) for i in IDS]
            with pytest.raises(motorbus.LocalProtocolError):
                bus.streamer().follow(actuators, mb.Setpoint([500, 600]), period=0.02)
            setpoint = mb.Setpoint([500, 600, 700])
            with bus.streamer().follow(actuators, setpoint, period=0.02, safe_action="pause"):
                eventually(lambda: seen(sim, {1: 500, 2: 600, 3: 700}), "the targets")
                with pytest.raises(motorbus.LocalProtocolError) as err:
                    setpoint.set([500, 600, 2500])
                assert err.value.field is not None and "targets" in err.value.field
                with pytest.raises(motorbus.LocalProtocolError):
                    setpoint.set({7: 100})  # not an actuator of this stream
                assert setpoint.targets == {1: 500, 2: 600, 3: 700}
                count = len(received(sim))
                eventually(lambda: len(received(sim)) > count + 2, "more ticks")
        frames = received(sim)
    sent = [broadcast_targets(f) for f in frames if is_broadcast_follow(f)]
    assert sent and all(t == {1: 500, 2: 600, 3: 700} for t in sent)


def test_ending_the_setpoint_ends_the_stream_with_its_safe_action(tmp_path: Path) -> None:
    with SimProcess(["la:1-3"], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        bus = open_bus(sim.path)
        setpoint = mb.Setpoint(1000)
        stream = bus.streamer().follow(bus.la(2), setpoint, period=0.02, safe_action="pause")
        eventually(lambda: seen(sim, {2: 1000}), "the target")
        setpoint.end()
        stream.wait()  # returns once the stream ended by itself
        assert stream.done and stream.error is None
        with pytest.raises(motorbus.LocalProtocolError, match="ended"):
            setpoint.set(900)
        frames = received(sim)  # before the bus's close
        bus.close()
    broadcasts = [i for i, f in enumerate(frames) if is_broadcast_follow(f)]
    assert_paused_after(frames, broadcasts[-1], [2])
