"""Ctrl-C, SIGTERM, an exception and the interpreter's exit stop blocking programs
safely: the simulator's record shows each actuator paused after its last motion.

In this process: a ``KeyboardInterrupt`` raised in the main thread (as Ctrl-C raises
it) while a blocking ``move_to(wait=True)`` or ``stream.wait()`` waits.  In child
processes: SIGINT and SIGTERM to a blocking script, a script that leaves a stream
running and simply ends (atexit), and one whose ``with`` block raises.
"""

from __future__ import annotations

import _thread
import os
import signal
import subprocess
import sys
import textwrap
import threading
from collections.abc import Callable
from pathlib import Path

import pytest

import motorbus
import motorbus.blocking as mb
from motorbus.protocol import la
from motorbus.sim.process import SimProcess
from tests.blocking.frames import (
    BAUD,
    HOST_MARGIN_S,
    assert_paused_after,
    is_broadcast_follow,
    received,
)

#: Longest wait for a condition, or for a child to start or exit (a bound, not a speed).
BOUND_S = 20.0


def when(condition: Callable[[], bool], then: Callable[[], None]) -> threading.Thread:
    """In a thread: wait (bounded) until ``condition()``, then call ``then()``."""

    def watch() -> None:
        stop = threading.Event()
        timer = threading.Timer(BOUND_S, stop.set)
        timer.start()
        while not stop.wait(0.005):
            if condition():
                break
        timer.cancel()
        then()  # also at the bound: the test then fails on what it finds, not by hanging

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    return thread


