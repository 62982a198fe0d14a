"""What a new user of the command line meets first: --version, flags anywhere, ID lists,
configuration (arguments > environment > bus file), port errors, help text, pipes."""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import pytest

from motorbus.cli.bus_options import (
    BACKEND_ENV,
    BAUD_ENV,
    BUS_ENV,
    BUS_FILE_ENV,
    ENV_VARS,
    PORT_ENV,
    available_ports,
    resolve_port,
)
from motorbus.cli.main import EXIT_OK, EXIT_USAGE, UsageError, build_parser, main
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager, default_bus_file
from motorbus.sim.process import SimProcess
from tests.helpers import cli, json_lines


@pytest.fixture(scope="module")
def sim() -> Iterator[SimProcess]:
    with SimProcess(["la:1-2"], baud=921600) as s:
        yield s


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """No MOTORBUS_* variables; XDG_CONFIG_HOME is an empty directory (returned)."""
    for name in ENV_VARS:
        monkeypatch.delenv(name, raising=False)
    config = tmp_path / "config"
    config.mkdir()
    monkeypatch.setenv("XDG_CONFIG_HOME", str(config))
    return config


def run_main(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


# -- --version, flags anywhere -----------------------------------------------------------------


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out == f"motorbus {importlib.metadata.version('motorbus')}\n"


@pytest.mark.parametrize(
    "args",
    [
        ["--json", "la", "status", "1"],
        ["la", "--json", "status", "1"],
        ["la", "status", "--json", "1"],
        ["la", "status", "1", "--json"],
    ],
)
def test_json_anywhere_on_the_line(
    sim: SimProcess, clean_env: Path, capsys: pytest.CaptureFixture[str], args: list[str]
) -> None:
    code, out, err = run_main(capsys, *args, "--port", sim.path)
    assert code == EXIT_OK, err
    assert json_lines(out)[0]["id"] == 1


def test_debug_after_the_command_shows_the_traceback(sim: SimProcess) -> None:
    r = cli("la", "status", "9", "--port", sim.path, "--debug")
    assert r.returncode == 1
    assert "Traceback (most recent call last)" in r.stderr


def test_json_on_a_command_without_data_is_a_usage_error(
    clean_env: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        main(["sim", "la:1", "--json"])
    assert info.value.code == EXIT_USAGE
    assert "--json: motorbus sim prints no data" in capsys.readouterr().err


# -- ID lists ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["la", "status", "3-1"], "motorbus la: id='3-1': reversed range 3-1: write 1-3"),
        (
            ["monitor", "--ids", "3-1", "--count", "1"],
            "motorbus monitor: --ids='3-1': reversed range 3-1: write 1-3",
        ),
        (
            ["stream", "x.csv", "--ids", "5-2"],
            "motorbus stream: --ids='5-2': reversed range 5-2: write 2-5",
        ),
        (["la", "pause", "1-3", "2"], "motorbus la: id='1,2,3,2' lists ID 2 twice"),
    ],
)
def test_reversed_ranges_are_named(
    clean_env: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    code, out, err = run_main(capsys, *args, "--port", "/dev/motorbus-no-such-port")
    assert (code, out, err) == (EXIT_USAGE, "", message + "\n")


# -- configuration: arguments > environment > bus file ---------------------------------------


BUS_FILE = """
[[bus]]
name = "arm"
url = "{arm}"
baud = {baud}
backend = "{backend}"
devices = ["la:1-2"]

[[bus]]
name = "feeder"
url = "/dev/motorbus-feeder"
baud = 9600
"""


def options(**given: object) -> argparse.Namespace:
    values: dict[str, object] = {
        "port": None,
        "baud": None,
        "backend": None,
        "bus_file": None,
        "bus": None,
        "_default_baud": 921600,
    }
    values.update(given)
    return argparse.Namespace(**values)


def test_bus_file_and_bus_name_fill_in_the_bus_options(clean_env: Path, tmp_path: Path) -> None:
    f = tmp_path / "buses.toml"
    f.write_text(
        BUS_FILE.format(arm="/dev/motorbus-arm", baud=115200, backend="pyserial-asyncio"),
        encoding="utf-8",
    )
    args = options(bus_file=str(f), bus="arm")
    assert resolve_port(args) == "/dev/motorbus-arm"
    assert (args.baud, args.backend) == (115200, "pyserial-asyncio")
    args = options(bus_file=str(f), bus="feeder")
    assert (resolve_port(args), args.baud, args.backend) == ("/dev/motorbus-feeder", 9600, "fast")
    with pytest.raises(UsageError, match=r"has 2 buses: choose one with --bus arm\|feeder"):
        resolve_port(options(bus_file=str(f)))
    with pytest.raises(UsageError, match="has no such bus: choose one of arm, feeder"):
        resolve_port(options(bus_file=str(f), bus="x"))
    with pytest.raises(UsageError, match="no such file"):
        resolve_port(options(bus_file=str(tmp_path / "missing.toml")))


def test_precedence_arguments_then_environment_then_file(
    clean_env: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    f = tmp_path / "buses.toml"
    f.write_text(
        BUS_FILE.format(arm="/dev/from-file", baud=115200, backend="pyserial-asyncio"),
        encoding="utf-8",
    )
    monkeypatch.setenv(BUS_FILE_ENV, str(f))
    monkeypatch.setenv(BUS_ENV, "arm")
    args = options()
    assert (resolve_port(args), args.baud, args.backend) == (
        "/dev/from-file",
        115200,
        "pyserial-asyncio",
    )
    monkeypatch.setenv(PORT_ENV, "/dev/from-env")
    monkeypatch.setenv(BAUD_ENV, "57600")
    monkeypatch.setenv(BACKEND_ENV, "serialx")
    args = options()
    assert (resolve_port(args), args.baud, args.backend) == ("/dev/from-env", 57600, "serialx")
    args = options(port="/dev/from-arg", baud=19200, backend="fast")
    assert (resolve_port(args), args.baud, args.backend) == ("/dev/from-arg", 19200, "fast")
    monkeypatch.setenv(BAUD_ENV, "fast")
    with pytest.raises(UsageError, match="MOTORBUS_BAUD='fast' is not an integer"):
        resolve_port(options())


def test_the_user_bus_file_is_read_by_the_cli_and_by_bus_manager(
    sim: SimProcess, clean_env: Path
) -> None:
    user_file = clean_env / "motorbus" / "buses.toml"
    assert default_bus_file() == user_file
    user_file.parent.mkdir()
    user_file.write_text(
        BUS_FILE.format(arm=sim.path, baud=921600, backend="fast"), encoding="utf-8"
    )
    assert list(BusManager.from_toml().specs) == ["arm", "feeder"]
    # Two buses: the user file applies once one is named.
    r = cli("la", "status", "1", "--json", env={"XDG_CONFIG_HOME": str(clean_env)})
    assert r.returncode == EXIT_USAGE
    assert "--port is required" in r.stderr
    env = {"XDG_CONFIG_HOME": str(clean_env), BUS_ENV: "arm"}
    r = cli("la", "status", "1", "--json", env=env)
    assert r.returncode == 0, r.stderr
    assert json_lines(r.stdout)[0]["id"] == 1


def test_the_user_bus_file_does_not_apply_to_a_port_given_on_the_line(
    clean_env: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    user_file = clean_env / "motorbus" / "buses.toml"
    user_file.parent.mkdir()
    user_file.write_text('[[bus]]\nurl = "/dev/la"\nbaud = 921600\n', encoding="utf-8")
    args = options(_default_baud=9600)
    assert (resolve_port(args), args.baud) == ("/dev/la", 921600)  # the only bus
    args = options(port="/dev/quad", _default_baud=9600)
    assert (resolve_port(args), args.baud) == ("/dev/quad", 9600)  # not the file's 921600
    monkeypatch.setenv(BUS_ENV, "nope")
    with pytest.raises(UsageError, match=r"--bus nope: .* has no such bus: choose one of bus0"):
        resolve_port(options(port="/dev/quad"))
    user_file.unlink()
    with pytest.raises(UsageError, match="--bus nope: no bus file: give --bus-file or create"):
        resolve_port(options())


def test_bad_toml_names_the_file_and_the_line(
    clean_env: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = tmp_path / "buses.toml"
    f.write_text('[[bus]]\nname = "arm"\nurl = \n', encoding="utf-8")
    code, _, err = run_main(capsys, "la", "status", "1", "--bus-file", str(f))
    assert code == EXIT_USAGE
    assert err.startswith(f"motorbus la: {f}: not valid TOML: ")
    assert "line 3" in err
    with pytest.raises(LocalProtocolError, match=rf"{f}: not valid TOML: .*line 3"):
        BusManager.from_toml(f)


# -- port errors, help text, pipes ----------------------------------------------------------


def test_a_port_error_is_one_line_listing_the_ports(
    clean_env: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from serial.tools import list_ports

    fake = [
        SimpleNamespace(device="/dev/ttyUSB0", description="FT232R USB UART"),
        SimpleNamespace(device="/dev/ttyACM0", description="n/a"),
    ]
    monkeypatch.setattr(list_ports, "comports", lambda: fake)
    code, _, err = run_main(capsys, "la", "status", "1", "--port", "/dev/motorbus-no-such-port")
    assert code == 1
    assert err == (
        "motorbus la: cannot open port /dev/motorbus-no-such-port: No such file or directory; "
        "available ports: /dev/ttyACM0, /dev/ttyUSB0 (FT232R USB UART)\n"
    )
    monkeypatch.setattr(list_ports, "comports", list)
    assert available_ports() == "no serial ports found on this machine"


def _parsers(parser: argparse.ArgumentParser) -> Iterator[argparse.ArgumentParser]:
    yield parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                yield from _parsers(child)


def test_help_texts_are_plain_text() -> None:
    helps = [p.format_help() for p in _parsers(build_parser())]
    assert len(helps) > 20
    for text in helps:
        assert "``" not in text, text
        assert "::\n" not in text, text


def _session(path: Path, records: int) -> Path:
    """A capture file of ``records`` status queries, 1 ms apart."""
    query = "55 AA 03 01 04 00 22 2A"
    record = {"kind": "frame", "family": "la", "direction": "request", "name": "Control"}
    lines = [
        json.dumps({"t": k / 1000, **record, "fields": {}, "hex": query}) for k in range(records)
    ]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


@pytest.mark.parametrize("command", ["decode", "replay"])
def test_a_closed_pipe_ends_quietly(tmp_path: Path, command: str) -> None:
    if command == "decode":
        source = tmp_path / "frames.txt"
        source.write_text("55 AA 03 01 04 00 22 2A\n" * 20000, encoding="utf-8")
        line = f"'{sys.executable}' -m motorbus decode < '{source}'"
    else:
        source = _session(tmp_path / "session.jsonl", 20000)
        line = f"'{sys.executable}' -m motorbus replay '{source}'"
    err = tmp_path / "err.txt"
    r = subprocess.run(
        f"{line} 2> '{err}' | head -n 1",
        shell=True,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert "la request Control" in r.stdout
    assert err.read_text(encoding="utf-8") == ""
