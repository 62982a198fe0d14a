"""The frame-log format (docs/frame-log.md) and ``motorbus replay`` of it: to the screen,
and through a ``Bus`` to a simulator."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from motorbus.cli.bus_options import PORT_ENV
from motorbus.cli.replay import load_records
from motorbus.errors import LocalProtocolError
from motorbus.protocol import framelog, la
from motorbus.sim.process import SimProcess
from tests.helpers import CLI_TIMEOUT_S, json_lines
from tests.zygote import run_motorbus

QUERY_1 = la.Control(1, la.ControlAction.QUERY_STATUS).encode()
QUERY_2 = la.Control(2, la.ControlAction.QUERY_STATUS).encode()
MOVE_1 = la.MoveTo(1, 1300).encode()


def hexof(raw: bytes) -> str:
    return raw.hex(" ").upper()


def run(*args: str) -> subprocess.CompletedProcess[str]:
    """``python -m motorbus ARGS`` with no terminal on standard input."""
    env = {k: v for k, v in os.environ.items() if k != PORT_ENV}
    return run_motorbus(args, env, CLI_TIMEOUT_S)


def write_log(path: Path, lines: list[dict[str, Any]]) -> Path:
    path.write_text("".join(json.dumps(x) + "\n" for x in lines), encoding="utf-8")
    return path


def request(t: float, raw: bytes) -> dict[str, Any]:
    return {"t": t, "kind": "frame", "direction": "request", "family": "la", "hex": hexof(raw)}


HEADER = framelog.header("capture", started_utc="2026-01-01T00:00:00.000000Z", families=["la"])


# -- the format ---------------------------------------------------------------------------


def test_simulator_records_translate_to_frame_log_records() -> None:
    rx = {"t": 0.12345678, "dir": "rx", "hex": hexof(QUERY_1), "family": "la", "fault": None}
    assert framelog.from_sim(rx) == {
        "t": 0.123457,
        "kind": "frame",
        "direction": "request",
        "family": "la",
        "hex": hexof(QUERY_1),
    }
    junk = {"t": 1.0, "dir": "rx", "hex": "00 01", "family": None, "fault": "discarded: noise"}
    assert framelog.from_sim(junk) == {
        "t": 1.0,
        "kind": "garbage",
        "direction": "request",
        "family": None,
        "name": "garbage",
        "reason": "noise",
        "hex": "00 01",
    }
    tx = {"t": 2.0, "dir": "tx", "hex": "EE DD", "family": "project_stepper", "fault": "dup"}
    assert framelog.from_sim(tx)["kind"] == "event"
    assert framelog.from_sim(tx)["fault"] == "dup"
    down = {"t": 3.0, "dir": "link", "hex": "", "family": None, "fault": "disconnect"}
    assert framelog.from_sim(down) == {
        "t": 3.0,
        "kind": "link",
        "direction": None,
        "family": None,
        "name": "down",
        "hex": "",
        "fault": "disconnect",
    }


def test_reader_keeps_sessions_apart_and_translates_old_simulator_lines() -> None:
    lines = [
        json.dumps(HEADER),
        json.dumps(request(0.5, QUERY_1)),
        json.dumps({**HEADER, "source": "sim"}),
        json.dumps({"t": 0.25, "dir": "rx", "hex": hexof(QUERY_2), "family": "la", "fault": None}),
        "",
    ]
    log = framelog.read_frame_log(lines)
    assert [h["source"] for h in log.headers] == ["capture", "sim"]
    assert [(r["session"], r["line"], r["hex"]) for r in log.records] == [
        (0, 2, hexof(QUERY_1)),
        (1, 4, hexof(QUERY_2)),
    ]
    assert log.translated == 1


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ('{"t": 0, "hex": ""}', "x line 1 is not a frame-log record: missing key 'kind'"),
        ('{"kind": "frame", "hex": ""}', "x line 1 is not a frame-log record: missing key 't'"),
        ('{"t": "soon", "kind": "frame", "hex": ""}', "x line 1: t='soon' is not a number"),
        ('{"t": 0, "kind": "tea", "hex": ""}', "x line 1: kind='tea' is not one of event,"),
        ('{"t": 0, "kind": "frame", "hex": "5G"}', "x line 1: hex='5G'"),
        ("[1, 2]", "x line 1 is not a frame-log record: a JSON list"),
        ("{nope", "x line 1 is not JSON"),
        ('{"format": "motorbus-frame-log", "version": 2}', "x line 1: version=2 is not one"),
        ('{"format": "pcap"}', "x line 1: format='pcap' is not 'motorbus-frame-log'"),
    ],
)
def test_reader_names_the_line_and_the_key(line: str, message: str) -> None:
    with pytest.raises(LocalProtocolError) as info:
        framelog.read_frame_log([line], "x")
    assert str(info.value).startswith(message)


# -- replay to the screen -------------------------------------------------------------------


@pytest.fixture(scope="module")
def la_sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimProcess]:
    log = tmp_path_factory.mktemp("framelog") / "frames.jsonl"
    with SimProcess(["la:1-3"], baud=921600, log_file=log) as sim:
        yield sim


def test_replay_reads_the_simulators_own_log(la_sim: SimProcess) -> None:
    """The demo's ``la-bus-frames.jsonl`` is such a log; replay used to fail on it."""
    r = run("la", "status", "1", "--port", la_sim.path)
    assert r.returncode == 0, r.stderr
    assert la_sim.log_file is not None
    r = run("replay", str(la_sim.log_file))
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()  # the log's last frames are this test's
    assert "la request Control id=1 action=QUERY_STATUS" in lines[-2]
    assert "la reply Status id=1 " in lines[-1]
    docs = json_lines(run("replay", str(la_sim.log_file), "--json").stdout)
    assert [(d["direction"], d["name"]) for d in docs[-2:]] == [
        ("request", "Control"),
        ("reply", "Status"),
    ]


