"""The dependency direction, part by part (a part is a subpackage or a top-level module of
motorbus; ``ALLOWED`` below is the whole picture, drawn in docs/architecture.md):

* the library: errors <- protocol <- validation <- transport <- bus <- devices <-
  streaming <- streams <- busfile <- manager;
* the seam ``motorbus.lifecycle`` (imports nothing), which the bus, devices and streams
  call, and the process runtime (``runtime``: signals, the guard, real-time mode,
  process groups) that fills it: the runtime uses the bus, busfile and manager use the
  runtime, and nothing from protocol to streams imports it;
* beside the library the simulator (errors, protocol and transport only); on top of it
  the tools (serve, doctor, rig, dashboard) and the blocking API, which it never imports;
* above everything the package root ``motorbus`` (the public names, each loaded from its
  module on first use), the command line ``cli`` (the public names, and errors,
  protocol, runtime, sim and the tools directly) and ``__main__``.

Every import between the parts points down this picture, without exception: every part
has its rules, and a part without rules fails the test.
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
    pure = ("targets.py", "budget.py", "model.py", "tick.py")
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
#: What each part of motorbus may import from the others (its own part always).  A part
#: is a subpackage or a top-level module; the package root (``motorbus/__init__.py``) is
#: the part ``"motorbus"``, and ``from motorbus import Bus`` imports that part.
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
    # The blocking API: a view of the library, on a thread of its own, and of the served
    # client (``motorbus.blocking.connect``), which never imports it.
    "blocking": _LIBRARY_BASE
    | {"transport", "bus", "devices", "streaming", "streams", "busfile", "manager", "runtime"}
    | {"serve"},
    "sim": {"errors", "protocol", "transport"},
    # Served buses: ``motorbus serve`` hands the server buses a BusManager opened.
    "serve": _LIBRARY_BASE | {"transport", "bus", "devices", "streaming", "streams"},
    # The public names (``motorbus/__init__.py``), each loaded from its module on first
    # use: the library, the runtime, and the doctor's ``diagnose`` and the served bus's
    # ``connect``; never the simulator, the rig, the dashboard, the blocking API or cli.
    "motorbus": _LIBRARY_BASE
    | {"transport", "bus", "devices", "streaming", "streams", "busfile", "manager"}
    | {"runtime", "doctor", "serve"},
    # The command line: the library through the public names only; directly, the
    # values and parts the public names leave out.
    "cli": {"motorbus", "errors", "protocol", "runtime", "sim", "rig", "dashboard", "serve"},
    "__main__": {"cli"},
}

#: The parts below the tools: none of them may import a tool, the blocking API, the
#: public names or the command line.
LIBRARY = (
    "errors",
    "protocol",
    "validation",
    "lifecycle",
    "transport",
    "bus",
    "devices",
    "streaming",
    "streams",
    "busfile",
    "manager",
    "runtime",
    "sim",
)
ON_TOP = {"serve", "doctor", "rig", "dashboard", "blocking", "motorbus", "cli", "__main__"}


def _part(path: Path, root: Path = SRC) -> str:
    rel = path.relative_to(root)
    name = rel.parts[0].removesuffix(".py")
    return "motorbus" if name == "__init__" else name


def _parts_of_src(root: Path = SRC) -> set[str]:
    """Every part of the package at ``root``: its subpackages and top-level modules."""
    return {_part(path, root) for path in root.glob("*.py")} | {
        path.parent.name for path in root.glob("*/__init__.py")
    }


def _lazy_modules(tree: ast.Module) -> set[str]:
    """``motorbus.*`` module names in module-level dict literals (keys or values): the
    tables a package's ``__getattr__`` loads its names from on first use."""
    names: set[str] = set()
    for node in tree.body:
        value = node.value if isinstance(node, ast.Assign | ast.AnnAssign) else None
        if isinstance(value, ast.Dict):
            for item in [*value.keys, *value.values]:
                text = item.value if isinstance(item, ast.Constant) else None
                if isinstance(text, str) and text.startswith("motorbus."):
                    names.add(text)
    return names


