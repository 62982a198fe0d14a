"""The kernel's clock for benchmark figures: when did this process call write(2)?

A Python receiver timestamps what it reads with its own wake-up lateness (100-500 µs on
a quiet machine, milliseconds under load), so spacing and jitter "seen at the simulator"
mix what the bus did with how late the receiver woke up.  The kernel's tracepoint of
the sender's ``write(2)`` does not: on a pty or a UART the bytes are on their way when
the syscall is entered.  :class:`KernelWriteTrace` records those tracepoints for this
process with ``perf``, on ``CLOCK_MONOTONIC`` (``perf record -k CLOCK_MONOTONIC``), so
the times compare with ``time.monotonic()``::

    with KernelWriteTrace() as trace:
        ...  # run the bus
    if trace.measured:
        times = trace.starts(fd)          # seconds, one per write(2) to fd
        gaps = write_gaps(times)          # smallest gap, gaps under 1 ms
        jitter = grid_jitter(times, 0.010)
    else:
        print("not measured:", trace.why)

Recording needs root (or a permissive ``perf_event_paranoid``), ``perf`` on the PATH
and the ``syscalls:sys_enter_write`` tracepoint; when one is missing the trace says
``measured = False`` and ``why``, and figures are reported as not measured, never made
up.  The trace starts disabled and is switched on through perf's control FIFO; its
``ack`` is awaited, so no write made inside the ``with`` block is missed.

The analysis functions (:func:`write_gaps`, :func:`grid_jitter`, :func:`parse_perf_script`)
are pure and unit-tested on synthetic data and on a captured ``perf script`` sample.
"""

from __future__ import annotations

import itertools
import math
import os
import re
import select
import shutil
import signal
import subprocess
import tempfile
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

__all__ = [
    "GapStats",
    "GridJitter",
    "KernelWriteTrace",
    "Syscall",
    "WriteCall",
    "busiest_fd",
    "grid_jitter",
    "not_measured",
    "parse_perf_script",
    "parse_syscalls",
    "port_figures",
    "worst_tick_figures",
    "write_gaps",
]

#: Events recorded: entry (time, fd, byte count) and exit (time, return value) of write(2).
EVENTS = "syscalls:sys_enter_write,syscalls:sys_exit_write"
#: Added with ``KernelWriteTrace(every_syscall=True)``: entry and exit of every system
#: call (its number only), to see how long the kernel held the process in each.
SYSCALL_EVENTS = "raw_syscalls:sys_enter,raw_syscalls:sys_exit"
#: x86-64 numbers of the calls in which an epoll event loop (asyncio's, uvloop's) waits
#: for its fds (epoll_wait, epoll_pwait, epoll_pwait2): time in them is sleep, not work
#: held up (``Syscall.waits``).  Not poll(2): the bus's ``poll(0)`` before a request
#: (``drain_input``) is a check that returns at once, and time held in it is the machine's.
WAIT_SYSCALLS = frozenset({232, 281, 441})
#: Where the kernel lists the tracepoint (tracefs, mounted in either place).
TRACEPOINT_DIRS = (
    "/sys/kernel/tracing/events/syscalls/sys_enter_write",
    "/sys/kernel/debug/tracing/events/syscalls/sys_enter_write",
)
#: Longest wait for perf to switch the events on, and to stop and write its file.
START_TIMEOUT_S = 15.0
STOP_TIMEOUT_S = 60.0
#: A gap shorter than this breaks the LA manual's 1 ms between commands.
SPACING_S = 1e-3
#: A tick later than this from its grid slot is "late".
LATE_S = 1e-3

_LINE = re.compile(
    r"(?P<pid>\d+)/(?P<tid>\d+)\s+(?P<time>\d+\.\d+):\s+syscalls:sys_(?P<kind>enter|exit)_write:"
    r"\s+(?P<rest>.*)$"
)
_RAW = re.compile(
    r"(?P<pid>\d+)/(?P<tid>\d+)\s+(?P<time>\d+\.\d+):\s+raw_syscalls:sys_(?P<kind>enter|exit):"
    r"\s+NR (?P<nr>-?\d+)"
)
_ENTER = re.compile(r"fd: (0x[0-9a-fA-F]+), buf: 0x[0-9a-fA-F]+, count: (0x[0-9a-fA-F]+)")
_EXIT = re.compile(r"(-?0x[0-9a-fA-F]+|-?\d+)\s*$")