def test_replay_reads_the_old_simulator_format(tmp_path: Path) -> None:
    old = [
        {"t": 0.5, "dir": "rx", "hex": hexof(QUERY_1), "family": "la", "fault": None},
        {"t": 0.6, "dir": "rx", "hex": "00 00", "family": None, "fault": "discarded: noise"},
    ]
    r = run("replay", str(write_log(tmp_path / "old.jsonl", old)))
    assert r.returncode == 0, r.stderr
    first, second = r.stdout.splitlines()
    assert first.startswith("  0.000000  la request Control id=1 action=QUERY_STATUS")
    assert second.startswith("  0.100000  garbage (noise) 2 bytes")


def test_replay_refuses_a_broken_line_in_one_line(tmp_path: Path) -> None:
    path = write_log(tmp_path / "broken.jsonl", [HEADER, request(0, QUERY_1), {"t": 1, "hex": ""}])
    r = run("replay", str(path))
    assert r.returncode == 2
    assert r.stderr == (
        f"motorbus replay: {path} line 3 is not a frame-log record: missing key 'kind' "
        "(every record has t, kind, hex)\n"
    )


# -- replay through a bus -----------------------------------------------------------------------


def received_since(sim: SimProcess, before: int) -> list[dict[str, Any]]:
    return sim.log_records()[before:]


@pytest.fixture
def burst(tmp_path: Path) -> Path:
    """Two queries recorded at the same instant, then a move."""
    return write_log(
        tmp_path / "burst.jsonl",
        [HEADER, request(0.0, QUERY_1), request(0.0, QUERY_2), request(0.01, MOVE_1)],
    )


def test_dry_run_prints_and_sends_nothing(burst: Path, la_sim: SimProcess) -> None:
    before = len(la_sim.log_records())
    r = run("replay", str(burst), "--to", la_sim.path, "--dry-run")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 3
    assert all(line.startswith("would send ") for line in lines)
    assert "MoveTo id=1 position=1300" in lines[2]
    assert "3 requests would be sent" in r.stderr
    assert received_since(la_sim, before) == []


def test_motion_without_yes_and_without_a_terminal_is_refused(
    burst: Path, la_sim: SimProcess
) -> None:
    before = len(la_sim.log_records())
    r = run("replay", str(burst), "--to", la_sim.path)
    assert r.returncode == 2
    assert r.stderr == (
        f"motorbus replay: {burst} has 1 motion command (MoveTo) among 3 requests; not sent: "
        "pass --yes to send them (no terminal to ask on), or --dry-run to see them\n"
    )
    assert r.stdout == ""
    assert received_since(la_sim, before) == []


