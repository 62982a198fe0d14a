"""Start-up of the command line: a command imports only what it needs (issue 23).

Behaviour, not timing: the modules a command loads, read from ``python -X importtime``
and from ``sys.modules`` at exit (``-X importtime`` leaves out the modules loaded by
``importlib.import_module``, as the command modules and the lazy ``motorbus`` names are).
benchmarks/bench_startup.py measures the seconds.
"""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

from motorbus.cli.main import COMMANDS, build_parser
from tests.helpers import CLI_TIMEOUT_S

#: What ``motorbus --version`` must never load: the event loop, the bus, the web server.
HEAVY = ("asyncio", "motorbus.bus", "aiohttp", "motorbus.dashboard")


def imported_modules(*args: str) -> list[str]:
    """The modules ``python -X importtime -m motorbus ARGS`` imports, in order."""
    out = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "motorbus", *args],
        capture_output=True,
        text=True,
        timeout=CLI_TIMEOUT_S,
    )
    assert out.returncode == 0, out.stderr
    return [
        line.rsplit("|", 1)[1].strip()
        for line in out.stderr.splitlines()
        if line.startswith("import time:") and not line.endswith("imported package")
    ]


#: Runs ``python -m motorbus ARGV`` and writes ``sys.modules`` at exit to the file OUT.
_AT_EXIT = """
import atexit, runpy, sys
out, sys.argv = sys.argv[1], ["motorbus", *sys.argv[2:]]
atexit.register(lambda: open(out, "w").write("\\n".join(sorted(sys.modules))))
runpy.run_module("motorbus", run_name="__main__", alter_sys=True)
"""


def modules_at_exit(tmp_path: Path, *args: str) -> list[str]:
    """Every module loaded by the end of ``python -m motorbus ARGS`` (exit code 0)."""
    out = tmp_path / "modules.txt"
    run = subprocess.run(
        [sys.executable, "-c", _AT_EXIT, str(out), *args],
        capture_output=True,
        text=True,
        timeout=CLI_TIMEOUT_S,
    )
    assert run.returncode == 0, run.stderr
    return out.read_text(encoding="utf-8").split()


def loaded(modules: list[str], name: str) -> bool:
    return any(m == name or m.startswith(name + ".") for m in modules)


def test_version_imports_neither_asyncio_nor_the_bus_nor_the_dashboard() -> None:
    modules = imported_modules("--version")
    assert "motorbus.cli.main" in modules  # the listing is read right
    assert [m for m in modules if any(loaded([m], h) for h in HEAVY)] == []


@pytest.mark.parametrize("args", [["--version"], ["--help"]])
def test_version_and_help_import_no_command_nor_the_bus(tmp_path: Path, args: list[str]) -> None:
    modules = modules_at_exit(tmp_path, *args)
    assert "motorbus.cli.main" in modules  # the listing is read right
    assert [m for m in modules if any(loaded([m], h) for h in HEAVY)] == []
    commands = [f"motorbus.cli.{name}" for name in COMMANDS]
    assert [m for m in modules if m in commands] == []


def test_la_status_imports_the_la_command_only(tmp_path: Path) -> None:
    modules = modules_at_exit(tmp_path, "la", "status", "--help")
    assert "motorbus.cli.la" in modules
    assert "motorbus.bus.bus" in modules
    others = [f"motorbus.cli.{name}" for name in COMMANDS if name != "la"]
    assert [m for m in modules if m in others] == []
    for name in (
        "aiohttp",
        "motorbus.dashboard",
        "motorbus.runtime.guard",  # only with --guard
        "motorbus.busfile",  # only when a bus file applies
        "motorbus.protocol.project_stepper",
        "motorbus.protocol.quad_stepper",
    ):
        assert not loaded(modules, name), name


def test_the_help_table_is_each_commands_own_help() -> None:
    # COMMANDS keeps the one-line help so that ``motorbus --help`` imports nothing; the
    # module's register() stays the source, and this keeps the two equal.
    for name, text in COMMANDS.items():
        sub = argparse.ArgumentParser().add_subparsers()
        importlib.import_module(f"motorbus.cli.{name}").register(sub)
        assert list(sub.choices) == [name]
        assert [a.help for a in sub._choices_actions] == [text]


def test_the_top_level_help_is_the_same_with_or_without_the_modules() -> None:
    assert build_parser(only=None).format_help() == build_parser().format_help()


def test_a_command_parses_the_same_alone_as_with_every_command() -> None:
    line = ["la", "status", "1-3", "--port", "/dev/null"]
    assert build_parser(only="la").parse_args(line) == build_parser().parse_args(line)


@pytest.mark.parametrize("command", list(COMMANDS))
def test_no_command_help_loads_the_web_server(tmp_path: Path, command: str) -> None:
    # aiohttp loads only when the dashboard runs (not even for ``dashboard --help``).
    modules = modules_at_exit(tmp_path, command, "--help")
    assert f"motorbus.cli.{command}" in modules
    assert not loaded(modules, "aiohttp")
