"""Scanning an LA bus for the IDs that answer (``scan``), in one or two passes with an
adaptive reply budget per ID; ``motorbus.devices.la`` re-exports ``scan``,
``ScanReport`` and ``ScanPass``."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from motorbus.bus.bus import REQUEST_TIMEOUT_MAX_S, Bus, Priority
from motorbus.errors import ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol.base import check_int, check_timeout

__all__ = ["ScanPass", "ScanReport", "scan"]

#: Host allowance of a scan's first pass (seconds), on top of the wire time of the query
#: and its reply and the LA's worst-case turnaround (800 us, manual 3.4.2): enough for a
#: pty or a low-latency USB adapter on an idle host (a reply from an 800 us actuator
#: over a pty to a simulator process lands ~0.2 ms after the wire says, p50).  A reply
#: that misses it is still seen (a late reply) and its ID is asked again, patiently.
SCAN_HOST_ALLOWANCE_S = 300e-6
#: The second pass gives every ID at least this much more than the first pass did...
SCAN_SECOND_PASS_EXTRA_S = 400e-6
#: ... or this share of the first pass's budget, whichever is more (slow baud rates).
SCAN_SECOND_PASS_SHARE = 0.25
#: The budget follows what the bus measured: at least this times the p99 reply latency
#: of the LA actuators that answered on it before the pass (the first pass's replies
#: shape the second's budget).
SCAN_MEASURED_FACTOR = 1.25
#: Ceiling of the adaptive budget: the fixed budget scans used before (10 ms), or twice
#: the floor at slow baud rates.
SCAN_BUDGET_MAX_S = 0.010
#: An ID whose answer came after its budget (a late reply: it is there, the host is
#: slow) is asked again with this budget: in the second pass, or at its end if the
#: late answer came during it.
SCAN_LATE_BUDGET_S = 0.050
#: After each pass of a two-pass scan, the scan waits this long (or two budgets, if
#: more) for late answers to the last IDs asked: an ID is only asked again patiently
#: if its late answer was seen.
SCAN_LATE_DRAIN_S = 0.010
#: Scans run one or two passes.
SCAN_PASSES_MAX = 2


@dataclass(slots=True)
class ScanPass:
    """One pass of :func:`scan` over the IDs still missing.

    Attributes:
        budget_s: the per-ID reply budget of the pass (IDs with a late reply get
            :data:`SCAN_LATE_BUDGET_S` instead).
        tried: the IDs asked, in order.
        found: the IDs that answered within their budget.
        late: the IDs whose answer came only after their budget.
        seconds: how long the pass took.
    """

    budget_s: float
    tried: list[int] = field(default_factory=list)
    found: list[int] = field(default_factory=list)
    late: list[int] = field(default_factory=list)
    seconds: float = 0.0


@dataclass(slots=True)
class ScanReport:
    """What :func:`scan` did (pass ``report=ScanReport()`` to have it filled in).

    Attributes:
        found: the IDs that answered, ascending.
        late: IDs that answered, but never within their budget (not in ``found``):
            they are there, and the host is slower than even :data:`SCAN_LATE_BUDGET_S`.
        passes: one :class:`ScanPass` per pass run.
        floor_s: the smallest budget the bus's baud rate and the LA turnaround allow.
        seconds: the whole scan.
    """

    found: list[int] = field(default_factory=list)
    late: list[int] = field(default_factory=list)
    passes: list[ScanPass] = field(default_factory=list)
    floor_s: float = 0.0
    seconds: float = 0.0

    def as_dict(self) -> dict[str, object]:
        """A JSON-ready summary (durations in milliseconds)."""
        return {
            "found": list(self.found),
            "late": list(self.late),
            "floor_ms": round(self.floor_s * 1e3, 3),
            "seconds": round(self.seconds, 4),
            "passes": [
                {
                    "budget_ms": round(p.budget_s * 1e3, 3),
                    "tried": len(p.tried),
                    "found": list(p.found),
                    "late": list(p.late),
                    "seconds": round(p.seconds, 4),
                }
                for p in self.passes
            ],
        }


class _ScanBudget:
    """The adaptive per-ID budgets of a scan on one bus."""

    def __init__(self, bus: Bus, fixed: float | None) -> None:
        query = bus.occupancy(la.Control(la.ID_MIN, la.ControlAction.QUERY_STATUS))
        self.bus = bus
        self.fixed = fixed
        # A scan's own host allowance in place of the bus's margin (SCAN_HOST_ALLOWANCE_S).
        self.floor = query.budget - query.margin + SCAN_HOST_ALLOWANCE_S
        self.ceiling = max(SCAN_BUDGET_MAX_S, 2 * self.floor)
        self.first = fixed if fixed is not None else self._follow_measured(self.floor)

    def _follow_measured(self, budget: float) -> float:
        """``budget``, or more if the LA replies measured on the bus so far need it."""
        measured = max(
            (
                d.latency.percentile(99)
                for key, d in self.bus.stats.devices.items()
                if key.startswith("la:") and d.latency.count
            ),
            default=0.0,
        )
        return min(self.ceiling, max(budget, SCAN_MEASURED_FACTOR * measured))

    def second(self) -> float:
        """Second-pass budget: longer than the first pass's, and following the replies
        the first pass measured."""
        if self.fixed is not None:
            return self.fixed
        extra = max(SCAN_SECOND_PASS_EXTRA_S, SCAN_SECOND_PASS_SHARE * self.first)
        return self._follow_measured(self.first + extra)

    def late_count(self, ident: int) -> int:
        device = self.bus.stats.devices.get(f"la:{ident}")
        return device.late_replies if device is not None else 0


async def scan(
    bus: Bus,
    ids: Iterable[int] = range(la.ID_MIN, la.ID_MAX + 1),
    *,
    timeout: float | None = None,
    passes: int = SCAN_PASSES_MAX,
    progress: Callable[[int, int, bool], None] | None = None,
    report: ScanReport | None = None,
) -> list[int]:
    """Find the LA actuators that answer a status query on ``bus``.

    Each ID is asked once (no bus retry).  The per-ID budget is adaptive unless
    ``timeout`` fixes it: the wire time of the query and its reply at the bus's baud
    rate, plus the LA's worst-case turnaround (``bus.config.turnaround[Family.LA]``,
    800 us by the manual), plus :data:`SCAN_HOST_ALLOWANCE_S` - or more, if the
    replies already measured on the bus (``bus.stats``) need it.  A second pass asks
    the IDs that did not answer again with a longer budget (an actuator that missed
    the first query is found too); an ID whose answer came after its budget is asked
    once more with :data:`SCAN_LATE_BUDGET_S`.  An absent ID costs its budget (at least
    the 1 ms bus spacing): 254 IDs take ~0.85 s at 921600 bit/s on an unloaded host,
    instead of ~2.8 s with a fixed 10 ms.

    Args:
        bus: an open bus carrying ``Family.LA``.
        ids: the IDs to try (default 1..254).
        timeout: a fixed per-ID budget in seconds for every pass (default: adaptive).
        passes: 1 (each ID asked once) or 2 (default: the missing IDs again).
        progress: called once per ID when its outcome is final, as
            ``progress(id, total, found)``: as soon as an ID answers, and for the IDs
            that did not, at the end of the scan (with one pass: at once).
        report: a :class:`ScanReport` to fill in (budgets, passes, late IDs, timing).

    Returns:
        The IDs that answered, in ascending order.

    Raises:
        LocalProtocolError: a bad ID, ``timeout`` or ``passes``, before anything is sent.
    """
    candidates = [check_int("id", i, la.ID_MIN, la.ID_MAX) for i in ids]
    if timeout is not None:
        check_timeout("timeout", timeout, REQUEST_TIMEOUT_MAX_S)
    check_int("passes", passes, 1, SCAN_PASSES_MAX)
    scanner = _Scanner(bus, _ScanBudget(bus, timeout), candidates, progress)
    out = report if report is not None else ScanReport()
    out.floor_s = scanner.budget.floor
    started = scanner.clock()
    remaining = candidates
    for n in range(passes):
        remaining = await scanner.run_pass(n, passes, remaining, out)
    if passes > 1:
        # Misses are final only now: an ID whose late answer came during the scan
        # was asked patiently at the end of the last pass.
        for i in remaining:
            scanner.tell(i, False)
    out.found = sorted(scanner.found)
    out.late = sorted(i for i in remaining if scanner.answered_late(i))
    out.seconds = scanner.clock() - started
    return out.found


class _Scanner:
    """The state of one :func:`scan` across its passes."""

    def __init__(
        self,
        bus: Bus,
        budget: _ScanBudget,
        candidates: list[int],
        progress: Callable[[int, int, bool], None] | None,
    ) -> None:
        self.bus = bus
        self.budget = budget
        self.total = len(candidates)
        self.progress = progress
        self.clock = bus.timer.now
        self.found: set[int] = set()
        self.patient: set[int] = set()  # asked with SCAN_LATE_BUDGET_S already
        self._late_at_start = {i: budget.late_count(i) for i in candidates}

    def tell(self, ident: int, hit: bool) -> None:
        if self.progress is not None:
            self.progress(ident, self.total, hit)

    def answered_late(self, ident: int) -> bool:
        """A reply from ``ident`` came after its budget at some point of this scan."""
        return self.budget.late_count(ident) > self._late_at_start[ident]

    async def run_pass(
        self, n: int, passes: int, remaining: list[int], out: ScanReport
    ) -> list[int]:
        """Ask ``remaining`` once (the late ones patiently); return the IDs still missing."""
        last = n == passes - 1
        budget = self.budget
        regular = budget.first if n == 0 else budget.second()
        late_budget = max(regular, SCAN_LATE_BUDGET_S)
        this = ScanPass(regular)
        out.passes.append(this)
        pass_start = self.clock()
        late_before = {i: budget.late_count(i) for i in remaining}

        def result(ident: int, hit: bool) -> None:
            this.tried.append(ident)
            if hit:
                self.found.add(ident)
                this.found.append(ident)
                self.tell(ident, True)
            elif passes == 1:
                self.tell(ident, False)  # one pass: every outcome is final at once

        patient = {i for i in remaining if n > 0 and self.answered_late(i)}
        self.patient |= patient
        asks = [(i, late_budget if i in patient else regular) for i in remaining]
        await _ask_all(self.bus, asks, result)
        remaining = [i for i in remaining if i not in self.found]
        if remaining and passes > 1:
            # Late answers to the last IDs asked are still on their way: wait for them.
            await self.bus.timer.sleep_until(self.clock() + max(SCAN_LATE_DRAIN_S, 2 * regular))
        if last and passes > 1:
            again = [i for i in remaining if self.answered_late(i) and i not in self.patient]
            self.patient.update(again)
            await _ask_all(self.bus, [(i, late_budget) for i in again], result)
            remaining = [i for i in remaining if i not in self.found]
        this.seconds = self.clock() - pass_start
        this.late = sorted(i for i in late_before if budget.late_count(i) > late_before[i])
        return remaining


async def _ask_all(
    bus: Bus, asks: list[tuple[int, float]], result: Callable[[int, bool], None]
) -> None:
    """Status-query each ``(id, budget)`` once; ``result(id, answered)`` in order.

    The whole list is queued at once: the bus sends each query from the timer callback
    that ends the previous one, without a round through this task (requests of a
    higher priority still go first).
    """
    queued = [
        (
            ident,
            bus.submit(
                la.Control(ident, la.ControlAction.QUERY_STATUS),
                timeout=per_id,
                retries=0,
                priority=Priority.BACKGROUND,
            ),
        )
        for ident, per_id in asks
    ]
    try:
        for ident, future in queued:
            try:
                await future
            except ReplyTimeoutError:
                result(ident, False)
            else:
                result(ident, True)
    finally:
        for _, future in queued:
            if not future.done():
                future.cancel()  # the scan was cancelled or failed: drop the rest
            elif not future.cancelled():
                future.exception()  # retrieved: no "never retrieved" warning