def test_ctrl_c_during_a_blocking_move_pauses_the_actuator_and_is_raised(tmp_path: Path) -> None:
    # stroke_speed=100 units/s: the move to 2000 takes 20 s, so the wait is still
    # waiting when the interrupt comes, however loaded the machine is.
    spec = "la:1,stroke_speed=100"
    move = la.MoveTo(1, 2000, True).encode()
    with SimProcess([spec], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        transport = motorbus.open_transport(sim.path, baudrate=BAUD)
        bus = mb.Bus(transport, families=[motorbus.Family.LA], host_margin=HOST_MARGIN_S)
        actuator = bus.la(1)
        actuator.enable()
        watcher = when(lambda: move in received(sim), _thread.interrupt_main)
        with pytest.raises(KeyboardInterrupt):
            actuator.move_to(2000, wait=True, timeout=60)
        watcher.join(BOUND_S)
        assert bus.closed  # every bus on the loop was closed safely before the re-raise
        frames = received(sim)
    assert move in frames
    assert_paused_after(frames, frames.index(move), [1])
    last = [f for f in frames if f[3:5] == bytes([1, la.CMD_CONTROL])][-1]
    assert last == la.Control(1, la.ControlAction.PAUSE).encode()


def test_ctrl_c_during_a_blocking_stream_wait_pauses_the_stream(tmp_path: Path) -> None:
    with SimProcess(["la:1-3"], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        transport = motorbus.open_transport(sim.path, baudrate=BAUD)
        bus = mb.Bus(transport, families=[motorbus.Family.LA], host_margin=HOST_MARGIN_S)
        actuators = [bus.la(i) for i in (1, 2, 3)]
        stream = bus.streamer().follow(
            actuators, mb.Setpoint([900, 1000, 1100]), period=0.02, safe_action="pause"
        )

        def streaming() -> bool:
            return sum(is_broadcast_follow(f) for f in received(sim)) >= 3

        watcher = when(streaming, _thread.interrupt_main)
        with pytest.raises(KeyboardInterrupt):
            stream.wait()  # the stream never ends by itself
        watcher.join(BOUND_S)
        assert stream.done and bus.closed
        frames = received(sim)
    broadcasts = [i for i, f in enumerate(frames) if is_broadcast_follow(f)]
    assert_paused_after(frames, broadcasts[-1], [1, 2, 3])


# -- child processes ----------------------------------------------------------------

STREAMING_SCRIPT = textwrap.dedent(
    """
    import sys, time
    import motorbus
    import motorbus.blocking as mb

    port, how = sys.argv[1], sys.argv[2]
    HOST_MARGIN_S = 0.25  # as tests/blocking/frames.py's (this program runs alone)
    transport = motorbus.open_transport(port, baudrate=921600)

    def start(bus):
        actuators = [bus.la(i) for i in (1, 2, 3)]
        setpoint = mb.Setpoint([900, 1000, 1100])
        stream = bus.streamer().follow(actuators, setpoint, period=0.02, safe_action="pause")
        for _ in range(1000):  # until a target went out (bounded)
            if stream.stats.frames >= 3:
                break
            time.sleep(0.01)
        print("streaming", flush=True)
        return stream, setpoint

    if how == "wait":  # no with block: the blocking call's own Ctrl-C handling
        bus = mb.Bus(transport, families=[motorbus.Family.LA], host_margin=HOST_MARGIN_S)
        stream, _ = start(bus)
        stream.wait()
    elif how == "loop":  # a control loop of the LeRobot kind, in a with block
        with mb.Bus(transport, families=[motorbus.Family.LA], host_margin=HOST_MARGIN_S) as bus:
            stream, setpoint = start(bus)
            k = 0
            while True:
                k += 1
                setpoint.set([900 + k % 100, 1000, 1100])
                time.sleep(0.01)
    elif how == "exit":  # the program just ends, the stream still running: atexit
        bus = mb.Bus(transport, families=[motorbus.Family.LA], host_margin=HOST_MARGIN_S)
        start(bus)
    elif how == "raise":
        with mb.Bus(transport, families=[motorbus.Family.LA], host_margin=HOST_MARGIN_S) as bus:
            start(bus)
            raise RuntimeError("the program failed")
    """
)


def default_signals() -> None:
    # A child started from a background job inherits SIGINT ignored: give it the default.
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)


def run_child(
    tmp_path: Path, how: str, sig: signal.Signals | None
) -> tuple[int, str, str, list[bytes]]:
    script = tmp_path / "blocking_program.py"
    script.write_text(STREAMING_SCRIPT, encoding="utf-8")
    with SimProcess(["la:1-3"], baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        proc = subprocess.Popen(
            [sys.executable, str(script), sim.path, how],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            preexec_fn=default_signals,
            start_new_session=True,
        )
        assert proc.stdout is not None
        first = proc.stdout.readline()
        if sig is not None and first.strip() == "streaming":
            proc.send_signal(sig)
        try:
            out, err = proc.communicate(timeout=BOUND_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
            pytest.fail(f"the program did not end: {out} {err}")
        frames = received(sim)
    assert first.strip() == "streaming", (first, out, err)
    return proc.returncode, first + out, err, frames


def assert_stream_paused(frames: list[bytes]) -> None:
    broadcasts = [i for i, f in enumerate(frames) if is_broadcast_follow(f)]
    assert broadcasts, "the stream sent nothing"
    assert_paused_after(frames, broadcasts[-1], [1, 2, 3])


@pytest.mark.parametrize("how", ["wait", "loop"])
def test_sigint_to_a_blocking_script_pauses_the_stream(tmp_path: Path, how: str) -> None:
    status, _, err, frames = run_child(tmp_path, how, signal.SIGINT)
    assert "KeyboardInterrupt" in err  # raised again once the motion was stopped
    assert status != 0
    assert_stream_paused(frames)


def test_sigterm_to_a_blocking_script_pauses_the_stream(tmp_path: Path) -> None:
    status, _, err, frames = run_child(tmp_path, "loop", signal.SIGTERM)
    assert status == -signal.SIGTERM, err  # ended as SIGTERM would, after the stop
    assert "stopping the motion safely" in err
    assert_stream_paused(frames)


def test_a_script_that_just_ends_pauses_its_stream_at_exit(tmp_path: Path) -> None:
    status, _, err, frames = run_child(tmp_path, "exit", None)
    assert status == 0, err
    assert_stream_paused(frames)


def test_an_exception_in_the_with_block_pauses_the_stream(tmp_path: Path) -> None:
    status, _, err, frames = run_child(tmp_path, "raise", None)
    assert status == 1 and "the program failed" in err
    assert_stream_paused(frames)
