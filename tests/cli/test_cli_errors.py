"""Error paths of the hardware commands: exit codes, one-line messages, nothing sent.

Input errors are checked in-process through ``main`` (the same code path, without a
Python start-up per case); failures that need a real process (a missing port, a
timeout, ``--debug`` tracebacks) run ``python -m motorbus``.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from motorbus.cli.bus_options import ENV_VARS
from motorbus.cli.main import EXIT_FAILURE, EXIT_USAGE, main
from motorbus.sim.process import SimProcess
from tests.helpers import NO_CONFIG_DIR, cli, rx_frames


@pytest.fixture(scope="module")
def quiet_sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimProcess]:
    """One LA actuator (ID 1), logging every frame it receives."""
    log = tmp_path_factory.mktemp("errors") / "frames.jsonl"
    with SimProcess(["la:1"], baud=921600, log_file=log) as sim:
        yield sim


def run_main(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, *args: str
) -> tuple[int, str, str]:
    """``main(args)`` in-process: (exit code, stdout, stderr)."""
    for name in ENV_VARS:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", NO_CONFIG_DIR)
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def one_line(text: str) -> str:
    lines = text.splitlines()
    assert len(lines) == 1, text
    return lines[0]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["la", "status", "0"], "motorbus la: id=0 is out of range: allowed 1..254"),
        (["la", "move", "255", "100"], "motorbus la: id=255 is out of range: allowed 1..254"),
        (
            ["la", "move", "1", "2001"],
            "motorbus la: position=2001 is out of range: allowed 0..2000",
        ),
        (
            ["la", "set", "1", "over_current_limit", "1501"],
            "motorbus la: over_current_limit=1501 is out of range: allowed 300..1500",
        ),
        (
            ["la", "set", "1", "position", "5"],
            "motorbus la: register POSITION (index 26) is read-only",
        ),
        (["la", "set-id", "1", "300"], "motorbus la: new id=300 is out of range: allowed 1..254"),
        (["scan", "--ids", "1-255"], "motorbus scan: --ids id=255 is out of range: allowed 1..254"),
        # The range the transport allows (it said 1..10000000, and then 5 was refused).
        (
            ["la", "status", "1", "--baud", "0"],
            "motorbus la: --baud=0 is out of range: allowed 300..4000000",
        ),
        (["scan", "--baud", "5"], "motorbus scan: --baud=5 is out of range: allowed 300..4000000"),
        (
            ["monitor", "--ids", "1", "--count", "0"],
            "motorbus monitor: --count=0 is out of range: allowed 1..1000000000",
        ),
    ],
)
def test_bad_input_exits_2_with_one_line_and_sends_nothing(
    quiet_sim: SimProcess,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    args: list[str],
    message: str,
) -> None:
    before = rx_frames(quiet_sim)
    code, out, err = run_main(capsys, monkeypatch, *args, "--port", quiet_sim.path)
    assert (code, out) == (EXIT_USAGE, "")
    assert one_line(err) == message
    assert rx_frames(quiet_sim) == before


def test_unknown_register_exits_2_naming_the_choices(
    quiet_sim: SimProcess, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    before = rx_frames(quiet_sim)
    code, _, err = run_main(
        capsys, monkeypatch, "la", "get", "1", "speed", "--port", quiet_sim.path
    )
    assert code == EXIT_USAGE
    line = one_line(err)
    assert line.startswith("motorbus la: register='speed' is not allowed: choose one of ID, BAUD")
    assert "OVER_CURRENT_LIMIT" in line
    assert rx_frames(quiet_sim) == before


def test_missing_port_exits_2() -> None:
    r = cli("la", "status", "1")
    assert r.returncode == EXIT_USAGE
    assert one_line(r.stderr) == (
        "motorbus la: --port is required (or set MOTORBUS_PORT, or use --bus-file): "
        "e.g. --port /dev/ttyUSB0"
    )


def test_a_port_that_does_not_exist_exits_1_with_one_line() -> None:
    r = cli("la", "status", "1", "--port", "/dev/motorbus-no-such-port")
    assert r.returncode == EXIT_FAILURE
    assert one_line(r.stderr).startswith(
        "motorbus la: cannot open port /dev/motorbus-no-such-port: "
    )


def test_a_silent_id_exits_1_with_a_timeout_message(quiet_sim: SimProcess) -> None:
    r = cli("la", "status", "9", "--port", quiet_sim.path)
    assert r.returncode == EXIT_FAILURE
    line = one_line(r.stderr)
    assert line.startswith("motorbus la: no reply from la:9 to Control (55 AA 03 09 04 00 22")
    assert " ms after 2 attempts" in line


def test_scan_finding_nothing_exits_1(quiet_sim: SimProcess) -> None:
    r = cli("scan", "--ids", "5-6", "--port", quiet_sim.path)
    assert (r.returncode, r.stdout) == (EXIT_FAILURE, "")
    assert "no actuator answered (2 IDs tried at" in r.stderr
    assert "docs/hardware.md" in r.stderr  # where to look next


def test_debug_shows_a_traceback(quiet_sim: SimProcess) -> None:
    r = cli("--debug", "la", "status", "9", "--port", quiet_sim.path)
    assert r.returncode != 0
    assert "Traceback (most recent call last)" in r.stderr
    assert "ReplyTimeoutError: no reply from la:9" in r.stderr


def test_bad_stepper_input_exits_2_before_the_port_opens(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # No simulator: the port is never opened, because the input is refused first.
    port = "/dev/motorbus-no-such-port"
    cases = [
        (["quad", "run", "5"], "motorbus quad: motor=5 is out of range: allowed 1..4"),
        (["quad", "led", "6", "on"], "motorbus quad: led=6 is out of range: allowed 1..5"),
        (["quad", "home", "1", "--input", "14"], "motorbus quad: --input=14 is out of range"),
        (["project", "run", "5"], "motorbus project: project=5 is out of range: allowed 1..4"),
    ]
    for args, message in cases:
        code, _, err = run_main(capsys, monkeypatch, *args, "--port", port)
        assert code == EXIT_USAGE, args
        assert one_line(err).startswith(message)
