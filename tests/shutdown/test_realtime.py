"""``motorbus.runtime.realtime``: what enable() applies, what it does when refused, GC control,
``MOTORBUS_REALTIME`` and ``--realtime``.

This sandbox runs as root, so the real ``enable()`` succeeds here: the tests that call
it for real do so in a child process; in-process tests replace the system calls.
"""

from __future__ import annotations

import errno
import gc
import json
import logging
import os
import subprocess
import sys
import textwrap
import threading
import weakref
from collections.abc import Iterator
from typing import Any

import pytest

from motorbus.bus.bus import Bus, BusState
from motorbus.bus.timer import default_timer
from motorbus.cli.main import build_parser
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager
from motorbus.runtime import realtime
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from tests.helpers import affinities, affinity_kept


@pytest.fixture(autouse=True)
def fresh_realtime_state(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Each test starts with no request, no environment setting and nothing frozen in
    GC (the suite freezes what collection built, tests/conftest.py: a test here that ran
    first in its worker saw that); afterwards GC is as it was."""
    monkeypatch.delenv(realtime.ENV_VAR, raising=False)
    monkeypatch.setattr(realtime, "_process", realtime._Process())
    threshold = gc.get_threshold()
    suite_froze = gc.get_freeze_count() > 0
    gc.unfreeze()
    yield
    realtime._gc.active = False
    gc.unfreeze()
    if suite_froze:
        gc.freeze()
    gc.set_threshold(*threshold)
    gc.enable()


def run_child(code: str) -> dict[str, Any]:
    """Run ``code`` in a fresh interpreter; it prints one JSON document last."""
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    result: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    result["stderr"] = out.stderr
    return result


# -- the real thing, in a child process ------------------------------------------------------


def test_enable_applies_everything_and_disable_undoes_it() -> None:
    r = run_child(
        """
        import gc, json, os
        from motorbus.runtime import realtime
        threshold = gc.get_threshold()
        report = realtime.enable(60, cpus=[0])
        during = {
            "policy": os.sched_getscheduler(0) & ~getattr(os, "SCHED_RESET_ON_FORK", 0),
            "priority": os.sched_getparam(0).sched_priority,
            "frozen": gc.get_freeze_count(),
            "threshold": gc.get_threshold(),
            "affinity": sorted(os.sched_getaffinity(0)),
            "controlled": realtime.gc_controlled(),
            "locked_kb": int([l for l in open("/proc/self/status") if l.startswith("VmLck")][0]
                             .split()[1]),
        }
        applied = report.as_dict()
        realtime.disable(report)
        after = {
            "policy": os.sched_getscheduler(0),
            "frozen": gc.get_freeze_count(),
            "threshold_restored": gc.get_threshold() == threshold,
            "controlled": realtime.gc_controlled(),
            "locked_kb": int([l for l in open("/proc/self/status") if l.startswith("VmLck")][0]
                             .split()[1]),
        }
        print(json.dumps({"report": applied, "during": during, "after": after,
                          "fifo": os.SCHED_FIFO, "other": os.SCHED_OTHER}))
        """
    )
    if r["report"]["refused"]:
        pytest.skip(f"this machine refuses real-time mode: {r['report']['refused']}")
    during, after = r["during"], r["after"]
    assert r["report"]["priority"] == 60 and r["report"]["memory_locked"]
    assert (during["policy"], during["priority"]) == (r["fifo"], 60)
    assert during["frozen"] > 0 and during["controlled"]
    assert during["threshold"][2] == realtime.GEN2_THRESHOLD_OFF
    assert during["affinity"] == [0]
    assert during["locked_kb"] > 0
    assert after == {
        "policy": r["other"],
        "frozen": 0,
        "threshold_restored": True,
        "controlled": False,
        "locked_kb": 0,
    }


def test_a_child_process_of_a_realtime_process_is_an_ordinary_one() -> None:
    r = run_child(
        """
        import json, os, subprocess, sys
        from motorbus.runtime import realtime
        report = realtime.enable(lock_memory=False, freeze_gc=False)
        child = subprocess.run([sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
                               capture_output=True, text=True).stdout.strip()
        print(json.dumps({"refused": report.refused, "child": int(child),
                          "other": os.SCHED_OTHER}))
        """
    )
    if r["refused"]:
        pytest.skip(f"this machine refuses SCHED_FIFO: {r['refused']}")
    assert r["child"] == r["other"]


# -- refusals: never silent, never a crash ---------------------------------------------------


def test_refusals_are_one_warning_line_and_the_program_carries_on(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def no_fifo(pid: int, policy: int, param: Any) -> None:
        raise PermissionError(errno.EPERM, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", no_fifo)
    monkeypatch.setattr(realtime, "_mlockall", lambda flags: errno.EPERM)
    monkeypatch.setattr(realtime, "_has_capability", lambda number: True)
    policy_before = os.sched_getscheduler(0)
    with caplog.at_level(logging.INFO, logger="motorbus.realtime"):
        report = realtime.enable(70, freeze_gc=False)
    assert set(report.refused) == {"sched_fifo", "mlockall"}
    assert report.applied == [] and report.priority is None and not report.memory_locked
    assert not report.ok
    assert "Operation not permitted" in report.refused["sched_fifo"]
    assert "rtprio 70" in report.refused["sched_fifo"]
    assert "cap_sys_nice" in report.refused["sched_fifo"]
    assert "CPUSchedulingPriority=70" in report.refused["sched_fifo"]
    assert "LimitMEMLOCK" in report.refused["mlockall"]
    records = [r for r in caplog.records if r.name == "motorbus.realtime"]
    assert [r.levelno for r in records] == [logging.WARNING]
    line = records[0].getMessage()
    assert "\n" not in line and "SCHED_FIFO 70" in line and "mlockall" in line
    assert os.sched_getscheduler(0) == policy_before


def test_a_finite_memlock_limit_is_refused_without_locking(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    calls: list[int] = []
    real_getrlimit = realtime.resource.getrlimit

    def getrlimit(which: int) -> tuple[int, int]:
        if which == realtime.resource.RLIMIT_MEMLOCK:
            return (8 << 20, 8 << 20)
        return real_getrlimit(which)

    monkeypatch.setattr(realtime.resource, "getrlimit", getrlimit)
    monkeypatch.setattr(realtime, "_has_capability", lambda number: False)
    monkeypatch.setattr(realtime, "_mlockall", lambda flags: calls.append(flags) or 0)
    monkeypatch.setattr(realtime, "_set_fifo", lambda prio, report: None)
    with caplog.at_level(logging.WARNING, logger="motorbus.realtime"):
        report = realtime.enable(freeze_gc=False)
    assert calls == []
    assert "8192 KiB" in report.refused["mlockall"]
    assert len(caplog.records) == 1


def test_bad_arguments_are_refused_before_anything_changes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls: list[object] = []
    monkeypatch.setattr(os, "sched_setscheduler", lambda *a: calls.append(a))
    monkeypatch.setattr(os, "sched_setaffinity", lambda *a: calls.append(a))
    monkeypatch.setattr(realtime, "_mlockall", lambda flags: calls.append(flags) or 0)
    for bad in (0, 100, -1, True, "50", 50.0):
        with pytest.raises(LocalProtocolError, match=r"priority=.*1\.\.99") as info:
            realtime.enable(bad)  # type: ignore[arg-type]
        assert info.value.field == "priority"
    top = (os.cpu_count() or 1) - 1
    for cpus in ([top + 1], [-1], [], "0", [True]):
        with pytest.raises(LocalProtocolError, match="cpus") as info:
            realtime.enable(cpus=cpus)  # type: ignore[arg-type]
        assert info.value.field == "cpus"
    assert calls == []
    assert gc.get_freeze_count() == 0 and not realtime.gc_controlled()


# -- pin(): every thread of the process ------------------------------------------------------


@pytest.fixture
def idle_thread() -> Iterator[threading.Thread]:
    """A thread that exists before the pin and lives until the test ends."""
    stop = threading.Event()
    thread = threading.Thread(target=stop.wait, daemon=True)
    thread.start()
    yield thread
    stop.set()
    thread.join()


def test_pin_moves_every_thread_and_restore_gives_each_its_cpus_back(
    idle_thread: threading.Thread,
) -> None:
    with affinity_kept() as allowed:
        cpu = max(allowed)
        assert idle_thread.native_id is not None
        os.sched_setaffinity(idle_thread.native_id, {min(allowed)})  # its own CPUs
        pinning = realtime.pin([cpu])
        assert pinning.cpus == frozenset({cpu})
        assert set(affinities().values()) == {frozenset({cpu})}
        stop = threading.Event()
        born = threading.Thread(target=stop.wait, daemon=True)  # started while pinned
        born.start()
        try:
            assert born.native_id is not None
            assert os.sched_getaffinity(born.native_id) == {cpu}  # inherited
            pinning.restore()
            assert os.sched_getaffinity(0) == allowed
            assert os.sched_getaffinity(idle_thread.native_id) == {min(allowed)}
            assert os.sched_getaffinity(born.native_id) == allowed  # the pinner's CPUs
        finally:
            stop.set()
            born.join()


def test_restore_leaves_a_thread_moved_since_the_pin(idle_thread: threading.Thread) -> None:
    with affinity_kept() as allowed:
        assert idle_thread.native_id is not None
        pinning = realtime.pin([max(allowed)])
        os.sched_setaffinity(idle_thread.native_id, {min(allowed)})  # someone else's choice
        pinning.restore()
        assert os.sched_getaffinity(idle_thread.native_id) == {min(allowed)}
        assert os.sched_getaffinity(0) == allowed
        pinning.restore()  # twice is harmless
        assert os.sched_getaffinity(0) == allowed


def test_a_refused_pin_leaves_every_thread_where_it_was(
    idle_thread: threading.Thread, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = os.sched_setaffinity
    with affinity_kept() as allowed:
        before = affinities()
        calls: list[int] = []

        def second_refused(tid: int, cpus: Any) -> None:
            calls.append(tid)
            if len(calls) == 2 and frozenset(cpus) != allowed:
                raise OSError(errno.EINVAL, "Invalid argument")
            real(tid, cpus)

        with monkeypatch.context() as patch:
            patch.setattr(os, "sched_setaffinity", second_refused)
            with pytest.raises(OSError, match=r"cannot run on CPUs \d: Invalid argument"):
                realtime.pin([max(allowed)])
        assert len(calls) >= 3  # one moved, one refused, the moved one put back
        assert affinities() == before
        with pytest.raises(LocalProtocolError, match="cpus"):
            realtime.pin([(os.cpu_count() or 1)])
        assert affinities() == before


# -- garbage-collector control ---------------------------------------------------------------


def test_gc_state_after_enable_and_disable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(realtime, "_set_fifo", lambda prio, report: None)
    threshold = gc.get_threshold()
    report = realtime.enable(lock_memory=False)
    # Another thread of the process (pytest-xdist's) may free a frozen object meanwhile:
    # it leaves the count, which nothing but a freeze raises.
    assert 0 < gc.get_freeze_count() <= report.gc_frozen
    assert gc.get_threshold() == (threshold[0], threshold[1], realtime.GEN2_THRESHOLD_OFF)
    assert gc.isenabled() and realtime.gc_controlled()
    before = gc.get_freeze_count()
    made = [[] for _ in range(1000)]  # created since enable(): refreeze() freezes them
    assert realtime.refreeze() > before
    del made
    again = realtime.enable(lock_memory=False)  # a second call keeps the saved thresholds
    assert gc.get_threshold()[2] == realtime.GEN2_THRESHOLD_OFF and again._threshold is None
    realtime.disable(again)
    assert realtime.gc_controlled()
    realtime.disable(report)
    assert gc.get_freeze_count() == 0 and gc.get_threshold() == threshold
    assert not realtime.gc_controlled()
    assert realtime.idle_hook() is False  # off: returns at once


def test_idle_hook_does_nothing_until_a_full_collection_is_due(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(realtime, "_set_fifo", lambda prio, report: None)
    realtime.enable(lock_memory=False)
    assert gc.get_count()[2] < realtime._gc.due_after  # just collected by enable()
    with realtime.GcPauseMonitor() as monitor:
        assert realtime.idle_hook() is False
    assert monitor.count(2) == 0


def test_collect_when_idle_defers_a_collection_that_does_not_fit(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(realtime, "_set_fifo", lambda prio, report: None)
    realtime.enable(lock_memory=False)
    monkeypatch.setattr(realtime._gc, "due_after", 0)  # always due
    monkeypatch.setattr(realtime._gc, "last_full_s", 1.0)  # the last one took a second
    ran = [realtime.collect_when_idle(1e-3) for _ in range(realtime.MAX_DEFERRALS + 1)]
    assert ran == [False] * realtime.MAX_DEFERRALS + [True]
    assert realtime._gc.deferred == 0


# The same allocation pattern with and without GC control, in a fresh interpreter:
# "ticks" that each build short-lived cycles and keep some objects a while (so they
# reach the old generation), and an idle call between ticks.
GC_WORKLOAD = """
    import gc, json, os
    from motorbus.runtime import realtime
    os.sched_setscheduler = lambda *args: None  # GC control only: no SCHED_FIFO here
    if {controlled}:
        realtime.enable(lock_memory=False)
    kept = []
    with realtime.GcPauseMonitor() as monitor:
        for tick in range(3000):
            for _ in range(100):
                a = []; a.append(a)  # a reference cycle: only the collector frees it
            kept.append([[] for _ in range(40)])
            if len(kept) > 1500:
                del kept[:500]
            realtime.idle_hook()
    gen2_left = gc.get_count()[2]
    print(json.dumps({{"auto2": monitor.count(2, "auto"), "idle2": monitor.count(2, "idle"),
                      "young": monitor.count(0) + monitor.count(1), "gen2_count": gen2_left,
                      "summary": monitor.summary()}}))
"""


def test_full_collections_leave_the_ticks_in_realtime_mode() -> None:
    plain = run_child(GC_WORKLOAD.format(controlled=False))
    controlled = run_child(GC_WORKLOAD.format(controlled=True))
    # Without control the interpreter runs full collections in the middle of the work...
    assert plain["auto2"] > 0 and plain["idle2"] == 0
    # ... with it, none: they all run from idle_hook, between ticks.
    assert controlled["auto2"] == 0
    assert controlled["idle2"] > 0
    assert controlled["young"] > 0  # young collections stay automatic
    assert controlled["gen2_count"] < 10  # no backlog of gen-1 collections left over
    assert set(controlled["summary"]) >= {"gen0-auto", "gen2-idle"}
    assert {"count", "max_us", "p99_us"} == set(controlled["summary"]["gen2-idle"])


def test_idle_collection_frees_cyclic_garbage(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(realtime, "_set_fifo", lambda prio, report: None)
    realtime.enable(lock_memory=False)

    class Node:
        ref: object = None

    node = Node()
    node.ref = node
    gone = weakref.ref(node)
    del node
    for _ in range(realtime._gc.due_after * gc.get_threshold()[1] + 1):
        gc.collect(0)  # young collections push the cycle to the old generation
        gc.collect(1)
    monkeypatch.setattr(realtime._gc, "due_after", 0)
    # Not put off by the budget: an earlier full collection of this process, slow on a
    # loaded machine, would make idle_hook defer this one (a test of its own above).
    monkeypatch.setattr(realtime._gc, "last_full_s", 0.0)
    assert realtime.idle_hook() is True
    assert gone() is None


def test_the_monitor_reports_per_generation() -> None:
    with realtime.GcPauseMonitor() as monitor:
        gc.collect(0)
        gc.collect(2)
    summary = monitor.summary()
    assert summary["gen0-auto"]["count"] == 1 and summary["gen2-auto"]["count"] == 1
    assert summary["gen2-auto"]["max_us"] >= summary["gen2-auto"]["p99_us"] > 0
    gc.collect(0)
    assert monitor.count(0) == 1  # stopped: not counted any more


# -- MOTORBUS_REALTIME and --realtime --------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "expected"),
    [(None, None), ("", None), ("  ", None), ("0", None), ("1", 50), ("2", 2), (" 60 ", 60),
     ("99", 99)],
)  # fmt: skip
def test_setting_parsing(text: str | None, expected: int | None) -> None:
    assert realtime.parse_setting(text) == expected


@pytest.mark.parametrize("text", ["100", "-1", "1.5", "yes", "on", "fifo", "0x10", "1e1"])
def test_bad_settings_name_the_variable_the_value_and_the_choices(text: str) -> None:
    with pytest.raises(LocalProtocolError, match=r"MOTORBUS_REALTIME=.*0 or empty.*2\.\.99") as e:
        realtime.parse_setting(text)
    assert e.value.value == text


def recording_enable(monkeypatch: pytest.MonkeyPatch) -> list[int | None]:
    calls: list[int | None] = []

    def fake_enable(priority: int | None = None, **options: Any) -> realtime.RealtimeReport:
        calls.append(priority)
        return realtime.RealtimeReport(applied=[f"SCHED_FIFO {priority}"], priority=priority)

    monkeypatch.setattr(realtime, "enable", fake_enable)
    return calls


async def test_bus_open_honours_the_variable_once_per_process(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls = recording_enable(monkeypatch)
    monkeypatch.setenv(realtime.ENV_VAR, "60")
    timer = default_timer()
    async with (
        MemorySim.start([LAModel(1)], timer=timer) as a,
        MemorySim.start([LAModel(1)], timer=timer) as b,
    ):
        for sim in (a, b, a):
            bus = Bus(sim.transport, timer=timer)
            async with bus:
                assert bus.state is BusState.OPEN
    assert calls == [60]
    report = realtime.on_bus_open()
    assert report is not None and report.priority == 60


async def test_off_values_do_not_enable(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = recording_enable(monkeypatch)
    monkeypatch.setenv(realtime.ENV_VAR, "0")
    async with MemorySim.start([LAModel(1)]) as sim, Bus(sim.transport):
        pass
    assert calls == [] and realtime.on_bus_open() is None


async def test_a_bad_variable_fails_the_open_before_the_port_opens(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls = recording_enable(monkeypatch)
    monkeypatch.setenv(realtime.ENV_VAR, "fast")
    async with MemorySim.start([LAModel(1)]) as sim:
        bus = Bus(sim.transport)
        with pytest.raises(LocalProtocolError, match="MOTORBUS_REALTIME='fast'"):
            await bus.open()
        assert bus.state is BusState.CLOSED and not sim.transport.is_open
        mgr = BusManager()
        mgr.add_bus("arm", "memory://arm", baud=921600, devices=["la:1"], transport=sim.transport)
        with pytest.raises(LocalProtocolError, match="MOTORBUS_REALTIME"):
            await mgr.open()
        assert not sim.transport.is_open
        monkeypatch.setenv(realtime.ENV_VAR, "1")  # fixed: the next open applies it
        async with mgr:
            pass
    assert calls == [realtime.DEFAULT_PRIORITY]


async def test_the_command_line_request_wins_over_the_environment(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    calls = recording_enable(monkeypatch)
    monkeypatch.setenv(realtime.ENV_VAR, "1")
    args = build_parser().parse_args(["scan", "--realtime=70", "--port", "x"])
    assert args.realtime == 70 and realtime.requested() == 70
    async with MemorySim.start([LAModel(1)]) as sim, Bus(sim.transport):
        pass
    assert calls == [70]


#: Every command that opens a bus (or, for demo, a BusManager).
BUS_COMMANDS = ["scan", "la", "monitor", "stream", "project", "quad", "capture", "demo"]


def subparsers_of(parser: Any) -> dict[str, Any]:
    for action in parser._actions:
        if hasattr(action, "choices") and isinstance(action.choices, dict):
            return dict(action.choices)
    return {}


def all_parsers(parser: Any) -> Iterator[Any]:
    yield parser
    for sub in subparsers_of(parser).values():
        yield from all_parsers(sub)


@pytest.mark.parametrize("command", BUS_COMMANDS)
def test_every_bus_command_takes_realtime(command: str) -> None:
    top = subparsers_of(build_parser())[command]
    leaves = [p for p in all_parsers(top) if not subparsers_of(p)]
    assert leaves
    for leaf in leaves:
        assert any("--realtime" in a.option_strings for a in leaf._actions), leaf.prog


def test_realtime_option_forms(monkeypatch: pytest.MonkeyPatch) -> None:
    parser = build_parser()
    assert parser.parse_args(["scan", "--realtime"]).realtime == realtime.DEFAULT_PRIORITY
    assert realtime.requested() == realtime.DEFAULT_PRIORITY
    assert parser.parse_args(["scan", "--realtime=5"]).realtime == 5
    realtime.request(None)
    assert parser.parse_args(["scan"]).realtime is None and realtime.requested() is None


@pytest.mark.parametrize("value", ["0", "100", "x"])
def test_a_bad_realtime_option_is_a_usage_error(
    value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        build_parser().parse_args(["scan", f"--realtime={value}"])
    assert info.value.code == 2
    assert f"--realtime='{value}' is out of range: allowed a SCHED_FIFO priority 1..99" in (
        capsys.readouterr().err
    )
    assert realtime.requested() is None
