"""The dependency direction: errors <- protocol <- transport <- bus <- devices <- streaming
<- streams <- busfile <- manager <- cli, with the simulator beside the library (protocol
and transport only), the tools (rig, doctor, dashboard) on top, and the process runtime
(runtime: signals, the guard, real-time mode, process groups) above the library's core:
the bus, devices and streams reach it only through the seam ``motorbus.lifecycle``.

Every import between motorbus subpackages points down this list, without exception.
"""

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
        for path in (SRC / layer).rglob("*.py"):
            bad = {n.split(".")[0] for n in imports_of(path)} & forbidden
            assert not bad, f"{path.name} imports {bad}"


def test_the_doctors_verdicts_are_pure() -> None:
    # motorbus doctor: probe.py gathers facts (I/O), checks.py and report.py judge them.
    forbidden = {"asyncio", "anyio", "serial", "time", "socket", "threading", "os"}
    for name in ("checks.py", "budget.py", "host.py", "report.py"):
        bad = {n.split(".")[0] for n in imports_of(SRC / "doctor" / name)} & forbidden
        assert not bad, f"doctor/{name} imports {bad}"


def test_the_pure_parts_of_streams_import_no_io_and_no_clock() -> None:
    # streaming/stream.py is the Stream handle (futures); the rest is arithmetic.
    forbidden = {"asyncio", "anyio", "serial", "time", "socket", "threading", "os"}
    pure = ("targets.py", "budget.py", "model.py")
    for name in pure:
        names = imports_of(SRC / "streaming" / name)
        bad = {n.split(".")[0] for n in names} & forbidden
        bad |= {n for n in names if n.startswith("motorbus.bus.") and n not in PURE_BUS}
        assert not bad, f"streaming/{name} imports {bad}"


#: The modules of ``motorbus.bus`` that are pure arithmetic and data.
PURE_BUS = {"motorbus.bus.occupancy", "motorbus.bus.stats"}
#: The bus's sans-I/O core (``BusCore``, which ``Bus`` holds): scheduling and reply
#: matching, driven by a time passed in.
BUS_CORE = {"motorbus.bus.core", "motorbus.bus.schedule", "motorbus.bus.matching"}


def test_the_bus_core_is_pure() -> None:
    # Bus (bus/bus.py) is the asyncio shell: timer, transport, futures, reconnect.
    forbidden = {"asyncio", "anyio", "serial", "time", "socket", "threading", "os"}
    for module in sorted(BUS_CORE):
        names = imports_of(SRC / "bus" / (module.rsplit(".", 1)[1] + ".py"))
        bad = {n.split(".")[0] for n in names} & forbidden
        bad |= {n for n in names if n.startswith("motorbus.bus.") and n not in PURE_BUS | BUS_CORE}
        assert not bad, f"{module} imports {bad}"


def test_library_modules_do_not_import_sim_or_cli() -> None:
    for layer in ("protocol", "bus", "transport", "devices", "doctor"):
        for path in (SRC / layer).rglob("*.py"):
            bad = {n for n in imports_of(path) if n.startswith(("motorbus.sim", "motorbus.cli"))}
            assert not bad, f"{layer}/{path.name} imports {bad}"


def test_simulator_models_are_pure() -> None:
    forbidden = {"asyncio", "anyio", "serial", "time", "socket", "threading"}
    models = ("model.py", "la.py", "project_stepper.py", "quad_stepper.py", "bus.py")
    # The parts the models are split into (storage and motion) are pure too.
    parts = (
        "la_motion.py",
        "la_table.py",
        "project_stepper_memory.py",
        "project_stepper_motion.py",
    )
    for name in models + parts:
        path = SRC / "sim" / name
        if path.exists():
            bad = {n.split(".")[0] for n in imports_of(path)} & forbidden
            assert not bad, f"sim/{name} imports {bad}"


_LIBRARY_BASE = {"errors", "protocol", "validation", "lifecycle"}
#: What each part of motorbus may import from the others (its own part always).
ALLOWED: dict[str, set[str]] = {
    "errors": set(),
    "protocol": {"errors"},
    "validation": {"errors", "protocol"},
    "lifecycle": set(),
    # The process runtime: the guard's transport is motorbus.transport.usb only (to find
    # a usb: URL's adapter when it acts); shutdown shares the bus's ``together``.
    "runtime": {"errors", "protocol", "transport", "bus", "lifecycle"},
    "transport": {"errors", "protocol", "validation"},
    "bus": _LIBRARY_BASE | {"transport"},
    "devices": _LIBRARY_BASE | {"transport", "bus"},
    "streaming": _LIBRARY_BASE | {"transport", "bus", "devices"},
    "streams": _LIBRARY_BASE | {"transport", "bus", "devices", "streaming"},
    "busfile": _LIBRARY_BASE | {"transport", "bus", "devices", "streaming", "streams", "runtime"},
    "manager": _LIBRARY_BASE
    | {"transport", "bus", "devices", "streaming", "streams", "busfile", "runtime"},
    # Tools built on the library (never imported by it): they use it, and nothing else.
    "rig": _LIBRARY_BASE | {"transport", "bus", "devices", "streaming", "streams"},
    "doctor": _LIBRARY_BASE
    | {"transport", "bus", "devices", "streaming", "streams", "busfile", "manager"},
    "dashboard": _LIBRARY_BASE | {"transport", "bus", "devices", "streaming", "streams"},
    # The blocking API: a view of the library, on a thread of its own.
    "blocking": _LIBRARY_BASE
    | {"transport", "bus", "devices", "streaming", "streams", "busfile", "manager", "runtime"},
    "sim": {"errors", "protocol", "transport"},
    "serve": _LIBRARY_BASE | {"transport", "bus", "devices", "streaming", "streams"},
}


