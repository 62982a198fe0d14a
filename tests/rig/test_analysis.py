"""The rig's figures against motions whose figures are known in closed form."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorbus.rig.analysis import (
    LEAD_MAX_DEG,
    Sample,
    distribution,
    frequency_point,
    repeat_figures,
    sample_rate,
    step_figures,
    track_figures,
)


def trapezoid(start: float, end: float, vmax: float, accel: float, dead: float, t: float) -> float:
    """Position at ``t`` s after the command of a trapezoidal move starting after ``dead``."""
    d = abs(end - start)
    sign = 1.0 if end > start else -1.0
    tau = t - dead
    if tau <= 0:
        return start
    ta = vmax / accel
    if accel * ta * ta > d:  # triangle: never reaches vmax
        ta = math.sqrt(d / accel)
        vmax = accel * ta
    da = 0.5 * accel * ta * ta
    tc = (d - 2 * da) / vmax
    if tau < ta:
        x = 0.5 * accel * tau * tau
    elif tau < ta + tc:
        x = da + vmax * (tau - ta)
    elif tau < 2 * ta + tc:
        r = 2 * ta + tc - tau
        x = d - 0.5 * accel * r * r
    else:
        x = d
    return start + sign * x


def sampled(fn, t0: float, t1: float, dt: float) -> list[Sample]:
    n = int((t1 - t0) / dt)
    return [Sample(t0 + i * dt, fn(t0 + i * dt)) for i in range(n + 1)]


@pytest.mark.parametrize(("start", "end"), [(500.0, 1500.0), (1500.0, 500.0)])
def test_step_figures_of_a_trapezoid(start: float, end: float) -> None:
    vmax, accel, dead = 2000.0, 20000.0, 0.012
    cmd = 10.0
    samples = sampled(
        lambda t: trapezoid(start, end, vmax, accel, dead, t - cmd), cmd, cmd + 1.0, 0.001
    )
    fig = step_figures(samples, cmd, start, end, noise_band=2.0)
    # Dead time: motion starts at 12 ms, and 2 units take sqrt(2*2/accel) = 14 ms more.
    assert fig.dead_time_ms == pytest.approx(12.0 + math.sqrt(4 / accel) * 1e3, abs=1.0)
    # 10 % -> 90 % of 1000 units at cruise (the ramps are 100 units each): 800 / 2000 s.
    assert fig.rise_time_ms == pytest.approx(400.0, rel=0.02)
    assert fig.peak_speed_units_per_s == pytest.approx(vmax, rel=0.02)
    assert fig.mean_speed_units_per_s == pytest.approx(vmax, rel=0.02)
    assert fig.overshoot_pct == 0.0
    # Settled (within 10 units) shortly before the end of the move: 12 + 100 + 450 ... ms
    end_of_move = dead + 2 * (vmax / accel) + (1000 - 200) / vmax
    r = math.sqrt(2 * 10 / accel)
    assert fig.settling_time_ms == pytest.approx((end_of_move - r) * 1e3, abs=1.5)
    assert fig.steady_state_error == 0.0


def test_step_overshoot_and_steady_state_error() -> None:
    cmd = 0.0

    def pos(t: float) -> float:  # overshoots to 1100 then settles at 1005
        if t < 0.1:
            return 500 + 6000 * t
        if t < 0.2:
            return 1100.0
        return 1005.0

    fig = step_figures(sampled(pos, cmd, 0.5, 0.001), cmd, 500.0, 1000.0)
    assert fig.overshoot_pct == pytest.approx(20.0)
    assert fig.steady_state_error == pytest.approx(5.0)
    # 1005 is inside the 1 % band (5 units): settled from 0.2 s
    assert fig.settling_time_ms == pytest.approx(200.0, abs=1.0)


def test_a_step_that_never_settles_says_nan() -> None:
    samples = sampled(lambda t: 500 + 100 * t, 0.0, 1.0, 0.01)
    fig = step_figures(samples, 0.0, 500.0, 1000.0)
    assert math.isnan(fig.settling_time_ms)
    assert math.isnan(fig.rise_time_ms)


def test_step_refuses_an_empty_step() -> None:
    with pytest.raises(ValueError, match="start and end are both 700"):
        step_figures([Sample(0.0, 700.0)], 0.0, 700.0, 700.0)
    with pytest.raises(ValueError, match="no sample after"):
        step_figures([Sample(0.0, 700.0)], 1.0, 700.0, 900.0)


@pytest.mark.parametrize("delay", [0.010, 0.037, 0.080])
def test_track_lag_of_a_pure_delay(delay: float) -> None:
    f = 1.0
    dt = 0.01  # 100 Hz targets

    def target(t: float) -> float:
        return 1000 + 300 * math.sin(2 * math.pi * f * t)

    tt = [i * dt for i in range(400)]
    targets = [target(t) for t in tt]
    samples = sampled(lambda t: target(t - delay), 0.0, 4.0, 0.002)
    fig = track_figures(tt, targets, samples, frequency_hz=f)
    # The held target is on average half a tick behind the sine itself.
    assert fig.lag_ms == pytest.approx((delay - dt / 2) * 1e3, abs=1.0)
    assert fig.response is not None
    assert fig.response.amplitude_ratio == pytest.approx(1.0, rel=0.01)
    assert fig.response.phase_deg == pytest.approx(-360 * f * delay, abs=1.0)


@pytest.mark.parametrize("lead", [0.0, 0.003, 0.008])
def test_a_small_lead_is_a_lead_not_a_lag_of_almost_a_cycle(lead: float) -> None:
    # Timing noise (a served stream's targets placed on the client's clock) can put the
    # output a few degrees ahead of its target: +2.7 deg, not -357.3.
    f, dt = 0.5, 0.002
    tt = [i * dt for i in range(2000)]
    targets = [1000 + 300 * math.sin(2 * math.pi * f * t) for t in tt]
    samples = sampled(lambda t: 1000 + 300 * math.sin(2 * math.pi * f * (t + lead)), 0.0, 4.0, dt)
    point = frequency_point(tt, targets, samples, f)
    assert point.phase_deg == pytest.approx(360 * f * lead, abs=0.5)
    assert -360 + LEAD_MAX_DEG < point.phase_deg <= LEAD_MAX_DEG


def test_track_bode_point_of_a_first_order_lag() -> None:
    # y' = (u - y) / tau; steady state: ratio 1/sqrt(1+(w tau)^2), phase -atan(w tau).
    tau, f = 0.05, 2.0
    w = 2 * math.pi * f
    ratio = 1 / math.sqrt(1 + (w * tau) ** 2)
    phase = -math.atan(w * tau)

    def out(t: float) -> float:
        return 1000 + 200 * ratio * math.sin(w * t + phase)

    tt = [i * 0.001 for i in range(3000)]
    targets = [1000 + 200 * math.sin(w * t) for t in tt]
    samples = sampled(out, 0.0, 3.0, 0.002)
    fig = track_figures(tt, targets, samples, frequency_hz=f)
    assert fig.response is not None
    assert fig.response.amplitude_ratio == pytest.approx(ratio, rel=0.02)
    assert fig.response.phase_deg == pytest.approx(math.degrees(phase), abs=1.0)
    assert fig.lag_ms == pytest.approx(-phase / w * 1e3, rel=0.05)


def test_repeat_figures_find_the_backlash() -> None:
    fig = repeat_figures(1000.0, [997.0, 998.0, 996.0], [1003.0, 1004.0, 1002.0])
    assert fig.backlash == pytest.approx(6.0)
    assert fig.spread == 8.0
    assert fig.from_below.max - fig.from_below.min == 2.0
    with pytest.raises(ValueError, match="each side"):
        repeat_figures(1000.0, [], [1.0])


@given(st.lists(st.floats(-1e6, 1e6), min_size=1, max_size=200))
def test_distribution_is_ordered(values: list[float]) -> None:
    d = distribution(values)
    assert d.min <= d.p50 <= d.p99 <= d.max
    assert d.count == len(values)


def test_sample_rate_and_jitter() -> None:
    samples = [Sample(i * 0.002 + (0.0005 if i % 2 else 0.0), 0.0) for i in range(101)]
    rate, gaps = sample_rate(samples)
    assert rate == pytest.approx(500.0, rel=0.01)
    assert gaps.max == pytest.approx(2.5)
    assert gaps.min == pytest.approx(1.5)


def test_peak_speed_ignores_replies_read_late() -> None:
    # Every 40th reply is read 10 ms late (a busy host): its stamp lies, its position not.
    def move(t: float) -> float:
        return trapezoid(500.0, 1500.0, 1000.0, 10000.0, 0.0, t)

    samples = [
        Sample(i * 0.001 + (0.010 if i % 40 == 0 else 0.0), move(i * 0.001)) for i in range(1500)
    ]
    samples.sort(key=lambda s: s.t)
    fig = step_figures(samples, 0.0, 500.0, 1500.0)
    assert fig.peak_speed_units_per_s == pytest.approx(1000.0, rel=0.02)


def test_peak_speed_where_a_busy_host_sampled_sparsely() -> None:
    # For 150 ms mid-move a starved host polled every 8 ms and read six replies in a
    # row 12 ms late (a loaded run of the suite read 1,208 units/s off an actuator at
    # 1,000 so); elsewhere it polled every millisecond.  The window then widens to 30
    # samples, where six late stamps cannot carry the median.
    def move(t: float) -> float:
        return trapezoid(500.0, 1500.0, 1000.0, 10000.0, 0.0, t)

    times = [i * 0.001 for i in range(400)]
    times += [0.4 + k * 0.008 for k in range(19)]
    times += [0.552 + i * 0.001 for i in range(1000)]
    late = set(range(404, 410))
    samples = [Sample(t + (0.012 if k in late else 0.0), move(t)) for k, t in enumerate(times)]
    samples.sort(key=lambda s: s.t)
    fig = step_figures(samples, 0.0, 500.0, 1500.0)
    assert fig.peak_speed_units_per_s == pytest.approx(1000.0, rel=0.05)
    # The same samples judged over 100 ms alone make the peak the stamps invented.
    sparse = step_figures(samples, 0.0, 500.0, 1500.0, speed_samples_min=2)
    assert sparse.peak_speed_units_per_s > 1050.0


def test_a_noisy_sample_is_not_a_motion() -> None:
    # At rest at 500 with one spike past the band at 5 ms; the motion starts at 20 ms.
    def pos(t: float) -> float:
        if abs(t - 0.005) < 1e-9:
            return 504.0
        return 500.0 if t < 0.020 else 500.0 + 1000.0 * (t - 0.020)

    fig = step_figures(sampled(pos, 0.0, 1.0, 0.001), 0.0, 500.0, 1000.0, noise_band=2.0)
    assert fig.dead_time_ms == pytest.approx(22.0, abs=1.0)
