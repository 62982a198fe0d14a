"""USB adapters named by what does not change, resolved against a fake sysfs tree."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from motorbus.errors import LocalProtocolError
from motorbus.transport import usb
from motorbus.transport.usb import (
    UsbSelector,
    list_serial_ports,
    parse_usb_url,
    port_info,
    resolve_port,
)
from tests.transport.fake_sysfs import CDC_ACM, CH340, FT232R, FT232R_B, FakeSysfs


@pytest.fixture
def fake(tmp_path: Path) -> FakeSysfs:
    return FakeSysfs(tmp_path)


def roots(fake: FakeSysfs) -> dict[str, str]:
    return {"sysfs": str(fake.sys), "dev": str(fake.dev)}


# -- parsing -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("url", "selector"),
    [
        ("usb:serial=A12345", UsbSelector(serial="A12345")),
        ("usb:0403:6001", UsbSelector("0403", "6001")),
        ("usb:0403:6001:A12345", UsbSelector("0403", "6001", "A12345")),
        ("usb:1A86:7523", UsbSelector("1a86", "7523")),  # sysfs writes lower case
        ("usb:0403:6001:AB:CD", UsbSelector("0403", "6001", "AB:CD")),
    ],
)
def test_the_three_forms_parse(url: str, selector: UsbSelector) -> None:
    assert parse_usb_url(url) == selector


def test_a_selector_prints_as_its_canonical_url() -> None:
    assert str(parse_usb_url("usb:1A86:7523")) == "usb:1a86:7523"
    assert str(parse_usb_url("usb:serial=A1")) == "usb:serial=A1"
    assert str(parse_usb_url("usb:0403:6001:A1")) == "usb:0403:6001:A1"


@pytest.mark.parametrize(
    ("url", "why"),
    [
        ("usb:", "give a serial number"),
        ("usb:0403", "give a serial number"),
        ("usb:serial=", "the serial number is empty"),
        ("usb:serial=A 1", "has a blank"),
        ("usb:0403:6001:", "the serial number is empty"),
        ("usb:403:6001", "the vendor ID '403' is not 4 hex digits"),
        ("usb:0403:60011", "the product ID '60011' is not 4 hex digits"),
        ("usb:04g3:6001", "the vendor ID '04g3' is not 4 hex digits"),
        ("usb:vid=0403", "give a serial number"),
        ("usb:vid:0403", "the vendor ID 'vid' is not 4 hex digits"),
    ],
)
def test_a_malformed_url_names_field_value_and_the_allowed_forms(url: str, why: str) -> None:
    with pytest.raises(LocalProtocolError) as caught:
        parse_usb_url(url)
    err = caught.value
    assert (err.field, err.value) == ("url", url)
    text = str(err)
    assert text.startswith(f"url={url!r}: ")
    assert why in text
    assert "usb:serial=SERIAL, usb:VID:PID, usb:VID:PID:SERIAL" in text
    assert "4 hex digits" in text


def test_the_field_name_is_the_callers() -> None:
    with pytest.raises(LocalProtocolError, match=r"^--port='usb:x'") as caught:
        parse_usb_url("usb:x", field="--port")
    assert caught.value.field == "--port"


# -- reading sysfs ------------------------------------------------------------------


def test_each_adapter_kind_is_read_from_sysfs(fake: FakeSysfs) -> None:
    fake.plug(FT232R, "ttyUSB0", usb_port="1-1")
    fake.plug(CH340, "ttyUSB1", usb_port="1-2")
    fake.plug(CDC_ACM, "ttyACM0", usb_port="1-3")
    ft, ch, acm = (port_info(n, **roots(fake)) for n in ("ttyUSB0", "ttyUSB1", "ttyACM0"))
    assert ft is not None and ch is not None and acm is not None
    by_id = str(fake.by_id / "usb-FTDI_FT232R_USB_UART_A12345-if00-port0")
    assert ft == usb.SerialPortInfo(
        name="ttyUSB0",
        device=str(fake.dev / "ttyUSB0"),
        by_id=(by_id,),
        vid="0403",
        pid="6001",
        serial="A12345",
        manufacturer="FTDI",
        product="FT232R USB UART",
        driver="ftdi_sio",
        latency_timer_ms=16,
    )
    # A CH340 has no serial number and no latency timer.
    assert (ch.vid, ch.pid, ch.serial, ch.driver, ch.latency_timer_ms) == (
        "1a86",
        "7523",
        "",
        "ch341-uart",
        None,
    )
    # CDC-ACM: the tty hangs off the USB interface, no usb-serial entry.
    assert (acm.vid, acm.pid, acm.serial, acm.driver, acm.latency_timer_ms) == (
        "2e8a",
        "000a",
        "E6614C311B4A",
        "cdc_acm",
        None,
    )
    assert acm.by_id == (str(fake.by_id / "usb-Raspberry_Pi_Pico_E6614C311B4A-if00"),)
    assert port_info("ttyUSB9", **roots(fake)) is None


def test_listing_is_usb_only_in_name_order_unless_all_is_asked(fake: FakeSysfs) -> None:
    fake.plug(FT232R, "ttyUSB10", usb_port="1-1")
    fake.plug(FT232R_B, "ttyUSB2", usb_port="1-2")
    fake.plug(CDC_ACM, "ttyACM0", usb_port="1-3")
    fake.add_uart("ttyS0")
    fake.add_virtual("tty0")
    names = [p.name for p in list_serial_ports(**roots(fake))]
    assert names == ["ttyACM0", "ttyUSB2", "ttyUSB10"]
    every = list_serial_ports(**roots(fake), usb_only=False)
    assert [p.name for p in every] == ["ttyACM0", "ttyS0", "ttyUSB2", "ttyUSB10"]
    uart = every[1]
    assert (uart.is_usb, uart.driver, uart.describe()) == (
        False,
        "serial8250",
        f"{fake.dev / 'ttyS0'} (not USB)",
    )


def test_no_sysfs_lists_nothing(tmp_path: Path) -> None:
    assert list_serial_ports(sysfs=str(tmp_path / "nothing"), dev=str(tmp_path)) == []


# -- resolving --------------------------------------------------------------------


def test_each_form_resolves_to_its_adapter(fake: FakeSysfs) -> None:
    fake.plug(FT232R, "ttyUSB0", usb_port="1-1")
    fake.plug(FT232R_B, "ttyUSB1", usb_port="1-2")
    fake.plug(CH340, "ttyUSB2", usb_port="1-3")
    fake.plug(CDC_ACM, "ttyACM0", usb_port="1-4")
    want = {
        "usb:serial=A12345": "ttyUSB0",
        "usb:0403:6001:B67890": "ttyUSB1",
        "usb:1a86:7523": "ttyUSB2",
        "usb:1A86:7523": "ttyUSB2",
        "usb:2e8a:000a": "ttyACM0",
        "usb:serial=E6614C311B4A": "ttyACM0",
    }
    for url, tty in want.items():
        assert resolve_port(url, **roots(fake)) == str(fake.dev / tty), url


def test_two_adapters_with_one_vid_pid_are_an_error_naming_both(fake: FakeSysfs) -> None:
    fake.plug(FT232R, "ttyUSB0", usb_port="1-1")
    fake.plug(FT232R_B, "ttyUSB1", usb_port="1-2")
    with pytest.raises(OSError) as caught:
        resolve_port("usb:0403:6001", **roots(fake))
    text = str(caught.value)
    assert caught.value.errno == errno.ENOTUNIQ
    assert text.startswith("usb:0403:6001 matches 2 adapters")
    assert f"{fake.dev / 'ttyUSB0'} (0403:6001 FTDI FT232R USB UART, serial A12345)" in text
    assert f"{fake.dev / 'ttyUSB1'} (0403:6001 FTDI FT232R USB UART, serial B67890)" in text
    assert "usb:VID:PID:SERIAL" in text


def test_no_match_is_an_error_listing_what_was_found(fake: FakeSysfs) -> None:
    fake.plug(CH340, "ttyUSB0", usb_port="1-1")
    fake.add_uart("ttyS0")
    with pytest.raises(OSError) as caught:
        resolve_port("usb:serial=A12345", **roots(fake))
    assert caught.value.errno == errno.ENODEV
    assert str(caught.value) == (
        "no USB serial adapter matches usb:serial=A12345: found "
        f"{fake.dev / 'ttyUSB0'} (1a86:7523 USB2.0-Serial, no serial number)"
    )
    fake.unplug("ttyUSB0")
    with pytest.raises(OSError, match=r"found none \(no USB serial adapter is plugged in\)"):
        resolve_port("usb:serial=A12345", **roots(fake))


def test_an_adapter_that_reenumerates_is_found_under_its_new_name(fake: FakeSysfs) -> None:
    """The reconnect case: unplugged while ttyUSB0 was still held, it comes back as
    ttyUSB1 (and the by-id link follows it); each resolution sees the tree as it is."""
    fake.plug(CH340, "ttyUSB1", usb_port="1-2")  # a bystander with another identity
    fake.plug(FT232R, "ttyUSB0", usb_port="1-1")
    link = str(fake.by_id / FT232R.by_id_name)
    for url in ("usb:serial=A12345", "usb:0403:6001", link):
        assert resolve_port(url, **roots(fake)) == str(fake.dev / "ttyUSB0")
    fake.unplug("ttyUSB0")
    with pytest.raises(OSError, match="no USB serial adapter matches"):
        resolve_port("usb:serial=A12345", **roots(fake))
    fake.plug(FT232R, "ttyUSB2", usb_port="1-1")
    for url in ("usb:serial=A12345", "usb:0403:6001", link):
        assert resolve_port(url, **roots(fake)) == str(fake.dev / "ttyUSB2")


def test_the_module_roots_are_the_defaults(
    fake: FakeSysfs, monkeypatch: pytest.MonkeyPatch
) -> None:
    fake.plug(FT232R, "ttyUSB3")
    monkeypatch.setattr(usb, "SYSFS", str(fake.sys))
    monkeypatch.setattr(usb, "DEV", str(fake.dev))
    assert resolve_port("usb:serial=A12345") == str(fake.dev / "ttyUSB3")
    assert [p.name for p in list_serial_ports()] == ["ttyUSB3"]


def test_paths_resolve_through_links_and_urls_stay_as_given(tmp_path: Path) -> None:
    assert resolve_port("/dev/pts/7") == "/dev/pts/7"  # a pty: as given
    target = tmp_path / "ttyUSB4"
    target.write_text("")
    link = tmp_path / "usb-FTDI-if00-port0"
    link.symlink_to(target)
    assert resolve_port(str(link)) == str(target)
    assert resolve_port("COM3") == "COM3"  # Windows: never made a path of the cwd
    assert resolve_port("/dev/cu.usbserial-A12345") == "/dev/cu.usbserial-A12345"
    assert resolve_port("socket://10.0.0.5:7012") == "socket://10.0.0.5:7012"
    assert resolve_port("rfc2217://host:2217") == "rfc2217://host:2217"
    missing = str(tmp_path / "gone")
    assert resolve_port(missing) == missing  # the open names the missing file


def test_without_sysfs_a_usb_url_says_it_needs_linux(tmp_path: Path) -> None:
    with pytest.raises(OSError) as caught:
        resolve_port("usb:serial=A12345", sysfs=str(tmp_path / "nosys"), dev=str(tmp_path))
    assert caught.value.errno == errno.ENODEV
    assert str(caught.value) == (
        f"usb:serial=A12345: a usb: URL is found through Linux sysfs, and "
        f"{tmp_path / 'nosys' / 'class' / 'tty'} is not there; name the port by its device "
        "(COM3, /dev/cu.usbserial-...) on this system"
    )


def test_a_malformed_url_fails_before_sysfs_is_read(tmp_path: Path) -> None:
    with pytest.raises(LocalProtocolError, match="vendor ID"):
        resolve_port("usb:xyz:6001", sysfs=str(tmp_path / "none"), dev=str(tmp_path))
