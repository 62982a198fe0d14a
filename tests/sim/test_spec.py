"""Device specs of ``motorbus sim``: forms, options, errors, default baud."""

from __future__ import annotations

import importlib.util

import pytest

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Family
from motorbus.sim.spec import (
    LA_DEFAULT_BAUD,
    STEPPER_DEFAULT_BAUD,
    default_baud,
    parse_device_spec,
    parse_device_specs,
)


def _has(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


needs_la = pytest.mark.skipif(not _has("motorbus.sim.la"), reason="sim/la.py not written yet")
needs_project = pytest.mark.skipif(
    not _has("motorbus.sim.project_stepper"), reason="sim/project_stepper.py not written yet"
)
needs_quad = pytest.mark.skipif(
    not _has("motorbus.sim.quad_stepper"), reason="sim/quad_stepper.py not written yet"
)


@needs_la
@pytest.mark.parametrize(
    ("spec", "ids"),
    [
        ("la", [1]),
        ("la:3", [3]),
        ("la:1-15", list(range(1, 16))),
        ("la:1,4,7", [1, 4, 7]),
        ("la:1-3,10", [1, 2, 3, 10]),
        ("LA:0x10", [16]),
        ("la:254", [254]),
    ],
)
def test_la_ids(spec: str, ids: list[int]) -> None:
    models = parse_device_spec(spec)
    assert [m.id for m in models] == ids  # type: ignore[attr-defined]
    assert all(m.family is Family.LA for m in models)


@needs_la
def test_la_options_reach_the_model() -> None:
    (model,) = parse_device_spec("la:2,write_reply=ack,temperature=40,force_sensor=no")
    assert model.temperature == 40.0  # type: ignore[attr-defined]
    assert model.force_sensor is False  # type: ignore[attr-defined]


@needs_project
def test_project_stepper_with_motor_option() -> None:
    (model,) = parse_device_spec("project-stepper:motor=3")
    assert model.family is Family.PROJECT_STEPPER
    assert parse_device_spec("project_stepper")[0].family is Family.PROJECT_STEPPER


@needs_quad
def test_quad_stepper() -> None:
    (model,) = parse_device_spec("quad-stepper")
    assert model.family is Family.QUAD_STEPPER
    (model,) = parse_device_spec("quad-stepper:run_ack_address=motor")
    assert model.run_ack_address == "motor"  # type: ignore[attr-defined]


@needs_la
@pytest.mark.parametrize(
    ("spec", "says"),
    [
        ("la:0", "1..254"),
        ("la:255", "1..254"),
        ("la:3-1", "backwards"),
        ("la:1,1", "twice"),
        ("la:x", "'x' is not an ID"),
        ("la:1,speed=3", "unknown option 'speed'"),
        ("la:1,id=4", "unknown option 'id'"),
        ("la:1,turnaround_max=abc", "turnaround_max"),
        ("la:1,write_reply=maybe", "write_reply"),
        ("servo:1", "unknown device kind 'servo'"),
    ],
)
def test_bad_specs_name_the_spec_and_the_accepted_forms(spec: str, says: str) -> None:
    with pytest.raises(LocalProtocolError) as info:
        parse_device_spec(spec)
    message = str(info.value)
    assert says in message
    assert repr(spec) in message
    assert "accepted forms" in message and "project-stepper" in message
    assert isinstance(info.value, ValueError)


@needs_quad
def test_stepper_specs_take_no_plain_items() -> None:
    with pytest.raises(LocalProtocolError, match="not a key=value option"):
        parse_device_spec("quad-stepper:3")


@needs_la
def test_duplicate_ids_across_specs_are_refused() -> None:
    with pytest.raises(LocalProtocolError, match="LA ID 3 is already used by 'la:1-3'"):
        parse_device_specs(["la:1-3", "la:3"])
    assert len(parse_device_specs(["la:1-3", "la:4"])) == 4


def test_no_device_is_refused() -> None:
    with pytest.raises(LocalProtocolError, match="no device"):
        parse_device_specs([])


@needs_la
@needs_quad
def test_default_baud_per_bus() -> None:
    assert default_baud(parse_device_specs(["la:1-3"])) == LA_DEFAULT_BAUD == 921600
    assert default_baud(parse_device_specs(["quad-stepper"])) == STEPPER_DEFAULT_BAUD == 9600
    assert default_baud(parse_device_specs(["la:1", "quad-stepper"])) == 9600
