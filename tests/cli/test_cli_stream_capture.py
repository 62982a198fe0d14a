"""``motorbus stream``, ``capture`` and ``replay`` against ``motorbus sim`` and a bare pty."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from motorbus.cli.stream import ramp_rows, read_trajectory
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.sim.process import SimProcess
from tests.helpers import CLI_TIMEOUT_S, cli, json_lines, raw_pty, rx_frames, stream_summary

#: A 0xF3 broadcast in the simulator's log, from byte 2 on: Len, ID FF, F3.
F3_AT_BYTE_2 = "FF F3"
QUERY = la.Control(1, la.ControlAction.QUERY_STATUS).encode()
REPLY = la.Status(1, target=1200, position=1195, temperature=30, current=150).encode()


@pytest.fixture(scope="module")
def la_sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimProcess]:
    log = tmp_path_factory.mktemp("stream") / "frames.jsonl"
    with SimProcess(["la:1-3"], baud=921600, log_file=log) as sim:
        yield sim


def write_csv(path: Path, rows: int, *, header: bool, period: float = 0.01) -> Path:
    lines = ["t,1,2,3"] if header else []
    lines += [f"{k * period:.3f},{1000 + k},{800 + 2 * k},{1200 - k}" for k in range(rows)]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def broadcasts(sim: SimProcess) -> list[str]:
    return [h for h in rx_frames(sim) if h.startswith(F3_AT_BYTE_2, 9)]


# -- stream -----------------------------------------------------------------------------------


def test_stream_20_rows_sends_20_ticks(la_sim: SimProcess, tmp_path: Path) -> None:
    before = len(broadcasts(la_sim))
    csv_file = write_csv(tmp_path / "path.csv", 20, header=True)
    r = cli(
        "stream", str(csv_file), "--period", "0.01", "--ramp", "0", "--json", "--port", la_sim.path
    )
    summary = stream_summary(r)  # every row is sent or counted as skipped
    assert (summary["ticks"] + summary["skipped"], summary["rows"]) == (20, 20)
    assert summary["ids"] == [1, 2, 3]
    sent = broadcasts(la_sim)[before:]
    assert len(sent) == summary["ticks"]
    if summary["skipped"] == 0:
        # Last row: 1019, 838, 1181 for IDs 1, 2, 3 (0xF3 entries: ID, position low, high).
        assert sent[-1][15:].startswith("01 FB 03 02 46 03 03 9D 04")


def test_stream_without_header_uses_ids_and_loops(la_sim: SimProcess, tmp_path: Path) -> None:
    before = len(rx_frames(la_sim))
    csv_file = write_csv(tmp_path / "bare.csv", 5, header=False, period=0.05)
    r = cli(
        "stream", str(csv_file), "--ids", "3,2,1", "--loop", "2", "--feedback",
        "--period", "0.05", "--ramp", "0", "--json", "--port", la_sim.path,
    )  # fmt: skip
    summary = stream_summary(r)
    assert (summary["rows"], summary["ticks"] + summary["skipped"]) == (10, 10)
    assert summary["ids"] == [3, 2, 1]
    # Feedback: one 0x20 per actuator and tick; columns follow --ids, so la:3 gets 1000 first.
    follows = [h for h in rx_frames(la_sim)[before:] if h[12:14] == "20"]
    assert len(follows) == 3 * summary["ticks"]
    assert follows[0].startswith("55 AA 04 03 20 37 E8 03")


def f3_entries(frame_hex: str) -> list[tuple[int, int]]:
    """(id, position) of each entry of a 0xF3 broadcast (from the simulator's log)."""
    data = bytes.fromhex(frame_hex)[5:-1]  # 55 AA Len FF F3 ... checksum
    return [(data[k], data[k + 1] | data[k + 2] << 8) for k in range(0, len(data), 3)]


def settled_positions(sim: SimProcess) -> tuple[int, ...]:
    """The positions of la:1-3 once each has stopped: reached its target, or been paused
    short of it (a stream ends with a pause), so two reads agree (bounded wait)."""
    deadline = time.monotonic() + CLI_TIMEOUT_S
    previous: list[int] = []
    while True:
        r = cli("la", "status", "1-3", "--json", "--port", sim.path)
        docs = json_lines(r.stdout)
        positions = [d["position"] for d in docs]
        if r.returncode == 0 and (
            all(d["position"] == d["target"] for d in docs) or positions == previous
        ):
            return tuple(positions)
        previous = positions
        assert time.monotonic() < deadline, f"the actuators never settled: {docs}"


def is_subsequence(part: list[tuple[int, ...]], whole: list[tuple[int, ...]]) -> bool:
    rest = iter(whole)
    return all(any(row == other for other in rest) for row in part)


def test_stream_ramps_from_the_reported_positions(la_sim: SimProcess, tmp_path: Path) -> None:
    r = cli("la", "move", "1", "100", "--port", la_sim.path)
    assert r.returncode == 0, r.stderr
    start = settled_positions(la_sim)
    before = len(broadcasts(la_sim))
    csv_file = write_csv(tmp_path / "path.csv", 5, header=True)
    r = cli(
        "stream", str(csv_file), "--ramp", "0.1", "--json", "--port", la_sim.path
    )  # 0.1 s at the default 10 ms: 10 ramp ticks, then the 5 rows
    summary = stream_summary(r)
    assert (summary["ramp_ticks"], summary["rows"]) == (10, 5)
    assert summary["ramp_from"] == list(start)
    first = (1000, 800, 1200)
    expected = ramp_rows(start, first, 10)
    assert expected[-1] == first and start[0] == 100
    # Each ramp step moves a tenth of the way: no jump to the first row.
    assert expected[0][0] == 100 + (1000 - 100) // 10
    rows = [(1000 + k, 800 + 2 * k, 1200 - k) for k in range(5)]
    sent = [tuple(p for _, p in f3_entries(h)) for h in broadcasts(la_sim)[before:]]
    # Each tick sent or skipped; a skip past the end still sends the last row, a tick later.
    assert len(sent) == summary["ticks"] in (15 - summary["skipped"], 16 - summary["skipped"])
    if summary["gaps"] == 0:  # a host stalled 3 ticks or more ramps in between (a gap)
        assert is_subsequence(sent, expected + rows), sent


def test_stream_refuses_to_start_when_an_actuator_is_silent(
    la_sim: SimProcess, tmp_path: Path
) -> None:
    before = len(rx_frames(la_sim))
    csv_file = write_csv(tmp_path / "bare.csv", 5, header=False)
    r = cli("stream", str(csv_file), "--ids", "1,9,2", "--port", la_sim.path)
    assert (r.returncode, r.stdout) == (1, "")
    assert r.stderr == (
        "motorbus stream: 1 actuator of 3 did not answer a status query (la:9): nothing "
        "streamed; check --ids (motorbus scan lists the IDs that answer) and --baud 921600\n"
    )
    sent = rx_frames(la_sim)[before:]
    assert sent and all(h[12:14] == "04" for h in sent), sent  # status queries only


def test_skipped_ticks_exit_1_saying_why(tmp_path: Path) -> None:
    # Every reply 30 ms late at a 10 ms period: feedback ticks cannot keep up.
    with SimProcess(["la:1-2"], baud=921600, faults="late=1:0.03") as sim:
        csv_file = write_csv(tmp_path / "path.csv", 20, header=True)
        csv_file.write_text(
            "\n".join(f"{k * 0.01:.2f},{1000 + k},{900 + k}" for k in range(20)) + "\n",
            encoding="utf-8",
        )
        r = cli(
            "stream", str(csv_file), "--ids", "1-2", "--feedback", "--ramp", "0",
            "--port", sim.path,
        )  # fmt: skip
    assert r.returncode == 1
    (line,) = [ln for ln in r.stderr.splitlines() if ln.startswith("motorbus stream: failed:")]
    assert " skipped - those targets were never sent, because a tick started more than a " in line
    assert line.endswith("feedback replies missing)")


def test_stream_of_a_missing_file_exits_2(tmp_path: Path) -> None:
    r = cli("stream", str(tmp_path / "nope.csv"), "--port", "/dev/motorbus-no-such-port")
    assert (r.returncode, r.stderr) == (
        2,
        f"motorbus stream: no such file: {tmp_path / 'nope.csv'}\n",
    )


def test_read_trajectory(tmp_path: Path) -> None:
    traj = read_trajectory(write_csv(tmp_path / "a.csv", 3, header=True), None, 0.01)
    assert traj.ids == [1, 2, 3]
    assert traj.rows == [(1000, 800, 1200), (1001, 802, 1199), (1002, 804, 1198)]


@pytest.mark.parametrize(
    ("text", "ids", "message"),
    [
        ("t,1\n0,100\n0.02,100\n", None, "line 3: time 0.02 does not follow 0.0 by the period"),
        ("t,1\n0,2001\n", None, "line 2 position of la:1=2001 is out of range: allowed 0..2000"),
        ("t,1,0\n0,1,1\n", None, "header id=0 is out of range: allowed 1..254"),
        ("t,1\n0,1,2\n", None, "line 2: 3 columns, expected 2"),
        ("t,1\n0,abc\n", None, "'abc' is not a number"),
        ("t,1,2\n0,1,2\n", [2, 1], "--ids 2,1 differs from the header's 1,2"),
        ("0,1\n", None, "has no header row"),
    ],
)
def test_bad_csv_is_refused(tmp_path: Path, text: str, ids: list[int] | None, message: str) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(LocalProtocolError, match=message.replace("(", r"\(")):
        read_trajectory(path, ids, 0.01)


def test_stream_bad_period_exits_2_and_sends_nothing(la_sim: SimProcess, tmp_path: Path) -> None:
    before = rx_frames(la_sim)
    csv_file = write_csv(tmp_path / "p.csv", 3, header=True)
    r = cli("stream", str(csv_file), "--period", "0.005", "--port", la_sim.path)
    assert r.returncode == 2
    assert r.stderr == (
        "motorbus stream: --period=0.005 is out of range: allowed 0.01..0.05 s (LA manual 3.5.3)\n"
    )
    assert rx_frames(la_sim) == before


# -- capture and replay -----------------------------------------------------------------------


@pytest.fixture
def bare_pty() -> Iterator[tuple[int, str]]:
    """A pty pair: bytes written to the master are what a listener on the slave hears."""
    with raw_pty() as pair:
        yield pair


def capture(master: int, port: str, out: Path, data: bytes) -> subprocess.CompletedProcess[str]:
    """Run ``motorbus capture`` on ``port`` and feed it ``data`` once it listens."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "motorbus", "capture", "--port", port, "--family", "la",
         "--seconds", "1", "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    assert proc.stderr is not None
    ready = proc.stderr.readline()
    assert ready.startswith(f"motorbus capture: listening on {port} (la, 921600 Bd)"), ready
    os.write(master, data)
    stdout, stderr = proc.communicate(timeout=CLI_TIMEOUT_S)
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, ready + stderr)


def test_capture_records_a_query_and_its_reply(bare_pty: tuple[int, str], tmp_path: Path) -> None:
    master, port = bare_pty
    out = tmp_path / "session.jsonl"
    r = capture(master, port, out, QUERY + b"\x00" + REPLY)
    assert r.returncode == 0, r.stderr
    assert "motorbus capture: 2 frames, 1 garbage run" in r.stderr
    header, *records = [json.loads(line) for line in out.read_text(encoding="utf-8").splitlines()]
    assert (header["format"], header["version"], header["source"]) == (
        "motorbus-frame-log",
        1,
        "capture",
    )
    assert (header["port"], header["baud"], header["families"]) == (port, 921600, ["la"])
    assert [(x["kind"], x["direction"], x["name"]) for x in records] == [
        ("frame", "request", "Control"),
        ("garbage", None, "garbage"),
        ("frame", "reply", "Status"),
    ]
    assert records[0]["hex"] == QUERY.hex(" ").upper()
    assert records[2]["fields"]["position"] == 1195
    assert all(0 <= x["t"] < 1 for x in records)


@pytest.fixture
def session(bare_pty: tuple[int, str], tmp_path: Path) -> Path:
    master, port = bare_pty
    out = tmp_path / "session.jsonl"
    assert capture(master, port, out, QUERY + REPLY).returncode == 0
    return out


def test_replay_prints_the_capture_decoded(session: Path) -> None:
    r = cli("replay", str(session))
    assert r.returncode == 0, r.stderr
    first, second = r.stdout.splitlines()
    assert first.startswith("  0.000000  la request Control id=1 action=QUERY_STATUS")
    assert "la reply Status id=1 " in second and "position=1195" in second
    r = cli("replay", str(session), "--json")
    docs = json_lines(r.stdout)
    assert [d["name"] for d in docs] == ["Control", "Status"]
    assert docs[0]["t"] == 0.0


def test_replay_to_a_simulator_resends_the_requests(session: Path, la_sim: SimProcess) -> None:
    before = rx_frames(la_sim)
    r = cli("replay", str(session), "--to", la_sim.path, "--wait", "0.3")
    assert r.returncode == 0, r.stderr
    assert rx_frames(la_sim)[len(before) :] == [QUERY.hex(" ").upper()]
    lines = r.stdout.splitlines()
    assert "la request Control id=1" in lines[0]
    assert "la reply Status id=1 " in lines[1]  # the simulator's own answer
    assert "1 requests sent" in r.stderr and "1 replies" in r.stderr


def test_replay_refuses_a_file_that_is_not_a_capture(tmp_path: Path) -> None:
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"t": 0}\n', encoding="utf-8")
    r = cli("replay", str(bad))
    assert r.returncode == 2
    assert r.stderr == (
        f"motorbus replay: {bad} line 1 is not a frame-log record: missing key 'kind' "
        "(every record has t, kind, hex)\n"
    )
