"""Opt-in real-time mode for the process that drives the buses (Linux).

``enable()`` asks the kernel and the interpreter for what a 1 ms bus loop needs:

* ``SCHED_FIFO`` at a chosen priority for the calling thread (the event loop's), so
  ordinary processes cannot delay a tick;
* ``mlockall(MCL_CURRENT | MCL_FUTURE)``, so no page of the process is swapped out or
  faulted in lazily in the middle of a tick;
* garbage-collector control: one full collection and ``gc.freeze()`` at set-up, then
  no automatic full (generation 2) collection at all; the full collections happen in
  idle time between ticks, from :func:`idle_hook` / :func:`collect_when_idle`;
* optionally, CPU affinity (``os.sched_setaffinity``).

:func:`pin` runs every thread of the process on a set of CPUs (a bus file's
``[process.NAME] cpus``, which ``BusManager`` applies when it opens that group's buses);
:meth:`Pinning.restore` undoes it.

What the system refuses (no ``CAP_SYS_NICE`` / ``RLIMIT_RTPRIO``, a finite
``RLIMIT_MEMLOCK``) is said in ONE warning line on the ``motorbus.realtime`` logger,
with how to grant it, and the program carries on normally.  The returned
:class:`RealtimeReport` says what was applied and what was refused, and why.

``MOTORBUS_REALTIME=1`` (or a priority 2..99) in the environment, or ``--realtime[=PRIO]``
on a command line, turns it on when the first :class:`~motorbus.bus.bus.Bus` or
:class:`~motorbus.manager.BusManager` of the process opens (:func:`on_bus_open`).
docs/realtime.md says how to grant the rights, what it costs and what can go wrong.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import gc
import logging
import math
import os
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from motorbus.errors import LocalProtocolError

if sys.platform != "win32":  # Windows has no resource module (nor SCHED_FIFO, mlockall)
    import resource

__all__ = [
    "DEFAULT_PRIORITY",
    "ENV_VAR",
    "GcPauseMonitor",
    "Pinning",
    "RealtimeReport",
    "check_cpus",
    "collect_when_idle",
    "disable",
    "enable",
    "gc_controlled",
    "idle_hook",
    "on_bus_open",
    "parse_setting",
    "pin",
    "refreeze",
    "request",
    "requested",
]

log = logging.getLogger("motorbus.realtime")

#: Environment variable read when the first bus opens: ``1`` (default priority),
#: ``2``..``99`` (that priority), ``0`` or empty (off).
ENV_VAR = "MOTORBUS_REALTIME"
#: SCHED_FIFO priority when none is given: the middle of the range, where PREEMPT_RT
#: kernels also run their interrupt threads; not above them, so our loop never
#: pre-empts the serial adapter's interrupt thread (at equal priority that thread runs
#: as soon as the loop blocks, which it does between ticks).
DEFAULT_PRIORITY = 50
PRIORITY_MIN = 1
PRIORITY_MAX = 99
#: Generation-2 threshold while the collector is controlled: automatic full
#: collections never trigger (CPython counts gen-1 collections against it).
GEN2_THRESHOLD_OFF = 1 << 30
#: Default idle budget of :func:`idle_hook`, seconds: a full collection of the
#: unfrozen objects of a bus process takes well under this.
IDLE_BUDGET_S = 2e-3
#: A full collection put off this many times because it would not fit the budget is
#: then run anyway (still in idle time), so cyclic garbage cannot grow without bound.
MAX_DEFERRALS = 50
#: mlockall(2) flags, <sys/mman.h> on Linux.
_MCL_CURRENT = 1
_MCL_FUTURE = 2
#: capability(7) number of CAP_IPC_LOCK (locking beyond RLIMIT_MEMLOCK).
_CAP_IPC_LOCK = 14

_HOW_TO_GRANT = {
    "sched_fifo": (
        "grant real-time priority: '@GROUP - rtprio {prio}' in /etc/security/limits.conf, "
        "or setcap cap_sys_nice+ep $(readlink -f $(which python3)), or in a systemd unit "
        "CPUSchedulingPolicy=fifo and CPUSchedulingPriority={prio}"
    ),
    "mlockall": (
        "allow locking memory: '@GROUP - memlock unlimited' in /etc/security/limits.conf, "
        "or LimitMEMLOCK=infinity in a systemd unit (or CAP_IPC_LOCK)"
    ),
    "affinity": "choose CPUs this process may use (see taskset -p, cgroup cpusets)",
}


@dataclass(slots=True)
class RealtimeReport:
    """What :func:`enable` applied and what the system refused.

    Attributes:
        applied: short descriptions of what took effect, e.g. ``"SCHED_FIFO 50"``.
        refused: what was refused, mapped to why (the error and how to grant it).
        priority: the SCHED_FIFO priority in effect, or ``None``.
        memory_locked: ``mlockall`` succeeded.
        gc_frozen: objects moved to the permanent generation by ``gc.freeze()``.
        cpus: the CPU set in effect if affinity was set, else ``None``.
    """

    applied: list[str] = field(default_factory=list)
    refused: dict[str, str] = field(default_factory=dict)
    priority: int | None = None
    memory_locked: bool = False
    gc_frozen: int = 0
    cpus: frozenset[int] | None = None
    # What disable() restores.
    _policy: tuple[int, int] | None = None
    _affinity: frozenset[int] | None = None
    _threshold: tuple[int, int, int] | None = None
    _gc_was_enabled: bool = True

    @property
    def ok(self) -> bool:
        """Everything asked for was applied."""
        return not self.refused

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready summary."""
        return {
            "applied": list(self.applied),
            "refused": dict(self.refused),
            "priority": self.priority,
            "memory_locked": self.memory_locked,
            "gc_frozen": self.gc_frozen,
            "cpus": sorted(self.cpus) if self.cpus is not None else None,
        }


