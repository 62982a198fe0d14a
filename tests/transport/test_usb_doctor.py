"""``motorbus doctor --port usb:...``: the adapter is found through sysfs, or its
absence is the red port finding (not "does not exist" at the argument)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from motorbus.doctor import DoctorConfig, Level, diagnose
from motorbus.errors import LocalProtocolError
from motorbus.sim.la import LAModel
from motorbus.sim.pty import PtySim
from motorbus.transport import usb
from tests.transport.fake_sysfs import FT232R, FakeSysfs

QUICK: dict[str, Any] = {"requests": 5, "measure_s": 0.0, "host_margin_s": 0.05}


@pytest.fixture
def fake(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> FakeSysfs:
    tree = FakeSysfs(tmp_path)
    monkeypatch.setattr(usb, "SYSFS", str(tree.sys))  # the bus opens through these
    monkeypatch.setattr(usb, "DEV", str(tree.dev))
    return tree


async def test_the_doctor_finds_the_adapter_by_its_serial_number(fake: FakeSysfs) -> None:
    with PtySim([LAModel(id=1)]) as sim:
        fake.plug(FT232R, "ttyUSB0", node=sim.path)
        config = DoctorConfig("usb:serial=A12345", 921600, ids=(1,), **QUICK)
        report = await diagnose(config, sysfs=str(fake.sys))
    port = report.finding("port")
    assert port.level is not Level.RED, report.format_text()
    assert str(fake.dev / "ttyUSB0") in port.summary
    assert report.finding("devices").data["found"] == [1]


async def test_no_adapter_is_the_red_port_finding(fake: FakeSysfs) -> None:
    config = DoctorConfig("usb:serial=A12345", 921600, ids=(1,), **QUICK)
    report = await diagnose(config, sysfs=str(fake.sys))
    port = report.finding("port")
    assert port.level is Level.RED
    assert port.summary.startswith("no USB serial adapter matches usb:serial=A12345: found none")
    assert "motorbus ports" in port.fix
    assert report.exit_code == 1


def test_a_malformed_usb_port_is_refused_by_the_config() -> None:
    with pytest.raises(LocalProtocolError, match=r"^port='usb:12:34': the vendor ID") as caught:
        DoctorConfig("usb:12:34", 921600)
    assert caught.value.field == "port"
