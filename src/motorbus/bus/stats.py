"""Counters and latency histograms for buses and devices, readable from code."""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, field

__all__ = ["BusStats", "DeviceStats", "LatencyHistogram"]

# Histogram buckets: 10 per decade from 10 us to 10 s (upper edges, seconds).
_EDGES = tuple(10 ** (e / 10) * 1e-5 for e in range(0, 61))


@dataclass(slots=True)
class LatencyHistogram:
    """A fixed-size log-bucketed histogram of durations in seconds (about 26 % resolution).

    Percentiles are reported as the upper edge of the bucket holding them, so they
    never understate; ``min``/``max``/``mean`` are exact.
    """

    counts: list[int] = field(default_factory=lambda: [0] * (len(_EDGES) + 1))
    count: int = 0
    total: float = 0.0
    min: float = math.inf
    max: float = 0.0

    def record(self, seconds: float) -> None:
        """Add one duration."""
        self.counts[bisect.bisect_left(_EDGES, seconds)] += 1
        self.count += 1
        self.total += seconds
        self.min = min(self.min, seconds)
        self.max = max(self.max, seconds)

    @property
    def mean(self) -> float:
        """Mean duration in seconds (0 when empty)."""
        return self.total / self.count if self.count else 0.0

    def percentile(self, p: float) -> float:
        """The ``p``-th percentile (0..100) in seconds, bucket upper edge; 0 when empty."""
        if not self.count:
            return 0.0
        rank = max(1, math.ceil(self.count * p / 100))
        seen = 0
        for i, c in enumerate(self.counts):
            seen += c
            if seen >= rank:
                return min(_EDGES[i], self.max) if i < len(_EDGES) else self.max
        return self.max

    def summary(self) -> dict[str, float]:
        """Count, mean, p50, p99 and max, durations in microseconds."""
        return {
            "count": self.count,
            "mean_us": self.mean * 1e6,
            "p50_us": self.percentile(50) * 1e6,
            "p99_us": self.percentile(99) * 1e6,
            "max_us": self.max * 1e6,
        }


@dataclass(slots=True)
class DeviceStats:
    """What happened to the requests addressed to one device."""

    requests: int = 0
    replies: int = 0
    timeouts: int = 0
    retries: int = 0
    late_replies: int = 0
    latency: LatencyHistogram = field(default_factory=LatencyHistogram)


@dataclass(slots=True)
class BusStats:
    """What happened on one bus.  Every byte the bus discards is counted here."""

    requests: int = 0  # frames written, replies expected or not (retries included)
    replies: int = 0  # frames matched to the pending request
    no_reply_frames: int = 0  # frames sent that expect no reply (broadcasts, 0x03, 0x19)
    timeouts: int = 0  # deadlines that ran out (each attempt)
    retries: int = 0
    failed: int = 0  # requests that ended in an error for the caller
    late_replies: int = 0  # replies that came after their request's deadline
    unexpected_frames: int = 0  # valid frames that answered nothing we asked
    garbage_bytes: int = 0  # bytes the reassembler discarded
    #: The same bytes by the reassembler's reason ("garbage", "bad checksum",
    #: "unexpected reply shape", ...).
    discarded_by_reason: dict[str, int] = field(default_factory=dict)
    resyncs: int = 0  # runs of discarded bytes
    events: int = 0  # device events delivered (EE DD, done replies, fault changes)
    done_watches_dropped: int = 0  # awaited "done" replies given up (never came)
    not_sent: int = 0  # requests dropped unsent: they could not start by their start_by
    dropped_by_refresh: int = 0  # queued frames no longer wanted when their turn came
    early_replies: int = 0  # frames refused by the wire floor (wire_floor=True only)
    #: Timeouts decided more than HOST_STALL_S after their deadline: the host was held up
    #: (a garbage collection, another process), so the device may not be at fault.
    timeouts_in_host_stall: int = 0
    host_stall_max: float = 0.0  # the longest such delay, seconds
    disconnects: int = 0
    reconnects: int = 0
    bytes_out: int = 0
    bytes_in: int = 0
    latency: LatencyHistogram = field(default_factory=LatencyHistogram)
    #: Per device, keyed like ``"la:3"``, ``"project_stepper"``, ``"quad_stepper"``.
    devices: dict[str, DeviceStats] = field(default_factory=dict)

    def device(self, key: str) -> DeviceStats:
        """The stats of one device (created on first use)."""
        stats = self.devices.get(key)
        if stats is None:
            stats = self.devices[key] = DeviceStats()
        return stats

    def as_dict(self) -> dict[str, object]:
        """A JSON-ready snapshot."""
        out: dict[str, object] = {
            name: getattr(self, name)
            for name in (
                "requests",
                "replies",
                "no_reply_frames",
                "timeouts",
                "retries",
                "failed",
                "late_replies",
                "unexpected_frames",
                "garbage_bytes",
                "resyncs",
                "events",
                "done_watches_dropped",
                "not_sent",
                "dropped_by_refresh",
                "early_replies",
                "timeouts_in_host_stall",
                "host_stall_max",
                "disconnects",
                "reconnects",
                "bytes_out",
                "bytes_in",
            )
        }
        out["discarded_by_reason"] = dict(self.discarded_by_reason)
        out["latency"] = self.latency.summary()
        out["devices"] = {
            k: {
                "requests": d.requests,
                "replies": d.replies,
                "timeouts": d.timeouts,
                "retries": d.retries,
                "late_replies": d.late_replies,
                "latency": d.latency.summary(),
            }
            for k, d in self.devices.items()
        }
        return out
