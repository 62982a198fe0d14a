"""The dependency direction of STYLE.md: errors <- protocol <- bus <- devices <- cli."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "motorbus"


def test_importing_the_protocol_layer_does_not_import_asyncio() -> None:
    code = (
        "import sys, motorbus.protocol, motorbus.protocol.reassembler, motorbus.protocol.base\n"
        "import pkgutil, importlib\n"
        "for m in pkgutil.iter_modules(motorbus.protocol.__path__):\n"
        "    importlib.import_module('motorbus.protocol.' + m.name)\n"
        "bad = [m for m in ('asyncio', 'serial', 'anyio') if m in sys.modules]\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", f"protocol layer imported: {out.stdout.strip()}"


def imports_of(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def test_pure_layers_import_no_io_and_no_clock() -> None:
    forbidden = {"asyncio", "anyio", "serial", "time", "socket", "threading", "os"}
    for layer in ("protocol",):
        for path in (SRC / layer).glob("*.py"):
            bad = {n.split(".")[0] for n in imports_of(path)} & forbidden
            assert not bad, f"{path.name} imports {bad}"


def test_library_modules_do_not_import_sim_or_cli() -> None:
    for layer in ("protocol", "bus", "transport", "devices"):
        for path in (SRC / layer).glob("*.py"):
            bad = {n for n in imports_of(path) if n.startswith(("motorbus.sim", "motorbus.cli"))}
            assert not bad, f"{layer}/{path.name} imports {bad}"


def test_simulator_models_are_pure() -> None:
    forbidden = {"asyncio", "anyio", "serial", "time", "socket", "threading"}
    for name in ("model.py", "la.py", "project_stepper.py", "quad_stepper.py", "bus.py"):
        path = SRC / "sim" / name
        if path.exists():
            bad = {n.split(".")[0] for n in imports_of(path)} & forbidden
            assert not bad, f"sim/{name} imports {bad}"
