"""``motorbus monitor --listen``: a table of what another program's traffic says, sending
nothing."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator

import pytest

from motorbus.cli.listen import Watch
from motorbus.cli.main import main
from motorbus.protocol import framelog, la, quad_stepper
from motorbus.protocol.base import Family
from tests.helpers import CLI_TIMEOUT_S, raw_pty

QUERY_1 = la.Control(1, la.ControlAction.QUERY_STATUS).encode()
STATUS_1 = la.Status(1, target=100, position=90).encode()
MOVE_2 = la.MoveTo(2, 1300).encode()
STATUS_2 = la.Status(2, target=1300, position=12, temperature=31).encode()


@pytest.fixture
def bare_pty() -> Iterator[tuple[int, str]]:
    with raw_pty(nonblocking_master=True) as pair:
        yield pair


def test_listen_shows_the_statuses_heard_and_sends_nothing(bare_pty: tuple[int, str]) -> None:
    master, port = bare_pty
    proc = subprocess.Popen(
        [sys.executable, "-m", "motorbus", "monitor", "--listen", "--port", port,
         "--count", "1", "--interval", "1", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stderr is not None
    ready = proc.stderr.readline()
    assert ready.startswith(f"motorbus monitor: listening on {port} (la, 921600 Bd)"), ready
    os.write(master, QUERY_1 + STATUS_1 + b"\x00" + MOVE_2 + STATUS_2)
    out, err = proc.communicate(timeout=CLI_TIMEOUT_S)
    assert proc.returncode == 0, err
    (refresh,) = [json.loads(line) for line in out.splitlines()]
    assert refresh["heard"] == {"request": 2, "reply": 2, "garbage": 1}
    one, two = refresh["devices"]
    assert (one["id"], one["status"]["position"], one["last_request"]["name"]) == (1, 90, "Control")
    assert (two["id"], two["status"]["target"], two["status"]["temperature_c"]) == (2, 1300, 31)
    assert two["last_request"] == {"name": "MoveTo", "fields": {"id": 2, "position": 1300,
                                                               "reply": True}}  # fmt: skip
    with pytest.raises(BlockingIOError):
        os.read(master, 100)  # the monitor wrote nothing to the line


def record(t: float, raw: bytes, direction: str, family: str = "la") -> dict[str, object]:
    return framelog.from_sim(
        {"t": t, "dir": "rx" if direction == "request" else "tx", "hex": raw.hex(" "),
         "family": family}
    )  # fmt: skip


def test_the_la_table_has_a_status_row_an_id_heard() -> None:
    watch = Watch(Family.LA)
    for rec in (record(0, QUERY_1, "request"), record(0.001, STATUS_1, "reply"),
                record(0.01, MOVE_2, "request")):  # fmt: skip
        watch.write(rec)
    header, first, second = watch.lines()
    assert header.split() == ["id", "target", "position", "temp", "current", "force", "errors"]
    assert first.split()[:3] == ["1", "100", "90"]
    assert second == "    2  no status heard yet (-> MoveTo position=1300 reply=True)"
    assert watch.summary() == "2 requests, 1 reply"


def test_ids_limit_what_the_table_shows() -> None:
    watch = Watch(Family.LA, frozenset({2}))
    for rec in (record(0, QUERY_1, "request"), record(0.001, STATUS_1, "reply"),
                record(0.01, MOVE_2, "request")):  # fmt: skip
        watch.write(rec)
    assert [d["id"] for d in watch.to_json()] == [2]


def test_a_stepper_table_has_counts_and_the_last_frame() -> None:
    watch = Watch(Family.QUAD_STEPPER)
    watch.write(record(0, quad_stepper.Stop(2).encode(), "request", "quad_stepper"))
    watch.write(record(0.1, quad_stepper.Stop(2).encode(), "request", "quad_stepper"))
    assert watch.lines() == [
        "  id  requests  replies  last frame",
        "    2         2        0  -> Stop",
    ]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--listen", "--plot"], "--plot does not go with --listen"),
        (["--seconds", "2"], "--family and --seconds go with --listen"),
        (["--family", "quad_stepper"], "--family and --seconds go with --listen"),
    ],
)
def test_listen_options_are_checked(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["monitor", "--port", "/dev/null", *args]) == 2
    assert capsys.readouterr().err == f"motorbus monitor: {message}\n"
