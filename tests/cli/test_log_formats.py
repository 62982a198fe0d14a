"""``--format jsonl|csv|text`` and the filters ``--id``, ``--family``, ``--dir``,
``--command`` of ``capture`` and ``replay``; ``replay --speed/--loop`` end to end."""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from motorbus.cli.main import main
from motorbus.errors import LocalProtocolError
from motorbus.protocol import framelog, la, logview
from motorbus.sim.process import SimProcess
from tests.helpers import CLI_TIMEOUT_S, LOADED_HOST_MARGIN_MS, raw_pty
from tests.zygote import run_motorbus

QUERY_1 = la.Control(1, la.ControlAction.QUERY_STATUS).encode()
STATUS_1 = la.Status(1, target=100, position=90).encode()
MOVE_2 = la.MoveTo(2, 1300).encode()
STATUS_2 = la.Status(2, target=1300, position=0).encode()
BROADCAST_1_3 = la.Broadcast(la.BroadcastMode.FOLLOW, ((1, 100), (3, 300))).encode()


def sim_line(t: float, direction: str, raw: bytes, family: str | None = "la", **kw: Any) -> Any:
    return framelog.from_sim({"t": t, "dir": direction, "hex": raw.hex(" ").upper(),
                              "family": family, **kw})  # fmt: skip


@pytest.fixture
def log(tmp_path: Path) -> Path:
    """A simulator's log: a query and its status, a move and its status, a broadcast to
    1 and 3, garbage, a link drop."""
    header = framelog.header("sim", started_utc="2026-01-01T00:00:00.000000Z", families=["la"])
    lines = [
        header,
        sim_line(0.0, "rx", QUERY_1),
        sim_line(0.001, "tx", STATUS_1),
        sim_line(0.01, "rx", MOVE_2),
        sim_line(0.011, "tx", STATUS_2),
        sim_line(0.02, "rx", BROADCAST_1_3),
        sim_line(0.03, "rx", b"\x00\x13", family=None, fault="discarded: junk"),
        sim_line(0.04, "link", b"", family=None, fault="disconnect"),
    ]
    path = tmp_path / "sim.jsonl"
    path.write_text("".join(json.dumps(x) + "\n" for x in lines), encoding="utf-8")
    return path


def names(log: Path, *args: str) -> list[str]:
    records = framelog.continuous_times(framelog.read_frame_log(log.read_bytes().splitlines()))
    keep = logview.RecordFilter.build(**_filter_kwargs(args))
    out = []
    for r in records:
        described = framelog.describe_record(r)
        if keep.keeps(r, described):
            out.append(described[0].name if described else str(r["name"]))
    return out


def _filter_kwargs(args: tuple[str, ...]) -> dict[str, Any]:
    kw: dict[str, Any] = {}
    for key, value in zip(args[::2], args[1::2], strict=True):
        kw[key] = [int(v) for v in value.split(",")] if key == "ids" else value.split(",")
    return kw


@pytest.mark.parametrize(
    ("criteria", "kept"),
    [
        ((), ["Control", "Status", "MoveTo", "Status", "Broadcast", "garbage", "down"]),
        (("ids", "1"), ["Control", "Status", "Broadcast"]),  # broadcast entries count
        (("ids", "3"), ["Broadcast"]),
        (("ids", "2"), ["MoveTo", "Status"]),
        (("directions", "reply"), ["Status", "Status"]),
        (("directions", "request"), ["Control", "MoveTo", "Broadcast", "garbage"]),
        (("commands", "status"), ["Status", "Status"]),  # any case
        (("commands", "QUERY_STATUS,moveto"), ["Control", "MoveTo"]),  # LA control action
        (("families", "la"), ["Control", "Status", "MoveTo", "Status", "Broadcast"]),
        (("families", "quad_stepper"), []),
        (("ids", "2", "directions", "reply"), ["Status"]),  # every criterion must hold
    ],
)
def test_filters_keep_what_they_name(log: Path, criteria: tuple[str, ...], kept: list[str]) -> None:
    assert names(log, *criteria) == kept


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"families": ["tea"]}, "--family=tea is not one of la, project_stepper, quad_stepper"),
        ({"directions": ["sideways"]}, "--dir=sideways is not one of request, reply"),
        ({"commands": [""]}, "--command must name one or more commands"),
    ],
)
def test_a_bad_filter_is_refused(kwargs: dict[str, Any], message: str) -> None:
    with pytest.raises(LocalProtocolError, match=message):
        logview.RecordFilter.build(**kwargs)