@dataclass(frozen=True, slots=True)
class WriteCall:
    """One write(2) as the kernel saw it.

    Attributes:
        pid, tid: process and thread that made the call.
        fd: file descriptor written to.
        count: bytes asked for.
        start: time the syscall was entered (s, CLOCK_MONOTONIC).
        end: time it returned (s), None if the exit was not recorded.
        ret: its return value (bytes written, or a negative errno), None with ``end``.
    """

    pid: int
    tid: int
    fd: int
    count: int
    start: float
    end: float | None = None
    ret: int | None = None

    @property
    def duration(self) -> float | None:
        """Seconds spent inside the syscall, None if its exit was not recorded."""
        return None if self.end is None else self.end - self.start


def parse_perf_script(text: str | Iterable[str], pid: int | None = None) -> list[WriteCall]:
    """Write calls in the output of ``perf script -F comm,pid,tid,time,event,trace --ns``.

    Each entry is paired with the next exit on the same thread.  Lines of other events
    or processes (``pid`` given) are skipped; so are lines that do not parse.

    Returns:
        The calls in the order they were entered.
    """
    lines = text.splitlines() if isinstance(text, str) else text
    calls: list[WriteCall] = []
    open_call: dict[int, int] = {}  # tid -> index in calls of its unfinished write
    for line in lines:
        m = _LINE.search(line)
        if m is None:
            continue
        p, tid, t = int(m["pid"]), int(m["tid"]), float(m["time"])
        if pid is not None and p != pid:
            continue
        if m["kind"] == "enter":
            e = _ENTER.search(m["rest"])
            if e is None:
                continue
            open_call[tid] = len(calls)
            calls.append(WriteCall(p, tid, int(e[1], 16), int(e[2], 16), t))
        else:
            index = open_call.pop(tid, None)
            x = _EXIT.search(m["rest"])
            if index is None or x is None:
                continue
            c = calls[index]
            ret = int(x[1], 0)
            if ret >= 1 << 63:  # perf prints a negative errno as an unsigned 64-bit value
                ret -= 1 << 64
            calls[index] = WriteCall(c.pid, c.tid, c.fd, c.count, c.start, t, ret)
    return calls


@dataclass(frozen=True, slots=True)
class Syscall:
    """One system call of any kind, as the kernel saw it (``every_syscall=True``).

    Attributes:
        tid: thread that made it.
        nr: its number (x86-64 numbering on this machine).
        start, end: entry and return (s, CLOCK_MONOTONIC).
    """

    tid: int
    nr: int
    start: float
    end: float

    @property
    def waits(self) -> bool:
        """True for the calls an event loop sleeps in (``WAIT_SYSCALLS``)."""
        return self.nr in WAIT_SYSCALLS


def parse_syscalls(text: str | Iterable[str], pid: int | None = None) -> list[Syscall]:
    """Every completed system call in ``perf script`` output of ``raw_syscalls`` events
    (other lines, other processes, and calls without an exit are skipped), in entry order."""
    lines = text.splitlines() if isinstance(text, str) else text
    out: list[Syscall] = []
    open_at: dict[int, tuple[int, float]] = {}  # tid -> (nr, entered)
    for line in lines:
        m = _RAW.search(line)
        if m is None or (pid is not None and int(m["pid"]) != pid):
            continue
        tid, t, nr = int(m["tid"]), float(m["time"]), int(m["nr"])
        if m["kind"] == "enter":
            open_at[tid] = (nr, t)
            continue
        entered = open_at.pop(tid, None)
        if entered is not None and entered[0] == nr:
            out.append(Syscall(tid, nr, entered[1], t))
    out.sort(key=lambda c: c.start)
    return out


def busiest_fd(calls: Sequence[WriteCall], sizes: Iterable[int] | None = None) -> int | None:
    """The fd > 2 with the most writes (of one of ``sizes`` bytes, if given); None if none."""
    wanted = None if sizes is None else set(sizes)
    counts = Counter(c.fd for c in calls if c.fd > 2 and (wanted is None or c.count in wanted))
    return counts.most_common(1)[0][0] if counts else None


