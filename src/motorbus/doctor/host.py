"""``motorbus doctor``'s host checks: timer, real-time grant, CPU governor, RT processes.

Pure: facts in (gathered by :mod:`motorbus.doctor.probe`), findings out; never red.
"""

from __future__ import annotations

from dataclasses import dataclass

from motorbus.doctor.checks import Finding, Level

__all__ = ["HostFacts", "check_host"]


@dataclass(frozen=True, slots=True)
class HostFacts:
    """What the host offers a tight loop."""

    timer: str  # "timerfd" or "loop"
    can_fifo: bool
    can_lock: bool
    governors: frozenset[str] = frozenset()  # empty: no cpufreq (a VM, a fixed clock)
    rt_processes: tuple[tuple[int, str], ...] = ()


def check_host(facts: HostFacts) -> list[Finding]:
    """Timer source, real-time grant, CPU governor, other real-time processes."""
    out = []
    if facts.timer == "timerfd":
        out.append(Finding("host timer", Level.GREEN, "timerfd: deadlines to ~0.1 ms"))
    else:
        out.append(
            Finding(
                "host timer",
                Level.YELLOW,
                f"{facts.timer}: asyncio timers, deadlines rounded to 1 ms",
                "run on Linux (timerfd) for sub-millisecond deadlines",
            )
        )
    missing = [
        n for n, ok in (("SCHED_FIFO", facts.can_fifo), ("mlockall", facts.can_lock)) if not ok
    ]
    if missing:
        out.append(
            Finding(
                "host realtime",
                Level.YELLOW,
                f"real-time mode cannot be granted ({' and '.join(missing)} refused)",
                'echo "$USER - rtprio 99" | sudo tee -a /etc/security/limits.conf; echo '
                '"$USER - memlock unlimited" | sudo tee -a /etc/security/limits.conf; log in '
                "again, then use --realtime",
                {"sched_fifo": facts.can_fifo, "mlockall": facts.can_lock},
            )
        )
    else:
        out.append(
            Finding(
                "host realtime",
                Level.GREEN,
                "real-time mode can be granted (SCHED_FIFO, mlockall): use --realtime",
                "",
                {"sched_fifo": True, "mlockall": True},
            )
        )
    slow = sorted(facts.governors - {"performance"})
    if slow:
        out.append(
            Finding(
                "host cpufreq",
                Level.YELLOW,
                f"CPU frequency governor {', '.join(slow)}: wake-ups slow down while the CPU "
                "clocks up",
                "echo performance | sudo tee /sys/devices/system/cpu/cpu*/cpufreq/scaling_governor",
                {"governors": sorted(facts.governors)},
            )
        )
    else:
        text = "governor performance" if facts.governors else "no cpufreq control (VM or fixed)"
        out.append(
            Finding("host cpufreq", Level.GREEN, text, "", {"governors": sorted(facts.governors)})
        )
    if facts.rt_processes:
        names = ", ".join(f"{n} ({p})" for p, n in facts.rt_processes[:5])
        out.append(
            Finding(
                "host rt-processes",
                Level.YELLOW,
                f"{len(facts.rt_processes)} other processes run at real-time priority: {names}",
                "give the bus process a higher priority (--realtime PRIO) or another CPU",
                {"processes": [{"pid": p, "name": n} for p, n in facts.rt_processes]},
            )
        )
    else:
        out.append(Finding("host rt-processes", Level.GREEN, "no other real-time processes"))
    return out
