"""LatencyHistogram: percentiles within 1 % of the exact ones, exact count/min/max/mean."""

from __future__ import annotations

import asyncio
import math
import random
import statistics

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motorbus.bus.bus import Bus, BusState
from motorbus.bus.stats import BusStats, LatencyHistogram, record_twice
from motorbus.protocol.base import Family
from motorbus.transport.memory import memory_pair

PERCENTILES = (0, 1, 10, 25, 50, 75, 90, 99, 99.9, 100)


def filled(samples: list[float]) -> LatencyHistogram:
    h = LatencyHistogram()
    for s in samples:
        h.record(s)
    return h


def nearest_rank(samples: list[float], p: float) -> float:
    return float(np.percentile(samples, p, method="inverted_cdf"))


@pytest.mark.parametrize(
    "name, draw",
    [
        ("lognormal around 400 us", lambda r: r.lognormvariate(math.log(400e-6), 0.6)),
        ("uniform 50 us .. 5 ms", lambda r: r.uniform(50e-6, 5e-3)),
        ("exponential, mean 1 ms", lambda r: r.expovariate(1e3)),
        (
            "bimodal 250 us / 20 ms",
            lambda r: r.gauss(250e-6, 20e-6) if r.random() < 0.9 else r.gauss(20e-3, 2e-3),
        ),
        ("wide: 1 us .. 10 s", lambda r: 10 ** r.uniform(-6, 1)),
    ],
)
def test_percentiles_within_1_percent_of_numpy(name: str, draw: object) -> None:
    rng = random.Random(name)
    samples = [abs(draw(rng)) for _ in range(20_000)]  # type: ignore[operator]
    h = filled(samples)
    for p in PERCENTILES:
        exact = nearest_rank(samples, p)
        assert h.percentile(p) == pytest.approx(exact, rel=0.01), (name, p)
        # and against numpy's default (linear) definition, which differs from nearest rank
        # only between two neighbouring samples
        assert h.percentile(p) == pytest.approx(float(np.percentile(samples, p)), rel=0.01)


def test_median_against_statistics() -> None:
    rng = random.Random(7)
    samples = [rng.lognormvariate(-8, 1) for _ in range(10_001)]  # odd: the median is a sample
    assert filled(samples).percentile(50) == pytest.approx(statistics.median(samples), rel=0.01)


def test_the_old_bucket_edges_are_gone() -> None:
    """The 10-per-decade histogram turned any p50 in 631..794 us into 794.33 us."""
    samples = [650e-6] * 60 + [700e-6] * 40
    h = filled(samples)
    assert h.percentile(50) == pytest.approx(650e-6, rel=0.01)
    assert h.percentile(99) == pytest.approx(700e-6, rel=0.01)
    assert h.summary()["p50_us"] == pytest.approx(650, rel=0.01)


@settings(max_examples=200)
@given(
    st.lists(st.floats(min_value=1e-7, max_value=50.0), min_size=1, max_size=300),
    st.floats(min_value=0, max_value=100),
)
def test_any_samples_any_p(samples: list[float], p: float) -> None:
    h = filled(samples)
    got = h.percentile(p)
    assert got == pytest.approx(nearest_rank(samples, p), rel=0.01)
    assert h.min <= got <= h.max


def test_exact_count_total_min_max_mean() -> None:
    rng = random.Random(3)
    samples = [rng.uniform(1e-4, 2e-3) for _ in range(5000)]
    h = filled(samples)
    assert h.count == 5000
    assert h.total == pytest.approx(math.fsum(samples), rel=1e-9)
    assert h.min == min(samples)
    assert h.max == max(samples)
    assert h.mean == pytest.approx(statistics.fmean(samples), rel=1e-9)
    assert h.percentile(0) == min(samples)
    assert h.percentile(100) == max(samples)


def test_zeros_and_out_of_range_durations() -> None:
    """Stream lateness is often exactly 0; a timeout may be longer than 100 s."""
    h = filled([0.0] * 90 + [1e-3] * 10)
    assert h.percentile(50) == 0.0
    assert h.percentile(95) == pytest.approx(1e-3, rel=0.01)
    big = filled([150.0, 200.0, 300.0])
    assert big.percentile(50) == pytest.approx(200.0, rel=0.5)  # past 100 s: clamped, coarse
    assert big.percentile(100) == 300.0
    assert 150.0 <= big.percentile(50) <= 300.0