@dataclass(frozen=True, slots=True)
class GapStats:
    """Start-to-start gaps between consecutive writes.

    Attributes:
        count: gaps measured (writes - 1).
        min_us: the smallest gap (µs), NaN without gaps.
        under: gaps shorter than the threshold.
        threshold_us: that threshold (µs).
    """

    count: int
    min_us: float
    under: int
    threshold_us: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "gaps": self.count,
            "min_gap_us": _round(self.min_us),
            "gaps_under_1000us" if self.threshold_us == 1000 else "gaps_under": self.under,
        }


def write_gaps(times: Sequence[float], threshold: float = SPACING_S) -> GapStats:
    """Gaps between consecutive ``times`` (s): smallest, and how many are under ``threshold``."""
    ordered = sorted(times)
    gaps = [b - a for a, b in itertools.pairwise(ordered)]
    return GapStats(
        count=len(gaps),
        min_us=min(gaps) * 1e6 if gaps else math.nan,
        under=sum(1 for g in gaps if g < threshold),
        threshold_us=threshold * 1e6,
    )


@dataclass(frozen=True, slots=True)
class GridJitter:
    """Distance of periodic writes from a least-squares grid ``t_k = a + k * P``.

    Attributes:
        ticks: writes fitted.
        p50_us, p99_us, max_us: of the absolute residuals (µs); NaN with fewer than 2 ticks.
        late: ticks more than ``late_threshold`` after their slot.
        missed: grid slots between the first and the last tick without a write.
        extra: writes beyond the first in a slot (a slot written twice).
        period_us: the fitted period P (µs).
        drift_ppm: (P - nominal period) / nominal period, in parts per million.
    """

    ticks: int
    p50_us: float
    p99_us: float
    max_us: float
    late: int
    missed: int
    extra: int
    period_us: float
    drift_ppm: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "ticks": self.ticks,
            "tick_jitter_p50_us": _round(self.p50_us),
            "tick_jitter_p99_us": _round(self.p99_us),
            "tick_jitter_max_us": _round(self.max_us),
            "late_ticks": self.late,
            "missed_ticks": self.missed,
            "extra_ticks": self.extra,
            "period_us": _round(self.period_us, 2),
            "drift_ppm": _round(self.drift_ppm, 1),
        }


def _percentile(ordered: Sequence[float], q: float) -> float:
    """Nearest-rank ``q`` quantile (0..1) of sorted values."""
    return ordered[min(len(ordered) - 1, max(0, round(q * (len(ordered) - 1))))]


def _fit(ks: Sequence[int], ts: Sequence[float]) -> tuple[float, float]:
    """Least-squares intercept and slope of ts against ks (at least two distinct ks)."""
    n = len(ks)
    mk = sum(ks) / n
    mt = sum(ts) / n
    skk = sum((k - mk) ** 2 for k in ks)
    skt = sum((k - mk) * (t - mt) for k, t in zip(ks, ts, strict=True))
    slope = skt / skk
    return mt - slope * mk, slope


