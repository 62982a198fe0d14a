"""The public API is one list, and the command line uses nothing but it."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import motorbus
from motorbus.cli import main as cli_main

SRC = Path(__file__).resolve().parents[1] / "src" / "motorbus"


def test_type_checking_imports_name_exactly_the_exports() -> None:
    tree = ast.parse((SRC / "__init__.py").read_text(encoding="utf-8"))
    block = next(
        n for n in tree.body if isinstance(n, ast.If) and ast.unparse(n.test) == "TYPE_CHECKING"
    )
    static: dict[str, set[str]] = {}
    for node in block.body:
        assert isinstance(node, ast.ImportFrom) and node.module
        for alias in node.names:
            assert alias.asname == alias.name  # "X as X": an explicit re-export
            static.setdefault(node.module, set()).add(alias.name)
    assert static == {m: set(names) for m, names in motorbus._EXPORTS.items()}


def test_all_is_made_from_the_exports_and_every_name_loads() -> None:
    names = [n for names in motorbus._EXPORTS.values() for n in names]
    assert len(names) == len(set(names))
    assert sorted(motorbus.__all__) == sorted([*names, "__version__"])
    for name in motorbus.__all__:
        assert getattr(motorbus, name) is not None


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
