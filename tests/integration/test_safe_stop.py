"""Ctrl-C (or an exception) during a stream stops every actuator before the port closes.

``examples/safe_stream.py`` runs in a child process against a simulator process that
logs every frame.  After SIGINT the log must show, for each actuator, the safe action
(CMD_MC pause ``55 AA 03 ID 04 00 14 CS`` or e-stop ``... 23 CS``, LA manual 3.5.4)
received after the last 0xF3 broadcast: a follow target sent after a pause would resume
the actuator.  The example ends a Ctrl-C with "stopped safely" and status 130, as the
command line does (docs/cli.md): the safe stop ran, and the caller learns that the
program was interrupted rather than finished.
"""

from __future__ import annotations

import asyncio
import signal
from pathlib import Path

import pytest

from motorbus.bus.bus import Bus
from motorbus.devices.la import InspireLA
from motorbus.protocol import la
from motorbus.protocol.base import Family
from motorbus.sim.process import SimProcess
from motorbus.streams import Streamer
from motorbus.transport.serial import open_transport
from tests.integration.conftest import (
    SIM_BAUD,
    SIM_DEVICES,
    assert_safe_action_after_last_broadcast,
    finish,
    received_frames,
    start_example,
)


@pytest.mark.parametrize(
    ("action", "sub"), [("pause", la.ControlAction.PAUSE), ("estop", la.ControlAction.ESTOP)]
)
def test_sigint_stops_every_actuator_safely(
    tmp_path: Path, action: str, sub: la.ControlAction
) -> None:
    with SimProcess(SIM_DEVICES, baud=SIM_BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        proc = start_example(sim.path, "--safe-action", action)
        proc.send_signal(signal.SIGINT)
        status, out, err = finish(proc)
    assert status == 130, err
    assert "interrupted (status 130)" in out
    assert "stopped safely" in out
    assert "Traceback" not in err
    assert_safe_action_after_last_broadcast(received_frames(sim.log_records()), sub)


def test_exception_in_user_code_still_stops_safely_and_propagates(tmp_path: Path) -> None:
    with SimProcess(SIM_DEVICES, baud=SIM_BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        proc = start_example(sim.path, "--fail-after", "0.3")
        status, out, err = finish(proc)
    assert status == 1
    assert "Traceback" in err
    assert "RuntimeError: your code failed 0.3 s into the stream" in err
    assert "stopped safely" not in out
    assert_safe_action_after_last_broadcast(
        received_frames(sim.log_records()), la.ControlAction.PAUSE
    )


async def test_a_silent_actuator_does_not_hold_up_the_other_pauses(tmp_path: Path) -> None:
    """la:1 is streamed but absent: its pause is never answered and is retried.  The
    simulator process (which has only la:2 and la:3) logs what it received: both their
    pauses came before la:1's retry, not after its attempts and late guards.  (A long
    guard: only a host stalled for all of it could let the retry go first.)"""
    with SimProcess(("la:2-3",), baud=SIM_BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        transport = open_transport(sim.path, baudrate=SIM_BAUD)
        bus = Bus(transport, families=[Family.LA], late_guard=0.5)
        async with bus:
            streamer = Streamer(bus)
            stream = streamer.follow(
                [InspireLA(bus, i) for i in (1, 2, 3)],
                lambda t, statuses: [1000, 1000, 1000],
                period=0.01,
                safe_action="pause",
            )
            await asyncio.sleep(0.1)
            await stream.stop()
            await streamer.close()
        records = sim.log_records()
    pause_of = {la.Control(i, la.ControlAction.PAUSE).encode(): i for i in (1, 2, 3)}
    pauses = [pause_of[f] for f in received_frames(records) if f in pause_of]
    assert pauses.count(1) >= 2, pauses  # la:1's pause was retried
    retry = pauses.index(1, pauses.index(1) + 1)
    assert {2, 3} <= set(pauses[:retry]), pauses