def grid_jitter(
    times: Sequence[float],
    period: float,
    late_threshold: float = LATE_S,
    *,
    by_index: bool = False,
) -> GridJitter:
    """Fit ``t_k = a + k * P`` to periodic ``times`` (s) and measure the residuals.

    Each time gets the slot ``k = round((t - t_first) / period)``; a and P are fitted by
    least squares, the slots are assigned once more from the fitted origin (nominal
    period) and the grid fitted again (so a late first tick does not shift every slot).
    A constant latency and a steady clock-rate difference are thus not counted; every
    wobble is.

    With ``by_index`` the k-th time is held to slot k and only a is fitted (P is the
    nominal period): for a sender with no grid (a sleep loop), whose drift is then
    counted as jitter, as it would be by a device expecting the period.
    """
    ordered = sorted(times)
    nan = math.nan
    if len(ordered) < 2 or period <= 0:
        return GridJitter(len(ordered), nan, nan, nan, 0, 0, 0, nan, nan)
    t0 = ordered[0]
    if by_index:
        a = sum(t - k * period for k, t in enumerate(ordered)) / len(ordered)
        residuals = [t - (a + k * period) for k, t in enumerate(ordered)]
        magnitudes = sorted(abs(r) for r in residuals)
        span = ordered[-1] - ordered[0]
        return GridJitter(
            ticks=len(ordered),
            p50_us=_percentile(magnitudes, 0.50) * 1e6,
            p99_us=_percentile(magnitudes, 0.99) * 1e6,
            max_us=magnitudes[-1] * 1e6,
            late=sum(1 for r in residuals if r > late_threshold),
            missed=0,
            extra=0,
            period_us=span / (len(ordered) - 1) * 1e6,
            drift_ppm=(span / (len(ordered) - 1) - period) / period * 1e6,
        )
    ks = [round((t - t0) / period) for t in ordered]
    if ks[-1] == ks[0]:
        return GridJitter(len(ordered), nan, nan, nan, 0, 0, len(ordered) - 1, nan, nan)
    a, p = _fit(ks, ordered)
    for _ in range(2):
        # Slots from the nominal period: a fitted one would follow a drifting sender
        # (a sleep loop) and hide its drift as re-numbered slots.
        ks = [round((t - a) / period) for t in ordered]
        if ks[-1] == ks[0]:
            break
        a, p = _fit(ks, ordered)
    residuals = [t - (a + k * p) for k, t in zip(ks, ordered, strict=True)]
    magnitudes = sorted(abs(r) for r in residuals)
    slots = set(ks)
    return GridJitter(
        ticks=len(ordered),
        p50_us=_percentile(magnitudes, 0.50) * 1e6,
        p99_us=_percentile(magnitudes, 0.99) * 1e6,
        max_us=magnitudes[-1] * 1e6,
        late=sum(1 for r in residuals if r > late_threshold),
        missed=(max(ks) - min(ks) + 1) - len(slots),
        extra=len(ks) - len(slots),
        period_us=p * 1e6,
        drift_ppm=(p - period) / period * 1e6,
    )


def _round(value: float, digits: int = 0) -> float | None:
    """``value`` rounded for a report; None for NaN (strict JSON has no NaN)."""
    if not math.isfinite(value):
        return None
    return round(value, digits) if digits else float(round(value))


def not_measured(why: str) -> dict[str, Any]:
    """The report entry of a kernel figure that could not be taken."""
    return {"measured": False, "why": why}


def port_figures(
    trace: KernelWriteTrace,
    frame_sizes: Sequence[int],
    *,
    tick_bytes: int | None = None,
    period: float = 0.010,
    expected_ticks: int = 0,
    by_index: bool = False,
) -> dict[str, Any]:
    """Spacing (and tick jitter) of the writes to the port, on the kernel's clock.

    The port is the fd with the most writes of ``frame_sizes`` bytes; ``kernel_*`` keys
    (µs; NaN where nothing to measure), or ``kernel_measured: False`` and ``kernel_why``.
    With ``tick_bytes``, the writes of that size are ticks of a ``period`` grid:
    jitter from a least-squares grid, late and missed ticks, and the share of the
    ``expected_ticks`` (or of the grid's slots, if more) that were sent.
    """
    if not trace.measured:
        return {"kernel_measured": False, "kernel_why": trace.why}
    fd = busiest_fd(trace.calls, frame_sizes)
    if fd is None:
        return {"kernel_measured": False, "kernel_why": "no frame-sized write(2) was recorded"}
    calls = trace.of(fd)
    starts = [c.start for c in calls]
    gaps = write_gaps(starts)
    # The spacing rule counts from when the previous write returned.
    after_return = [b.start - a.end for a, b in itertools.pairwise(calls) if a.end is not None]
    durations = sorted(c.duration for c in calls if c.duration is not None)
    out: dict[str, Any] = {
        "kernel_measured": True,
        "kernel_fd": fd,
        "kernel_writes": len(calls),
        "kernel_odd_size_writes": sum(1 for c in calls if c.count not in frame_sizes),
        "kernel_min_gap_us": gaps.min_us,
        "kernel_gaps_under_1000us": gaps.under,
        "kernel_min_gap_after_return_us": min(after_return) * 1e6 if after_return else math.nan,
        "kernel_write_p50_us": _percentile(durations, 0.5) * 1e6 if durations else math.nan,
        "kernel_write_p99_us": _percentile(durations, 0.99) * 1e6 if durations else math.nan,
        "kernel_write_max_us": durations[-1] * 1e6 if durations else math.nan,
    }
    if tick_bytes is not None:
        ticks = grid_jitter(
            [c.start for c in calls if c.count == tick_bytes], period, by_index=by_index
        )
        # Ticks the stream should have sent in its run (targets for `seconds`), or the
        # grid slots between the first and the last tick, whichever is more.
        slots = max(expected_ticks, ticks.ticks - ticks.extra + ticks.missed)
        out.update(
            {
                "kernel_ticks": ticks.ticks,
                "kernel_ticks_sent_pct": 100 * (ticks.ticks - ticks.extra) / slots
                if slots
                else math.nan,
                "kernel_tick_jitter_p50_us": ticks.p50_us,
                "kernel_tick_jitter_p99_us": ticks.p99_us,
                "kernel_tick_jitter_max_us": ticks.max_us,
                "kernel_late_ticks": ticks.late,
                "kernel_missed_ticks": ticks.missed,
            }
        )
    return out


