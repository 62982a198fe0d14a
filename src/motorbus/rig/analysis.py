"""The rig's figures, computed from samples: pure (no clock, no I/O, no numpy).

A *sample* is what one status reply says, stamped with the time its bytes arrived (the
bus's reply timestamp, seconds on the host's monotonic clock).  A *command time* is when
the bus wrote a target to the port (the write's completion time).  Every figure below is
a function of those two kinds of time and the positions; ``docs/rig.md`` defines each
one, its units and its uncertainty (about one sample period for every time figure).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = [
    "LEAD_MAX_DEG",
    "Distribution",
    "FrequencyPoint",
    "RepeatFigures",
    "Sample",
    "StepFigures",
    "TrackFigures",
    "distribution",
    "frequency_point",
    "repeat_figures",
    "sample_rate",
    "step_figures",
    "track_figures",
]


@dataclass(frozen=True, slots=True)
class Sample:
    """One status reply: arrival time ``t`` (s), position (0..2000 units), current (mA)
    and force (grams) as the actuator reported them."""

    t: float
    """When the reply arrived, seconds on the bus's clock."""
    position: float
    """Position, 0..2000 units (the full stroke)."""
    current: float = 0.0
    """Motor current, mA."""
    force: float = 0.0
    """Force, grams (the LA's status reply, A2-05)."""


@dataclass(frozen=True, slots=True)
class Distribution:
    """Order statistics of a set of values (same units as the values)."""

    count: int
    """Number of values (every other figure is NaN when it is 0)."""
    p50: float
    """Median, linear interpolation between closest ranks (numpy's default)."""
    p99: float
    """99th percentile, interpolated like ``p50``."""
    max: float
    """Largest value."""
    min: float
    """Smallest value."""
    mean: float
    """Arithmetic mean."""
    std: float
    """Population standard deviation (divided by ``count``, not ``count - 1``)."""


def _percentile(ordered: Sequence[float], q: float) -> float:
    # Linear interpolation between closest ranks (numpy's default "linear" method).
    if not ordered:
        return math.nan
    pos = (len(ordered) - 1) * q
    lo = math.floor(pos)
    hi = min(lo + 1, len(ordered) - 1)
    return ordered[lo] + (ordered[hi] - ordered[lo]) * (pos - lo)


def distribution(values: Sequence[float]) -> Distribution:
    """p50, p99, max, min, mean and (population) standard deviation of ``values``;
    NaN for each figure when ``values`` is empty."""
    ordered = sorted(values)
    n = len(ordered)
    if n == 0:
        nan = math.nan
        return Distribution(0, nan, nan, nan, nan, nan, nan)
    mean = sum(ordered) / n
    std = math.sqrt(sum((v - mean) ** 2 for v in ordered) / n)
    return Distribution(
        n, _percentile(ordered, 0.5), _percentile(ordered, 0.99), ordered[-1], ordered[0], mean, std
    )


def sample_rate(samples: Sequence[Sample]) -> tuple[float, Distribution]:
    """The achieved sample rate (Hz, from the mean interval) and the distribution of
    the intervals between samples (ms)."""
    gaps = [(b.t - a.t) * 1e3 for a, b in itertools.pairwise(samples)]
    dist = distribution(gaps)
    rate = 1e3 / dist.mean if gaps and dist.mean > 0 else math.nan
    return rate, dist


# -- step -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class StepFigures:
    """What one step (start -> end, written at ``command_t``) did.  Times in ms from
    the write of the target; speeds in position units per second; NaN where the motion
    never got there (e.g. no settling within the samples)."""

    start: float
    """Position the step started from, units."""
    end: float
    """Target of the step, units."""
    dead_time_ms: float
    """Write of the target to the first of ``MOVED_SAMPLES`` (3) samples in a row more
    than the noise band (``noise_band`` units, at least 2) from ``start``, ms."""
    rise_time_ms: float
    """Between the 10 % and the 90 % crossings of the step (interpolated), ms."""
    peak_speed_units_per_s: float
    """Largest robust slope over any window of 100 ms (``speed_window_s``) and 30
    samples (``speed_samples_min``) or more, units/s."""
    mean_speed_units_per_s: float
    """80 % of the step over the rise time, units/s."""
    overshoot_pct: float
    """How far the position went past ``end``, percent of the step (0 if never)."""
    settling_time_ms: float
    """Write of the target to the first sample after which every sample stays within
    1 % of the step (``settle_band_pct``) around ``end``, ms."""
    steady_state_error: float
    """Mean of position - ``end`` over the last 100 ms of samples (``tail_s``), units."""
    peak_current: float
    """Largest reported current during the step (absolute), mA."""
    peak_force: float
    """Largest reported force during the step (absolute), grams."""
    #: When the target was written (the bus's clock, seconds): where the plot starts.
    command_t: float = math.nan


