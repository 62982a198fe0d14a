"""``motorbus la``, ``scan`` and ``monitor`` as subprocesses against ``motorbus sim`` on a pty.

The command-line helpers (``cli``...) are in ``tests.helpers``.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from motorbus.cli.bus_options import PORT_ENV
from motorbus.cli.ids import parse_id_args, parse_ids
from motorbus.cli.la import baud_code, format_value, status_json, status_row
from motorbus.cli.main import build_parser
from motorbus.cli.output import LiveText
from motorbus.cli.scan import ProgressBar
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.sim.process import SimProcess
from tests.helpers import cli, json_lines, rx_frames


@pytest.fixture(scope="module")
def la_sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimProcess]:
    """Three simulated LA actuators (IDs 1..3) on a pty, logging every frame."""
    log = tmp_path_factory.mktemp("la") / "frames.jsonl"
    with SimProcess(["la:1-3"], baud=921600, log_file=log) as sim:
        yield sim


# -- happy paths ------------------------------------------------------------------------------


def test_status_prints_a_table_of_every_id(la_sim: SimProcess) -> None:
    r = cli("la", "status", "1", "2", "3", "--port", la_sim.path)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[0].split() == ["id", "target", "position", "temp", "current", "force", "errors"]
    assert [int(line.split()[0]) for line in lines[1:]] == [1, 2, 3]


def test_move_then_status_json_shows_the_target(la_sim: SimProcess) -> None:
    r = cli("la", "move", "2", "1500", "--port", la_sim.path, "--json")
    assert r.returncode == 0, r.stderr
    assert json_lines(r.stdout)[0]["target"] == 1500
    r = cli("la", "status", "2", "--port", la_sim.path, "--json")
    assert r.returncode == 0, r.stderr
    (doc,) = json_lines(r.stdout)
    assert doc["id"] == 2 and doc["target"] == 1500 and doc["errors"] == []
    assert "55 AA 04 02 21 37 DC 05" in " ".join(rx_frames(la_sim))  # 0x21, 1500 = 0x05DC


def test_move_without_reply_sends_0x03(la_sim: SimProcess) -> None:
    r = cli("la", "move", "1", "700", "--no-reply", "--port", la_sim.path)
    assert (r.returncode, r.stdout) == (0, "sent\n"), r.stderr
    assert any(h.startswith("55 AA 04 01 03 37 BC 02") for h in rx_frames(la_sim))


def test_set_then_get_a_register_with_its_unit(la_sim: SimProcess) -> None:
    r = cli("la", "set", "1", "OVER_CURRENT_LIMIT", "800", "--port", la_sim.path)
    assert r.returncode == 0, r.stderr
    assert r.stdout == (
        "la:1 over_current_limit set to 800 mA: effective now, lost at power-off unless "
        "`motorbus la save 1`\n"
    )
    r = cli("la", "set", "1", "baud", "115200", "--port", la_sim.path)
    assert r.returncode == 0, r.stderr
    assert "takes effect only after `motorbus la save 1` and a power cycle" in r.stdout
    assert cli("la", "set", "1", "baud", "921600", "--port", la_sim.path).returncode == 0
    r = cli("la", "get", "1", "over_current_limit", "--port", la_sim.path)
    assert (r.returncode, r.stdout) == (0, "la:1 over_current_limit = 800 mA\n")
    r = cli("la", "get", "1", "Over_Temperature_Limit", "--port", la_sim.path, "--json")
    assert json_lines(r.stdout) == [
        {"id": 1, "register": "over_temperature_limit", "value": 800, "unit": "0.1 degC"}
    ]


def test_set_id_moves_the_actuator_and_back(la_sim: SimProcess) -> None:
    r = cli("la", "set-id", "3", "7", "--port", la_sim.path)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("la:3 is now la:7")
    assert cli("la", "status", "7", "--port", la_sim.path).returncode == 0
    r = cli("la", "set-id", "7", "3", "--port", la_sim.path, "--json")
    assert json_lines(r.stdout) == [{"old": 7, "new": 3, "saved": False}]


@pytest.mark.parametrize("ids", [["1-3"], ["1,2,3"], ["1", "2", "3"], ["1-2", "3"]])
def test_status_takes_lists_and_ranges(la_sim: SimProcess, ids: list[str]) -> None:
    r = cli("la", "status", *ids, "--port", la_sim.path, "--json")
    assert r.returncode == 0, r.stderr
    assert [d["id"] for d in json_lines(r.stdout)] == [1, 2, 3]


def test_a_silent_id_among_several_gets_a_row_and_exit_1(la_sim: SimProcess) -> None:
    r = cli("la", "status", "1", "9", "2", "--port", la_sim.path)
    assert r.returncode == 1
    rows = r.stdout.splitlines()[1:]
    assert [row.split()[0] for row in rows] == ["1", "9", "2"]
    assert rows[1].split()[1:] == ["timeout", "(no", "reply)"]
    assert rows[0].split()[3].endswith("°C")
    assert r.stderr.splitlines() == [
        "motorbus la: 1 actuator of 3 did not answer (la:9): check the IDs (motorbus scan "
        "lists the ones that answer) and --baud 921600"
    ]
    r = cli("la", "pause", "9,1", "--port", la_sim.path, "--json")
    assert r.returncode == 1
    rows = json_lines(r.stdout)
    assert rows[:2] == [{"id": 9, "error": "timeout"}, rows[1]]
    assert rows[1]["id"] == 1
    # Then the one error object of a failure (docs/cli.md): code, and which IDs.
    assert len(rows) == 3
    assert (rows[2]["code"], rows[2]["command"], rows[2]["ids"]) == (1, "la", [9])


def test_set_id_onto_an_id_that_answers_is_refused(la_sim: SimProcess) -> None:
    before = rx_frames(la_sim)
    r = cli("la", "set-id", "1", "2", "--port", la_sim.path)
    assert (r.returncode, r.stdout) == (2, "")
    assert r.stderr.startswith("motorbus la: new id=2 already answers on ")
    assert "nothing written" in r.stderr and "--force" in r.stderr
    sent = rx_frames(la_sim)[len(before) :]
    # Only the look at la:2 (a status query, 0x04 sub 0x22) went out: no write.
    assert sent and all(h.startswith("55 AA 03 02 04 00 22") for h in sent), sent
    assert cli("la", "status", "1", "2", "--port", la_sim.path).returncode == 0


def test_get_baud_shows_the_rate_and_the_code(la_sim: SimProcess) -> None:
    r = cli("la", "get", "1", "baud", "--port", la_sim.path)
    assert (r.returncode, r.stdout) == (0, "la:1 baud = 921600 (code 3)\n"), r.stderr
    r = cli("--json", "la", "get", "1", "baud", "--port", la_sim.path)
    assert json_lines(r.stdout) == [
        {"id": 1, "register": "baud", "value": 3, "unit": "code", "baud": 921600}
    ]


def test_controls_answer_ok(la_sim: SimProcess) -> None:
    for action in ("pause", "enable"):
        r = cli("la", action, "1", "2", "--port", la_sim.path)
        assert (r.returncode, r.stdout) == (0, "la:1 ok\nla:2 ok\n"), r.stderr


def test_scan_finds_the_three_actuators(la_sim: SimProcess) -> None:
    r = cli("scan", "--ids", "1-6", "--port", la_sim.path)
    assert (r.returncode, r.stdout) == (0, "1,2,3\n"), r.stderr
    assert "6/6 IDs decided, found 3" in r.stderr  # stderr is not a tty: progress lines
    r = cli("scan", "--ids", "1-4", "--port", la_sim.path, "--json")
    assert json_lines(r.stdout) == [{"ids": [1, 2, 3], "tried": 4}]


def test_monitor_count_2_prints_two_refreshes(la_sim: SimProcess) -> None:
    r = cli("monitor", "--ids", "1-3", "--count", "2", "--interval", "0.01", "--port", la_sim.path)
    assert r.returncode == 0, r.stderr
    assert [ln.split()[1] for ln in r.stdout.splitlines() if ln.startswith("refresh")] == ["1", "2"]
    r = cli(
        "monitor", "--ids", "1,2", "--count", "2", "--interval", "0.01", "--json",
        "--port", la_sim.path,
    )  # fmt: skip
    docs = json_lines(r.stdout)
    assert [d["refresh"] for d in docs] == [1, 2]
    assert [[s["id"] for s in d["statuses"]] for d in docs] == [[1, 2], [1, 2]]


def test_port_from_the_environment(la_sim: SimProcess) -> None:
    r = cli("la", "status", "1", "--json", env={PORT_ENV: la_sim.path})
    assert r.returncode == 0, r.stderr
    assert json_lines(r.stdout)[0]["id"] == 1


# -- pure helpers -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "ids"),
    [("1", [1]), ("1-3", [1, 2, 3]), ("3,1, 7-8", [3, 1, 7, 8]), ("254", [254])],
)
def test_parse_ids(text: str, ids: list[int]) -> None:
    assert parse_ids(text) == ids


@pytest.mark.parametrize("text", ["0", "255", "1-300", "a", "3-1", "1,1", ""])
def test_parse_ids_refuses(text: str) -> None:
    with pytest.raises(LocalProtocolError, match="--ids"):
        parse_ids(text)


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("3-1", "--ids='3-1': reversed range 3-1: write 1-3"),
        ("1-3,2", "--ids='1-3,2' lists ID 2 twice"),
        ("1,x", "--ids='1,x': 'x' is not an ID or a range like 1-15"),
        ("1-255", "--ids id=255 is out of range: allowed 1..254"),
    ],
)
def test_parse_ids_messages(text: str, message: str) -> None:
    with pytest.raises(LocalProtocolError) as info:
        parse_ids(text)
    assert str(info.value) == message


def test_id_arguments_join_lists_and_ranges() -> None:
    assert parse_id_args(["1-3", "7"]) == [1, 2, 3, 7]
    assert parse_id_args(["1,2", "3"]) == [1, 2, 3]
    with pytest.raises(LocalProtocolError, match="lists ID 2 twice"):
        parse_id_args(["1-3", "2"])


def test_status_formats() -> None:
    s = la.Status(4, target=1500, position=1490, temperature=31, current=250, force=-12, errors=5)
    assert status_json(s) == {
        "id": 4,
        "target": 1500,
        "position": 1490,
        "temperature_c": 31,
        "current_ma": 250,
        "force_g": -12,
        "errors": ["stall", "over_current"],
    }
    assert status_row(s).split() == [
        "4",
        "1500",
        "1490",
        "31°C",
        "250mA",
        "-12g",
        "stall,over_current",
    ]
    assert status_json(la.Status(1, target=0, position=0, errors=0x30))["errors"] == ["0x30"]


def test_format_value() -> None:
    assert format_value(la.Register.OVER_CURRENT_LIMIT, 800) == "800 mA"
    assert format_value(la.Register.RECOVERY_TEMPERATURE, 600) == "600 (60.0 °C)"
    assert format_value(la.Register.ID, 3) == "3"
    assert format_value(la.Register.BAUD, 3) == "921600 (code 3)"
    assert format_value(la.Register.BAUD, 0) == "19200 (code 0)"


def test_baud_takes_a_code_or_its_rate_and_lists_both() -> None:
    assert baud_code(2) == 2
    assert baud_code(115200) == 2
    with pytest.raises(LocalProtocolError) as info:
        baud_code(9600)
    assert str(info.value) == (
        "baud=9600 is not allowed: give a code or its rate: 0 (19200 bit/s), "
        "1 (57600 bit/s), 2 (115200 bit/s), 3 (921600 bit/s)"
    )


class _Tty:
    def __init__(self) -> None:
        self.text = ""

    def write(self, s: str) -> int:
        self.text += s
        return len(s)

    def flush(self) -> None:
        pass

    def isatty(self) -> bool:
        return True


def test_progress_bar_redraws_in_place_on_a_tty() -> None:
    out = _Tty()
    bar = ProgressBar(out, tty=True)  # type: ignore[arg-type]
    bar(1, 2, True)
    bar(2, 2, False)
    assert out.text == (
        "\r[" + "#" * 15 + "." * 15 + "] 1/2 IDs decided, found 1: la:1"
        "\r[" + "#" * 30 + "] 2/2 IDs decided, found 1: la:1\n"
    )


def test_live_text_moves_the_cursor_up_on_a_tty() -> None:
    out = _Tty()
    live = LiveText(out, tty=True)  # type: ignore[arg-type]
    live.show(["a", "b"])
    live.show(["c"])
    assert out.text == "a\nb\n\x1b[2F\x1b[Jc\n"


def test_help_lists_every_hardware_command() -> None:
    text = build_parser().format_help()
    for command in ("scan", "la", "stream", "monitor", "project", "quad", "capture", "replay"):
        assert f"    {command} " in text
