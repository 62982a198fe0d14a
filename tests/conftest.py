"""Shared fixtures; the shared helpers live in ``tests.helpers`` (``sim_bus`` fails a
test whose bus leaves tasks running behind it; ``PACINGS``)."""

from __future__ import annotations

import gc
import os
import shutil
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, settings

from tests.helpers import PACINGS as PACINGS
from tests.helpers import sim_bus as sim_bus
from tests.zygote import fork_simulators

# Simulator processes fork from a zygote that has imported them (tests/zygote.py).
fork_simulators()

ROOT = Path(__file__).resolve().parents[1]

# The property tests assert behaviour, never speed: on this shared 2-core machine with
# the suite's workers, one example took 1.1 s to generate (a data-generation health
# check failed CI) and Hypothesis's default 200 ms deadline per example is a timing
# assertion.  Neither applies here; each test still sets its own ``max_examples``.
settings.register_profile("motorbus", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("motorbus")

#: The modules whose tests take longest (fresh venvs with pip installs, mypy, the docs
#: site, rig runs in real time), slowest first.  They run before the rest: with ``-n``,
#: a worker busy with one of them leaves the others to the short tests, instead of
#: running it alone at the end.
SLOW_FIRST = (
    "tests/test_interpreters.py",
    "tests/test_quality.py",
    "tests/test_docs.py",
    "tests/test_sdist.py",
    "tests/cli/test_cli_rig.py",
)


def pytest_configure(config: pytest.Config) -> None:
    """Give Ctrl-C back to the programs the tests start, if this run was started with it
    ignored (``nohup``, or ``cmd &`` from a script): they inherit an ignored SIGINT,
    Python then installs no KeyboardInterrupt for it, and the tests that interrupt a
    command (tests/cli/test_exit_codes.py) would wait for the command to end by itself.
    A handler is not inherited: a child starts with the default disposition."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    _cache_bytecode(config)
    _warm_bytecode(config)


def _cache_bytecode(config: pytest.Config) -> None:
    """Where the environment says ``PYTHONDONTWRITEBYTECODE`` (this machine's does), let
    the suite's Python processes cache their bytecode in a temporary directory of this
    run (``PYTHONPYCACHEPREFIX``), never in the source tree.  The suite starts about 750
    Python processes (simulators, servers, the commands under test); without a cache
    each compiled every module it imported, and a simulator spent 0.15 s of CPU where
    it now spends 0.11 s.  The workers (``-n``) start after this and inherit it."""
    if "PYTHONPYCACHEPREFIX" in os.environ or not os.environ.get("PYTHONDONTWRITEBYTECODE"):
        return
    prefix = tempfile.mkdtemp(prefix="motorbus-tests-pyc-")
    del os.environ["PYTHONDONTWRITEBYTECODE"]
    os.environ["PYTHONPYCACHEPREFIX"] = prefix
    config.add_cleanup(lambda: shutil.rmtree(prefix, ignore_errors=True))


def _warm_bytecode(config: pytest.Config) -> None:
    """Before the workers (``-n``) start, compile the modules they will import, once.

    Each worker collects every test, and on a fresh clone each one rewrote the asserts
    of every test module and compiled every module it imported (10 s of CPU; 2 s with
    the compiled files there): four workers on two CPUs spent the suite's first 19 s
    doing the same work four times.  Here one collection a CPU, each of a share of the
    test files, writes the compiled files (pytest's own, with the asserts rewritten)
    where the workers then read them.  A collection error is left to the workers to
    report."""
    workers = config.getoption("numprocesses", None)
    if (
        not isinstance(workers, int)
        or workers < 2
        or hasattr(config, "workerinput")
        or os.environ.get("MOTORBUS_TESTS_WARMING")
        or os.environ.get("PYTHONDONTWRITEBYTECODE")  # nothing would be written
    ):
        return
    files = sorted(
        {
            found
            for arg in (config.args or [str(ROOT / "tests")])
            for found in _test_files(config.invocation_params.dir / arg.split("::", 1)[0])
        },
        key=lambda f: -f.stat().st_size,
    )
    shares: list[list[str]] = [[] for _ in range(min(workers, _cpus(), len(files)))]
    for i, found in enumerate(files):  # largest first, dealt round the shares
        shares[i % len(shares)].append(str(found))
    env = {**os.environ, "MOTORBUS_TESTS_WARMING": "1"}
    command = [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"]
    children = [
        subprocess.Popen(
            [*command, "-p", "no:xdist", *share],
            cwd=config.rootpath,
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        for share in shares
    ]
    for child in children:
        child.wait()


def _test_files(path: Path) -> list[Path]:
    """The test modules at or under ``path`` (collecting them imports the conftests)."""
    if path.is_dir():
        return list(path.rglob("test_*.py"))
    return [path] if path.suffix == ".py" and path.is_file() else []


@pytest.hookimpl(optionalhook=True)  # xdist's hook: pytest without xdist runs too
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: three workers a CPU.  Much of a test's time is waiting (simulated
    motion in real time, child processes starting, replies paced at the baud): with one
    worker a CPU the CPUs stood idle half the time, with two still a tenth of it, with
    three a twentieth (vmstat, 2 CPUs).  The suite took 156 to 193 s with three (mean
    177 s of 5 runs) and 180 to 198 s with two (mean 186 s of 3), in runs one after the
    other on this shared machine; four were slower again and broke a rig run's timing."""
    return 3 * _cpus()


def _cpus() -> int:
    """The CPUs this run may use."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return cpus or 1


@pytest.hookimpl(optionalhook=True)  # xdist's hook: pytest without xdist runs too
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``-n`` (``--dist load``): work stealing, so that a worker left idle takes tests
    queued at a busy one; plain load balancing hands out fixed runs of tests, and the
    worker whose run holds the slow modules (``SLOW_FIRST``) would finish long after
    the others."""
    if config.getoption("dist") != "load":
        return None
    from xdist.scheduler import WorkStealingScheduling

    return WorkStealingScheduling(config, log)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The slow modules first (``SLOW_FIRST``), each test otherwise where it was."""

    def rank(item: pytest.Item) -> int:
        where = item.path.relative_to(ROOT).as_posix() if item.path.is_relative_to(ROOT) else ""
        return SLOW_FIRST.index(where) if where in SLOW_FIRST else len(SLOW_FIRST)

    items.sort(key=rank)


@pytest.fixture
def make_sim_bus() -> Callable[..., Any]:
    return sim_bus


def pytest_collection_finish(session: pytest.Session) -> None:
    """Freeze what collection built: full garbage collections over the suite's large heap
    took 60-137 ms, long enough to turn an on-time reply into a late one (the bus decides
    lateness by time, as it must)."""
    gc.collect()
    gc.freeze()
