"""The benchmarks' harness: a JSON report's machine description and date, and its writing.

A module, not a benchmark.  It imports nothing of the other benchmarks, so any of them
can use it (``run_results.py``, which used to hold :func:`machine_info`, imports every
benchmark); the scripts write their reports with :func:`write_report`.
"""

from __future__ import annotations

import json
import os
import platform
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any


def machine_info() -> dict[str, Any]:
    """This machine: platform string, Python version, CPU count, load average now."""
    return {
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "cpus": os.cpu_count(),
        "load_avg": [round(x, 2) for x in os.getloadavg()],
    }


def steal_seconds() -> float | None:
    """CPU time the hypervisor gave to others, all CPUs, since boot (s; ``/proc/stat``'s
    "steal" column, in clock ticks); None where not available."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            fields = f.readline().split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def write_report(out: Path, result: dict[str, Any]) -> None:
    """Write ``result`` to ``out`` as indented JSON, with ``machine`` and ``date`` added
    (the machine now, the time now in UTC), creating its folder; print where it went.
    A ``machine`` of ``result``'s own adds its keys to the machine description (e.g. the
    load average before the run)."""
    machine = {**machine_info(), **result.get("machine", {})}
    report = {**result, "machine": machine, "date": now_utc()}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {out}")


class TimerProbe:
    """What a bus timer's wake-ups cost, counted from outside the library.

    ``wakeups``: the timerfd's wake-ups; ``spin_s``: the CPU they spent spinning before a
    precise deadline (seconds); ``arms``: its ``timerfd_settime`` calls that armed it
    (disarming not counted), each of which reprograms the CPU's timer, which a VM pays
    for.  Through the timer's ``wake_observer`` (an observer already there is still
    told) and a counting wrapper of its own syscall object; ``counted`` is False (and
    all stay 0) for a timer without a timerfd (``LoopTimer``).  A probe counts from when
    it was attached.
    """

    def __init__(self, timer: Any) -> None:
        self.wakeups = 0
        self.spin_s = 0.0
        self.arms = 0
        self.counted = hasattr(timer, "wake_observer") and getattr(timer, "_api", None) is not None
        if not self.counted:
            return
        told = timer.wake_observer

        def on_wake(armed: float, woke: float, spun_until: float) -> None:
            self.wakeups += 1
            self.spin_s += spun_until - woke
            if told is not None:
                told(armed, woke, spun_until)

        timer.wake_observer = on_wake
        timer._api = _CountedSettime(timer._api, self)


class _CountedSettime:
    """A timer's syscall object (``motorbus.bus.timerfd.TimerfdApi``) whose arming calls
    a ``TimerProbe`` counts."""

    def __init__(self, api: Any, probe: TimerProbe) -> None:
        self._api = api
        self._probe = probe

    def set_absolute_ns(self, fd: int, deadline_ns: int) -> None:
        if deadline_ns:
            self._probe.arms += 1
        self._api.set_absolute_ns(fd, deadline_ns)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._api, name)


def now_utc() -> str:
    """The time now, UTC, to the second (ISO 8601)."""
    return datetime.now(UTC).isoformat(timespec="seconds")
