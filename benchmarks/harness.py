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
    (the machine now, the time now in UTC), creating its folder; print where it went."""
    report = {**result, "machine": machine_info(), "date": now_utc()}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {out}")


def now_utc() -> str:
    """The time now, UTC, to the second (ISO 8601)."""
    return datetime.now(UTC).isoformat(timespec="seconds")
