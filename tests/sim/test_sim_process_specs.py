"""``SimProcess`` refuses a bad device or fault spec at construction, with the project's
error naming the spec, the value and what is allowed - before any child starts.

Before, ``SimProcess(["lx:1"])`` started a child that refused the spec, and ``start()``
raised a bare ``RuntimeError("motorbus sim did not start: ...")`` (issue 41, point 8).
"""

from __future__ import annotations

import subprocess

import pytest

from motorbus.errors import LocalProtocolError
from motorbus.sim.process import SimProcess


@pytest.fixture
def no_child(monkeypatch: pytest.MonkeyPatch) -> list[object]:
    """Record any attempt to start a process (there must be none)."""
    started: list[object] = []

    def popen(*args: object, **kwargs: object) -> None:
        started.append(args)
        raise AssertionError("a child process was started")

    monkeypatch.setattr(subprocess, "Popen", popen)
    return started


def test_an_unknown_device_kind_is_refused_at_construction(no_child: list[object]) -> None:
    with pytest.raises(LocalProtocolError) as info:
        SimProcess(["la:1", "lx:1"])
    err = info.value
    assert (err.field, err.value) == ("device", "lx:1")
    text = str(err)
    assert "device spec 'lx:1'" in text
    assert "unknown device kind 'lx'" in text
    assert "allowed kinds: la, project-stepper, quad-stepper" in text
    assert no_child == []


@pytest.mark.parametrize(
    ("devices", "faults", "named"),
    [
        (["la:0"], None, "la:0"),
        (["la:1", "la:1"], None, "already used"),
        (["quad-stepper:bogus=1"], None, "unknown option 'bogus'"),
        (["la:1"], "garbage=2", "garbage"),
    ],
)
def test_other_bad_specs_are_refused_at_construction(
    no_child: list[object], devices: list[str], faults: str | None, named: str
) -> None:
    with pytest.raises(LocalProtocolError, match=named):
        SimProcess(devices, faults=faults)
    assert no_child == []


def test_a_good_spec_still_starts() -> None:
    with SimProcess(["la:1-2", "project-stepper"], baud=9600) as sim:
        assert sim.path.startswith("/dev/")
