"""The guard opens a ``usb:`` port where the adapter is when the program dies."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from motorbus.runtime.guard import GuardDevice, GuardPort, send_safe_frames
from motorbus.transport import usb
from tests.transport.fake_sysfs import CH340, FT232R, FakeSysfs
from tests.transport.test_serial_transport import Pty


@pytest.fixture
def pty() -> Iterator[Pty]:
    p = Pty()
    yield p
    p.close()


def test_the_guard_resolves_a_usb_url_and_writes_the_safe_frames(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, pty: Pty
) -> None:
    fake = FakeSysfs(tmp_path)
    monkeypatch.setattr(usb, "SYSFS", str(fake.sys))
    monkeypatch.setattr(usb, "DEV", str(fake.dev))
    fake.plug(CH340, "ttyUSB0", usb_port="1-1")
    fake.plug(FT232R, "ttyUSB1", usb_port="1-2", node=pty.path)  # replugged: now ttyUSB1
    port = GuardPort("usb:serial=A12345", 921600, {}, (GuardDevice("la:1", "o", (b"\x55\xaa",)),))
    result = send_safe_frames(port, spacing=0)
    assert (result.error, result.frames) == (None, 1)
    assert os.read(pty.master, 16) == b"\x55\xaa"  # written and drained before close


def test_the_guard_reports_an_absent_adapter(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fake = FakeSysfs(tmp_path)
    monkeypatch.setattr(usb, "SYSFS", str(fake.sys))
    monkeypatch.setattr(usb, "DEV", str(fake.dev))
    port = GuardPort("usb:serial=A12345", 921600, {}, (GuardDevice("la:1", "o", (b"\x01",)),))
    result = send_safe_frames(port, spacing=0)
    assert result.frames == 0
    assert result.error == (
        "cannot open usb:serial=A12345: no USB serial adapter matches usb:serial=A12345: "
        "found none (no USB serial adapter is plugged in)"
    )
