"""The sampler's lookup of the samples since a time: the settle loop asks it every 10 ms,
so it finds them by bisection, and must find exactly what a scan would."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from motorbus.rig.analysis import Sample
from motorbus.rig.sampler import Sampler

# Few distinct times, so that runs of equal arrival times (a tie at t) come up often.
TIMES = st.lists(st.integers(0, 12).map(lambda k: k * 0.25), max_size=40)


@settings(max_examples=300)
@given(times=TIMES, t=st.integers(-1, 14).map(lambda k: k * 0.25 - 0.1 * (k % 2)))
def test_since_is_every_sample_that_arrived_at_or_after_t(times: list[float], t: float) -> None:
    sampler = Sampler(None, [7], max_current_ma=1000, max_force_g=1000)  # type: ignore[arg-type]
    sampler.samples[7] = [Sample(at, float(i)) for i, at in enumerate(sorted(times))]
    assert sampler.since(7, t) == [s for s in sampler.samples[7] if s.t >= t]


def test_since_an_actuator_without_samples_is_empty() -> None:
    sampler = Sampler(None, [1, 2], max_current_ma=1000, max_force_g=1000)  # type: ignore[arg-type]
    sampler.samples[1] = [Sample(1.0, 10.0)]
    assert sampler.since(2, 0.0) == [] and sampler.since(1, 1.5) == []
    assert sampler.since(1, 1.0) == [Sample(1.0, 10.0)]