def test_empty_histogram() -> None:
    h = LatencyHistogram()
    assert h.percentile(50) == 0.0
    assert h.mean == 0.0
    assert h.summary() == {"count": 0, "mean_us": 0.0, "p50_us": 0.0, "p99_us": 0.0, "max_us": 0.0}


@pytest.mark.parametrize("p", [-1, 100.5, math.nan])
def test_bad_percentile_is_refused(p: float) -> None:
    h = filled([1e-3])
    with pytest.raises(ValueError, match=r"p=.* is out of range: allowed 0\.\.100"):
        h.percentile(p)


def test_memory_does_not_grow_with_samples() -> None:
    h = LatencyHistogram()
    size = h.counts.buffer_info()[1]
    for i in range(10_000):
        h.record(i * 1e-6)
    assert h.counts.buffer_info()[1] == size
    assert sum(h.counts) == h.count == 10_000


def test_bus_stats_snapshot_uses_the_histogram() -> None:
    stats = BusStats()
    for us in (300, 310, 320, 330, 2000):
        stats.latency.record(us * 1e-6)
        stats.device("la:1").latency.record(us * 1e-6)
    snap = stats.as_dict()
    assert snap["latency"]["p50_us"] == pytest.approx(320, rel=0.01)  # type: ignore[index]
    assert snap["devices"]["la:1"]["latency"]["max_us"] == pytest.approx(2000)  # type: ignore[index]


def test_percentile_scan_and_record_agree_on_buckets() -> None:
    """``percentile`` scans only the buckets between min's and max's, as ``record`` fills."""
    from motorbus.bus import stats

    rng = random.Random(11)
    for _ in range(2000):
        x = 10 ** rng.uniform(-9, 3)
        h = LatencyHistogram()
        h.record(x)
        assert h.counts[stats._bucket_of(x)] == 1
    edges = [0.0, 1e-8, 1e-8 * 1.01, 100.0, 1e9]
    for x in edges:
        h = LatencyHistogram()
        h.record(x)
        assert h.counts[stats._bucket_of(x)] == 1, x


def test_record_twice_is_a_record_in_each() -> None:
    """A reply's latency goes into the bus's and the device's histograms at once
    (``record_twice``): exactly what a ``record`` in each does, edges included."""
    rng = random.Random(12)
    samples = [10 ** rng.uniform(-9, 3) for _ in range(500)] + [-1.0, 0.0, 1e-8, 100.0, 1e9]
    single, first, second = LatencyHistogram(), LatencyHistogram(), LatencyHistogram()
    for x in samples:
        single.record(x)
        record_twice(first, second, x)
    for hist in (first, second):
        assert (hist.count, hist.total, hist.min, hist.max) == (
            single.count,
            single.total,
            single.min,
            single.max,
        )
        assert hist.counts == single.counts


async def test_discards_are_counted_once_by_the_reassembler_and_kept_across_reconnects() -> None:
    """``garbage_bytes``, ``discarded_by_reason`` and ``resyncs`` read the reassembler's
    counters (one set, not a second tally in the bus), and a reconnect, which starts a
    new reassembler, keeps adding to them."""
    host, peer = memory_pair()
    async with Bus(host, families={Family.LA}) as bus:
        peer.send(b"\x01\x02\x03")
        await asyncio.sleep(0.01)
        assert bus.stats.reassembler.discarded_bytes == bus.stats.garbage_bytes == 3
        peer.unplug()
        await asyncio.wait_for(bus.wait_state(BusState.LOST), 2.0)
        peer.plug()
        await asyncio.wait_for(bus.wait_state(BusState.OPEN), 5.0)
        peer.send(b"\x04\x05")
        await asyncio.sleep(0.01)
        stats = bus.stats
        assert stats.garbage_bytes == stats.reassembler.discarded_bytes == 5
        assert stats.discarded_by_reason == {"garbage": 5} == stats.as_dict()["discarded_by_reason"]
        assert stats.resyncs == stats.reassembler.resyncs == 2
        assert stats.as_dict()["garbage_bytes"] == 5
