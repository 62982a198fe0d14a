"""``motorbus doctor``'s cycle budget: the occupancy model's theory beside a measurement.

Pure: the theory comes from :mod:`motorbus.bus.occupancy` (the frames a broadcast tick
and a status read hold the bus), the measurement from :mod:`motorbus.doctor.probe`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from motorbus.bus.occupancy import BusTiming
from motorbus.doctor.checks import Finding, Level, LineFacts, poll_occupancy
from motorbus.protocol import la
from motorbus.streaming.budget import TICK_BUDGET_SHARE, broadcast_tick, feedback_slot

__all__ = [
    "BUDGET_GAP_SHARE",
    "BudgetTheory",
    "MeasuredBudget",
    "StreamMeasured",
    "budget_theory",
    "check_budget",
]

#: Theory and measurement of the cycle budget further apart than this share: yellow.
BUDGET_GAP_SHARE = 0.20


@dataclass(frozen=True, slots=True)
class BudgetTheory:
    """What the occupancy model says ``actuators`` LA actuators need at ``period_s``."""

    actuators: int
    period_s: float
    tick_s: float  # the broadcast follow frames of one tick
    broadcast_frames: int
    poll_s: float  # one status query and its reply
    polls_between_ticks: int
    broadcast_capacity: int  # actuators one tick's broadcasts can carry at this period
    feedback_capacity: int  # actuators with a 0x20 follow + status reply per tick
    shortest_period_s: float  # the tick alone
    shortest_period_polled_s: float  # the tick and one status read of each actuator

    def as_dict(self) -> dict[str, Any]:
        return {
            "actuators": self.actuators,
            "period_ms": self.period_s * 1e3,
            "tick_ms": self.tick_s * 1e3,
            "broadcast_frames": self.broadcast_frames,
            "poll_ms": self.poll_s * 1e3,
            "polls_between_ticks": self.polls_between_ticks,
            "broadcast_capacity": self.broadcast_capacity,
            "feedback_capacity": self.feedback_capacity,
            "shortest_period_ms": self.shortest_period_s * 1e3,
            "shortest_period_polled_ms": self.shortest_period_polled_s * 1e3,
        }


def budget_theory(timing: BusTiming, actuators: int, period_s: float) -> BudgetTheory:
    """The cycle budget from the bus core's occupancy model (no measurement)."""
    tick, frames = broadcast_tick(timing, actuators)
    poll = poll_occupancy(timing).answered
    follow = feedback_slot(timing)
    full_frame, _ = broadcast_tick(timing, la.MAX_BROADCAST_ENTRIES)
    # What Streamer.follow admits: the ticks may fill TICK_BUDGET_SHARE of the period.
    usable = period_s * TICK_BUDGET_SHARE
    capacity = min(la.ID_MAX, math.floor(usable / full_frame + 1e-9) * la.MAX_BROADCAST_ENTRIES)
    return BudgetTheory(
        actuators=actuators,
        period_s=period_s,
        tick_s=tick,
        broadcast_frames=frames,
        poll_s=poll,
        polls_between_ticks=max(0, math.floor((period_s - tick) / poll + 1e-9)),
        broadcast_capacity=capacity,
        feedback_capacity=math.floor(usable / follow + 1e-9),
        shortest_period_s=tick,
        shortest_period_polled_s=tick + actuators * poll,
    )


@dataclass(frozen=True, slots=True)
class MeasuredBudget:
    """Status reads in the gaps a stream's ticks would leave, for a few seconds."""

    ticks: int
    polls: int  # answered
    lost: int
    polls_per_tick: float
    started: float  # monotonic clock, the window measured
    ended: float


