"""Ctrl-C (or an exception) during a stream stops every actuator before the port closes.

``examples/safe_stream.py`` runs in a child process against a simulator process that
logs every frame.  After SIGINT the log must show, for each actuator, the safe action
(CMD_MC pause ``55 AA 03 ID 04 00 14 CS`` or e-stop ``... 23 CS``, LA manual 3.5.4)
received after the last 0xF3 broadcast: a follow target sent after a pause would resume
the actuator.  The example ends a Ctrl-C with "stopped safely" and status 0 (not 130):
the interrupt was handled, and the safe stop is the program's normal way out.
"""

from __future__ import annotations

import signal
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
    assert status == 0, err
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
