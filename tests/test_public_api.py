"""The public API is one list, and the command line uses nothing but it."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from motorbus.cli import main as cli_main
from tests.helpers import CLI_TIMEOUT_S

SRC = Path(__file__).resolve().parents[1] / "src" / "motorbus"


#: The packages whose public names load on first use, each from one ``_EXPORTS`` list.
LAZY_PACKAGES = (
    "motorbus",
    "motorbus.blocking",
    "motorbus.rig",
    "motorbus.protocol.project_stepper",
)


def _package(name: str) -> Any:
    return importlib.import_module(name)


@pytest.mark.parametrize("name", LAZY_PACKAGES)
def test_type_checking_imports_name_exactly_the_exports(name: str) -> None:
    package = _package(name)
    tree = ast.parse(Path(package.__file__).read_text(encoding="utf-8"))
    block = next(
        n for n in tree.body if isinstance(n, ast.If) and ast.unparse(n.test) == "TYPE_CHECKING"
    )
    static: dict[str, set[str]] = {}
    for node in block.body:
        assert isinstance(node, ast.ImportFrom) and node.module
        for alias in node.names:
            assert alias.asname == alias.name  # "X as X": an explicit re-export
            static.setdefault(node.module, set()).add(alias.name)
    assert static == {m: set(names) for m, names in package._EXPORTS.items()}


@pytest.mark.parametrize("name", LAZY_PACKAGES)
def test_all_is_made_from_the_exports_and_every_name_loads(name: str) -> None:
    package = _package(name)
    names = [n for names in package._EXPORTS.values() for n in names]
    assert len(names) == len(set(names))
    extra = ["__version__"] if name == "motorbus" else []
    assert sorted(package.__all__) == sorted([*names, *extra])
    for module, exported in package._EXPORTS.items():
        for export in exported:  # the very object of the module named for it
            assert getattr(package, export) is getattr(importlib.import_module(module), export)
    with pytest.raises(AttributeError, match="no attribute 'NoSuchName'"):
        package.NoSuchName  # noqa: B018


def run_python(code: str) -> subprocess.CompletedProcess[str]:
    """``code`` run by a fresh interpreter (what it imports is all its own), which must
    succeed."""
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=CLI_TIMEOUT_S
    )
    assert out.returncode == 0, out.stderr
    return out


def test_an_la_program_loads_no_stepper_protocol() -> None:
    """What the lazy names are for: a bus file, a manager and a served bus of LA
    actuators leave the project stepper's commands and the quad stepper unloaded (their
    dataclasses were ~40 ms of every such program's start-up)."""
    code = (
        "import sys, motorbus, motorbus.busfile, motorbus.manager, motorbus.serve.server, "
        "motorbus.serve.client, motorbus.dashboard.state\n"
        "from motorbus.protocol import la\n"
        "from motorbus.protocol.base import Family\n"
        "from motorbus.serve.keys import decode_frame\n"
        "motorbus.busfile.parse_devices(['la:1-3'])\n"
        "assert decode_frame(la.MoveTo(1, 500).encode(), [Family.LA]) == la.MoveTo(1, 500)\n"
        "print(sorted(m for m in sys.modules if 'stepper' in m))"
    )
    out = run_python(code)
    assert out.stdout.split() == [
        "['motorbus.protocol.project_stepper',",
        "'motorbus.protocol.project_stepper.wire']",
    ]


def test_a_blocking_la_program_loads_no_stepper_and_no_zenoh() -> None:
    """The blocking API's names load on first use too: a script of LA actuators and a
    stream leaves the stepper devices and the served bus's client (and Zenoh) unloaded;
    asking for a stepper loads it then."""
    code = (
        "import sys, motorbus.blocking as mb\n"
        "mb.Bus, mb.BusManager, mb.InspireLA, mb.Streamer, mb.Setpoint, mb.read_statuses\n"
        "def loaded():\n"
        "    return sorted(m for m in sys.modules if 'stepper' in m or m.startswith("
        "('zenoh', 'motorbus.serve')))\n"
        "print(*loaded())\n"
        "mb.ProjectStepper, mb.QuadStepper\n"
        "print(*loaded())\n"
    )
    out = run_python(code)
    before, after = (line.split() for line in out.stdout.splitlines())
    assert before == ["motorbus.protocol.project_stepper", "motorbus.protocol.project_stepper.wire"]
    assert {"motorbus.devices.project_stepper", "motorbus.devices.quad_stepper"} <= set(after)
    assert not [m for m in after if m.startswith(("zenoh", "motorbus.serve"))]


#: What the command line may import: the package itself, its public modules and,
#: for the commands that run simulators, ``motorbus.sim`` (the process runtime is public:
#: ``--guard`` starts its guard, ``--realtime`` its real-time mode).
PUBLIC = (
    "motorbus.errors",
    "motorbus.runtime",
    "motorbus.protocol",
    "motorbus.cli",
)
#: Tools built on the library, whose packages export their public names.
TOOLS = ("motorbus.rig", "motorbus.dashboard", "motorbus.serve")
SIMULATOR_COMMANDS = {"sim.py", "demo.py"}


def test_the_cli_imports_the_public_api_only() -> None:
    bad = []
    for path in sorted((SRC / "cli").glob("*.py")):
        allowed = PUBLIC + (("motorbus.sim",) if path.name in SIMULATOR_COMMANDS else ())
        allowed += tuple(f"{t}" for t in TOOLS if path.name == t.rsplit(".", 1)[1] + ".py")
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            modules = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                modules = [node.module]
            elif isinstance(node, ast.Import):
                modules = [a.name for a in node.names]
            for module in modules:
                if module.startswith("motorbus.") and not module.startswith(allowed):
                    bad.append(f"cli/{path.name}: {module}")
    assert bad == []


def test_a_command_module_that_does_not_import_is_an_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(cli_main, "COMMAND_MODULES", (*cli_main.COMMAND_MODULES, "no_such"))
    with pytest.raises(ModuleNotFoundError, match=r"motorbus\.cli\.no_such"):
        cli_main.build_parser()
