"""Every way a program can end stops every streamed actuator after its last target.

Each case runs a real program in a child process against a simulator process that
logs every frame it receives, ends the program one way, and checks from the
simulator's record that each actuator got its safe action (pause or e-stop) after the
last 0xF3 broadcast: a follow target after a pause would resume the actuator.

Two kinds of program:

* ``examples/safe_stream.py``: a ``BusManager`` under ``motorbus.run`` (the helper an
  application installs in one line): SIGINT once, twice 3 ms apart, three times,
  SIGTERM and SIGHUP all end with the safe stop, "stopped safely" and status 0.
* a plain ``Bus`` + ``Streamer`` program under a bare ``asyncio.run``, which installs
  nothing: SIGINT (once, and twice 3 ms apart) and SIGTERM still stop the stream safely
  (the bus's close hook, and motorbus's own SIGTERM guard while a bus is open).
"""

from __future__ import annotations

import signal
import textwrap
import time
from pathlib import Path

import pytest

from motorbus.protocol import la
from motorbus.sim.process import SimProcess
from tests.integration.conftest import (
    SIM_BAUD,
    SIM_DEVICES,
    assert_safe_action_after_last_broadcast,
    finish,
    received_frames,
    start_example,
)

PLAIN_PROGRAM = textwrap.dedent(
    """
    import argparse, asyncio, math
    import motorbus

    async def main(port: str) -> None:
        transport = motorbus.open_transport(port, baudrate=921600)
        async with motorbus.Bus(transport, families=[motorbus.Family.LA]) as bus:
            actuators = [motorbus.InspireLA(bus, i) for i in (1, 2, 3)]
            for a in actuators:
                await a.enable()
            started = asyncio.Event()

            def targets(t, statuses):
                if t > 0:
                    started.set()
                return [1000 + 300 * math.sin(t + i) for i in range(3)]

            stream = motorbus.Streamer(bus).follow(
                actuators, targets, period=0.01, safe_action="pause"
            )
            await started.wait()
            print("streaming", flush=True)
            await stream.wait()  # not inside "async with": nothing but motorbus stops it

    p = argparse.ArgumentParser()
    p.add_argument("--port")
    p.add_argument("--baud")
    p.add_argument("--ids")
    asyncio.run(main(p.parse_args().port))
    """
)


def send(proc_pid_signal: tuple[object, signal.Signals], times: int, gap_s: float) -> None:
    proc, sig = proc_pid_signal
    for k in range(times):
        if k:
            time.sleep(gap_s)
        proc.send_signal(sig)  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("sig", "times", "gap_s"),
    [
        (signal.SIGINT, 2, 0.003),
        (signal.SIGINT, 3, 0.001),
        (signal.SIGTERM, 1, 0.0),
        (signal.SIGHUP, 1, 0.0),
        (signal.SIGTERM, 2, 0.003),
    ],
    ids=["sigint-twice-3ms", "sigint-three-times", "sigterm", "sighup", "sigterm-twice"],
)
def test_bus_manager_program_stops_safely(
    tmp_path: Path, sig: signal.Signals, times: int, gap_s: float
) -> None:
    with SimProcess(SIM_DEVICES, baud=SIM_BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        proc = start_example(sim.path, "--safe-action", "pause")
        send((proc, sig), times, gap_s)
        status, out, err = finish(proc)
    assert status == 0, (out, err)
    assert "stopped safely" in out
    assert "Traceback" not in err
    assert_safe_action_after_last_broadcast(
        received_frames(sim.log_records()), la.ControlAction.PAUSE
    )


@pytest.mark.parametrize(
    ("sig", "times", "gap_s"),
    [(signal.SIGINT, 1, 0.0), (signal.SIGINT, 2, 0.003), (signal.SIGTERM, 1, 0.0)],
    ids=["sigint", "sigint-twice-3ms", "sigterm"],
)
def test_plain_bus_and_streamer_program_stops_safely(
    tmp_path: Path, sig: signal.Signals, times: int, gap_s: float
) -> None:
    program = tmp_path / "plain_stream.py"
    program.write_text(PLAIN_PROGRAM, encoding="utf-8")
    with SimProcess(SIM_DEVICES, baud=SIM_BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        proc = start_example(sim.path, example=program)
        send((proc, sig), times, gap_s)
        status, _, err = finish(proc)
    # It ends as the signal says (KeyboardInterrupt, or killed by SIGTERM) - but only
    # after the stream's safe action went out.
    assert status != 0
    if sig == signal.SIGTERM:
        assert status == -signal.SIGTERM, err
    assert_safe_action_after_last_broadcast(
        received_frames(sim.log_records()), la.ControlAction.PAUSE
    )