def _crossing(samples: Sequence[Sample], level: float, rising: bool) -> float:
    """Time at which the position first reaches ``level`` (linear interpolation between
    the two samples around it), or NaN."""
    prev: Sample | None = None
    for s in samples:
        reached = s.position >= level if rising else s.position <= level
        if reached:
            if prev is None:
                return s.t
            span = s.position - prev.position
            frac = 0.0 if span == 0 else (level - prev.position) / span
            return prev.t + max(0.0, min(1.0, frac)) * (s.t - prev.t)
        prev = s
    return math.nan


def _slope(window: Sequence[Sample]) -> float:
    """Robust speed over a window (units/s): the median of the slopes between samples
    half a window apart.  One sample stamped late (a reply read after a stall of the
    host) changes two of those slopes, and the median not at all."""
    half = len(window) // 2
    slopes = sorted(
        (b.position - a.position) / (b.t - a.t)
        for a, b in zip(window, window[half:], strict=False)
        if b.t > a.t
    )
    return _percentile(slopes, 0.5) if slopes else 0.0


#: The largest phase lead a tracking point shows as a lead (degrees); beyond it, a lag
#: (``frequency_point``).
LEAD_MAX_DEG = 30.0
#: A sample counts as moved past the noise band only if the next ones stay past it too
#: (one noisy sample is not a motion).
MOVED_SAMPLES = 3


def _moved(samples: Sequence[Sample], level: float, rising: bool) -> float:
    """Time of the first sample past ``level`` that the next ``MOVED_SAMPLES - 1``
    samples stay past too, interpolated as in ``_crossing``; NaN if none."""
    past = [(s.position >= level) if rising else (s.position <= level) for s in samples]
    for i in range(len(samples)):
        if all(past[i : i + MOVED_SAMPLES]) and i + MOVED_SAMPLES <= len(samples):
            return _crossing(samples[max(0, i - 1) :], level, rising)
    return math.nan


def step_figures(
    samples: Sequence[Sample],
    command_t: float,
    start: float,
    end: float,
    *,
    noise_band: float = 2.0,
    settle_band_pct: float = 1.0,
    tail_s: float = 0.1,
    speed_window_s: float = 0.1,
    speed_samples_min: int = 30,
) -> StepFigures:
    """Figures of one step from ``start`` to ``end`` commanded at ``command_t``.

    Args:
        samples: the samples from the write of the target on (earlier ones are ignored),
            at least until the actuator has settled.
        noise_band: the position has "moved" once it is more than this many units
            from ``start`` toward ``end`` on ``MOVED_SAMPLES`` samples in a row (dead
            time; one noisy sample is not a motion).
        settle_band_pct: the settling band, in percent of the step size.
        tail_s: the steady-state error is the mean error of the samples in the last
            ``tail_s`` seconds.
        speed_window_s: the peak speed is the largest robust slope (see ``_slope``)
            of the positions over any window of at least this length ...
        speed_samples_min: ... and of at least this many samples: where a busy host
            sampled sparsely, the window widens, so that a few replies read late (each
            stamped late) cannot make a peak.  (A run of the suite on two loaded CPUs
            sampled 13 times in 100 ms, and two late stamps read 1,208 units/s off an
            actuator moving at 1,000.)

    Raises:
        ValueError: ``start == end`` or no sample after ``command_t``.
    """
    if start == end:
        raise ValueError(f"step: start and end are both {start}; a step needs two positions")
    after = [s for s in samples if s.t >= command_t]
    if not after:
        raise ValueError("step: no sample after the target was written")
    rising = end > start
    sign = 1.0 if rising else -1.0
    size = abs(end - start)

    def frac_level(f: float) -> float:
        return start + sign * size * f

    moved_t = _moved(after, start + sign * noise_band, rising)
    dead_ms = (moved_t - command_t) * 1e3
    t10 = _crossing(after, frac_level(0.1), rising)
    t90 = _crossing(after, frac_level(0.9), rising)
    rise_ms = (t90 - t10) * 1e3
    # Speed over a window, not between neighbours: positions are whole units, and two
    # samples 0.5 ms apart one unit apart would read as 2,000 units/s; and a median
    # slope, so that one reply read late cannot make a peak.
    peak_speed = 0.0
    j = 0
    for i, a in enumerate(after):
        j = max(j, i + 1)
        while j < len(after) and (
            after[j].t - a.t < speed_window_s or j - i + 1 < speed_samples_min
        ):
            j += 1
        if j == len(after):
            break
        slope = _slope(after[i : j + 1])
        peak_speed = max(peak_speed, sign * slope)
    mean_speed = 0.8 * size / (t90 - t10) if t90 > t10 else math.nan
    beyond = max(sign * (s.position - end) for s in after)
    overshoot = max(0.0, beyond) / size * 100.0
    band = size * settle_band_pct / 100.0
    settled_t = math.nan
    for i, s in enumerate(after):
        if all(abs(x.position - end) <= band for x in after[i:]):
            settled_t = s.t
            break
    settling_ms = (settled_t - command_t) * 1e3
    last_t = after[-1].t
    tail = [s for s in after if s.t >= last_t - tail_s]
    steady = sum(s.position - end for s in tail) / len(tail)
    return StepFigures(
        command_t=command_t,
        start=start,
        end=end,
        dead_time_ms=dead_ms,
        rise_time_ms=rise_ms,
        peak_speed_units_per_s=peak_speed,
        mean_speed_units_per_s=mean_speed,
        overshoot_pct=overshoot,
        settling_time_ms=settling_ms,
        steady_state_error=steady,
        peak_current=max(abs(s.current) for s in after),
        peak_force=max(abs(s.force) for s in after),
    )


