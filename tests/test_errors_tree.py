"""Every exception class lives in motorbus.errors; the old import paths still work."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import motorbus
from motorbus import errors

SRC = Path(__file__).resolve().parents[1] / "src" / "motorbus"


def _exception_classes_outside_errors() -> list[str]:
    names = {n for n in dir(errors) if isinstance(getattr(errors, n), type)}
    found = []
    for path in SRC.rglob("*.py"):
        if path.name == "errors.py" and path.parent == SRC:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                bases = {ast.unparse(b).split(".")[-1] for b in node.bases}
                if bases & (names | {"Exception", "BaseException"}):
                    found.append(f"{path.relative_to(SRC)}:{node.name}")
    return found


def test_no_exception_class_is_defined_outside_errors() -> None:
    assert _exception_classes_outside_errors() == []


def test_every_error_is_a_motorbus_error_and_drawn_in_the_docstring() -> None:
    assert errors.__doc__ is not None
    for name in errors.__all__:
        cls = getattr(errors, name)
        assert issubclass(cls, errors.MotorbusError)
        assert f"+-- {name}" in errors.__doc__, name


def test_old_import_paths_name_the_same_classes() -> None:
    from motorbus.cli.main import CommandFailed, UsageError
    from motorbus.devices.project_stepper import ProjectStopped, ProjectVerifyError
    from motorbus.streams import StreamEnded

    assert StreamEnded is errors.StreamEnded is motorbus.StreamEnded
    assert ProjectStopped is errors.ProjectStopped is motorbus.ProjectStopped
    assert ProjectVerifyError is errors.ProjectVerifyError is motorbus.ProjectVerifyError
    assert UsageError is errors.UsageError
    assert CommandFailed is errors.CommandFailed


def test_device_fault_error_is_gone() -> None:
    # It was exported but never raised (an LA with a latched fault still answers; its
    # Status and FaultChanged events carry the fault), so it left the package.
    assert "DeviceFaultError" not in motorbus.__all__
    with pytest.raises(AttributeError):
        errors.DeviceFaultError  # noqa: B018
