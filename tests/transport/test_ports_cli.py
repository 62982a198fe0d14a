"""``motorbus ports`` against a fake sysfs tree, and on this machine as it is."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from motorbus.cli.main import EXIT_OK, main
from motorbus.cli.ports import stable_url
from motorbus.transport import usb
from tests.transport.fake_sysfs import CDC_ACM, CH340, FT232R, FT232R_B, FakeSysfs


@pytest.fixture
def fake(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> FakeSysfs:
    tree = FakeSysfs(tmp_path)
    monkeypatch.setattr(usb, "SYSFS", str(tree.sys))
    monkeypatch.setattr(usb, "DEV", str(tree.dev))
    return tree


def run(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    code = main(["ports", *argv])
    out, err = capsys.readouterr()
    assert (code, err) == (EXIT_OK, "")
    return out


def test_the_table_names_each_adapter_for_good(
    fake: FakeSysfs, capsys: pytest.CaptureFixture[str]
) -> None:
    fake.plug(FT232R, "ttyUSB0", usb_port="1-1")
    fake.plug(CH340, "ttyUSB1", usb_port="1-2")
    dev = str(fake.dev)
    lines = run(capsys).splitlines()
    assert [re.split(r" {2,}", line.strip()) for line in lines] == [
        ["port", "usb", "serial", "driver", "latency", "name for a bus file"],
        [f"{dev}/ttyUSB0", "0403:6001", "A12345", "ftdi_sio", "16 ms", "usb:serial=A12345"],
        ["FTDI FT232R USB UART"],
        [f"{dev}/serial/by-id/usb-FTDI_FT232R_USB_UART_A12345-if00-port0"],
        [f"{dev}/ttyUSB1", "1a86:7523", "-", "ch341-uart", "-", "usb:1a86:7523"],
        ["USB2.0-Serial"],
        [f"{dev}/serial/by-id/usb-1a86_USB2.0-Serial-if00-port0"],
    ]
    # Columns line up; the strings and links stand under the second column.
    header, ft, strings, _, ch, _, _ = lines
    for title, a, b in (
        ("usb", "0403", "1a86"),
        ("driver", "ftdi_sio", "ch341"),
        ("name", "usb:s", "usb:1"),
    ):
        assert header.index(title) == ft.index(a) == ch.index(b)
    assert strings.index("FTDI") == header.index("usb")


def test_json_has_every_field_and_the_name_that_tells_adapters_apart(
    fake: FakeSysfs, capsys: pytest.CaptureFixture[str]
) -> None:
    fake.plug(FT232R, "ttyUSB0", usb_port="1-1")
    fake.plug(FT232R_B, "ttyUSB1", usb_port="1-2")
    fake.plug(CH340, "ttyUSB2", usb_port="1-3")
    fake.plug(CH340, "ttyUSB3", usb_port="1-4")  # two alike, no serial numbers
    fake.plug(CDC_ACM, "ttyACM0", usb_port="1-5")
    fake.add_uart("ttyS0")
    doc = json.loads(run(capsys, "--json"))
    rows = {p["name"]: p for p in doc["ports"]}
    assert list(rows) == ["ttyACM0", "ttyUSB0", "ttyUSB1", "ttyUSB2", "ttyUSB3"]
    assert rows["ttyUSB0"] == {
        "name": "ttyUSB0",
        "device": str(fake.dev / "ttyUSB0"),
        "by_id": [str(fake.by_id / FT232R.by_id_name)],
        "vid": "0403",
        "pid": "6001",
        "serial": "A12345",
        "manufacturer": "FTDI",
        "product": "FT232R USB UART",
        "driver": "ftdi_sio",
        "latency_timer_ms": 16,
        "url": "usb:serial=A12345",
    }
    assert rows["ttyUSB1"]["url"] == "usb:serial=B67890"  # same VID:PID, by serial
    assert rows["ttyUSB2"]["url"] is None and rows["ttyUSB3"]["url"] is None
    assert rows["ttyACM0"]["url"] == "usb:serial=E6614C311B4A"
    # Each URL it offers resolves to its own port.
    for row in rows.values():
        if row["url"] is not None:
            assert usb.resolve_port(row["url"]) == row["device"]
    every = json.loads(run(capsys, "--all", "--json"))["ports"]
    names = ["ttyACM0", "ttyS0", "ttyUSB0", "ttyUSB1", "ttyUSB2", "ttyUSB3"]
    assert [p["name"] for p in every] == names


def test_a_serial_number_two_ports_share_is_not_offered(fake: FakeSysfs) -> None:
    fake.plug(FT232R, "ttyUSB0", usb_port="1-1")
    fake.plug(FT232R, "ttyUSB1", usb_port="1-2")  # one dual-port chip, or a cloned serial
    ports = usb.list_serial_ports()
    assert [stable_url(p, ports) for p in ports] == [None, None]


def test_no_adapter_is_said_and_is_not_an_error(
    fake: FakeSysfs, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run(capsys) == "no USB serial adapters found (--all lists the other serial ports)\n"
    assert json.loads(run(capsys, "--json")) == {"ports": []}
    assert run(capsys, "--all") == "no serial ports found\n"
    fake.add_uart("ttyS0")
    assert run(capsys).startswith("no USB serial adapters found")
    assert run(capsys, "--all").splitlines()[1].split() == [
        str(fake.dev / "ttyS0"),
        "-",
        "-",
        "serial8250",
        "-",
        "-",
    ]


def test_it_runs_on_this_machine(capsys: pytest.CaptureFixture[str]) -> None:
    out = run(capsys)
    assert out.startswith(("no USB serial adapters found", "port "))
    assert isinstance(json.loads(run(capsys, "--json"))["ports"], list)