def worst_tick_figures(trace: KernelWriteTrace, tick_bytes: int, period: float) -> dict[str, Any]:
    """Every fd with writes of ``tick_bytes`` bytes is a bus: its grid jitter, worst bus."""
    if not trace.measured:
        return {"kernel_measured": False, "kernel_why": trace.why}
    fds = sorted({c.fd for c in trace.calls if c.count == tick_bytes and c.fd > 2})
    fits = [grid_jitter(trace.starts(fd, [tick_bytes]), period) for fd in fds]
    gaps = [write_gaps(trace.starts(fd)) for fd in fds]
    if not fits:
        return {"kernel_measured": False, "kernel_why": "no tick-sized write(2) was recorded"}
    return {
        "kernel_measured": True,
        "kernel_buses": len(fds),
        "kernel_tick_jitter_p99_us": max(f.p99_us for f in fits),
        "kernel_tick_jitter_max_us": max(f.max_us for f in fits),
        "kernel_late_ticks": sum(f.late for f in fits),
        "kernel_missed_ticks": sum(f.missed for f in fits),
        "kernel_min_gap_us": min(g.min_us for g in gaps),
    }


# -- recording -----------------------------------------------------------------------------


def _unavailable() -> str | None:
    """Why perf cannot trace write(2) here, or None if it should work."""
    if shutil.which("perf") is None:
        return "perf is not installed (Debian: apt-get install linux-perf)"
    if os.geteuid() != 0:
        try:
            paranoid = int(Path("/proc/sys/kernel/perf_event_paranoid").read_text().strip())
        except (OSError, ValueError):
            paranoid = 2
        if paranoid > -1:
            return f"not root and kernel.perf_event_paranoid={paranoid} (tracepoints need -1)"
    if not any(os.path.isdir(d) for d in TRACEPOINT_DIRS):
        return (
            "the syscalls:sys_enter_write tracepoint is missing (no tracefs or no ftrace; "
            "as root: mount -t tracefs nodev /sys/kernel/tracing)"
        )
    return None


