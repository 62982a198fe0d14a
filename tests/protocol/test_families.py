"""The family registry is the one place for each family's facts."""

from __future__ import annotations

import pytest

from motorbus.bus.bus import DEFAULT_TURNAROUND
from motorbus.cli import demo
from motorbus.cli.bus_options import LA_BAUD, STEPPER_BAUD
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la, quad_stepper
from motorbus.protocol.base import Family
from motorbus.protocol.families import (
    DEFAULT_BAUD,
    FAMILIES,
    SPEC_NAMES,
    by_spec_name,
    default_bus_baud,
)
from motorbus.sim import spec


def test_registry_values() -> None:
    assert DEFAULT_BAUD == {
        Family.LA: 921600,
        Family.PROJECT_STEPPER: 9600,
        Family.QUAD_STEPPER: 9600,
    }
    assert dict(DEFAULT_TURNAROUND) == {
        Family.LA: 800e-6,
        Family.PROJECT_STEPPER: 30e-3,
        Family.QUAD_STEPPER: 30e-3,
    }
    assert SPEC_NAMES == ("la", "project-stepper", "quad-stepper")
    assert [i.key for i in FAMILIES.values()] == ["la", "project_stepper", "quad_stepper"]
    assert FAMILIES[Family.LA].id_range == (1, 254)
    assert FAMILIES[Family.LA].broadcast_id == 255


def test_every_consumer_reads_the_registry() -> None:
    assert (LA_BAUD, STEPPER_BAUD) == (921600, 9600)
    assert (demo.LA_BAUD, demo.STEPPER_BAUD) == (921600, 9600)
    assert (spec.LA_DEFAULT_BAUD, spec.STEPPER_DEFAULT_BAUD) == (921600, 9600)
    assert spec.DEVICE_KINDS == SPEC_NAMES
    assert quad_stepper.DEFAULT_BAUD == 9600
    assert (la.ID_MIN, la.ID_MAX, la.BROADCAST_ID) == (1, 254, 255)


def test_spec_names_and_bus_baud() -> None:
    assert by_spec_name("project-stepper").family is Family.PROJECT_STEPPER
    with pytest.raises(LocalProtocolError, match="'stepper' is unknown: allowed la, "):
        by_spec_name("stepper")
    assert default_bus_baud([Family.LA, Family.LA]) == 921600
    assert default_bus_baud([Family.LA, Family.QUAD_STEPPER]) == 9600
    assert default_bus_baud([]) == 9600
