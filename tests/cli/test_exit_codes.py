"""One exit-code convention for every command, checked as one table (docs/cli.md).

Every command of ``COMMANDS`` is run against the same faults, and each cell says the
code it must end with - or why the fault does not apply to that command:

* 0 success (and the ordinary end, by Ctrl-C, of a command that runs until stopped:
  ``sim``, ``monitor`` without ``--count``, ``capture`` without ``--seconds``,
  ``dashboard``);
* 1 the bus or a device failed - a port that cannot be opened (missing, forbidden, or
  held by another program), a silent device - or a comparison regressed;
* 2 bad input (arguments, files, values): nothing was sent;
* 130 interrupted (Ctrl-C) before the command was done; what it started is stopped first.

With ``--json`` a failure ends standard output with one JSON object: ``error`` (the
message), ``code`` (the exit code), ``command`` and what it concerns.

The cells run in this process through ``motorbus.cli.main.main`` (no Python start-up
each), except Ctrl-C: a child process gets SIGINT once it has started its work (sent a
frame to the simulator, or printed its first line).  A port in use is a simulator's pty
that another process holds with the exclusive lock serial ports are opened with.

Before this table, on the same faults: a missing port gave 2 from ``doctor`` and 1 from
``la status`` and ``scan``; ``doctor --json`` (and every other command) with a bad port
printed nothing on standard output; ``monitor --count`` on a silent actuator ended 0.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from motorbus.cli.bus_options import ENV_VARS
from motorbus.cli.main import COMMANDS, main
from motorbus.protocol import framelog, la
from motorbus.sim.process import SimProcess
from tests.helpers import CLI_TIMEOUT_S, NO_CONFIG_DIR, cli, rx_frames

FAULTS = (
    "missing port",
    "port in use",
    "bad argument",
    "bad file",
    "device silent",
    "regression",
    "ctrl-c",
)


@dataclass(frozen=True)
class Cell:
    """A command line (``{name}`` fields filled in from the fixtures) and its exit code.

    ``ready`` (Ctrl-C cells only): when the child has started its work - ``frame`` (the
    simulator ``{port}`` names received a frame from it), ``stdout`` (it printed its
    first line), ``stdin`` (it answered a line written to its standard input).
    """

    code: int
    argv: tuple[str, ...]
    ready: str = ""
    port: str = "live"


def cell(code: int, *argv: str, ready: str = "", port: str = "live") -> Cell:
    return Cell(code, argv, ready, port)


NO_PORT = "opens no serial port"
OWN_PTY = "serves its own pseudo-terminal"
NO_DEVICE = "talks to no device"
NO_COMPARISON = "compares nothing"

#: command -> fault -> the cell, or why the fault does not apply.
TABLE: dict[str, dict[str, Cell | str]] = {
    "demo": {
        "missing port": "runs its own simulators: " + NO_PORT + " given to it",
        "port in use": "runs its own simulators: " + NO_PORT + " given to it",
        "bad argument": cell(2, "demo", "--seconds", "0", "--json"),
        "bad file": cell(2, "demo", "--out", "{a_file}/demo", "--json"),
        "device silent": "its simulators always answer",
        "regression": NO_COMPARISON,
        "ctrl-c": cell(
            130, "demo", "--seconds", "60", "--no-plot", "--out", "{tmp}/demo", ready="stdout"
        ),
    },
    "sim": {
        "missing port": OWN_PTY,
        "port in use": OWN_PTY,
        "bad argument": cell(2, "sim", "la:0"),
        "bad file": cell(2, "sim", "--log", "{tmp}/no-such-folder/frames.jsonl", "la:1"),
        "device silent": "it is the device",
        "regression": NO_COMPARISON,
        "ctrl-c": cell(0, "sim", "la:1", ready="stdout"),  # a signal is how it ends
    },
    "decode": {
        "missing port": NO_PORT,
        "port in use": NO_PORT,
        "bad argument": cell(2, "decode", "55", "AA", "zz", "--json"),
        "bad file": "reads its arguments or standard input, no file",
        "device silent": NO_DEVICE,
        "regression": NO_COMPARISON,
        "ctrl-c": cell(130, "decode", ready="stdin"),
    },
    "scan": {
        "missing port": cell(
            1, "scan", "--ids", "1", "--baud", "921600", "--port", "{missing}", "--json",
        ),
        "port in use": cell(
            1, "scan", "--ids", "1", "--baud", "921600", "--port", "{held}", "--json",
        ),
        "bad argument": cell(
            2, "scan", "--ids", "0", "--baud", "921600", "--port", "{live}", "--json",
        ),
        "bad file": cell(2, "scan", "--bus-file", "{tmp}/missing.toml", "--bus", "arm", "--json"),
        "device silent": cell(
            1, "scan", "--ids", "1-3", "--baud", "921600", "--port", "{silent}", "--json",
        ),
        "regression": NO_COMPARISON,
        "ctrl-c": cell(
            130, "scan", "--ids", "2-254", "--baud", "921600", "--timeout", "0.05",
            "--port", "{live}", ready="frame",
        ),
    },
    "ports": {
        "missing port": "lists the ports: " + NO_PORT,
        "port in use": "lists the ports: " + NO_PORT,
        "bad argument": "takes no option with a value (only --all and --json)",
        "bad file": "reads no file",
        "device silent": NO_DEVICE,
        "regression": NO_COMPARISON,
        "ctrl-c": "lists the ports and returns at once",
    },
    "doctor": {
        "missing port": cell(1, "doctor", "--port", "{missing}", "--json"),
        "port in use": cell(
            1, "doctor", "--ids", "1", "--seconds", "0", "--port", "{held}", "--json",
        ),
        "bad argument": cell(2, "doctor", "--period", "5", "--port", "{live}", "--json"),
        "bad file": cell(2, "doctor", "--bus-file", "{tmp}/missing.toml", "--json"),
        "device silent": cell(
            1, "doctor", "--ids", "1", "--seconds", "0", "--requests", "3",
            "--port", "{silent}", "--json",
        ),
        "regression": NO_COMPARISON,
        "ctrl-c": cell(
            130, "doctor", "--ids", "1", "--seconds", "60", "--port", "{live}", ready="frame"
        ),
    },
    "la": {
        "missing port": cell(1, "la", "status", "1", "--port", "{missing}", "--json"),
        "port in use": cell(1, "la", "status", "1", "--port", "{held}", "--json"),
        "bad argument": cell(2, "la", "move", "1", "2001", "--port", "{live}", "--json"),
        "bad file": cell(2, "la", "status", "1", "--bus-file", "{tmp}/missing.toml", "--json"),
        "device silent": cell(1, "la", "status", "1", "--port", "{silent}", "--json"),
        "regression": NO_COMPARISON,
        "ctrl-c": cell(130, "la", "status", "2-254", "--port", "{live}", ready="frame"),
    },
    "stream": {
        "missing port": cell(1, "stream", "{csv}", "--port", "{missing}", "--json"),
        "port in use": cell(1, "stream", "{csv}", "--port", "{held}", "--json"),
        "bad argument": cell(
            2, "stream", "{csv}", "--period", "0.001", "--port", "{live}", "--json",
        ),
        "bad file": cell(2, "stream", "{tmp}/missing.csv", "--port", "{live}", "--json"),
        "device silent": cell(1, "stream", "{csv}", "--port", "{silent}", "--json"),
        "regression": NO_COMPARISON,
        "ctrl-c": cell(130, "stream", "{long_csv}", "--port", "{live}", ready="frame"),
    },
    "monitor": {
        "missing port": cell(
            1, "monitor", "--ids", "1", "--count", "1", "--port", "{missing}", "--json",
        ),
        "port in use": cell(
            1, "monitor", "--ids", "1", "--count", "1", "--port", "{held}", "--json",
        ),
        "bad argument": cell(
            2, "monitor", "--ids", "1", "--interval", "-1", "--port", "{live}", "--json",
        ),
        "bad file": cell(2, "monitor", "--ids", "1", "--bus-file", "{tmp}/missing.toml", "--json"),
        "device silent": cell(
            1, "monitor", "--ids", "1", "--count", "1", "--port", "{silent}", "--json",
        ),
        "regression": NO_COMPARISON,
        # Without --count a monitor runs until stopped: Ctrl-C is its ordinary end.
        "ctrl-c": cell(0, "monitor", "--ids", "1", "--port", "{live}", ready="frame"),
    },
    "project": {
        "missing port": cell(1, "project", "stop", "--port", "{missing}", "--json"),
        "port in use": cell(1, "project", "stop", "--port", "{held}", "--json"),
        "bad argument": cell(2, "project", "run", "0", "--port", "{live}", "--json"),
        "bad file": cell(
            2, "project", "upload", "{tmp}/missing.toml", "--port", "{live}", "--json",
        ),
        "device silent": cell(1, "project", "stop", "--port", "{silent}", "--json"),
        "regression": NO_COMPARISON,
        "ctrl-c": cell(
            130, "project", "run", "1", "--timeout", "60", "--port", "{project}",
            ready="frame", port="project",
        ),
    },
    "quad": {
        "missing port": cell(1, "quad", "stop", "all", "--port", "{missing}", "--json"),
        "port in use": cell(1, "quad", "stop", "all", "--port", "{held}", "--json"),
        "bad argument": cell(2, "quad", "run", "9", "--port", "{live}", "--json"),
        "bad file": cell(2, "quad", "stop", "all", "--bus-file", "{tmp}/missing.toml", "--json"),
        "device silent": cell(1, "quad", "stop", "all", "--port", "{silent}", "--json"),
        "regression": NO_COMPARISON,
        "ctrl-c": cell(
            130, "quad", "run", "4", "--timeout", "60", "--port", "{quad}",
            ready="frame", port="quad",
        ),
    },
    "capture": {
        "missing port": cell(
            1, "capture", "--family", "la", "--seconds", "0.1", "--port", "{missing}",
        ),
        "port in use": cell(1, "capture", "--family", "la", "--seconds", "0.1", "--port", "{held}"),
        "bad argument": cell(2, "capture", "--family", "la", "--seconds", "-1", "--port", "{live}"),
        "bad file": cell(2, "capture", "--family", "la", "--bus-file", "{tmp}/missing.toml"),
        "device silent": "listens only: it asks no device anything",
        "regression": NO_COMPARISON,
        # Without --seconds a capture runs until stopped: Ctrl-C is its ordinary end.
        "ctrl-c": cell(0, "capture", "--family", "la", "--port", "{live}", ready="stdout"),
    },
    "replay": {
        "missing port": cell(1, "replay", "{log}", "--to", "{missing}", "--yes", "--json"),
        "port in use": cell(1, "replay", "{log}", "--to", "{held}", "--yes", "--json"),
        "bad argument": cell(2, "replay", "{log}", "--to", "{live}", "--speed", "0", "--json"),
        "bad file": cell(2, "replay", "{bad_log}", "--to", "{live}", "--yes", "--json"),
        "device silent": cell(1, "replay", "{log}", "--to", "{silent}", "--yes", "--json"),
        "regression": NO_COMPARISON,
        "ctrl-c": cell(130, "replay", "{long_log}", "--to", "{live}", ready="frame"),
    },
    "rig": {
        "missing port": cell(1, "rig", "1", "--out", "{tmp}/rig", "--port", "{missing}", "--json"),
        "port in use": cell(1, "rig", "1", "--out", "{tmp}/rig", "--port", "{held}", "--json"),
        "bad argument": cell(
            2, "rig", "1", "--out", "{tmp}/rig", "--min", "3000", "--port", "{live}", "--json",
        ),
        "bad file": cell(2, "rig", "compare", "{tmp}/missing", "{rig_old}", "--json"),
        "device silent": cell(1, "rig", "1", "--out", "{tmp}/rig", "--port", "{silent}", "--json"),
        "regression": cell(1, "rig", "compare", "{rig_old}", "{rig_new}", "--json"),
        "ctrl-c": cell(
            130, "rig", "1", "--out", "{tmp}/rig-int", "--port", "{live}", ready="frame",
        ),
    },
    "dashboard": {
        "missing port": cell(
            1, "dashboard", "--ids", "1", "--listen", "127.0.0.1:0", "--port", "{missing}",
        ),
        "port in use": cell(
            1, "dashboard", "--ids", "1", "--listen", "127.0.0.1:0", "--port", "{held}",
        ),
        "bad argument": cell(2, "dashboard", "--ids", "1", "--push-hz", "999", "--port", "{live}"),
        "bad file": cell(2, "dashboard", "--bus-file", "{tmp}/missing.toml"),
        "device silent": "shows a silent device on its page, and runs on until stopped",
        "regression": NO_COMPARISON,
        # A dashboard runs until stopped: Ctrl-C is its ordinary end.
        "ctrl-c": cell(
            0, "dashboard", "--ids", "1", "--listen", "127.0.0.1:0", "--port", "{live}",
            ready="stdout",
        ),
    },
    "serve": {
        "missing port": cell(
            1, "serve", "--port", "{missing}", "--baud", "921600", "--devices", "la:1",
            "--listen", "tcp/127.0.0.1:0",
        ),
        "port in use": cell(
            1, "serve", "--port", "{held}", "--baud", "921600", "--devices", "la:1",
            "--listen", "tcp/127.0.0.1:0",
        ),
        "bad argument": cell(
            2, "serve", "--port", "{live}", "--baud", "921600", "--devices", "la:0",
        ),
        "bad file": cell(2, "serve", "{tmp}/missing.toml"),
        "device silent": "serves a silent device: its clients get the timeouts",
        "regression": NO_COMPARISON,
        # A server runs until stopped: Ctrl-C is its ordinary end (its devices paused).
        "ctrl-c": cell(
            0, "serve", "--port", "{live}", "--baud", "921600", "--devices", "la:1",
            "--listen", "tcp/127.0.0.1:0", ready="stdout",
        ),
    },
}  # fmt: skip

CELLS = [
    pytest.param(command, fault, TABLE[command][fault], id=f"{command}-{fault.replace(' ', '-')}")
    for command in TABLE
    for fault in FAULTS
    if isinstance(TABLE.get(command, {}).get(fault), Cell)
]


def test_every_command_has_a_row_and_every_row_every_fault() -> None:
    assert list(TABLE) == list(COMMANDS), "add a row to TABLE for every command"
    for command, row in TABLE.items():
        assert list(row) == list(FAULTS), f"{command}: one entry per fault, in FAULTS order"
        for fault, entry in row.items():
            assert isinstance(entry, Cell) or entry.strip(), f"{command} {fault}: say why not"
            if isinstance(entry, Cell):
                assert entry.argv[0] == command, (command, fault)
                assert (fault == "ctrl-c") == bool(entry.ready), (command, fault)


def test_the_table_in_docs_cli_md_is_this_table() -> None:
    docs = Path(__file__).resolve().parents[2] / "docs" / "cli.md"
    text = docs.read_text(encoding="utf-8").split("## Exit codes", 1)[1]
    documented: dict[str, list[str]] = {}
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == len(FAULTS) + 1 and cells[0].startswith("`"):
            documented[cells[0].strip("`")] = [c.split()[0] for c in cells[1:]]
    expected = {
        command: [str(e.code) if isinstance(e, Cell) else "-" for e in row.values()]
        for command, row in TABLE.items()
    }
    assert documented == expected


# -- the fixtures the cells name ---------------------------------------------------------------

QUERY = la.Control(1, la.ControlAction.QUERY_STATUS).encode().hex(" ").upper()
HEADER = framelog.header("capture", started_utc="2026-01-01T00:00:00.000000Z", families=["la"])


def frame_log(path: Path, requests: int, every_s: float) -> str:
    records = [
        {"t": round(every_s * n, 3), "kind": "frame", "family": "la", "direction": "request",
         "hex": QUERY}
        for n in range(requests)
    ]  # fmt: skip
    path.write_text("".join(json.dumps(x) + "\n" for x in [HEADER, *records]), encoding="utf-8")
    return str(path)


def rig_results(path: Path, p50_ms: float) -> str:
    path.mkdir()
    doc = {
        "format": "motorbus-rig-results",
        "version": 1,
        "devices": {"la:1": {"latency.p50_ms": p50_ms}},
    }
    (path / "results.json").write_text(json.dumps(doc), encoding="utf-8")
    return str(path)


#: Holds a port the way serial ports are opened exclusively (``flock``), from another
#: process, until its standard input closes.
HOLDER = (
    "import fcntl, os, sys\n"
    "fd = os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)\n"
    "fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)\n"
    "print('holding', flush=True)\n"
    "sys.stdin.read()\n"
)


@pytest.fixture(scope="module")
def sims(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, SimProcess]]:
    """``live``: la:1, answering; ``silent``: only la:5 (nothing else answers);
    ``held``: la:1, its pty held by another process; ``project``: a project stepper
    holding project 1 as a project that repeats forever; ``quad``: a quad stepper whose
    motor 4 is set up for a run far longer than any test."""
    base = tmp_path_factory.mktemp("exit-codes")
    specs = {
        "live": ["la:1"],
        "silent": ["la:5"],
        "held": ["la:1"],
        "project": ["project-stepper"],
        "quad": ["quad-stepper"],
    }
    started = {
        name: SimProcess(spec, baud=921600 if name != "project" and name != "quad" else 9600,
                         log_file=base / f"{name}.jsonl").start()
        for name, spec in specs.items()
    }  # fmt: skip
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER, started["held"].path],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "holding"
        example = Path(__file__).resolve().parents[2] / "examples" / "project.toml"
        text = example.read_text(encoding="utf-8").replace("repeat = 0", 'repeat = "forever"')
        forever = base / "forever.toml"
        forever.write_text(text, encoding="utf-8")
        r = cli("project", "upload", str(forever), "--no-save", "--port", started["project"].path)
        assert r.returncode == 0, r.stderr
        r = cli(
            "quad", "config", "4", "--subdivision", "8", "--pulses", "16777215",
            "--start-hz", "10", "--accel", "0", "--rpm", "1", "--port", started["quad"].path,
        )  # fmt: skip
        assert r.returncode == 0, r.stderr
        yield started
    finally:
        if holder.stdin is not None:
            holder.stdin.close()
        holder.wait(CLI_TIMEOUT_S)
        for sim in started.values():
            sim.stop()


@pytest.fixture(scope="module")
def fields(sims: dict[str, SimProcess], tmp_path_factory: pytest.TempPathFactory) -> dict[str, str]:
    base = tmp_path_factory.mktemp("exit-code-files")
    csv = base / "traj.csv"
    csv.write_text("t,1\n0,1000\n0.01,1001\n0.02,1002\n", encoding="utf-8")
    long_csv = base / "long.csv"
    rows = [f"{k * 0.01:.2f},{900 + k % 400}" for k in range(6000)]
    long_csv.write_text("t,1\n" + "\n".join(rows) + "\n", encoding="utf-8")
    bad_log = base / "bad.jsonl"
    bad_log.write_text(json.dumps(HEADER) + "\n{not json\n", encoding="utf-8")
    a_file = base / "a-file"
    a_file.write_text("", encoding="utf-8")
    return {
        "tmp": str(base),
        "missing": str(base / "no-such-port"),
        "live": sims["live"].path,
        "silent": sims["silent"].path,
        "held": sims["held"].path,
        "project": sims["project"].path,
        "quad": sims["quad"].path,
        "csv": str(csv),
        "long_csv": str(long_csv),
        "log": frame_log(base / "queries.jsonl", 3, 0.01),
        "long_log": frame_log(base / "long.jsonl", 600, 0.05),
        "bad_log": str(bad_log),
        "a_file": str(a_file),
        "rig_old": rig_results(base / "rig-old", 10.0),
        "rig_new": rig_results(base / "rig-new", 20.0),
    }


def command_line(c: Cell, fields: dict[str, str]) -> list[str]:
    return [arg.format(**fields) for arg in c.argv]


def clean_environment(monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    for name in ENV_VARS:
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", NO_CONFIG_DIR)
    return dict(os.environ)


def check_json_error(command: str, code: int, out: str) -> None:
    """With ``--json``, standard output ends with the one error object of the failure."""
    lines = [line for line in out.splitlines() if line.strip()]
    assert lines, f"motorbus {command} --json printed nothing on standard output"
    doc: Any = json.loads(lines[-1])
    assert isinstance(doc, dict) and {"error", "code", "command"} <= set(doc), lines[-1]
    assert (doc["code"], doc["command"]) == (code, command), doc
    assert isinstance(doc["error"], str) and doc["error"], doc
    assert len([x for x in lines if '"error":' in x and '"code":' in x]) == 1, out


# -- the table ---------------------------------------------------------------------------------


@pytest.mark.parametrize(("command", "fault", "expected"), CELLS)
def test_exit_code(
    command: str,
    fault: str,
    expected: Cell,
    sims: dict[str, SimProcess],
    fields: dict[str, str],
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    env = clean_environment(monkeypatch)
    argv = command_line(expected, fields)
    live_frames = len(rx_frames(sims["live"]))
    if fault == "ctrl-c":
        code, out, err = interrupted(argv, expected, sims, env)
    else:
        try:
            code = main(argv)
        except SystemExit as end:  # argparse's own errors
            code = end.code if isinstance(end.code, int) else 1
        out, err = capsys.readouterr()
    assert code == expected.code, f"{argv}: exit {code}, expected {expected.code}\n{err}"
    if fault in ("bad argument", "bad file"):
        assert len(rx_frames(sims["live"])) == live_frames, "bad input: nothing may be sent"
    if expected.code not in (0, 130) and "--json" in argv:
        check_json_error(command, expected.code, out)
    elif expected.code:
        assert f"motorbus {command}" in err, err


def interrupted(
    argv: list[str], c: Cell, sims: dict[str, SimProcess], env: dict[str, str]
) -> tuple[int, str, str]:
    """Run ``motorbus ARGV`` as a child; SIGINT once it started its work; its exit."""
    sim = sims[c.port]
    before = len(rx_frames(sim))
    proc = subprocess.Popen(
        [sys.executable, "-m", "motorbus", *argv],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**env, "PYTHONUNBUFFERED": "1"},
        start_new_session=True,  # the SIGINT goes to the child alone
    )
    assert proc.stdin is not None and proc.stdout is not None
    try:
        if c.ready == "frame":
            deadline = time.monotonic() + CLI_TIMEOUT_S
            while len(rx_frames(sim)) == before:
                assert proc.poll() is None, proc.communicate()
                assert time.monotonic() < deadline, f"{argv}: sent nothing"
                time.sleep(0.02)  # polling the simulator's frame log
        else:
            if c.ready == "stdin":
                proc.stdin.write(QUERY + "\n")
                proc.stdin.flush()
            first = proc.stdout.readline()
            assert first, proc.communicate()
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=CLI_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    if c.ready == "stdout" or c.ready == "stdin":
        out = first + out
    assert "Traceback" not in err, err
    return proc.returncode, out, err