# -- checking input -------------------------------------------------------------------


def _check_priority(priority: object, field_name: str = "priority") -> int:
    if isinstance(priority, bool) or not isinstance(priority, int):
        raise LocalProtocolError(
            f"{field_name}={priority!r} must be an integer SCHED_FIFO priority "
            f"{PRIORITY_MIN}..{PRIORITY_MAX}",
            field=field_name,
            value=priority,
        )
    if not PRIORITY_MIN <= priority <= PRIORITY_MAX:
        raise LocalProtocolError(
            f"{field_name}={priority} is out of range: allowed {PRIORITY_MIN}..{PRIORITY_MAX}",
            field=field_name,
            value=priority,
        )
    return priority


def check_cpus(cpus: Iterable[int]) -> frozenset[int]:
    """Return ``cpus`` as a set if each is a CPU number of this machine, 0..cpu_count-1.

    Raises:
        LocalProtocolError: text, an empty set, or a CPU out of range (field ``cpus``).
    """
    if isinstance(cpus, str | bytes):
        raise LocalProtocolError(
            f"cpus={cpus!r} must be CPU numbers such as [0] or {{2, 3}}", field="cpus", value=cpus
        )
    top = (os.cpu_count() or 1) - 1
    out: set[int] = set()
    for cpu in cpus:
        if isinstance(cpu, bool) or not isinstance(cpu, int) or not 0 <= cpu <= top:
            raise LocalProtocolError(
                f"cpus: CPU {cpu!r} is out of range: allowed 0..{top} (this machine's CPUs)",
                field="cpus",
                value=cpu,
            )
        out.add(cpu)
    if not out:
        raise LocalProtocolError("cpus is empty: give at least one CPU", field="cpus", value=[])
    return frozenset(out)


def parse_setting(text: str | None, field_name: str = ENV_VAR) -> int | None:
    """Parse a real-time setting: ``None``, ``""`` or ``"0"`` is off (``None``); ``"1"`` is
    on at :data:`DEFAULT_PRIORITY`; ``"2"``..``"99"`` is on at that priority.

    Raises:
        LocalProtocolError: anything else, naming the field, the value and what is allowed.
    """
    if text is None or not text.strip() or text.strip() == "0":
        return None
    value = text.strip()
    if not value.isdigit() or not PRIORITY_MIN <= int(value) <= PRIORITY_MAX:
        raise LocalProtocolError(
            f"{field_name}={text!r} is not allowed: use 0 or empty (off), 1 (on, priority "
            f"{DEFAULT_PRIORITY}) or a SCHED_FIFO priority 2..{PRIORITY_MAX}",
            field=field_name,
            value=text,
        )
    number = int(value)
    return DEFAULT_PRIORITY if number == 1 else number


