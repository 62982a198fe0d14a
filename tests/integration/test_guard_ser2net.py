"""The guard behind ser2net: a program streaming over ``socket://`` is SIGKILLed, and the
guard reaches the devices through the same ser2net and pauses them (issue 19).

A killed program's TCP connection closes with it; the guard then opens its own
connection to the same accepter and writes the safe frames.  The simulator behind
ser2net records what arrived: after the last motion frame, every actuator's pause.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

from motorbus.protocol import la
from tests.integration.conftest import IDS, Ser2netServer

ROOT = Path(__file__).resolve().parents[2]
VICTIM = ROOT / "benchmarks" / "guard_victim.py"
#: Longest wait for the victim to stream, to exit, and for the pauses to arrive.
WAIT_S = 20.0
PAUSES = {la.Control(i, la.ControlAction.PAUSE).encode().hex(" ").upper() for i in IDS}


def requests(server: Ser2netServer) -> list[str]:
    return [r["hex"] for r in server.sim.log_records() if r["direction"] == "request"]


def is_motion(hex_: str) -> bool:
    """An LA follow-mode target broadcast (0xF3) or a single-ID position command."""
    return hex_.startswith("55 AA") and hex_.split()[4] in ("F3", "F2", "21")


def test_sigkill_behind_ser2net_the_guard_pauses_every_actuator(
    ser2net_server: Ser2netServer,
) -> None:
    ids = f"{min(IDS)}-{max(IDS)}"
    proc = subprocess.Popen(
        [sys.executable, str(VICTIM), "--port", ser2net_server.raw_url, "--ids", ids, "--guard"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()  # "streaming" once the bus sends targets
        assert line == "streaming\n", proc.communicate(timeout=WAIT_S)
        time.sleep(0.2)  # let the stream run; any moment would do
        proc.send_signal(signal.SIGKILL)
        _, err = proc.communicate(timeout=WAIT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    deadline = time.monotonic() + WAIT_S
    while not set(requests(ser2net_server)) >= PAUSES:
        assert time.monotonic() < deadline, (err, requests(ser2net_server)[-6:])
        time.sleep(0.02)  # polling the simulator's log
    sent = requests(ser2net_server)
    last_motion = max(n for n, h in enumerate(sent) if is_motion(h))
    assert set(sent[last_motion + 1 :]) == PAUSES, sent[-6:]
    assert "motorbus guard: program " in err and ser2net_server.raw_url in err, err
