"""Counters and latency histograms for buses and devices, readable from code."""

from __future__ import annotations

import math
from array import array
from bisect import bisect_left
from dataclasses import dataclass, field
from itertools import accumulate

from motorbus.protocol.reassembler import ReassemblerStats

__all__ = ["BusStats", "DeviceStats", "LatencyHistogram"]

# Histogram buckets: each 1 % wider than the one before, from 10 ns to 100 s.  Bucket 0
# holds everything up to 10 ns, the last one everything from 100 s on; bucket ``i`` in
# between holds [_LOW * _RATIO**(i - 1), _LOW * _RATIO**i).
_LOW = 1e-8
_HIGH = 100.0
_RATIO = 1.01
_PER_LN = 1 / math.log(_RATIO)
_BUCKETS = math.ceil(math.log(_HIGH / _LOW) * _PER_LN) + 2  # 2317
_INV_LOW = 1 / _LOW
_log = math.log


def _bucket_of(seconds: float) -> int:
    """The bucket ``record`` puts ``seconds`` in (it and ``record_twice`` inline this)."""
    if seconds > _LOW:
        i = int(_log(seconds * _INV_LOW) * _PER_LN) + 1
        return i if i < _BUCKETS else _BUCKETS - 1
    return 0


def record_twice(first: LatencyHistogram, second: LatencyHistogram, seconds: float) -> None:
    """``first.record(seconds)`` and ``second.record(seconds)`` with one ``log`` and one
    call: a bus's latency and its device's, for every reply."""
    if seconds > _LOW:
        i = int(_log(seconds * _INV_LOW) * _PER_LN) + 1
        if i >= _BUCKETS:
            i = _BUCKETS - 1
    else:
        i = 0
    for hist in (first, second):
        hist.count += 1
        hist.total += seconds
        if seconds < hist.min:
            hist.min = seconds
        if seconds > hist.max:
            hist.max = seconds
        hist.counts[i] += 1


def _new_counts() -> array[int]:
    return array("Q", bytes(8 * _BUCKETS))


@dataclass(slots=True)
class LatencyHistogram:
    """Durations in seconds: exact count/total/min/max/mean, percentiles within 0.5 %.

    Samples go into fixed log buckets each 1 % wide from 10 ns to 100 s (2317 counters,
    18.5 KiB, allocated once: memory does not grow with the number of samples).  A
    percentile is the nearest-rank sample (the ``ceil(count * p / 100)``-th smallest,
    numpy's ``method="inverted_cdf"``) as the geometric middle of its bucket, clamped to
    the exact ``min``/``max``: at most 0.5 % from the exact value between 10 ns and 100 s,
    within 10 ns below that (as ``min``), and never above ``max``.  ``record`` is one
    ``log`` and a few comparisons, so it stays cheap on the reply path.
    """

    counts: array[int] = field(default_factory=_new_counts)  #: samples per bucket (2317)
    count: int = 0  #: samples recorded
    total: float = 0.0  #: sum of the samples, seconds
    min: float = math.inf  #: smallest sample, seconds (``inf`` while empty)
    max: float = 0.0  #: largest sample, seconds

    def record(self, seconds: float) -> None:
        """Add one duration (anything up to 10 ns, negative too, counts in the lowest bucket)."""
        self.count += 1
        self.total += seconds
        if seconds < self.min:
            self.min = seconds
        if seconds > self.max:
            self.max = seconds
        if seconds > _LOW:
            i = int(_log(seconds * _INV_LOW) * _PER_LN) + 1
            self.counts[i if i < _BUCKETS else _BUCKETS - 1] += 1
        else:
            self.counts[0] += 1

    @property
    def mean(self) -> float:
        """Mean duration in seconds (0 when empty)."""
        return self.total / self.count if self.count else 0.0

    def percentile(self, p: float) -> float:
        """The ``p``-th percentile (0..100) in seconds, nearest rank; 0 when empty."""
        if not 0 <= p <= 100:
            raise ValueError(f"p={p!r} is out of range: allowed 0..100")
        if not self.count:
            return 0.0
        rank = max(1, math.ceil(self.count * p / 100))
        if rank >= self.count:
            return self.max
        if rank == 1:
            return self.min
        # Only the buckets between min's and max's hold samples: a short scan, in C.
        lo, hi = _bucket_of(self.min), _bucket_of(self.max)
        cumulative = list(accumulate(self.counts[lo : hi + 1]))
        at = bisect_left(cumulative, rank)
        if at >= len(cumulative):  # cannot happen while record() and _bucket_of agree
            return self.max
        bucket = lo + at
        if bucket == 0:
            return self.min  # within 10 ns of the sample
        if bucket == _BUCKETS - 1:
            return self.max
        return min(max(_LOW * math.exp((bucket - 0.5) / _PER_LN), self.min), self.max)

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
    """What happened to the requests addressed to one device (counts, as ``BusStats``)."""

    requests: int = 0  #: frames written to the device (retries included)
    replies: int = 0  #: its replies matched to the pending request
    timeouts: int = 0  #: its deadlines that ran out (each attempt)
    retries: int = 0  #: requests to it written again after a timeout
    late_replies: int = 0  #: its replies after their deadline was decided (as ``BusStats``)
    #: Write of each request to its reply, seconds.
    latency: LatencyHistogram = field(default_factory=LatencyHistogram)