@dataclass(frozen=True, slots=True)
class StreamMeasured:
    """A real broadcast stream (``--stream``): each actuator sent the position it reported."""

    ticks_planned: int
    ticks: int
    late: int
    skipped: int
    slipped: int
    polls: int
    polls_skipped: int
    jitter_p99_s: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "ticks_planned": self.ticks_planned,
            "ticks": self.ticks,
            "late": self.late,
            "skipped": self.skipped,
            "slipped": self.slipped,
            "polls": self.polls,
            "polls_skipped": self.polls_skipped,
            "jitter_p99_us": self.jitter_p99_s * 1e6,
        }


def check_budget(
    theory: BudgetTheory,
    measured: MeasuredBudget | None,
    *,
    adapter_ms: int | None = None,
    slow_device: bool = False,
    line: LineFacts | None = None,
    stream: StreamMeasured | None = None,
) -> Finding:
    """Theory and measurement side by side; measurement short by over 20 %: yellow.

    The reason named is the first that applies: the adapter holds replies (latency timer
    over 1 ms), a device slower than its turnaround (a red turnaround check), replies
    lost on the line, else the host (late replies, a loop that wakes late).
    """
    t = theory
    data: dict[str, Any] = {"theory": t.as_dict()}
    text = (
        f"{t.actuators} actuator{'s' if t.actuators != 1 else ''} at {t.period_s * 1e3:g} ms: "
        f"tick {t.tick_s * 1e3:.2f} ms ({t.broadcast_frames} broadcast), "
        f"{t.polls_between_ticks} status reads fit between ticks; up to "
        f"{t.broadcast_capacity} actuators by broadcast or {t.feedback_capacity} with feedback "
        f"per tick; the bus alone could tick every {t.shortest_period_s * 1e3:.2f} ms "
        f"({t.shortest_period_polled_s * 1e3:.2f} ms reading each status every tick)"
    )
    if measured is None:
        return Finding("budget", Level.GREEN, text + "; not measured", "", data)
    data["measured"] = {
        "ticks": measured.ticks,
        "polls": measured.polls,
        "lost": measured.lost,
        "polls_per_tick": measured.polls_per_tick,
        "window_s": measured.ended - measured.started,
        "started": measured.started,  # monotonic clock: to compare with a bus log
        "ended": measured.ended,
    }
    text += f"; measured {measured.polls_per_tick:.1f} reads a tick over {measured.ticks} ticks"
    if stream is not None:
        data["stream"] = stream.as_dict()
        text += (
            f"; a real stream sent {stream.ticks}/{stream.ticks_planned} ticks ({stream.late} "
            f"late, {stream.skipped} skipped, jitter p99 {stream.jitter_p99_s * 1e6:.0f} us)"
        )
        short = stream.ticks_planned - stream.ticks
        if (
            stream.skipped
            or short > BUDGET_GAP_SHARE * stream.ticks_planned
            or (stream.late > BUDGET_GAP_SHARE * stream.ticks_planned)
        ):
            return Finding(
                "budget",
                Level.YELLOW,
                f"{text}: the stream could not keep its ticks",
                "run with --realtime on a quieter host, or a longer --period",
                data,
            )
    expected = t.polls_between_ticks
    if expected and measured.polls_per_tick < expected * (1 - BUDGET_GAP_SHARE):
        lost = max(0, line.timeouts - line.late_replies) if line is not None else 0
        if adapter_ms is not None and adapter_ms > 1:
            why, fix = "the adapter holds replies", "see the latency check"
        elif slow_device:
            why, fix = "device turnaround", "see the turnaround checks"
        elif lost:
            why, fix = "replies lost on the line", "see the line check"
        else:
            late = f", {measured.lost} replies late" if measured.lost else ""
            why = f"host jitter{late}"
            fix = (
                "run with --realtime on a quieter host, or raise host_margin_ms (a timeout "
                "holds its device for the 20 ms late guard)"
            )
        gap = 1 - measured.polls_per_tick / expected
        data["gap"] = gap
        return Finding(
            "budget", Level.YELLOW, f"{text}: {gap * 100:.0f} % short ({why})", fix, data
        )
    return Finding("budget", Level.GREEN, text, "", data)
