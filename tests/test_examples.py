"""Every example runs against the simulators (README's and docs/' blocks: tests/test_docs.py)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import stream_rows

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"

EXPECTED = {
    "la_basics.py": "over-current limit 1000 mA",
    "stream_sine.py": "300 ticks",
    "project_stepper.py": "project finished (EE DD)",
    "quad_stepper.py": "motor 1 done",
    "many_buses.py": "left-arm: 51 ticks (sent or skipped)",
}


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_example_runs_against_the_simulator(name: str) -> None:
    # Tests assert behaviour, not speed: on a loaded CI machine a simulator process can
    # miss the default 2 ms host margin, so the examples get 50 ms here.
    env = {**os.environ, "MOTORBUS_HOST_MARGIN_MS": "50"}
    out = subprocess.run(
        [sys.executable, str(EXAMPLES / name)],
        cwd=EXAMPLES,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    if name == "stream_sine.py":
        # Every row is a tick sent, or one a loaded machine skipped (a tick that started
        # more than a period late), and the stream's summary counts both.
        rows = int(EXPECTED[name].split()[0])
        assert stream_rows(out.stdout) == rows, out.stdout
    elif name == "many_buses.py":
        # 51 ticks at 20 ms, each sent or skipped (a loaded machine skips a late one).
        m = re.search(r"^left-arm: (\d+) ticks, (\d+) skipped", out.stdout, re.M)
        assert m and int(m[1]) + int(m[2]) == 51, out.stdout
    else:
        assert EXPECTED[name] in out.stdout
