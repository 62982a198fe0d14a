"""Helpers the tests share, in one place: simulated buses, the command line as a user
runs it, and bounded waits (``tests.waiting.eventually``).

``PACINGS`` are the simulator pacings every bus-facing test runs against: ``"wire"``
(replies when their last byte would arrive at the baud, as on a UART) and ``"prompt"``
(replies the moment a request is complete, as from a USB-CDC device or a TCP bridge).
A test that passes only against one of them shares an assumption with the bus.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import subprocess
import tty
from collections.abc import AsyncIterator, Iterator, Sequence
from contextlib import asynccontextmanager, contextmanager
from pathlib import Path
from typing import Any

import pytest

from motorbus.bus.bus import Bus
from motorbus.bus.timer import default_timer
from motorbus.cli.bus_options import ENV_VARS
from motorbus.protocol.base import Family
from motorbus.sim.bus import PACING_MODES, Pacing
from motorbus.sim.memory import MemorySim
from motorbus.sim.model import DeviceModel
from motorbus.sim.process import SimProcess
from tests.waiting import eventually
from tests.zygote import run_motorbus

__all__ = [
    "CLI_TIMEOUT_S",
    "LOADED_HOST_MARGIN_MS",
    "NO_CONFIG_DIR",
    "PACINGS",
    "affinities",
    "affinity_kept",
    "bus_file",
    "cli",
    "eventually",
    "json_lines",
    "loaded_bus_file",
    "raw_pty",
    "rx_frames",
    "sim_bus",
    "stream_rows",
]

#: Simulator pacings, for ``pytest.mark.parametrize("pacing", PACINGS)``.
PACINGS: list[Pacing] = list(PACING_MODES)


@asynccontextmanager
async def sim_bus(
    models: Sequence[DeviceModel],
    *,
    baud: int | None = None,
    delivery: str = "whole",
    faults: Any = None,
    seed: int = 0,
    pacing: Pacing = "wire",
    **bus_options: Any,
) -> AsyncIterator[tuple[Bus, MemorySim]]:
    """A bus talking to simulated devices over the in-memory link.

    ``pacing`` is the simulator's (``MemorySim.start``): ``"wire"`` or ``"prompt"``.
    """
    timer = default_timer()
    before = set(asyncio.all_tasks())
    async with MemorySim.start(
        models,
        baud=baud,
        delivery=delivery,
        faults=faults,
        seed=seed,
        timer=timer,  # type: ignore[arg-type]
        pacing=pacing,
    ) as sim:
        families = {m.family for m in models} or set(Family)
        # Tests assert behaviour, not speed: a generous host margin keeps a loaded CI
        # machine from turning a slow reply into a timeout.  Timeout tests pass their own.
        bus_options.setdefault("host_margin", 0.05)
        bus = Bus(sim.transport, name="sim", families=families, timer=timer, **bus_options)
        async with bus:
            yield bus, sim
    await asyncio.sleep(0)
    leaked = [t for t in asyncio.all_tasks() - before if not t.done()]
    assert not leaked, f"the bus leaked tasks: {leaked}"


#: Generous ceiling for one CLI run (a stuck command fails the test instead of hanging).
CLI_TIMEOUT_S = 60


#: A configuration directory with no motorbus/buses.toml: the user's own never leaks in.
NO_CONFIG_DIR = "/nonexistent/motorbus-test-config"


def cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    """Run ``python -m motorbus ARGS``; the ``MOTORBUS_*`` variables are unset and there is
    no user bus file unless ``env`` sets them."""
    base = {k: v for k, v in os.environ.items() if k not in ENV_VARS}
    base["XDG_CONFIG_HOME"] = NO_CONFIG_DIR
    return run_motorbus(args, {**base, **(env or {})}, CLI_TIMEOUT_S)


#: Host margin (ms) for a command-line run whose test never waits for a timeout: with the
#: suite's workers on two CPUs, a reply can be read tens of ms after the simulator wrote
#: it (a rig's move timed out at the command line's 50 ms in a 4-worker run).
LOADED_HOST_MARGIN_MS = 250


def bus_file(folder: Path, url: str, *, baud: int, name: str = "arm", **keys: object) -> Path:
    """``folder/buses.toml``: one bus ``name`` on ``url`` at ``baud``, with the given
    extra keys (booleans as TOML's, the rest as their ``repr``)."""
    lines = ["[[bus]]", f"name = {json.dumps(name)}", f"url = {json.dumps(url)}", f"baud = {baud}"]
    for key, value in keys.items():
        text = str(value).lower() if isinstance(value, bool) else repr(value)
        lines.append(f"{key} = {text}")
    path = folder / "buses.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def loaded_bus_file(folder: Path, url: str, baud: int, devices: Sequence[str]) -> Path:
    """``bus_file`` with ``devices`` and ``LOADED_HOST_MARGIN_MS``: for ``--bus-file``
    where a test's command would otherwise take the command line's default margin for
    ``--port``."""
    return bus_file(
        folder, url, baud=baud, devices=list(devices), host_margin_ms=LOADED_HOST_MARGIN_MS
    )


def stream_rows(out: str) -> int:
    """The ticks a stream's summary line in ``out`` (``StreamStats.summary``) counts as
    sent or skipped: every row of a stream is one or the other (a loaded machine skips
    a tick that started more than a period late)."""
    m = re.search(r"^(\d+) ticks \(\d+ frames\), \d+ late, (\d+) skipped", out, re.M)
    assert m, out
    return int(m[1]) + int(m[2])


def json_lines(out: str) -> list[Any]:
    """Every line of ``out`` parsed as JSON."""
    return [json.loads(line) for line in out.splitlines() if line.strip()]


def stream_summary(r: subprocess.CompletedProcess[str]) -> dict[str, Any]:
    """``motorbus stream --json``'s summary.  A tick may be skipped on a loaded machine:
    the exit code is then 1 and one error object follows the summary, naming the skipped
    ticks (count, do not time)."""
    summary, *failed = json_lines(r.stdout)
    skipped = summary["skipped"]
    assert r.returncode == (0 if skipped == 0 else 1), r.stderr
    assert [doc["skipped"] for doc in failed] == ([skipped] if skipped else []), r.stdout
    return summary  # type: ignore[no-any-return]


def rx_frames(sim: SimProcess) -> list[str]:
    """Hex of every frame the simulator received so far."""
    return [r["hex"] for r in sim.log_records() if r["direction"] == "request"]


@contextmanager
def raw_pty(*, nonblocking_master: bool = False) -> Iterator[tuple[int, str]]:
    """A raw pseudo-terminal: (master fd, slave path).  What a program writes to the
    slave path the test reads from the master, and the other way round."""
    master, slave = os.openpty()
    tty.setraw(slave)
    if nonblocking_master:
        os.set_blocking(master, False)
    try:
        yield master, os.ttyname(slave)
    finally:
        os.close(master)
        os.close(slave)


def affinities() -> dict[int, frozenset[int]]:
    """The CPUs of every thread of this process, by thread id (Linux)."""
    out = {}
    for tid in map(int, os.listdir("/proc/self/task")):
        try:
            out[tid] = frozenset(os.sched_getaffinity(tid))
        except ProcessLookupError:
            continue
    return out


@contextmanager
def affinity_kept() -> Iterator[frozenset[int]]:
    """Yield the CPUs this thread may use; afterwards every thread that is still there
    gets its CPUs back, whatever the test did (a failed pin must not leak into the
    next test).  Skips where the process has no CPU affinity or a single CPU (a pin
    to it could not be told from no pin)."""
    if not hasattr(os, "sched_setaffinity") or not os.path.isdir("/proc/self/task"):
        pytest.skip("no CPU affinity on this platform")
    before = affinities()
    allowed = frozenset(os.sched_getaffinity(0))
    if len(allowed) < 2:
        pytest.skip("this process may use one CPU only")
    try:
        yield allowed
    finally:
        for tid, cpus in before.items():
            try:
                os.sched_setaffinity(tid, cpus)
            except ProcessLookupError:
                continue
