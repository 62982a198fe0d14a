"""README's set-up commands must stay true: CI runs exactly the test command."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def setup_commands() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    first_block = re.search(r"```(?:sh|bash|console)?\n(.*?)```", text, re.S)
    assert first_block, "README must start with a code block holding the set-up commands"
    return [ln.strip() for ln in first_block.group(1).splitlines() if ln.strip() and ln[0] != "#"]


def test_readme_starts_with_demo_and_test_commands() -> None:
    commands = setup_commands()
    assert len(commands) == 2
    assert "motorbus demo" in commands[0]
    assert "pytest" in commands[1]


def test_ci_runs_exactly_the_readme_test_command() -> None:
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert setup_commands()[1] in ci.splitlines()
