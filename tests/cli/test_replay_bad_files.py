"""A table of bad frame logs: each one exits 2 with the file, the line and the reason,
and nothing reaches the port (``motorbus replay`` to the screen and ``--to``)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from motorbus.cli.main import main
from motorbus.protocol import framelog, la, quad_stepper
from tests.helpers import raw_pty

HEADER = json.dumps(
    framelog.header("capture", started_utc="2026-01-01T00:00:00.000000Z", families=["la"])
)
QUERY = la.Control(1, la.ControlAction.QUERY_STATUS).encode().hex(" ").upper()
QUAD = quad_stepper.StopAll().encode().hex(" ").upper()


def request(t: object, hex_: str = QUERY, **extra: Any) -> str:
    doc = {"t": t, "kind": "frame", "family": "la", "direction": "request", "hex": hex_}
    doc.update(extra)
    return json.dumps(doc)


def raw_t(text: str) -> str:
    """A request whose ``t`` is written as-is (JSON that json.dumps would not write)."""
    return request("T").replace('"T"', text)


#: (case, lines after nothing, line named, reason): shown and sent alike.
BAD_FILES: list[tuple[str, list[str | bytes], int, str]] = [
    ("t of 400 digits", [HEADER, raw_t("1" + "0" * 400)], 2, "t=1000"),
    ("t overflowing a float", [HEADER, raw_t("1e400")], 2, "t=inf is out of range"),
    ("t of 31 years", [HEADER, request(0), request(1e9)], 3, "t=1000000000.0 is out of range"),
    ("t negative", [HEADER, request(-1)], 2, "t=-1 is out of range: allowed 0..10000000"),
    ("t NaN", [HEADER, raw_t("NaN")], 2, "t=nan is not a number of seconds"),
    ("deeply nested", [HEADER, "[" * 100_000 + "]" * 100_000], 2, "JSON nested too deeply"),
    ("not UTF-8", [HEADER, b"\xff\xfe{}"], 2, "is not UTF-8 text: byte 0xFF at column 1"),
    ("a family the header does not name",
     [HEADER, request(0), request(0.1, QUAD, family="quad_stepper")], 3,
     "a quad_stepper frame in a session whose header (line 1) names la: refused"),
    ("an unknown family", [HEADER, request(0, family="tea")], 2, "family='tea' is not one of"),
    ("an unknown direction", [HEADER, request(0, direction="up")], 2, "direction='up' is not"),
    ("hex not a string", [HEADER, request(0, hex_=5)], 2, "hex=5 is not a string"),  # type: ignore[arg-type]
    ("fields not an object", [HEADER, request(0, name="Control", fields=[1])], 2,
     "fields=[1] is not an object"),
    ("a header naming no known family",
     [HEADER.replace('["la"]', '["tea"]'), request(0)], 1, "families=['tea'] is not a list"),
    ("a header without families",
     [HEADER.replace('"families": ["la"], ', ""), request(0)], 1, "families=None is not a list"),
]  # fmt: skip


@pytest.fixture
def port() -> Iterator[tuple[int, str]]:
    """A pty: what a replay writes to the slave path can be read from the master."""
    with raw_pty(nonblocking_master=True) as pair:
        yield pair


def write(path: Path, lines: list[str | bytes]) -> Path:
    path.write_bytes(b"".join((x if isinstance(x, bytes) else x.encode()) + b"\n" for x in lines))
    return path


def written(master: int) -> bytes:
    try:
        return os.read(master, 4096)
    except BlockingIOError:
        return b""


@pytest.mark.parametrize(
    ("lines", "line", "reason"), [c[1:] for c in BAD_FILES], ids=[c[0] for c in BAD_FILES]
)
@pytest.mark.parametrize("send", [False, True], ids=["show", "send"])
def test_a_bad_file_exits_2_naming_file_line_and_reason(
    tmp_path: Path,
    port: tuple[int, str],
    capsys: pytest.CaptureFixture[str],
    lines: list[str | bytes],
    line: int,
    reason: str,
    send: bool,
) -> None:
    master, path = port
    log = write(tmp_path / "bad.jsonl", lines)
    args = ["replay", str(log)] + (["--to", path, "--yes", "--wait", "0"] if send else [])
    assert main(args) == 2
    out, err = capsys.readouterr()
    assert err.startswith(f"motorbus replay: {log} line {line}"), err
    assert reason in err, err
    assert err.count("\n") == 1  # one line, no traceback
    if send:
        assert out == ""
        assert written(master) == b""


def test_a_frame_of_another_family_without_a_family_key_is_not_sent(
    tmp_path: Path, port: tuple[int, str], capsys: pytest.CaptureFixture[str]
) -> None:
    """The family is read from the bytes then, and checked against the header all the same."""
    master, path = port
    quad = json.dumps({"t": 0.1, "kind": "frame", "direction": "request", "hex": QUAD})
    log = write(tmp_path / "quad.jsonl", [HEADER, request(0), quad])
    assert main(["replay", str(log), "--to", path, "--yes", "--wait", "0"]) == 2
    _, err = capsys.readouterr()
    assert err == (
        f"motorbus replay: {log} line 3: request {QUAD} is a quad_stepper frame; the "
        "session's header names la; nothing was sent\n"
    )
    assert written(master) == b""


def test_a_gap_over_a_minute_needs_max_gap(
    tmp_path: Path, port: tuple[int, str], capsys: pytest.CaptureFixture[str]
) -> None:
    master, path = port
    log = write(tmp_path / "gap.jsonl", [HEADER, request(0), request(0.5), request(70.5)])
    assert main(["replay", str(log), "--to", path, "--yes", "--wait", "0"]) == 2
    _, err = capsys.readouterr()
    assert err == (
        f"motorbus replay: {log} line 4: a wait of 70 s after the request on line 3 is over "
        "--max-gap=60 s (pass a larger --max-gap to replay it); nothing was sent\n"
    )
    assert written(master) == b""
    # The gap is the wait at --speed; --max-gap raises the limit.
    assert main(["replay", str(log), "--to", path, "--dry-run", "--speed", "2"]) == 0
    assert main(["replay", str(log), "--to", path, "--dry-run", "--max-gap", "71"]) == 0
    out, _ = capsys.readouterr()
    assert "would send  70.500000" in out


@pytest.mark.parametrize(
    ("option", "message"),
    [
        (["--speed", "0"], "--speed=0.0 is out of range: allowed 0.001..1000"),
        (["--speed", "nan"], "--speed=nan is out of range"),
        (["--loop", "0"], "--loop"),
        (["--max-gap", "inf"], "--max-gap=inf is out of range"),
    ],
)
def test_bad_speed_loop_and_max_gap_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: list[str], message: str
) -> None:
    log = write(tmp_path / "ok.jsonl", [HEADER, request(0)])
    assert main(["replay", str(log), *option]) == 2
    _, err = capsys.readouterr()
    assert err.startswith(f"motorbus replay: {message}"), err


@pytest.mark.parametrize("option", [["--speed", "2"], ["--loop", "2"], ["--max-gap", "5"]])
def test_pace_options_go_with_to(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: list[str]
) -> None:
    log = write(tmp_path / "ok.jsonl", [HEADER, request(0)])
    assert main(["replay", str(log), *option]) == 2
    _, err = capsys.readouterr()
    assert err == "motorbus replay: --speed, --loop and --max-gap go with --to URL\n"
