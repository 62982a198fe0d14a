"""Bad bus files, one table: each is refused at load with the file and the line (or the
bus and the key), by the library and - with the same message, exit code 2 - by the CLI.

Issue 19 case 8 and "one process, one port": deeply nested TOML raised RecursionError,
non-UTF-8 bytes a UnicodeDecodeError without the file, a NUL in ``url`` passed the
check, ``baud = 12345`` on an LA bus loaded, and two buses on one port (by the same
path, another spelling or a symlink) loaded and read each other's replies.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from motorbus.busfile import (
    BusSpec,
    family_baud_rates,
    load_bus_file,
    port_identity,
)
from motorbus.cli.main import EXIT_USAGE, main
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager
from motorbus.protocol import la
from motorbus.protocol.base import Family

#: Nesting deeper than Python's recursion limit (the TOML parser recurses per level).
DEEP = 5000

LA = 'name = "arm"\nurl = "/dev/ttyUSB0"\n'


def _file(tmp_path: Path, body: bytes | str) -> Path:
    path = tmp_path / "buses.toml"
    path.write_bytes(body.encode() if isinstance(body, str) else body)
    return path


#: id -> (file body, fragments the message must hold after "<file>: ")
BAD_FILES: dict[str, tuple[bytes | str, list[str]]] = {
    "not-utf8": (
        b'[[bus]]\nname = "arm"\nurl = "/dev/tty\xffUSB0"\nbaud = 921600\n',
        ["line 3: not UTF-8 text (byte 0xff at offset 36)"],
    ),
    "deep-nesting": (
        '[[bus]]\nurl = "/dev/ttyUSB0"\nbaud = 9600\ndevices = ' + "[" * DEEP + "]" * DEEP,
        ["not valid TOML: arrays or tables nested too deeply"],
    ),
    "nul-in-url": (
        '[[bus]]\nname = "arm"\nurl = "/dev/tty\\u0000USB0"\nbaud = 921600\n',
        ["bus 'arm' (#1): url='/dev/tty\\x00USB0' has the control character '\\x00' at 8"],
    ),
    "newline-in-url": (
        '[[bus]]\nname = "arm"\nurl = "/dev/ttyUSB0\\n"\nbaud = 921600\n',
        ["bus 'arm' (#1): url='/dev/ttyUSB0\\n' has the control character"],
    ),
    "la-baud-12345": (
        f'[[bus]]\n{LA}baud = 12345\ndevices = ["la:1-3"]\n',
        [
            "bus 'arm' (#1): baud=12345 is not a rate of the la devices on this bus: "
            "allowed 19200 | 57600 | 115200 | 921600"
        ],
    ),
    "project-stepper-at-921600": (
        f'[[bus]]\n{LA}baud = 921600\ndevices = ["project-stepper"]\n',
        ["bus 'arm' (#1): baud=921600 is not a rate of the project-stepper devices", "9600"],
    ),
    "la-and-project-stepper-share-no-rate": (
        f'[[bus]]\n{LA}baud = 9600\ndevices = ["la:1", "project-stepper"]\n',
        ["bus 'arm' (#1): baud=9600 is not a rate of the la devices"],
    ),
    "typo-key": (
        f"[[bus]]\n{LA}baud = 921600\nremove_ecko = true\n",
        ["bus 'arm' (#1): unknown keys ['remove_ecko']; allowed: ", "'remove_echo'"],
    ),
    "bad-value": (
        f"[[bus]]\n{LA}baud = 921600\nmin_spacing_ms = 500\n",
        ["bus 'arm' (#1): min_spacing_ms=500 ms is out of range: allowed 0..100 ms"],
    ),
    "same-url-twice": (
        f'[[bus]]\n{LA}baud = 921600\n\n[[bus]]\nname = "b"\nurl = "/dev/ttyUSB0"\nbaud = 9600\n',
        ["bus 'b' (#2): url='/dev/ttyUSB0' is the port of bus 'arm': one bus per port"],
    ),
    "same-port-spelled-twice": (
        f'[[bus]]\n{LA}baud = 921600\n\n[[bus]]\nname = "b"\nurl = "/dev/../dev/ttyUSB0"\n'
        "baud = 9600\n",
        ["bus 'b' (#2): url='/dev/../dev/ttyUSB0' is the port of bus 'arm' (both are "],
    ),
    "same-socket-twice": (
        '[[bus]]\nname = "arm"\nurl = "socket://10.0.0.5:7012"\nbaud = 9600\n\n'
        '[[bus]]\nname = "b"\nurl = "socket://10.0.0.5:7012"\nbaud = 9600\n',
        ["bus 'b' (#2): url='socket://10.0.0.5:7012' is the port of bus 'arm'"],
    ),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_a_bad_file_is_refused_by_the_library_naming_the_file(tmp_path: Path, case: str) -> None:
    body, fragments = BAD_FILES[case]
    path = _file(tmp_path, body)
    with pytest.raises(LocalProtocolError) as info:
        load_bus_file(path)
    text = str(info.value)
    assert "\n" not in text, text
    assert text.startswith(f"{path}: "), text
    for fragment in fragments:
        assert fragment in text, text
    with pytest.raises(LocalProtocolError) as again:
        BusManager.from_toml(path)
    assert str(again.value) == text  # one reader: the same words


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_the_cli_refuses_a_bad_file_with_the_library_message(
    tmp_path: Path,
    case: str,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "no-config"))
    body, _ = BAD_FILES[case]
    path = _file(tmp_path, body)
    with pytest.raises(LocalProtocolError) as info:
        load_bus_file(path)
    code = main(["la", "status", "1", "--bus-file", str(path), "--bus", "arm"])
    out, err = capsys.readouterr()
    assert code == EXIT_USAGE, err
    assert err == f"motorbus la: {info.value}\n"
    assert out == ""


def test_two_buses_on_one_port_through_a_symlink(tmp_path: Path) -> None:
    device = tmp_path / "ttyUSB0"
    device.touch()
    link = tmp_path / "by-id-adapter"
    link.symlink_to(device)
    path = _file(
        tmp_path,
        f'[[bus]]\nname = "arm"\nurl = "{device}"\nbaud = 921600\n\n'
        f'[[bus]]\nname = "b"\nurl = "{link}"\nbaud = 9600\n',
    )
    with pytest.raises(LocalProtocolError) as info:
        load_bus_file(path)
    text = str(info.value)
    assert f"bus 'b' (#2): url='{link}' is the port of bus 'arm' (both are '{device}')" in text
    # Built in code, the same rule.
    mgr = BusManager()
    mgr.add_bus("arm", str(device), baud=921600)
    with pytest.raises(LocalProtocolError, match=r"^bus 'b' \(#2\): url=.* is the port of bus"):
        mgr.add_bus("b", str(link), baud=9600)
    assert list(mgr.specs) == ["arm"]


def test_port_identity_resolves_device_paths_only(tmp_path: Path) -> None:
    link = tmp_path / "link"
    link.symlink_to(tmp_path / "dev")
    assert port_identity(str(link)) == os.path.realpath(tmp_path / "dev")
    assert port_identity("socket://host:1") == "socket://host:1"
    assert port_identity("memory://x") == "memory://x"


def test_the_family_rates_come_from_the_protocol() -> None:
    assert family_baud_rates(Family.LA) == tuple(sorted(c.baud for c in la.BaudCode))
    assert family_baud_rates(Family.PROJECT_STEPPER) == (9600,)
    assert family_baud_rates(Family.QUAD_STEPPER) is None  # doc 001 states none (A1-01)


@pytest.mark.parametrize(
    ("devices", "baud"),
    [
        (["la:1"], 115200),
        (["la:1"], 19200),
        (["project-stepper"], 9600),
        (["quad-stepper"], 115200),  # no stated rate: any plausible one
        (["quad-stepper", "project-stepper"], 9600),
        ([], 12345),  # no devices listed: no family to check against
    ],
)
def test_rates_the_families_take_load(devices: list[str], baud: int) -> None:
    spec = BusSpec.from_mapping({"url": "/dev/ttyUSB0", "baud": baud, "devices": devices})
    assert spec.baud == baud


def test_a_good_file_keeps_which_keys_each_table_set(tmp_path: Path) -> None:
    path = _file(
        tmp_path,
        f"[[bus]]\n{LA}baud = 921600\nremove_echo = true\nguard = true\n\n"
        '[[bus]]\nname = "feeder"\nurl = "/dev/ttyUSB1"\nbaud = 9600\n',
    )
    loaded = load_bus_file(path)
    assert loaded.names() == ["arm", "feeder"]
    assert loaded.given["arm"] == {"name", "url", "baud", "remove_echo", "guard"}
    arm = loaded.spec("arm")
    assert (arm.remove_echo, arm.guard, arm.share) == (True, True, False)
    with pytest.raises(LocalProtocolError, match="has no bus 'x': choose one of arm, feeder"):
        loaded.spec("x")