@dataclass(slots=True)
class BusStats:
    """What happened on one bus.  Every byte the bus discards is counted here."""

    requests: int = 0  #: frames written, replies expected or not (retries included)
    replies: int = 0  #: frames matched to the pending request
    no_reply_frames: int = 0  #: frames sent that expect no reply (broadcasts, 0x03, 0x19)
    timeouts: int = 0  #: deadlines that ran out (each attempt)
    retries: int = 0  #: requests written again after a timeout
    failed: int = 0  #: requests that ended in an error for the caller
    #: Replies that came after their request timed out (its deadline decided), within
    #: ``LATE_WINDOW_S`` (2 s) of it: recognised, counted, not delivered.
    late_replies: int = 0
    #: Replies taken although the bus read them after their deadline: they were already
    #: in when it looked, but it looked late (the host stalled or was busy).
    replies_past_deadline: int = 0
    unexpected_frames: int = 0  #: valid frames that answered nothing we asked
    #: The reassembler's own counters (frames cut, ``EE DD`` markers, discarded bytes by
    #: reason, resyncs), kept across reconnects: the one place discards are counted.
    reassembler: ReassemblerStats = field(default_factory=ReassemblerStats)
    events: int = 0  #: device events delivered (EE DD, done replies, fault changes)
    done_watches_dropped: int = 0  #: awaited "done" replies given up (never came)
    not_sent: int = 0  #: requests dropped unsent: they could not start by their start_by
    dropped_by_refresh: int = 0  #: queued frames no longer wanted when their turn came
    early_replies: int = 0  #: frames refused by the wire floor (wire_floor=True only)
    #: Timeouts decided more than HOST_STALL_S (1 ms) after their deadline: the host was
    #: held up (a garbage collection, another process), so the device may not be at fault.
    timeouts_in_host_stall: int = 0
    host_stall_max: float = 0.0  #: the longest such delay, seconds
    #: How long after its deadline the latest late reply came, seconds.
    late_reply_max: float = 0.0
    disconnects: int = 0  #: times the port was lost
    reconnects: int = 0  #: times it was opened again after a loss
    bytes_out: int = 0  #: bytes written
    bytes_in: int = 0  #: bytes read (discarded ones included)
    #: Write of each request to its matched reply, seconds.
    latency: LatencyHistogram = field(default_factory=LatencyHistogram)
    #: Per device, keyed like ``"la:3"``, ``"project_stepper"``, ``"quad_stepper"``.
    devices: dict[str, DeviceStats] = field(default_factory=dict)

    @property
    def garbage_bytes(self) -> int:
        """Bytes the reassembler discarded (``reassembler.discarded_bytes``)."""
        return self.reassembler.discarded_bytes

    @property
    def discarded_by_reason(self) -> dict[str, int]:
        """The same bytes by the reassembler's reason ("garbage", "bad checksum",
        "unexpected reply shape", ...): ``reassembler.by_reason``."""
        return self.reassembler.by_reason

    @property
    def resyncs(self) -> int:
        """Runs of discarded bytes (``reassembler.resyncs``)."""
        return self.reassembler.resyncs

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
                "replies_past_deadline",
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
                "late_reply_max",
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