def test_text_is_one_line_a_frame_in_columns(log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(log), "--format", "text"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == (
        "(     0.000000) la              ->   1 [  8] 55 AA 03 01 04 00 22 2A  "
        "Control action=QUERY_STATUS"
    )
    assert lines[2].startswith("(     0.010000) la              ->   2 [  9] 55 AA 04 02 21")
    assert lines[3].startswith("(     0.011000) la              <-   2 [ 22] AA 55 11 02")
    assert " ->   - [ 12] 55 AA 07 FF F3 " in lines[4]  # a broadcast names several IDs
    assert lines[5] == "(     0.030000) -               ->   - [  2] 00 13  garbage (junk)"
    assert lines[6] == "(     0.040000) link            down  fault=disconnect"


def test_csv_has_a_header_row_and_a_row_a_record(
    log: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["replay", str(log), "--format", "csv", "--dir", "reply"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [(r["t"], r["name"], r["id"], r["direction"]) for r in rows] == [
        ("0.001000", "Status", "1", "reply"),
        ("0.011000", "Status", "2", "reply"),
    ]
    assert json.loads(rows[1]["fields"])["target"] == 1300
    assert rows[0]["hex"] == STATUS_1.hex(" ").upper()


def test_jsonl_is_a_filtered_frame_log_that_replay_reads(
    log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["replay", str(log), "--format", "jsonl", "--id", "2"]) == 0
    copy = tmp_path / "copy.jsonl"
    copy.write_text(capsys.readouterr().out, encoding="utf-8")
    again = framelog.read_frame_log(copy.read_bytes().splitlines(), str(copy))
    assert again.headers[0]["filter"] == {"id": [2]}
    assert [r["hex"] for r in again.records] == [MOVE_2.hex(" ").upper(), STATUS_2.hex(" ").upper()]
    assert [r["t"] for r in again.records] == [0.01, 0.011]  # the session's own times


def test_format_does_not_go_with_json(log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["replay", str(log), "--format", "csv", "--json"]) == 2
    assert "--format shows a log" in capsys.readouterr().err


@pytest.fixture
def bare_pty() -> Iterator[tuple[int, str]]:
    with raw_pty() as pair:
        yield pair


def test_dry_run_sends_only_the_filtered_requests_at_speed(
    log: Path, bare_pty: tuple[int, str], capsys: pytest.CaptureFixture[str]
) -> None:
    _, port = bare_pty
    args = ["replay", str(log), "--to", port, "--dry-run", "--id", "1", "--speed", "4"]
    assert main([*args, "--loop", "3"]) == 0
    out, err = capsys.readouterr()
    assert [line.split()[2:5] for line in out.splitlines()] == [
        ["0.000000", "la", "request"],
        ["0.005000", "la", "request"],  # 0.02 s at 4 times the speed
    ]
    assert "Control id=1" in out and "Broadcast" in out and "MoveTo" not in out
    assert err == f"motorbus replay: dry run, 2 requests would be sent to {port}, 3 times\n"


def test_capture_writes_text_and_filters(bare_pty: tuple[int, str], tmp_path: Path) -> None:
    master, port = bare_pty
    out = tmp_path / "heard.txt"
    proc = subprocess.Popen(
        [sys.executable, "-m", "motorbus", "capture", "--port", port, "--family", "la",
         "--seconds", "1", "--out", str(out), "--format", "text", "--id", "2"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stderr is not None
    assert proc.stderr.readline().startswith("motorbus capture: listening on")
    os.write(master, QUERY_1 + STATUS_1 + MOVE_2 + STATUS_2)
    _, err = proc.communicate(timeout=CLI_TIMEOUT_S)
    assert proc.returncode == 0, err
    assert "2 frames (2 left out by the filter)" in err
    lines = out.read_text(encoding="utf-8").splitlines()
    assert [line.split()[2:5] for line in lines] == [["la", "->", "2"], ["la", "<-", "2"]]
    assert "MoveTo position=1300" in lines[0] and "Status target=1300" in lines[1]


def test_replay_loops_at_speed_through_a_simulator(tmp_path: Path) -> None:
    header = framelog.header("capture", started_utc="2026-01-01T00:00:00.000000Z", families=["la"])
    queries = [la.Control(i, la.ControlAction.QUERY_STATUS).encode() for i in (1, 2)]
    lines = [header] + [
        {"t": 0.02 * n, "kind": "frame", "family": "la", "direction": "request",
         "hex": q.hex(" ").upper()} for n, q in enumerate(queries)
    ]  # fmt: skip
    path = tmp_path / "two.jsonl"
    path.write_text("".join(json.dumps(x) + "\n" for x in lines), encoding="utf-8")
    # Behaviour, not speed: the loaded-host margin (replay --to takes no bus file; a reply
    # once came more than the command line's 50 ms late in a fresh-clone run).
    env = {**os.environ, "MOTORBUS_HOST_MARGIN_MS": str(LOADED_HOST_MARGIN_MS)}
    with SimProcess(["la:1-2"], baud=921600, log_file=tmp_path / "sim.jsonl") as sim:
        r = run_motorbus(
            ["replay", str(path), "--to", sim.path, "--loop", "3", "--speed", "2", "--wait", "0.1"],
            env,
            CLI_TIMEOUT_S,
        )
        heard = [x["hex"] for x in sim.log_records() if x["direction"] == "request"]
    assert r.returncode == 0, r.stderr
    assert heard == [q.hex(" ").upper() for q in queries] * 3
    assert "6 requests sent" in r.stderr and "(3 passes), 6 replies, 0 failed" in r.stderr
