"""Lint and type checks run with the tests, so CI and README's test command cover them; and
the rules that keep the code and the suite lean (module size, cheap collection)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run(*cmd: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)


@pytest.mark.timeout(600)  # a cold run on a loaded 2-core machine
def test_ruff_is_clean() -> None:
    # ruff of this interpreter, so the test runs (never skips) without an activated venv
    out = run(sys.executable, "-m", "ruff", "check", "src", "tests", "benchmarks", "examples")
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.mark.timeout(600)
def test_mypy_strict_is_clean_on_src() -> None:
    out = run(sys.executable, "-m", "mypy")
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-2000:]


#: h11 keeps each module under this; a module that grows past it holds two concerns.
MODULE_LINES_MAX = 700


def test_no_module_in_src_is_over_700_lines() -> None:
    long = {
        str(p.relative_to(ROOT)): n
        for p in sorted((ROOT / "src").rglob("*.py"))
        if (n := len(p.read_text(encoding="utf-8").splitlines())) > MODULE_LINES_MAX
    }
    assert not long, f"split these modules by concern (lines): {long}"


#: Imported by no test module at its top level: every process that collects the suite
#: (the six workers here, and the two that warm the bytecode first) would pay for them,
#: whether it runs the test or not (matplotlib was 0.4 s of each collection).
HEAVY_AT_COLLECTION = ("matplotlib", "report_plots")


def test_no_test_module_imports_a_heavy_module_at_its_top_level() -> None:
    found = []
    for path in sorted((ROOT / "tests").rglob("*.py")):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names = [node.module]
            else:
                continue
            found += [
                f"{path.relative_to(ROOT)}:{node.lineno} {name}"
                for name in names
                if name.split(".")[0] in HEAVY_AT_COLLECTION
            ]
    assert not found, f"import these inside the tests that use them: {found}"
