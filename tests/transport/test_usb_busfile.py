"""A bus file's ``url`` may name a USB adapter: the form is checked at load (the adapter
need not be plugged in), a bad one is refused there, by the library and the CLI alike."""

from __future__ import annotations

from pathlib import Path

import pytest

from motorbus.busfile import load_bus_file, port_identity
from motorbus.cli.main import EXIT_FAILURE, EXIT_USAGE, main
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager
from motorbus.transport import usb


def bus_file(tmp_path: Path, *urls: str) -> Path:
    path = tmp_path / "buses.toml"
    tables = [
        f'[[bus]]\nname = "b{n}"\nurl = "{url}"\nbaud = 921600\ndevices = ["la:1"]\n'
        for n, url in enumerate(urls)
    ]
    path.write_text("\n".join(tables), encoding="utf-8")
    return path


@pytest.mark.parametrize("url", ["usb:serial=A12345", "usb:0403:6001", "usb:0403:6001:A12345"])
def test_each_usb_form_loads_without_the_adapter(tmp_path: Path, url: str) -> None:
    (spec,) = load_bus_file(bus_file(tmp_path, url)).specs
    assert spec.url == url


@pytest.mark.parametrize(
    ("url", "why"),
    [
        ("usb:403:6001", "the vendor ID '403' is not 4 hex digits"),
        ("usb:serial=", "the serial number is empty"),
        ("usb:0403", "give a serial number"),
    ],
)
def test_a_bad_usb_url_is_refused_at_load(
    tmp_path: Path, url: str, why: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = bus_file(tmp_path, url)
    with pytest.raises(LocalProtocolError) as caught:
        load_bus_file(path)
    text = str(caught.value)
    assert text.startswith(f"{path}: bus 'b0' (#1): url={url!r}: {why}")
    assert "; allowed forms: usb:serial=SERIAL, usb:VID:PID, usb:VID:PID:SERIAL" in text
    with pytest.raises(LocalProtocolError) as again:
        BusManager.from_toml(path)
    assert str(again.value) == text
    code = main(["la", "status", "1", "--bus-file", str(path), "--bus", "b0"])
    assert (code, capsys.readouterr().err) == (EXIT_USAGE, f"motorbus la: {text}\n")


def test_one_adapter_spelled_twice_is_one_port(tmp_path: Path) -> None:
    assert port_identity("usb:1A86:7523") == port_identity("usb:1a86:7523") == "usb:1a86:7523"
    path = bus_file(tmp_path, "usb:0403:6001:A12345", "usb:0403:6001:A12345")
    with pytest.raises(LocalProtocolError, match="is the port of bus 'b0'"):
        load_bus_file(path)


def test_the_cli_on_an_absent_adapter_fails_naming_what_it_found(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "sys" / "class" / "tty").mkdir(parents=True)  # Linux, nothing plugged in
    monkeypatch.setattr(usb, "SYSFS", str(tmp_path / "sys"))
    monkeypatch.setattr(usb, "DEV", str(tmp_path / "dev"))
    code = main(["la", "status", "1", "--port", "usb:serial=A12345"])
    err = capsys.readouterr().err
    assert code == EXIT_FAILURE, err
    assert "no USB serial adapter matches usb:serial=A12345: found none" in err
    code = main(["la", "status", "1", "--port", "usb:0403"])
    assert code == EXIT_USAGE
    assert "url='usb:0403': give a serial number" in capsys.readouterr().err