# -- tracking ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class FrequencyPoint:
    """The actuator's response at one frequency: output amplitude over target amplitude
    and the phase of the output against the target (degrees, negative = lagging)."""

    frequency_hz: float
    """The frequency of the target sine, Hz."""
    amplitude_ratio: float
    """Amplitude of the positions over amplitude of the targets (least-squares sine
    fits; 1 = full amplitude, no unit)."""
    phase_deg: float
    """Phase of the positions against the targets, degrees (negative = lagging)."""


@dataclass(frozen=True, slots=True)
class TrackFigures:
    """How well positions followed targets: error in position units, lag in ms (from the
    cross-correlation of target and position), and the response at the frequency, if one
    was given."""

    rms_error: float
    """Root mean square of position - target, units; the target of a sample is the
    last one written before it arrived."""
    max_error: float
    """Largest absolute position - target, units."""
    lag_ms: float
    """Shift of the positions that best matches the targets (peak of their
    cross-correlation on a 1 ms grid, refined by a parabola), ms."""
    response: FrequencyPoint | None
    """Amplitude ratio and phase at the tracking frequency; None without one."""


def _value_at(times: Sequence[float], values: Sequence[float], t: float) -> float:
    """Linear interpolation of a time series at ``t`` (clamped at the ends)."""
    if t <= times[0]:
        return values[0]
    if t >= times[-1]:
        return values[-1]
    lo, hi = 0, len(times) - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if times[mid] <= t:
            lo = mid
        else:
            hi = mid
    span = times[hi] - times[lo]
    frac = 0.0 if span == 0 else (t - times[lo]) / span
    return values[lo] + (values[hi] - values[lo]) * frac


def _held_value(times: Sequence[float], values: Sequence[float], t: float) -> float:
    """The value last set at or before ``t`` (a target holds until the next one)."""
    lo, hi = 0, len(times)
    while lo < hi:
        mid = (lo + hi) // 2
        if times[mid] <= t:
            lo = mid + 1
        else:
            hi = mid
    return values[max(0, lo - 1)]


def _fit_sine(times: Sequence[float], values: Sequence[float], f: float) -> tuple[float, float]:
    """Least-squares fit of ``a sin(wt) + b cos(wt) + c``: returns (amplitude, phase rad)."""
    w = 2.0 * math.pi * f
    rows = [(math.sin(w * t), math.cos(w * t), 1.0) for t in times]
    # Normal equations (3x3), solved by Gaussian elimination.
    m = [[sum(r[i] * r[j] for r in rows) for j in range(3)] for i in range(3)]
    v = [sum(r[i] * y for r, y in zip(rows, values, strict=True)) for i in range(3)]
    for col in range(3):
        pivot = max(range(col, 3), key=lambda r: abs(m[r][col]))
        m[col], m[pivot] = m[pivot], m[col]
        v[col], v[pivot] = v[pivot], v[col]
        if m[col][col] == 0:
            return math.nan, math.nan
        for r in range(col + 1, 3):
            k = m[r][col] / m[col][col]
            m[r] = [a - k * b for a, b in zip(m[r], m[col], strict=True)]
            v[r] -= k * v[col]
    x = [0.0, 0.0, 0.0]
    for r in (2, 1, 0):
        x[r] = (v[r] - sum(m[r][c] * x[c] for c in range(r + 1, 3))) / m[r][r]
    a, b = x[0], x[1]
    return math.hypot(a, b), math.atan2(b, a)