# -- the pieces -------------------------------------------------------------------------

_libc: Any = None


def _mlockall(flags: int) -> int:
    """``mlockall(flags)`` through libc; return 0 or the errno."""
    global _libc
    if _libc is None:
        _libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
    if _libc.mlockall(flags) == 0:
        return 0
    return ctypes.get_errno() or errno.EPERM


def _munlockall() -> None:
    if _libc is not None:
        _libc.munlockall()


def _has_capability(number: int) -> bool:
    """The effective capability set holds ``number`` (from /proc/self/status)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("CapEff:"):
                    return bool(int(line.split()[1], 16) >> number & 1)
    except (OSError, ValueError):
        pass
    return False


def _set_fifo(priority: int, report: RealtimeReport) -> None:
    if not hasattr(os, "sched_setscheduler"):
        report.refused["sched_fifo"] = f"SCHED_FIFO is not available on {sys.platform}"
        return
    previous = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)
    # RESET_ON_FORK: child processes (simulators, shells) start as ordinary processes.
    policy = os.SCHED_FIFO | getattr(os, "SCHED_RESET_ON_FORK", 0)
    try:
        os.sched_setscheduler(0, policy, os.sched_param(priority))
    except OSError as err:
        limit = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
        shown = "unlimited" if limit == resource.RLIM_INFINITY else str(limit)
        report.refused["sched_fifo"] = (
            f"SCHED_FIFO {priority}: {err.strerror or err} (RLIMIT_RTPRIO {shown}); "
            + _HOW_TO_GRANT["sched_fifo"].format(prio=priority)
        )
        return
    report._policy = previous
    report.priority = priority
    report.applied.append(f"SCHED_FIFO {priority}")


def _lock_memory(report: RealtimeReport) -> None:
    if not sys.platform.startswith("linux"):
        report.refused["mlockall"] = f"mlockall is not used on {sys.platform}"
        return
    limit = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0]
    if limit != resource.RLIM_INFINITY and not _has_capability(_CAP_IPC_LOCK):
        # With MCL_FUTURE every later allocation past the limit would fail: refuse
        # rather than turn a memory limit into MemoryError in the middle of a run.
        report.refused["mlockall"] = (
            f"RLIMIT_MEMLOCK is {limit // 1024} KiB, not unlimited: locking future memory "
            "would make allocations fail past it; " + _HOW_TO_GRANT["mlockall"]
        )
        return
    code = _mlockall(_MCL_CURRENT | _MCL_FUTURE)
    if code:
        report.refused["mlockall"] = f"mlockall: {os.strerror(code)}; " + _HOW_TO_GRANT["mlockall"]
        return
    report.memory_locked = True
    report.applied.append("mlockall(MCL_CURRENT|MCL_FUTURE)")


def _set_affinity(cpus: frozenset[int], report: RealtimeReport) -> None:
    if not hasattr(os, "sched_setaffinity"):
        report.refused["affinity"] = f"CPU affinity is not available on {sys.platform}"
        return
    previous = frozenset(os.sched_getaffinity(0))
    try:
        os.sched_setaffinity(0, cpus)
    except OSError as err:
        report.refused["affinity"] = (
            f"CPUs {sorted(cpus)}: {err.strerror or err}; " + _HOW_TO_GRANT["affinity"]
        )
        return
    report._affinity = previous
    report.cpus = cpus
    report.applied.append(f"affinity {sorted(cpus)}")


# -- pinning the whole process ----------------------------------------------------------


def _thread_ids() -> list[int]:
    """Every thread of this process (Linux: /proc/self/task), else the calling one (0)."""
    try:
        return sorted(int(tid) for tid in os.listdir("/proc/self/task"))
    except OSError:
        return [0]


@dataclass(slots=True)
class Pinning:
    """What :func:`pin` changed, so that :meth:`restore` can put it back.

    Attributes:
        cpus: the CPUs every thread of the process was pinned to.
    """

    cpus: frozenset[int]
    #: thread id -> its CPUs before the pin.
    _before: dict[int, frozenset[int]] = field(default_factory=dict)
    #: the calling thread's CPUs before the pin: what threads born since get back.
    _default: frozenset[int] | None = None

    def restore(self) -> None:
        """Give every thread still on :attr:`cpus` the CPUs it had before the pin (a
        thread started since gets the pinning thread's); one moved elsewhere since stays."""
        if self._default is None:
            return
        for tid in _thread_ids():
            try:
                if frozenset(os.sched_getaffinity(tid)) == self.cpus:
                    os.sched_setaffinity(tid, self._before.get(tid, self._default))
            except ProcessLookupError:  # the thread ended meanwhile
                continue
        self._before.clear()
        self._default = None


def pin(cpus: Iterable[int]) -> Pinning:
    """Run every thread of this process on ``cpus``; threads and processes it starts
    later inherit them.  (``enable(cpus=...)`` pins the calling thread only.)

    Returns:
        What to undo with :meth:`Pinning.restore`.

    Raises:
        LocalProtocolError: a CPU this machine does not have (nothing is changed).
        OSError: this platform has no CPU affinity, or the kernel refused the set (a
            cpuset - container, cgroup, systemd ``AllowedCPUs=`` - may exclude it);
            every thread keeps the CPUs it had.
    """
    cpu_set = check_cpus(cpus)
    shown = ",".join(map(str, sorted(cpu_set)))
    if not hasattr(os, "sched_setaffinity"):
        raise OSError(
            errno.ENOSYS, f"cannot run on CPUs {shown}: no CPU affinity on {sys.platform}"
        )
    default = frozenset(os.sched_getaffinity(0))
    pinning = Pinning(cpu_set, _default=default)
    try:
        for tid in _thread_ids():
            try:
                before = frozenset(os.sched_getaffinity(tid))
                os.sched_setaffinity(tid, cpu_set)
            except ProcessLookupError:  # the thread ended meanwhile
                continue
            pinning._before[tid] = before
    except OSError as err:
        now = ",".join(map(str, sorted(default)))
        pinning.restore()
        raise OSError(
            err.errno,
            f"cannot run on CPUs {shown}: {err.strerror or err}; this process runs on CPUs "
            f"{now}; " + _HOW_TO_GRANT["affinity"],
        ) from err
    return pinning


# -- garbage collector ------------------------------------------------------------------


@dataclass(slots=True)
class _GcControl:
    active: bool = False
    due_after: int = 10  # the interpreter's own gen-2 threshold, kept for idle_hook
    last_full_s: float = 0.0
    deferred: int = 0
    idle_collections: int = 0
    in_idle_collection: bool = False


_gc = _GcControl()


def gc_controlled() -> bool:
    """Automatic full collections are off and :func:`idle_hook` runs them."""
    return _gc.active


def _control_gc(report: RealtimeReport) -> None:
    if _gc.active:  # an earlier enable() controls it already: freeze what is new
        report.gc_frozen = refreeze()
        report.applied.append(f"gc already controlled, refrozen ({report.gc_frozen} objects)")
        return
    threshold = gc.get_threshold()
    report._threshold = threshold
    report._gc_was_enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    report.gc_frozen = gc.get_freeze_count()
    # Young collections (gen 0/1) stay automatic: they only scan young objects.
    gc.set_threshold(threshold[0], threshold[1], GEN2_THRESHOLD_OFF)
    gc.enable()
    _gc.active = True
    _gc.due_after = max(1, threshold[2])
    _gc.deferred = 0
    report.applied.append(f"gc frozen ({report.gc_frozen} objects), automatic full collections off")


def refreeze() -> int:
    """Freeze the objects created since :func:`enable` (call it after your own set-up).

    Returns the number of objects now in the permanent generation.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def collect_when_idle(budget_s: float) -> bool:
    """Run a full collection now if one is due and the last one took at most ``budget_s``.

    Call it from idle time between ticks.  Cheap when nothing is due (one
    ``gc.get_count()``).  A collection that would not fit is put off, at most
    :data:`MAX_DEFERRALS` times in a row; then it runs anyway.

    Returns:
        True if a full collection ran.
    """
    if not _gc.active or gc.get_count()[2] < _gc.due_after:
        return False
    if _gc.last_full_s > budget_s and _gc.deferred < MAX_DEFERRALS:
        _gc.deferred += 1
        return False
    _gc.in_idle_collection = True
    start = time.perf_counter()
    try:
        gc.collect(2)
    finally:
        _gc.in_idle_collection = False
    _gc.last_full_s = time.perf_counter() - start
    _gc.deferred = 0
    _gc.idle_collections += 1
    return True


def idle_hook(budget_s: float = IDLE_BUDGET_S) -> bool:
    """The stream loop's idle-time call: returns at once unless real-time GC control is on
    and a full collection is due (see :func:`collect_when_idle`).  True if one ran."""
    if not _gc.active:
        return False
    return collect_when_idle(budget_s)


class GcPauseMonitor:
    """Measures garbage-collector pauses through ``gc.callbacks``.

    Each collection is recorded with its generation and whether :func:`collect_when_idle`
    ran it (``"idle"``) or the interpreter did on its own (``"auto"``: inside whatever
    code was allocating - a tick, in a bus process).  Use as a context manager or call
    :meth:`start` / :meth:`stop`.

    Args:
        keep: most recent pauses kept per (generation, origin) for percentiles.
    """

    def __init__(self, keep: int = 100_000) -> None:
        self._keep = keep
        self._pauses: dict[tuple[int, str], deque[float]] = {}
        self._counts: dict[tuple[int, str], int] = {}
        self._started = 0.0
        self._clock: Callable[[], float] = time.perf_counter

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._started = self._clock()
            return
        pause = self._clock() - self._started
        key = (int(info.get("generation", 2)), "idle" if _gc.in_idle_collection else "auto")
        ring = self._pauses.get(key)
        if ring is None:
            ring = self._pauses[key] = deque(maxlen=self._keep)
        ring.append(pause)
        self._counts[key] = self._counts.get(key, 0) + 1

    def start(self) -> GcPauseMonitor:
        """Begin recording."""
        if self._callback not in gc.callbacks:
            gc.callbacks.append(self._callback)
        return self

    def stop(self) -> None:
        """Stop recording (the numbers stay)."""
        if self._callback in gc.callbacks:
            gc.callbacks.remove(self._callback)

    def __enter__(self) -> GcPauseMonitor:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def count(self, generation: int, origin: str | None = None) -> int:
        """Collections of ``generation`` seen (``origin`` "auto", "idle" or both)."""
        return sum(
            n for (g, o), n in self._counts.items() if g == generation and origin in (None, o)
        )

    def summary(self) -> dict[str, dict[str, float]]:
        """Per ``"gen<N>-<origin>"``: count, max_us and p99_us (nearest rank)."""
        out: dict[str, dict[str, float]] = {}
        for (gen, origin), ring in sorted(self._pauses.items()):
            ordered = sorted(ring)
            rank = max(1, math.ceil(len(ordered) * 0.99))
            out[f"gen{gen}-{origin}"] = {
                "count": self._counts[(gen, origin)],
                "max_us": ordered[-1] * 1e6,
                "p99_us": ordered[rank - 1] * 1e6,
            }
        return out


# -- enable / disable -------------------------------------------------------------------


def enable(
    priority: int | None = None,
    *,
    cpus: Iterable[int] | None = None,
    lock_memory: bool = True,
    freeze_gc: bool = True,
) -> RealtimeReport:
    """Put the calling thread (the event loop's) and the process in real-time mode.

    Args:
        priority: SCHED_FIFO priority 1..99 (default :data:`DEFAULT_PRIORITY`).
        cpus: pin the calling thread to these CPUs (default: leave the affinity alone).
        lock_memory: ``mlockall(MCL_CURRENT | MCL_FUTURE)``.
        freeze_gc: full collection and ``gc.freeze()`` now, then no automatic full
            collection; :func:`idle_hook` runs them between ticks.

    Returns:
        What was applied and what was refused (refusals are also logged, in one
        WARNING line on the ``motorbus.realtime`` logger).

    Raises:
        LocalProtocolError: a priority outside 1..99 or a CPU this machine does not have,
            before anything is changed.
    """
    prio = DEFAULT_PRIORITY if priority is None else _check_priority(priority)
    cpu_set = None if cpus is None else check_cpus(cpus)
    report = RealtimeReport()
    if cpu_set is not None:
        _set_affinity(cpu_set, report)
    _set_fifo(prio, report)
    if freeze_gc:
        _control_gc(report)  # before locking: what is collected need not be locked
    if lock_memory:
        _lock_memory(report)
    if report.refused:
        log.warning(
            "real-time mode: applied %s; refused %s",
            ", ".join(report.applied) or "nothing",
            "; ".join(f"{what}: {why}" for what, why in report.refused.items()),
        )
    else:
        log.info("real-time mode: %s", ", ".join(report.applied))
    return report


def disable(report: RealtimeReport) -> None:
    """Undo what ``report``'s :func:`enable` applied: policy, affinity, memory lock, GC."""
    if report._policy is not None:
        policy, prio = report._policy
        os.sched_setscheduler(0, policy, os.sched_param(prio))
        report._policy = None
        report.priority = None
    if report._affinity is not None:
        os.sched_setaffinity(0, report._affinity)
        report._affinity = None
        report.cpus = None
    if report.memory_locked:
        _munlockall()
        report.memory_locked = False
    if report._threshold is not None:
        gc.unfreeze()
        gc.set_threshold(*report._threshold)
        if not report._gc_was_enabled:
            gc.disable()
        report._threshold = None
        _gc.active = False


# -- the environment variable and the command line ------------------------------------


@dataclass(slots=True)
class _Process:
    requested: int | None = None  # from --realtime; wins over the environment
    applied: RealtimeReport | None = None
    done: bool = False


_process = _Process()


def request(priority: int | None) -> None:
    """Ask for real-time mode at ``priority`` when the first bus opens (``None``: no ask).

    ``--realtime[=PRIO]`` calls this; it takes precedence over ``MOTORBUS_REALTIME``.

    Raises:
        LocalProtocolError: a priority outside 1..99.
    """
    _process.requested = None if priority is None else _check_priority(priority)


def requested() -> int | None:
    """The priority asked for with :func:`request`, if any."""
    return _process.requested


def wanted() -> bool:
    """Whether real-time mode is on or asked for (:func:`enable`, :func:`request`,
    ``MOTORBUS_REALTIME``): the bus timer then spins before precise deadlines
    (``motorbus.bus.timer.spin_asked``).  A malformed ``MOTORBUS_REALTIME`` asks for
    nothing here; :func:`on_bus_open` reports it."""
    if _process.applied is not None or _process.requested is not None or _gc.active:
        return True
    try:
        return parse_setting(os.environ.get(ENV_VAR)) is not None
    except LocalProtocolError:
        return False


def on_bus_open() -> RealtimeReport | None:
    """Honour ``--realtime`` / ``MOTORBUS_REALTIME`` once per process (``Bus.open`` calls it).

    Returns:
        The report of the one :func:`enable` call, or ``None`` if real-time mode is off.

    Raises:
        LocalProtocolError: ``MOTORBUS_REALTIME`` holds something other than 0..99 or
            empty (raised at every open, until it is fixed).
    """
    if _process.done:
        return _process.applied
    priority = _process.requested
    if priority is None:
        priority = parse_setting(os.environ.get(ENV_VAR))
    _process.done = True
    if priority is not None:
        _process.applied = enable(priority)
    return _process.applied
