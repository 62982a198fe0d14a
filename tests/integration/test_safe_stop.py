"""Ctrl-C (or an exception) during a stream stops every actuator before the port closes.

``examples/safe_stream.py`` runs in a child process against a simulator process that
logs every frame.  After SIGINT the log must show, for each actuator, the safe action
(CMD_MC pause ``55 AA 03 ID 04 00 14 CS`` or e-stop ``... 23 CS``, LA manual 3.5.4)
received after the last 0xF3 broadcast: a follow target sent after a pause would resume
the actuator.  The example ends a Ctrl-C with "stopped safely" and status 0 (not 130):
the interrupt was handled, and the safe stop is the program's normal way out.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from motorbus.protocol import la
from motorbus.sim.process import SimProcess
from tests.integration.conftest import SIM_BAUD, SIM_DEVICES, is_broadcast_follow, received_frames

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "safe_stream.py"
IDS = (1, 2, 3)
#: Longest wait for the child to start streaming, and to exit after the signal.
START_TIMEOUT_S = 20.0
EXIT_TIMEOUT_S = 10.0


def _default_sigint() -> None:
    # A child started from a background job inherits SIGINT ignored, and Python then
    # installs no KeyboardInterrupt handler; the test needs Ctrl-C's real behaviour.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_example(port: str, *extra: str) -> subprocess.Popen[str]:
    """Run the example on ``port`` for IDs 1-3 and wait until it prints "streaming"."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    args = [sys.executable, str(EXAMPLE), "--port", port, "--baud", str(SIM_BAUD), "--ids", "1-3"]
    proc = subprocess.Popen(
        [*args, *extra],
        cwd=EXAMPLE.parent,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_sigint,
        start_new_session=True,  # our signal goes to the child alone
    )
    assert proc.stdout is not None
    lines = []
    for line in proc.stdout:  # ends at EOF if the child dies before streaming
        lines.append(line)
        if line.strip() == "streaming":
            return proc
    proc.wait(EXIT_TIMEOUT_S)
    err = proc.stderr.read() if proc.stderr else ""
    pytest.fail(f"the example exited ({proc.returncode}) before streaming: {lines} {err}")


def finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    """Wait (bounded) for the child to exit; return its status and the rest of its output."""
    try:
        out, err = proc.communicate(timeout=EXIT_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"the example did not exit within {EXIT_TIMEOUT_S} s: {out} {err}")
    return proc.returncode, out, err


def assert_safe_action_after_last_broadcast(frames: list[bytes], sub: la.ControlAction) -> None:
    """Each actuator's CMD_MC ``sub`` frame arrived after the last 0xF3 broadcast."""
    broadcasts = [i for i, f in enumerate(frames) if is_broadcast_follow(f)]
    assert broadcasts, "the stream sent no broadcast follow frame"
    last_broadcast = broadcasts[-1]
    later = frames[last_broadcast + 1 :]
    for ident in IDS:
        expected = la.Control(ident, sub).encode()
        assert expected[:7] == bytes([0x55, 0xAA, 0x03, ident, 0x04, 0x00, int(sub)])
        assert expected in later, f"no {sub.name} frame for la:{ident} after the last 0xF3"


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