def frequency_point(
    target_times: Sequence[float],
    targets: Sequence[float],
    samples: Sequence[Sample],
    frequency_hz: float,
) -> FrequencyPoint:
    """Amplitude ratio and phase of the positions against the targets at one frequency
    (a sine fit of each at that frequency).  The phase wraps into (-360 + LEAD_MAX_DEG,
    LEAD_MAX_DEG]: a lag down to almost a full cycle, and a small lead (timing noise, a
    device ahead of its target) as the lead it is, not as a lag of almost a cycle."""
    amp_in, ph_in = _fit_sine(target_times, targets, frequency_hz)
    amp_out, ph_out = _fit_sine([s.t for s in samples], [s.position for s in samples], frequency_hz)
    phase = math.degrees(ph_out - ph_in)
    while phase > LEAD_MAX_DEG:
        phase -= 360.0
    while phase <= LEAD_MAX_DEG - 360.0:
        phase += 360.0
    ratio = amp_out / amp_in if amp_in > 0 else math.nan
    return FrequencyPoint(frequency_hz, ratio, phase)


def track_figures(
    target_times: Sequence[float],
    targets: Sequence[float],
    samples: Sequence[Sample],
    *,
    frequency_hz: float | None = None,
    max_lag_s: float = 0.5,
    grid_s: float = 0.001,
) -> TrackFigures:
    """Tracking figures of ``samples`` against the targets written at ``target_times``.

    The error of a sample is its position minus the target in force when it arrived
    (the last one written before it).  The lag is the shift (0..``max_lag_s``) that
    best aligns position with target: the peak of their cross-correlation on a
    ``grid_s`` grid, refined by a parabola through the peak and its neighbours.

    Raises:
        ValueError: fewer than two targets or samples.
    """
    if len(target_times) < 2 or len(samples) < 2:
        raise ValueError("track: need at least two targets and two samples")
    errors = [s.position - _held_value(target_times, targets, s.t) for s in samples]
    rms = math.sqrt(sum(e * e for e in errors) / len(errors))
    max_err = max(abs(e) for e in errors)

    times = [s.t for s in samples]
    positions = [s.position for s in samples]
    t0 = max(target_times[0], times[0])
    t1 = min(target_times[-1], times[-1])
    lag_ms = math.nan
    if t1 - t0 > 2 * grid_s:
        n = int((t1 - t0) / grid_s)
        grid = [t0 + i * grid_s for i in range(n)]
        tgt = [_held_value(target_times, targets, t) for t in grid]
        pos = [_value_at(times, positions, t) for t in grid]
        max_k = min(int(max_lag_s / grid_s), n // 2)

        def corr(k: int) -> float:
            # Pearson correlation of the target at t with the position at t + k*grid,
            # over their overlap (so a shorter overlap does not bias the peak).
            a = tgt[: n - k]
            b = pos[k:]
            ma = sum(a) / len(a)
            mb = sum(b) / len(b)
            sab = sum((x - ma) * (y - mb) for x, y in zip(a, b, strict=True))
            saa = sum((x - ma) ** 2 for x in a)
            sbb = sum((y - mb) ** 2 for y in b)
            return sab / math.sqrt(saa * sbb) if saa > 0 and sbb > 0 else 0.0

        scores = [corr(k) for k in range(max_k + 1)]
        best = max(range(len(scores)), key=scores.__getitem__)
        shift = float(best)
        if 0 < best < len(scores) - 1:
            y0, y1, y2 = scores[best - 1], scores[best], scores[best + 1]
            denom = y0 - 2 * y1 + y2
            if denom != 0:
                shift += 0.5 * (y0 - y2) / denom
        lag_ms = shift * grid_s * 1e3
    response = (
        frequency_point(target_times, targets, samples, frequency_hz)
        if frequency_hz is not None
        else None
    )
    return TrackFigures(rms, max_err, lag_ms, response)


# -- repeatability ----------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class RepeatFigures:
    """Where N approaches to one point ended, per side (from below / from above):
    spread (max - min) and standard deviation per side, the overall spread, and the
    backlash (mean from above minus mean from below), all in position units."""

    target: float
    """The point approached, units."""
    from_below: Distribution
    """Settled positions of the approaches from below, units."""
    from_above: Distribution
    """Settled positions of the approaches from above, units."""
    spread: float
    """Largest minus smallest settled position over every approach, units."""
    backlash: float
    """Mean from above minus mean from below, units."""


def repeat_figures(
    target: float, from_below: Sequence[float], from_above: Sequence[float]
) -> RepeatFigures:
    """Figures of the settled positions of approaches to ``target`` from each side.

    Raises:
        ValueError: either side has no approach.
    """
    if not from_below or not from_above:
        raise ValueError("repeat: need at least one approach from each side")
    below = distribution(from_below)
    above = distribution(from_above)
    every = list(from_below) + list(from_above)
    return RepeatFigures(
        target=target,
        from_below=below,
        from_above=above,
        spread=max(every) - min(every),
        backlash=above.mean - below.mean,
    )
