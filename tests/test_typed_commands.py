"""``Command[R]``: ``Bus.request`` returns the command's reply type (checked by mypy)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SNIPPET = ROOT / "tests" / "typing" / "typed_commands.py"


@pytest.mark.timeout(600)
def test_request_is_typed_by_its_command() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "mypy", "--strict", "--no-error-summary", str(SNIPPET)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    lines = [line for line in out.stdout.splitlines() if ": error:" in line]
    expected = [
        n for n, text in enumerate(SNIPPET.read_text().splitlines(), 1) if "EXPECT-ERROR" in text
    ]
    flagged = sorted({int(line.split(":")[1]) for line in lines})
    assert flagged == expected, out.stdout + out.stderr
