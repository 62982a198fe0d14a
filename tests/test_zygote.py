"""The suite's forked command runs (tests/zygote.py) end as ``python -m motorbus`` does.

Each case runs once in a fresh interpreter and once forked from the zygote: the two
must agree on the exit status and on every character of output.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
from pathlib import Path

import pytest

import motorbus.sim.process
from motorbus.protocol import framelog, la
from tests import zygote
from tests.waiting import eventually
from tests.zygote import FRESH_ENV, ForkedProcess, ForkedTimeout, run_motorbus, spawn_motorbus

#: The tests of forked runs, where this run forks none.
needs_forks = pytest.mark.skipif(
    os.environ.get(FRESH_ENV) == "1", reason=f"{FRESH_ENV}=1: every command runs fresh"
)
QUERY = la.Control(1, la.ControlAction.QUERY_STATUS).encode().hex(" ").upper()


def both(
    args: list[str], env: dict[str, str] | None = None, stdin: str | None = None
) -> tuple[subprocess.CompletedProcess[str], subprocess.CompletedProcess[str]]:
    env = dict(os.environ if env is None else env)
    fresh = run_motorbus(args, {**env, FRESH_ENV: "1"}, 60, stdin)
    zygote.warm(env)
    forks = zygote.forks
    forked = run_motorbus(args, env, 60, stdin)
    assert zygote.forks == forks + 1  # it was forked
    return fresh, forked


def same(fresh: subprocess.CompletedProcess[str], forked: subprocess.CompletedProcess[str]) -> None:
    assert (forked.returncode, forked.stdout, forked.stderr) == (
        fresh.returncode,
        fresh.stdout,
        fresh.stderr,
    )


@needs_forks
@pytest.mark.parametrize(
    "args",
    [
        ["--help"],
        ["la", "status", "1", "--port", "/nonexistent"],  # 1: the port cannot open
        ["la", "move", "1"],  # 2: a usage error
        ["decode", "55 AA 03 01 04 00 22 2A", "ZZ"],  # 2: bad hex, named
    ],
    ids=["help", "no-port", "usage", "bad-hex"],
)
def test_a_forked_run_says_and_ends_as_a_fresh_one(args: list[str]) -> None:
    fresh, forked = both(args)
    assert fresh.returncode in (0, 1, 2)
    same(fresh, forked)


@needs_forks
def test_standard_input_reaches_the_command() -> None:
    fresh, forked = both(["decode", "--json"], stdin=f"{QUERY}\n")
    assert fresh.returncode == 0 and json.loads(fresh.stdout.splitlines()[0])
    same(fresh, forked)


@needs_forks
def test_an_environment_read_at_import_is_the_callers() -> None:
    """``MOTORBUS_HOST_MARGIN_MS`` is read when ``motorbus.bus`` is imported: a run with
    a bad value must fail as a fresh interpreter does, not run with the value a zygote
    imported with."""
    env = {**os.environ, "MOTORBUS_HOST_MARGIN_MS": "abc"}
    fresh, forked = both(["la", "status", "1", "--port", "/dev/null"], env)
    assert fresh.returncode == 2 and "MOTORBUS_HOST_MARGIN_MS" in fresh.stderr
    same(fresh, forked)


@needs_forks
def test_a_relative_path_is_read_from_the_callers_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    header = json.dumps(
        framelog.header("capture", started_utc="2026-01-01T00:00:00Z", families=["la"])
    )
    frame = {"kind": "frame", "family": "la", "direction": "request", "hex": QUERY}
    lines = [header] + [json.dumps({"t": t, **frame}) for t in (0, 0.25)]
    (tmp_path / "here.jsonl").write_text("\n".join(lines) + "\n", encoding="utf-8")
    monkeypatch.chdir(tmp_path)
    fresh, forked = both(["replay", "here.jsonl", "--to", "/nonexistent", "--dry-run"])
    assert fresh.returncode == 0 and fresh.stdout.count("would send") == 2, fresh.stderr
    same(fresh, forked)


@needs_forks
async def test_a_run_past_its_timeout_is_killed_and_says_so_as_subprocess_run_does() -> None:
    """The zygote's child is killed at the timeout, and ``TimeoutExpired`` raised."""
    zygote.warm(os.environ)
    # Waits for frames on a port that never sends any (a pty nobody writes to).
    master, slave = os.openpty()
    try:
        args = ["capture", "--family", "la", "--port", os.ttyname(slave)]
        with pytest.raises(ForkedTimeout) as info:
            run_motorbus(args, None, 1.0)
    finally:
        os.close(master)
        os.close(slave)
    assert info.value.timeout == 1.0
    pid = info.value.pid
    assert pid is not None

    def gone() -> bool:
        try:
            return Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z"
        except FileNotFoundError:
            return True

    await eventually(gone, "the timed-out child to be killed")


@needs_forks
@pytest.mark.parametrize("fresh", [True, False], ids=["fresh", "forked"])
def test_a_spawned_command_is_its_own_session_and_ends_on_sigterm(
    fresh: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``spawn_motorbus``: the first line as the command prints it, a session of its
    own (``start_new_session``), and the status and summary that SIGTERM gives."""
    if fresh:
        monkeypatch.setenv(FRESH_ENV, "1")
    else:
        zygote.warm(os.environ)
    proc = spawn_motorbus(["sim", "la:1"], new_session=True)
    assert isinstance(proc, ForkedProcess) != fresh
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().startswith("/dev/pts/")
        assert os.getsid(proc.pid) == proc.pid != os.getpid()
        assert proc.poll() is None
        os.kill(proc.pid, signal.SIGTERM)
        rest = proc.stdout.read()
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert rest.startswith("motorbus sim: 0 requests, 0 replies"), rest


@needs_forks
@pytest.mark.parametrize("fresh", [True, False], ids=["fresh", "forked"])
async def test_an_ended_child_keeps_its_pid_until_it_is_waited_for(
    fresh: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """As a ``Popen`` child stays a zombie until ``wait``, a forked one is reaped only
    once its status is read: a signal sent just after it ended is not an error (a
    served test's teardown sent SIGTERM then SIGCONT, and the zygote had reaped it)."""
    if fresh:
        monkeypatch.setenv(FRESH_ENV, "1")
    else:
        zygote.warm(os.environ)
    proc = spawn_motorbus(["sim", "la:1"])
    assert isinstance(proc, ForkedProcess) != fresh
    assert proc.stdout is not None and proc.stdout.readline()
    os.kill(proc.pid, signal.SIGKILL)
    stat = Path(f"/proc/{proc.pid}/stat")
    await eventually(lambda: stat.read_text().split()[2] == "Z", "the child to be a zombie")
    if isinstance(proc, ForkedProcess):  # and the zygote has seen it end
        await eventually(lambda: select.select([proc._conn], [], [], 0)[0], "its status")
    os.kill(proc.pid, signal.SIGCONT)  # a zombie: no ProcessLookupError
    assert proc.wait(timeout=30) == -signal.SIGKILL


def test_sim_process_starts_its_own_child_where_the_suite_does_not_fork_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The suite forks ``SimProcess``'s simulators (tests/conftest.py); its own
    ``Popen``, the path a user's tests take, still starts one."""
    monkeypatch.setattr(motorbus.sim.process, "subprocess", subprocess)
    with motorbus.sim.process.SimProcess(["la:1"]) as sim:
        assert type(sim.proc) is subprocess.Popen
        assert sim.path.startswith("/dev/pts/")
    assert sim.summary.startswith("motorbus sim: 0 requests, 0 replies"), sim.summary