@dataclass
class KernelWriteTrace:
    """Record this process's write(2) calls with ``perf`` for the ``with`` block.

    Attributes:
        pid: the process traced (default: this one).
        every_syscall: trace every system call too (``syscalls``), not only write(2):
            more events, so a little more disturbance; for ``bench_late_ticks.py``.
        measured: True once the trace was recorded and parsed.
        why: why not, when ``measured`` is False.
        calls: every write call of ``pid`` (all threads), in order.
        syscalls: with ``every_syscall``, every completed system call of ``pid``.
    """

    pid: int = field(default_factory=os.getpid)
    every_syscall: bool = False
    measured: bool = False
    why: str = "not started"
    calls: list[WriteCall] = field(default_factory=list)
    syscalls: list[Syscall] = field(default_factory=list)
    _proc: subprocess.Popen[bytes] | None = None
    _tmp: tempfile.TemporaryDirectory[str] | None = None
    _fds: tuple[int, int] | None = None

    def __enter__(self) -> KernelWriteTrace:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._proc is not None

    def start(self) -> None:
        """Start perf and wait until its events are on; on failure set ``why``."""
        why = _unavailable()
        if why is not None:
            self.why = why
            return
        self._tmp = tempfile.TemporaryDirectory(prefix="motorbus-perf-")
        tmp = Path(self._tmp.name)
        ctl, ack = tmp / "ctl", tmp / "ack"
        os.mkfifo(ctl)
        os.mkfifo(ack)
        # O_RDWR: opening a FIFO that way never blocks, even if perf dies before opening it.
        ctl_fd, ack_fd = os.open(ctl, os.O_RDWR), os.open(ack, os.O_RDWR)
        self._fds = (ctl_fd, ack_fd)
        events = f"{EVENTS},{SYSCALL_EVENTS}" if self.every_syscall else EVENTS
        cmd = [
            "perf", "record", "-q", "-e", events, "-k", "CLOCK_MONOTONIC",
            "-D", "-1", "--control", f"fifo:{ctl},{ack}",
            "-o", str(tmp / "out.perf"), "-p", str(self.pid),
        ]  # fmt: skip
        self._proc = subprocess.Popen(
            cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
        )
        os.write(ctl_fd, b"enable\n")
        ready, _, _ = select.select([ack_fd], [], [], START_TIMEOUT_S)
        if ready and os.read(ack_fd, 64).startswith(b"ack"):
            self.why = "running"
            return
        self._fail("perf did not acknowledge 'enable' in time")

    def _fail(self, why: str) -> None:
        proc, self._proc = self._proc, None
        err = b""
        if proc is not None:
            if proc.poll() is None:
                proc.kill()
            _, err = proc.communicate(timeout=STOP_TIMEOUT_S)
        detail = err.decode(errors="replace").strip().splitlines()
        self.why = why + (f" (perf: {detail[-1]})" if detail else "")
        self._cleanup()

    def _cleanup(self) -> None:
        if self._fds is not None:
            for fd in self._fds:
                os.close(fd)
            self._fds = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def stop(self) -> None:
        """Stop perf (SIGINT), parse its file into ``calls``; on failure set ``why``."""
        proc = self._proc
        if proc is None or self._tmp is None:
            self._cleanup()
            return
        proc.send_signal(signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            self._fail("perf did not stop after SIGINT")
            return
        self._proc = None
        data = Path(self._tmp.name) / "out.perf"
        if not data.exists():
            detail = err.decode(errors="replace").strip().splitlines()
            self.why = "perf wrote no data" + (f" (perf: {detail[-1]})" if detail else "")
            self._cleanup()
            return
        script = subprocess.run(
            ["perf", "script", "-i", str(data), "-F", "comm,pid,tid,time,event,trace", "--ns"],
            capture_output=True,
            text=True,
            timeout=STOP_TIMEOUT_S * 5,
            check=False,
        )
        self._cleanup()
        if script.returncode != 0:
            self.why = f"perf script failed: {script.stderr.strip()[-200:]}"
            return
        self.calls = parse_perf_script(script.stdout, pid=self.pid)
        if self.every_syscall:
            self.syscalls = parse_syscalls(script.stdout, pid=self.pid)
        self.measured = True
        self.why = ""

    # -- views --------------------------------------------------------------------------

    def writes(self) -> dict[int, list[tuple[float, int]]]:
        """Per fd: (time the write was entered, byte count) in order."""
        out: dict[int, list[tuple[float, int]]] = {}
        for c in self.calls:
            out.setdefault(c.fd, []).append((c.start, c.count))
        return out

    def of(self, fd: int, sizes: Iterable[int] | None = None) -> list[WriteCall]:
        """The calls to ``fd`` (of one of ``sizes`` bytes, if given)."""
        wanted = None if sizes is None else set(sizes)
        return [c for c in self.calls if c.fd == fd and (wanted is None or c.count in wanted)]

    def starts(self, fd: int, sizes: Iterable[int] | None = None) -> list[float]:
        """Entry times (s) of the calls to ``fd`` (of one of ``sizes`` bytes, if given)."""
        return [c.start for c in self.of(fd, sizes)]
