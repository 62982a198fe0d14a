"""What the doctor reads from the system: sysfs (a fake tree), /proc, the latency timer."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from motorbus.doctor import Level
from motorbus.doctor.checks import check_latency, check_port
from motorbus.doctor.system import holders, latency_facts, port_facts, usb_info
from motorbus.transport import serial as serial_transport

from .test_checks import timing


def fake_sysfs(root: Path, latency_ms: int = 16) -> Path:
    """An FT232R at ttyUSB0 as Linux lays it out (only the files the doctor reads)."""
    usb = root / "devices" / "pci0000:00" / "usb1" / "1-1"
    iface = usb / "1-1:1.0" / "ttyUSB0"
    iface.mkdir(parents=True)
    for name, value in {
        "idVendor": "0403",
        "idProduct": "6001",
        "serial": "A50285BI",
        "product": "FT232R USB UART",
        "manufacturer": "FTDI",
    }.items():
        (usb / name).write_text(value + "\n")
    driver = root / "bus" / "usb-serial" / "drivers" / "ftdi_sio"
    driver.mkdir(parents=True)
    (iface / "driver").symlink_to(driver)
    (iface / "latency_timer").write_text(f"{latency_ms}\n")
    tty = root / "class" / "tty" / "ttyUSB0"
    tty.mkdir(parents=True)
    (tty / "device").symlink_to(iface)
    devices = root / "bus" / "usb-serial" / "devices"
    devices.mkdir(parents=True)
    (devices / "ttyUSB0").symlink_to(iface)
    return root


def test_the_adapter_is_read_from_sysfs(tmp_path: Path) -> None:
    info = usb_info("ttyUSB0", str(fake_sysfs(tmp_path / "sys")))
    assert info is not None
    assert (info.vid, info.pid, info.driver, info.serial) == (
        "0403",
        "6001",
        "ftdi_sio",
        "A50285BI",
    )
    assert (
        info.describe() == "USB 0403:6001, FTDI FT232R USB UART, driver ftdi_sio, serial A50285BI"
    )
    assert usb_info("ttyS0", str(tmp_path / "sys")) is None


def test_latency_timer_is_read_and_fix_writes_1(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    sysfs = fake_sysfs(tmp_path / "sys")
    monkeypatch.setattr(serial_transport, "USB_SERIAL_SYSFS", str(sysfs / "bus/usb-serial/devices"))
    port = tmp_path / "ttyUSB0"  # stands in for /dev/ttyUSB0 (not a tty: no TIOCGSERIAL)
    port.write_text("")
    seen = latency_facts(str(port), "ftdi_sio")
    assert (seen.tty_name, seen.latency_timer_ms, seen.low_latency_flag) == ("ttyUSB0", 16, None)
    assert check_latency(seen, timing(), 0.010).level is Level.RED
    timer = sysfs / "bus/usb-serial/devices/ttyUSB0/latency_timer"
    assert timer.read_text().strip() == "16"  # read-only without --fix
    fixed = latency_facts(str(port), "ftdi_sio", fix=True)
    assert timer.read_text().strip() == "1"
    assert fixed.latency_timer_ms == 1 and "16 -> 1 ms" in fixed.fixed
    finding = check_latency(fixed, timing(), 0.010)
    assert finding.level is Level.GREEN and finding.data["fixed"] == fixed.fixed


def test_a_process_holding_the_port_is_named_from_proc(tmp_path: Path) -> None:
    port = tmp_path / "ttyUSB0"
    port.write_text("")
    proc = tmp_path / "proc"
    (proc / "4242" / "fd").mkdir(parents=True)
    (proc / "4242" / "comm").write_text("minicom\n")
    (proc / "4242" / "fd" / "3").symlink_to(port)
    (proc / "77" / "fd").mkdir(parents=True)
    (proc / "77" / "fd" / "0").symlink_to("/dev/null")
    assert holders(str(port), str(proc)) == ((4242, "minicom"),)


def test_a_regular_file_is_no_port(tmp_path: Path) -> None:
    path = tmp_path / "notaport"
    path.write_text("")
    os.chmod(path, 0o666)
    facts = port_facts(str(path), uid=1000, gids=[1000], proc=str(tmp_path))
    assert facts.kind == "file"
    assert check_port(facts).level is Level.RED
