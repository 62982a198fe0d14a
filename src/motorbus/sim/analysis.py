"""Timing analysis of what a simulator received: tick jitter, drift and missed ticks.

Streams are judged where the frames land, not where they leave: these functions take
the arrival times the simulator logged and compare them with the ideal grid
``t0 + k * period``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = ["TickTiming", "percentile", "tick_timing"]


def percentile(values: Sequence[float], p: float) -> float:
    """The ``p``-th percentile (0..100) by nearest rank; 0.0 for no values."""
    if not values:
        return 0.0
    ordered = sorted(values)
    rank = max(1, math.ceil(len(ordered) * p / 100))
    return ordered[min(rank, len(ordered)) - 1]


@dataclass(frozen=True, slots=True)
class TickTiming:
    """How well a train of arrivals kept to its grid (durations in seconds).

    ``jitter`` is each arrival's offset from the grid, shifted so the earliest is 0
    (a constant latency is not jitter).  ``drift`` is the slope of the offsets over the
    run: seconds gained or lost per second.  ``missed`` counts grid slots with no
    arrival.
    """

    count: int
    missed: int
    jitter_p50: float
    jitter_p99: float
    jitter_max: float
    drift: float
    offsets: tuple[float, ...]

    def as_dict(self) -> dict[str, float]:
        """JSON-ready figures in microseconds (drift in parts per million)."""
        return {
            "frames": self.count,
            "missed_ticks": self.missed,
            "tick_jitter_p50_us": self.jitter_p50 * 1e6,
            "tick_jitter_p99_us": self.jitter_p99 * 1e6,
            "tick_jitter_max_us": self.jitter_max * 1e6,
            "drift_ppm": self.drift * 1e6,
        }


def tick_timing(times: Sequence[float], period: float, *, by_index: bool = False) -> TickTiming:
    """Compare arrival ``times`` (seconds, ascending) with the grid of ``period``.

    By default each arrival is matched to its nearest grid slot (so gaps show up as
    missed ticks).  With ``by_index`` the k-th arrival is held to slot k: a loop whose
    period stretches (a naive ``sleep(period)`` loop) then shows its walk away from
    the grid as growing offsets, which is what drift does to a trajectory.
    """
    if len(times) < 2:
        return TickTiming(len(times), 0, 0.0, 0.0, 0.0, 0.0, ())
    t0 = times[0]
    slots = list(range(len(times))) if by_index else [round((t - t0) / period) for t in times]
    raw = [t - t0 - k * period for t, k in zip(times, slots, strict=True)]
    base = min(raw)
    offsets = tuple(r - base for r in raw)
    # Slots spanned minus frames that arrived: robust to one jittery arrival being
    # rounded into its neighbour's slot (which would show as a gap and a double).
    missed = max(0, slots[-1] - slots[0] + 1 - len(slots))
    # Least-squares slope of the offsets against time: the stream's drift.
    n = len(times)
    mean_t = sum(times) / n
    mean_o = sum(raw) / n
    var = sum((t - mean_t) ** 2 for t in times)
    drift = sum((t - mean_t) * (o - mean_o) for t, o in zip(times, raw, strict=True)) / var
    return TickTiming(
        count=n,
        missed=missed,
        jitter_p50=percentile(offsets, 50),
        jitter_p99=percentile(offsets, 99),
        jitter_max=max(offsets),
        drift=drift,
        offsets=offsets,
    )
