"""Each device example in examples/ against a ``motorbus sim`` child on a real pty, wire and prompt.

``tests/test_examples.py`` runs the examples with their built-in (wire-paced) simulator;
here each one is pointed with ``--port`` at a simulator process we start ourselves, once
emulating wire time and once answering at once (``--pacing prompt``, as a USB-CDC
device or a TCP bridge would).  A reply that comes sooner than the wire allows must be
taken like any other.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from motorbus.sim.bus import Pacing
from motorbus.sim.process import SimProcess
from tests.helpers import PACINGS, stream_rows

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"

#: example -> (simulated devices, baud, extra arguments, text its output must contain)
CASES: dict[str, tuple[list[str], int, list[str], str]] = {
    "la_basics.py": (["la:1"], 921600, [], "over-current limit 1000 mA"),
    "stream_sine.py": (["la:1-15"], 921600, ["--seconds", "1"], "100 ticks"),  # sent or skipped
    "project_stepper.py": (["project-stepper"], 9600, [], "project finished (EE DD)"),
    "quad_stepper.py": (["quad-stepper"], 9600, [], "motor 1 done"),
}


@pytest.mark.parametrize("pacing", PACINGS)
@pytest.mark.parametrize("name", sorted(CASES))
def test_example_against_a_sim_process(name: str, pacing: Pacing) -> None:
    devices, baud, extra, expected = CASES[name]
    # Tests assert behaviour, not speed: a loaded CI machine gets a 50 ms host margin.
    env = {**os.environ, "MOTORBUS_HOST_MARGIN_MS": "50"}
    with SimProcess(devices, baud=baud, pacing=pacing) as sim:
        out = subprocess.run(
            [sys.executable, str(EXAMPLES / name), "--port", sim.path, *extra],
            cwd=EXAMPLES,
            env=env,
            capture_output=True,
            text=True,
            timeout=120,
        )
        summary = sim.stop()
    assert out.returncode == 0, out.stderr[-3000:]
    assert "no --port given" not in out.stdout  # it used our simulator, not its own
    if name == "stream_sine.py":
        assert stream_rows(out.stdout) == int(expected.split()[0]), out.stdout[-2000:]
    else:
        assert expected in out.stdout, out.stdout[-2000:]
    for timeouts in re.findall(r"(\d+) timeouts", out.stdout):
        assert timeouts == "0", out.stdout[-2000:]
    # The simulator answered, and the bus never talked over a transmitting device.
    requests, replies = map(int, re.findall(r"(\d+) requests, (\d+) replies", summary)[0])
    assert requests > 0 and replies > 0, summary
    assert "0 missed while transmitting" in summary, summary