def _part(path: Path) -> str:
    rel = path.relative_to(SRC)
    return rel.parts[0].removesuffix(".py")


def _motorbus_parts(path: Path) -> set[str]:
    parts = set()
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
            if node.module == "motorbus":
                names = [f"motorbus.{a.name}" for a in node.names]
        for name in names:
            bits = name.split(".")
            if bits[0] == "motorbus" and len(bits) > 1:
                parts.add(bits[1])
    return parts


def test_every_import_points_down_the_layers() -> None:
    bad = []
    for path in SRC.rglob("*.py"):
        part = _part(path)
        if part not in ALLOWED:
            continue
        for target in _motorbus_parts(path) - {part} - ALLOWED[part]:
            bad.append(f"{path.relative_to(SRC)} -> {target}")
    assert bad == []


#: The library below the process runtime: none of it imports motorbus.runtime (it calls
#: motorbus.lifecycle, which the runtime fills).
BELOW_THE_RUNTIME = ("protocol", "transport", "bus", "devices", "streaming", "streams")


def test_the_library_does_not_import_the_runtime() -> None:
    bad = []
    for part in BELOW_THE_RUNTIME:
        paths = [SRC / f"{part}.py"] if (SRC / f"{part}.py").exists() else []
        paths += sorted((SRC / part).rglob("*.py")) if (SRC / part).is_dir() else []
        assert paths, part
        for path in paths:
            names = imports_of(path)
            tree = ast.parse(path.read_text(encoding="utf-8"))
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom) and node.module == "motorbus":
                    names |= {f"motorbus.{a.name}" for a in node.names}
            names |= {n for n in _imported_names(path) if n.startswith("motorbus.")}
            bad += [
                f"{path.relative_to(SRC)} -> {n}"
                for n in sorted(names)
                if n == "motorbus.runtime" or n.startswith("motorbus.runtime.")
            ]
    assert bad == []


def test_the_seam_to_the_runtime_is_pure() -> None:
    # motorbus.lifecycle only holds the hooks; signals and the loop are the runtime's.
    forbidden = {"asyncio", "anyio", "signal", "threading", "os", "time", "motorbus"}
    bad = {n.split(".")[0] for n in imports_of(SRC / "lifecycle.py")} & forbidden
    assert not bad, f"lifecycle.py imports {bad}"


def _imported_names(path: Path) -> set[str]:
    """Modules named in ``importlib.import_module("...")`` and ``sys.modules.get("...")``
    calls: the ways around an import statement."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(node, ast.Call) or not node.args:
            continue
        first = node.args[0]
        if isinstance(first, ast.Constant) and isinstance(first.value, str):
            func = ast.unparse(node.func)
            if func.endswith(("import_module", "__import__", "sys.modules.get")):
                names.add(first.value)
    return names


def test_the_runtime_layering_test_sees_a_runtime_import(tmp_path: Path) -> None:
    # The check above would pass on anything if it read imports wrongly.
    sample = tmp_path / "sample.py"
    sample.write_text(
        "from motorbus import runtime\n"
        "import importlib\n"
        "importlib.import_module('motorbus.runtime.shutdown')\n",
        encoding="utf-8",
    )
    assert "motorbus.runtime.shutdown" in _imported_names(sample)
    assert _motorbus_parts(sample) == {"runtime"}


def test_the_bus_imports_no_devices_streams_or_manager() -> None:
    for path in (SRC / "bus").rglob("*.py"):
        assert not _motorbus_parts(path) & {"devices", "streams", "manager", "sim", "cli"}


def test_the_bus_knows_no_family_module() -> None:
    # Each family answers for itself (Command.device_key, Command.fault_state).
    families = ("la", "project_stepper", "quad_stepper")
    for path in (SRC / "bus").rglob("*.py"):
        names = imports_of(path)
        bad = {n for n in names if n.startswith(tuple(f"motorbus.protocol.{f}" for f in families))}
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module == "motorbus.protocol":
                bad |= {a.name for a in node.names if a.name in families}
        assert not bad, f"bus/{path.name} imports {bad}"


def test_family_codecs_do_not_reach_into_the_reassembler() -> None:
    # The reassembler cuts frames using the families' facts, never the other way round.
    for name in ("la", "project_stepper", "quad_stepper"):
        paths = list((SRC / "protocol").glob(f"{name}.py")) + list(
            (SRC / "protocol" / name).rglob("*.py")
        )
        assert paths
        for path in paths:
            assert "motorbus.protocol.reassembler" not in imports_of(path), path


def test_project_values_do_not_import_the_commands() -> None:
    # Projects are values; turning one into commands lives beside the commands
    # (upload.project_commands), so no two of these modules import each other:
    # project <- commands <- upload, and project <- upload.
    package = SRC / "protocol" / "project_stepper"
    commands = "motorbus.protocol.project_stepper.commands"
    upload = "motorbus.protocol.project_stepper.upload"
    assert not {commands, upload} & imports_of(package / "project.py")
    assert upload not in imports_of(package / "commands.py")


def test_the_rig_core_is_pure() -> None:
    for name in ("analysis.py", "compare.py", "plan.py"):
        bad = {n.split(".")[0] for n in imports_of(SRC / "rig" / name)} & {
            "asyncio", "time", "serial", "socket", "threading",
        }  # fmt: skip
        assert not bad, f"rig/{name} imports {bad}"