def test_replay_goes_through_a_bus_spacing_and_awaiting_replies(
    burst: Path, la_sim: SimProcess
) -> None:
    before = len(la_sim.log_records())
    r = run("replay", str(burst), "--to", la_sim.path, "--yes", "--wait", "0.1")
    assert r.returncode == 0, r.stderr
    wire = received_since(la_sim, before)
    # Recorded back to back, sent one at a time: each request waits for its reply (written
    # straight to the port, as before, the simulator heard both queries before answering).
    assert [(x["direction"], x["hex"][:11]) for x in wire] == [
        ("request", hexof(QUERY_1)[:11]),
        ("reply", "AA 55 11 01"),
        ("request", hexof(QUERY_2)[:11]),
        ("reply", "AA 55 11 02"),
        ("request", hexof(MOVE_1)[:11]),
        ("reply", "AA 55 11 01"),
        # The replayed move is owned by the bus's lease: closing the bus pauses la:1.
        ("request", hexof(la.Control(1, la.ControlAction.PAUSE).encode())[:11]),
        ("reply", "AA 55 11 01"),
    ]
    assert "3 requests sent" in r.stderr and "3 replies, 0 failed" in r.stderr
    assert "then 1 safe-stop frame as the bus closed" in r.stderr
    out = r.stdout.splitlines()
    # Printed as they cross the wire, the closing pause and its reply included.
    assert ["request" in line for line in out] == [True, False] * 4


def test_a_request_no_decoder_accepts_is_refused_before_sending(
    tmp_path: Path, la_sim: SimProcess
) -> None:
    # A valid frame (checksum right) with a command byte no LA request has.
    body = bytes([0x03, 0x01, 0x7E, 0x00, 0x00])
    odd = b"\x55\xaa" + body + bytes([sum(body) & 0xFF])
    path = write_log(tmp_path / "odd.jsonl", [HEADER, request(0, QUERY_1), request(0, odd)])
    before = len(la_sim.log_records())
    r = run("replay", str(path), "--to", la_sim.path, "--yes")
    assert r.returncode == 2
    assert r.stderr.startswith(f"motorbus replay: {path} line 3: request {hexof(odd)} cannot")
    assert r.stderr.endswith("nothing was sent\n")
    assert received_since(la_sim, before) == []


def test_dry_run_needs_to(burst: Path) -> None:
    r = run("replay", str(burst), "--dry-run")
    assert r.returncode == 2
    assert r.stderr == "motorbus replay: --dry-run and --yes go with --to URL\n"


def test_a_reply_the_simulator_corrupted_shows_what_a_listener_would_see() -> None:
    reply = la.Status(1, target=0, position=0).encode()
    record = framelog.from_sim(
        {
            "t": 1.0,
            "dir": "tx",
            "hex": hexof(reply + b"\x00\x13"),
            "family": "la",
            "fault": "garbage",
        }
    )
    assert (record["kind"], record["fault"]) == ("frame", "garbage")
    shown = framelog.describe_record(record)
    assert [(d.kind, d.name) for d in shown] == [("frame", "Status"), ("garbage", "garbage")]


@pytest.mark.parametrize(("answer", "sent"), [(b"y\n", True), (b"n\n", False)])
def test_motion_is_sent_after_a_yes_at_the_terminal(
    burst: Path, la_sim: SimProcess, answer: bytes, sent: bool
) -> None:
    master, slave = os.openpty()
    before = len(la_sim.log_records())
    try:
        proc = subprocess.Popen(
            [sys.executable, "-m", "motorbus", "replay", str(burst), "--to", la_sim.path,
             "--wait", "0.1"],
            stdin=slave,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        os.write(master, answer)  # read once the question is asked; the tty buffers it
        out, err = proc.communicate(timeout=CLI_TIMEOUT_S)
    finally:
        os.close(master)
        os.close(slave)
    assert "has 1 motion command (MoveTo) among 3 requests. Send them to" in err
    wire = [x["hex"] for x in received_since(la_sim, before) if x["direction"] == "request"]
    if sent:
        assert proc.returncode == 0, err
        # The replayed move is owned by the bus's lease: closing the bus pauses la:1.
        pause = hexof(la.Control(1, la.ControlAction.PAUSE).encode())
        assert wire == [hexof(QUERY_1), hexof(QUERY_2), hexof(MOVE_1), pause]
    else:
        assert proc.returncode == 2
        assert err.endswith("motorbus replay: not sent\n")
        assert wire == [] and out == ""


def test_replay_times_run_on_across_sessions(tmp_path: Path) -> None:
    """The simulator appends a session per run; its clock restarts, replay's does not."""
    path = write_log(
        tmp_path / "two.jsonl",
        [HEADER, request(0.5, QUERY_1), request(1.0, QUERY_2), HEADER, request(0.2, QUERY_1),
         request(0.4, QUERY_2)],
    )  # fmt: skip
    assert [r["t"] for r in load_records(path)] == [0.0, 0.5, 0.5, 0.7]