def _motorbus_parts(path: Path, root: Path = SRC) -> set[str]:
    """The parts of motorbus that ``path`` imports: import statements (relative ones
    too, for a file under ``root``), ``from motorbus import NAME`` (the part NAME, or
    the package root for a public name), ``importlib.import_module("motorbus...")`` and
    the lazy tables of ``_lazy_modules``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                if not path.is_relative_to(root):
                    continue
                package = list(path.relative_to(root).parts[:-1])
                package = package[: len(package) - (node.level - 1)]
                module = ".".join(["motorbus", *package, *([module] if module else [])])
            if module == "motorbus":
                names.update(f"motorbus.{a.name}" for a in node.names)
            else:
                names.add(module)
    names |= _imported_names(path) | _lazy_modules(tree)
    parts: set[str] = set()
    for name in names:
        bits = name.split(".")
        if bits[0] != "motorbus":
            continue
        if len(bits) > 1 and ((root / bits[1]).is_dir() or (root / f"{bits[1]}.py").exists()):
            parts.add(bits[1])
        elif len(bits) <= 2:
            parts.add("motorbus")  # ``import motorbus``, ``from motorbus import Bus``
    return parts


def test_every_part_has_its_rules() -> None:
    # A new part (a subpackage or a top-level module) must say what it may import, and a
    # part that is gone must leave the rules: no part is skipped by the check below.
    assert _parts_of_src() == set(ALLOWED)


def test_every_import_points_down_the_layers() -> None:
    bad = []
    for path in sorted(SRC.rglob("*.py")):
        part = _part(path)
        allowed = ALLOWED.get(part)
        if allowed is None:
            bad.append(f"{path.relative_to(SRC)}: part {part!r} has no rules")
            continue
        for target in sorted(_motorbus_parts(path) - {part} - allowed):
            bad.append(f"{path.relative_to(SRC)} -> {target}")
    assert bad == []


def test_the_rules_point_one_way() -> None:
    # No cycle among the parts: each layer only ever looks down.
    assert all(targets <= set(ALLOWED) for targets in ALLOWED.values())
    order: list[str] = []
    left = {part: set(targets) - {part} for part, targets in ALLOWED.items()}
    while left:
        ready = sorted(part for part, targets in left.items() if targets <= set(order))
        assert ready, f"a cycle among {sorted(left)}"
        order += ready
        for part in ready:
            del left[part]


def test_the_library_never_imports_what_is_on_top() -> None:
    # Loosening a rule of the library towards the tools, the blocking API, the public
    # names or the command line fails here, not only when an import is written.
    assert set(LIBRARY) | ON_TOP == set(ALLOWED)
    for part in LIBRARY:
        assert not ALLOWED[part] & ON_TOP, part
    assert not ALLOWED["protocol"] - {"errors"}
    assert not ALLOWED["bus"] & {"devices", "streaming", "streams", "busfile", "manager"}
    assert "runtime" not in ALLOWED["bus"] | ALLOWED["devices"] | ALLOWED["streams"]


def test_the_part_reader_sees_every_kind_of_import(tmp_path: Path) -> None:
    # The checks above would pass on anything if they read imports wrongly.
    package = tmp_path / "motorbus"
    (package / "bus").mkdir(parents=True)
    (package / "serve").mkdir()
    (package / "cli.py").write_text("", encoding="utf-8")
    sample = package / "bus" / "sample.py"
    sample.write_text(
        "import motorbus\n"
        "from motorbus import Bus\n"
        "from ..serve import client\n"
        "from . import core\n"
        "_LAZY = {'run': 'motorbus.cli'}\n",
        encoding="utf-8",
    )
    assert _motorbus_parts(sample, package) == {"motorbus", "serve", "bus", "cli"}
    assert _parts_of_src(package) == {"cli"}  # no __init__.py: bus/ is no package yet
    (package / "bus" / "__init__.py").write_text("", encoding="utf-8")
    assert _parts_of_src(package) == {"cli", "bus"}


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
