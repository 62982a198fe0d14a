"""Run a :class:`RigPlan` on an open bus: the asyncio shell around ``rig.analysis``.

Actuators are tested one after the other (the poller then samples the one under test as
fast as the bus allows).  Each test first brings the actuator to its start in
positioning mode (the actuator's own profile ramps it there from wherever it is), so
the rig never jumps; every target is inside the plan's window (checked at plan time
and again here before any write).  However the run ends, every actuator under test
is paused after its last target (``finally``), and the ceilings of the plan pause
everything at once from the reply that crossed them.

The rig fails what fails.  An actuator that does not follow (a move that does not get
halfway to its target within the plan's ``settle_timeout``, a sine it does not move
with), a figure that cannot be computed (the motion never got there) and an abort are
each a :class:`Failure` naming the actuator, the test and why.  An actuator that does
not follow is paused and its remaining tests are skipped; the next actuator is tested.
``RigResult.passed`` is False when anything failed.
"""

from __future__ import annotations

import asyncio
import logging
import math
import statistics
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

from motorbus.bus.bus import Bus, Priority
from motorbus.devices.la import InspireLA
from motorbus.errors import ArrivalTimeoutError, LocalProtocolError, ReplyTimeoutError
from motorbus.lifecycle import deferred_interrupts
from motorbus.protocol import la
from motorbus.rig.analysis import (
    RepeatFigures,
    Sample,
    StepFigures,
    TrackFigures,
    distribution,
    repeat_figures,
    sample_rate,
    step_figures,
    track_figures,
)
from motorbus.rig.plan import RigPlan
from motorbus.rig.sampler import RigAborted, Sampler
from motorbus.streaming.model import DEFAULT_MAX_SPEED, MAX_SPEED_LIMIT
from motorbus.streams import Streamer

__all__ = ["DeviceResult", "Failure", "Progress", "RigResult", "run_rig"]

log = logging.getLogger("motorbus.rig")

#: A sample window counts as still when its positions span at most this many noise bands.
STILL_WINDOW_S = 0.08
#: Settled: still, and within this share of the move (or 2 noise bands) of the target.
SETTLE_SHARE = 0.05
#: The steady state after a settle is sampled this long before the next move.
TAIL_S = 0.15

#: Most runs of one tracking frequency on a served bus (a run whose sine did not reach
#: the actuator as sent, ``TicksMissed``, is run again).
SERVED_TRACK_RUNS = 3
#: Most share of a served sine's ticks the server may leave unwritten as sent (skipped,
#: their rows late, ramped after a gap); those rows are left out of the figures.
UNWRITTEN_SHARE = 0.05

#: ``progress(what, done_fraction)``: called as the plan goes.
Progress = Callable[[str, float], None]

#: Why a figure can be missing (NaN, ``null`` in results.json): docs/rig.md's definitions.
WHY_MISSING = {
    "step.dead_time_ms": "the position never left the noise band around the start",
    "step.rise_time_ms": "the position never crossed both 10 % and 90 % of the step",
    "step.mean_speed_units_per_s": "the position never crossed both 10 % and 90 % of the step",
    "step.settling_time_ms": "the position never stayed within 1 % of the step around the end",
    "track.lag_ms": "the targets and positions overlap too briefly to correlate",
}


class TicksMissed(ValueError):
    """A served stream's sine did not reach the actuator as sent: too many of its ticks
    were not written as sent (the server says which)."""


@dataclass(frozen=True, slots=True)
class Failure:
    """One actuator failed one test (``test``: one of ``TESTS``) for the reason ``why``."""

    id: int
    test: str
    why: str

    def __str__(self) -> str:
        return f"la:{self.id} {self.test}: {self.why}"

    def as_dict(self) -> dict[str, str]:
        return {"device": f"la:{self.id}", "test": self.test, "why": self.why}


@dataclass
class DeviceResult:
    """Everything measured on one actuator."""

    id: int  #: the actuator's ID (1..254)
    steps: list[StepFigures] = field(default_factory=list)  #: each step, in order
    #: Each tracking run, one per frequency (or the one run without a frequency).
    tracks: list[TrackFigures] = field(default_factory=list)
    #: (first, last) write time of each tracking run's targets (bus clock, s).
    track_windows: list[tuple[float, float]] = field(default_factory=list)
    #: Dead time of each latency step (write of the target to the first move), ms.
    dead_times_ms: list[float] = field(default_factory=list)
    repeat: RepeatFigures | None = None  #: the repeatability figures, if that test ran
    #: Where each repeatability approach ended, per side ("below", "above").
    ends: dict[str, list[float]] = field(default_factory=dict)
    #: Position noise at rest: standard deviation of the positions, units (NaN if never
    #: measured).
    noise: float = math.nan
    #: What failed on this actuator, in the order it happened (empty: it passed).
    failures: list[Failure] = field(default_factory=list)

    def figures(self) -> dict[str, float]:
        """The flat figures ``results.json`` lists (docs/rig.md defines each)."""
        out: dict[str, float] = {}
        if self.steps:

            def mean(attr: str) -> float:
                return statistics.fmean(getattr(s, attr) for s in self.steps)

            out["step.dead_time_ms"] = mean("dead_time_ms")
            out["step.rise_time_ms"] = mean("rise_time_ms")
            out["step.speed_units_per_s"] = mean("peak_speed_units_per_s")
            out["step.mean_speed_units_per_s"] = mean("mean_speed_units_per_s")
            out["step.overshoot_pct"] = max(s.overshoot_pct for s in self.steps)
            out["step.settling_time_ms"] = mean("settling_time_ms")
            out["step.steady_state_error"] = max(
                (abs(s.steady_state_error) for s in self.steps), default=math.nan
            )
            out["step.peak_current_ma"] = max(s.peak_current for s in self.steps)
            out["step.peak_force_g"] = max(s.peak_force for s in self.steps)
        if self.tracks:
            out["track.rms_error"] = max(t.rms_error for t in self.tracks)
            out["track.max_error"] = max(t.max_error for t in self.tracks)
            out["track.lag_ms"] = statistics.fmean(t.lag_ms for t in self.tracks)
        finite = [v for v in self.dead_times_ms if math.isfinite(v)]
        if self.dead_times_ms:
            d = distribution(finite)
            out["latency.p50_ms"] = d.p50
            out["latency.p99_ms"] = d.p99
            out["latency.max_ms"] = d.max
        if self.repeat is not None:
            out["repeat.spread"] = self.repeat.spread
            out["repeat.backlash"] = self.repeat.backlash
            out["repeat.std_below"] = self.repeat.from_below.std
            out["repeat.std_above"] = self.repeat.from_above.std
        return out

    def details(self) -> dict[str, Any]:
        return {
            "noise_std": self.noise,
            "steps": [asdict(s) for s in self.steps],
            "tracks": [asdict(t) for t in self.tracks],
            "dead_times_ms": self.dead_times_ms,
            "repeat": asdict(self.repeat) if self.repeat is not None else None,
            "repeat_ends": self.ends,
            "failures": [f.as_dict() for f in self.failures],
        }


@dataclass
class RigResult:
    """A whole run: per actuator results, the raw samples and the achieved sampling."""

    plan: RigPlan  #: what was asked
    devices: dict[int, DeviceResult]  #: per actuator ID, what was measured
    samples: dict[int, list[Sample]]  #: per actuator ID, every status reply, in order
    #: Per actuator ID, each target written: (bus clock when the write completed,
    #: seconds; position, units).
    targets: dict[int, list[tuple[float, int]]]
    started: float  #: when the run started, seconds since the epoch (``time.time()``)
    seconds: float  #: how long the run took, seconds
    polls: int  #: status queries sent
    poll_timeouts: int  #: status queries without a reply (timed out, or the port lost)
    #: Why the run stopped early (a ceiling or a fault tripped), or None for a complete
    #: run.
    aborted: str | None = None

    @property
    def failures(self) -> list[Failure]:
        """Every failure of every actuator tested, in plan order."""
        return [f for d in self.devices.values() for f in d.failures]

    @property
    def untested(self) -> list[int]:
        """Actuators of the plan the run never got to (it was aborted first)."""
        return [i for i in self.plan.ids if i not in self.devices]

    @property
    def passed(self) -> bool:
        """True when every actuator of the plan was tested and nothing failed."""
        return self.aborted is None and not self.failures and not self.untested

    def sampling(self) -> dict[str, float]:
        """Achieved sample rate (Hz) and interval jitter (ms) over every actuator."""
        rates, p99s, maxes = [], [], []
        for samples in self.samples.values():
            if len(samples) > 2:
                rate, gaps = sample_rate(samples)
                rates.append(rate)
                p99s.append(gaps.p99)
                maxes.append(gaps.max)
        return {
            "rate_hz": statistics.fmean(rates) if rates else math.nan,
            "interval_p99_ms": max(p99s, default=math.nan),
            "interval_max_ms": max(maxes, default=math.nan),
        }


class _Rig:
    def __init__(self, bus: Bus, plan: RigPlan, sampler: Sampler, progress: Progress) -> None:
        self.bus = bus
        self.plan = plan
        self.sampler = sampler
        self.progress = progress
        self.total = plan.estimate_seconds()
        #: Position noise (standard deviation) of each actuator at its last rest.
        self.rest_noise: dict[int, float] = {}
        self.t0 = time.monotonic()

    def tell(self, what: str) -> None:
        self.progress(what, min(1.0, (time.monotonic() - self.t0) / self.total))

    async def move(self, ident: int, target: int) -> float:
        """Write a positioning target (inside the window); return its write time."""
        if not self.plan.in_window(target):  # plan-time checks make this unreachable
            raise LocalProtocolError(f"target {target} is outside the window {self.plan.window}")
        self.sampler.check()
        await self.bus.request(la.MoveTo(ident, target), priority=Priority.HIGH)
        return self.sampler.last_write(ident)

    def noise_band(self, ident: int) -> float:
        """The band a position must leave to count as moved: four standard deviations
        of the noise measured at the last rest (at least 2 units: positions are whole)."""
        return max(2.0, 4.0 * self.rest_noise.get(ident, 0.0))

    def measure_noise(self, ident: int) -> float:
        """Standard deviation of the positions over the last still window (call at rest)."""
        now = self.bus.timer.now()
        recent = [s.position for s in self.sampler.since(ident, now - STILL_WINDOW_S)]
        noise = statistics.pstdev(recent) if len(recent) > 2 else 0.0
        self.rest_noise[ident] = noise
        return noise

    async def settle(self, ident: int, target: int, since: float, size: float) -> bool:
        """Wait until the actuator is still near ``target``; False on timeout.

        Still: the positions of the last 80 ms span at most the noise band measured at
        the last rest (never the noise of the motion itself)."""
        deadline = since + self.plan.settle_timeout
        band = self.noise_band(ident)
        near = max(2 * band, SETTLE_SHARE * size)
        while self.bus.timer.now() < deadline:
            await self.sampler.sleep(0.01)
            now = self.bus.timer.now()
            recent = self.sampler.since(ident, max(since, now - STILL_WINDOW_S))
            if len(recent) < 4 or recent[0].t > now - 0.75 * STILL_WINDOW_S:
                continue
            spread = max(s.position for s in recent) - min(s.position for s in recent)
            if spread <= band and abs(recent[-1].position - target) <= near:
                return True
        return False

    async def arrive(self, ident: int, target: int, since: float, start: float) -> None:
        """Wait for the actuator to settle at ``target`` (written at ``since``, from
        ``start``).  An actuator that, when the plan's ``settle_timeout`` ends, is as far
        from the target as half the move, and as the plan's smallest move
        (``latency_step``) does not follow: ArrivalTimeoutError says where it is.  One
        that got closer but is not still or not near is left to the figures."""
        size = abs(target - start)
        if await self.settle(ident, target, since, max(size, 1)):
            return
        now = self.bus.timer.now()
        seen = self.sampler.since(ident, since)
        timeout = self.plan.settle_timeout
        if not seen:
            raise ArrivalTimeoutError(
                f"no status sample in the {timeout:g} s after target {target} was written",
                id=ident,
                target=target,
                status=None,
            )
        at = self.rest_position(ident, seen[-1].position)
        slack = max(size / 2, 2 * self.noise_band(ident), self.plan.latency_step)
        if abs(at - target) < slack:
            return
        span = max(s.position for s in seen) - min(s.position for s in seen)
        how = "did not move" if span <= self.noise_band(ident) else f"stopped at {at:.0f}"
        raise ArrivalTimeoutError(
            f"did not follow: sent from {start:.0f} to {target}, it {how} "
            f"(at {at:.0f} after {now - since:.1f} s; limit settle_timeout={timeout:g} s)",
            id=ident,
            target=target,
            status=seen[-1],
        )

    async def goto(self, ident: int, target: int) -> None:
        status = await self.bus.request(la.Control(ident, la.ControlAction.QUERY_STATUS))
        t = await self.move(ident, target)
        await self.arrive(ident, target, t, status.position)
        await self.sampler.sleep(TAIL_S)
        self.measure_noise(ident)

    def rest_position(self, ident: int, fallback: float) -> float:
        """Where the actuator is at rest now: the mean of the last still window (a dead
        band or an offset leaves it short of its last target, and the dead time is
        measured from where it really is)."""
        now = self.bus.timer.now()
        recent = [s.position for s in self.sampler.since(ident, now - STILL_WINDOW_S)]
        return statistics.fmean(recent) if recent else fallback

    async def step(self, ident: int, start: int, end: int) -> StepFigures:
        await self.goto(ident, start)
        band = self.noise_band(ident)
        rest = self.rest_position(ident, start)
        t = await self.move(ident, end)
        await self.arrive(ident, end, t, rest)
        await self.sampler.sleep(TAIL_S)
        return step_figures(self.sampler.since(ident, t), t, rest, end, noise_band=band)

    async def track(self, ident: int, frequency: float) -> TrackFigures:
        """One frequency of the tracking test.  On a served bus, a run whose sine did not
        reach the actuator as sent (``TicksMissed``: the network or the server's host,
        not the actuator) is run again, up to ``SERVED_TRACK_RUNS`` runs."""
        for run in range(1, SERVED_TRACK_RUNS + 1):
            try:
                return await self.track_once(ident, frequency)
            except TicksMissed as err:
                if run == SERVED_TRACK_RUNS:
                    raise ValueError(f"{err} (in each of {run} runs)") from None
                log.warning("la:%d track: %s; running it again", ident, err)
        raise AssertionError("unreachable")

    async def track_once(self, ident: int, frequency: float) -> TrackFigures:
        plan = self.plan
        assert plan.amplitude is not None
        await self.goto(ident, plan.center)
        seconds = plan.track_seconds(frequency)
        w = 2 * math.pi * frequency
        amp, center = plan.amplitude, plan.center

        # The whole sine, known ahead: row k is tick k's target (k * period after tick 0).
        rows = [
            round(center + amp * math.sin(w * k * plan.period))
            for k in range(math.floor(seconds / plan.period + 1e-9) + 1)
        ]
        streamer = Streamer(self.bus)
        try:
            first_write = len(self.sampler.targets[ident])
            # After a gap (a stalled host) the stream ramps back to the sine at twice the
            # sine's peak speed: back on it within about the gap's length.
            speed = min(MAX_SPEED_LIMIT, max(DEFAULT_MAX_SPEED, 2 * amp * w))
            stream = streamer.follow(
                InspireLA(streamer.bus, ident),
                rows,
                period=plan.period,
                safe_action="pause",
                max_speed=speed,
            )
            self.sampler.stream = stream
            while not stream.done:
                self.tell(f"la:{ident} track {frequency:g} Hz")
                await self.sampler.sleep(0.05)
            await stream.wait()
        finally:
            self.sampler.stream = None
            await streamer.close(safe=True)
        self.sampler.check()
        if getattr(stream, "remote", False):
            self.sampler.targets[ident].extend(_served_targets(stream, rows, frequency))
        written = self.sampler.targets[ident][first_write:]
        if not written:
            raise ValueError(f"{frequency:g} Hz: no target of the sine was written")
        # Skip the first cycle (or half the run): the response has to settle into the sine.
        skip = min(1.0 / frequency, seconds / 2)
        start = written[0][0] + skip
        kept = [(t, x) for t, x in written if t >= start]
        if len(kept) < 2:
            raise ValueError(f"{frequency:g} Hz: too few targets after the first cycle")
        samples = [s for s in self.sampler.since(ident, start) if s.t <= kept[-1][0]]
        span = max((s.position for s in samples), default=0.0) - min(
            (s.position for s in samples), default=0.0
        )
        if span <= self.noise_band(ident):
            raise ArrivalTimeoutError(
                f"did not follow: the {frequency:g} Hz sine spanned {2 * amp} units, "
                f"the position {span:.0f}",
                id=ident,
                target=center + amp,
                status=samples[-1] if samples else None,
            )
        figures = track_figures(
            [t for t, _ in kept],
            [float(x) for _, x in kept],
            samples,
            frequency_hz=frequency,
            max_lag_s=min(0.5, 0.5 / frequency),
        )
        r = figures.response
        if r is not None and not (math.isfinite(r.amplitude_ratio) and math.isfinite(r.phase_deg)):
            raise ValueError(f"{frequency:g} Hz: no sine fits the targets or the positions")
        return figures

    async def latency(self, ident: int, result: DeviceResult) -> None:
        plan = self.plan
        base = plan.center
        await self.goto(ident, base)
        for k in range(plan.latency_count):
            start, end = (
                (base, base + plan.latency_step)
                if k % 2 == 0
                else (
                    base + plan.latency_step,
                    base,
                )
            )
            band = min(self.noise_band(ident), plan.latency_step / 2)
            rest = self.rest_position(ident, start)
            t = await self.move(ident, end)
            await self.arrive(ident, end, t, rest)
            await self.sampler.sleep(TAIL_S)
            self.measure_noise(ident)
            fig = step_figures(self.sampler.since(ident, t), t, rest, end, noise_band=band)
            result.dead_times_ms.append(fig.dead_time_ms)
            self.tell(f"la:{ident} latency {k + 1}/{plan.latency_count}")
        lost = sum(1 for v in result.dead_times_ms if not math.isfinite(v))
        if lost:
            raise ValueError(
                f"{lost} of {len(result.dead_times_ms)} small steps have no dead time: "
                f"{WHY_MISSING['step.dead_time_ms']}"
            )

    async def repeat(self, ident: int, result: DeviceResult) -> RepeatFigures:
        plan = self.plan
        assert plan.repeat_point is not None
        point = plan.repeat_point
        ends: dict[str, list[float]] = {"below": [], "above": []}
        result.ends = ends
        for side, away in (("below", -plan.repeat_approach), ("above", plan.repeat_approach)):
            for k in range(plan.repeat_count):
                await self.goto(ident, point + away)
                t = await self.move(ident, point)
                await self.arrive(ident, point, t, point + away)
                await self.sampler.sleep(TAIL_S)
                now = self.bus.timer.now()
                tail = self.sampler.since(ident, now - TAIL_S)
                if not tail:
                    raise ValueError(f"no status sample after approach {k + 1} from {side}")
                ends[side].append(statistics.fmean(s.position for s in tail))
                self.tell(f"la:{ident} repeat from {side} {k + 1}/{plan.repeat_count}")
        return repeat_figures(point, ends["below"], ends["above"])

    async def run_test(self, ident: int, test: str, result: DeviceResult) -> None:
        plan = self.plan
        if test == "step":
            assert plan.step_start is not None and plan.step_end is not None
            for a, b in ((plan.step_start, plan.step_end), (plan.step_end, plan.step_start)):
                self.tell(f"la:{ident} step {a} -> {b}")
                result.steps.append(await self.step(ident, a, b))
            result.noise = self.rest_noise.get(ident, math.nan)
        elif test == "track":
            for f in plan.frequencies:
                first = len(self.sampler.targets[ident])
                result.tracks.append(await self.track(ident, f))
                written = self.sampler.targets[ident][first:]
                if written:
                    result.track_windows.append((written[0][0], written[-1][0]))
        elif test == "latency":
            await self.latency(ident, result)
        else:
            result.repeat = await self.repeat(ident, result)

    async def device(self, ident: int, result: DeviceResult) -> None:
        """Run the plan's tests on one actuator; what fails goes to ``result.failures``.

        Raises:
            RigAborted: a ceiling tripped (the failure is recorded first).
        """
        tests = self.plan.tests
        test = tests[0]
        self.sampler.poll([ident])
        try:
            status = await self.bus.request(la.Control(ident, la.ControlAction.QUERY_STATUS))
            await self.bus.request(la.Control(ident, la.ControlAction.WORK))
            self.tell(f"la:{ident} at {status.position}")
            for test in tests:
                try:
                    await self.run_test(ident, test, result)
                except ValueError as err:  # the analysis could not compute a figure
                    result.failures.append(Failure(ident, test, str(err)))
                    continue
                for name, value in result.figures().items():
                    if name.startswith(f"{test}.") and not math.isfinite(value):
                        why = WHY_MISSING.get(name, "no sample to compute it from")
                        result.failures.append(
                            Failure(ident, test, f"{name} could not be computed: {why}")
                        )
        except (ArrivalTimeoutError, ReplyTimeoutError) as err:
            # It does not follow (or answer): its other tests would only wait for it.
            why = str(err) if isinstance(err, ArrivalTimeoutError) else f"no reply: {err}"
            skipped = tests[tests.index(test) + 1 :]
            if skipped:
                why += f"; not run: {', '.join(skipped)}"
            result.failures.append(Failure(ident, test, why))
            self.sampler.poll(())
            await _pause_all(self.bus, (ident,))
        except RigAborted as err:
            result.failures.append(Failure(ident, test, self.sampler.tripped or str(err)))
            raise


def _served_targets(stream: Any, rows: list[int], frequency: float) -> list[tuple[float, int]]:
    """The sine's targets as a served stream wrote them: row ``k`` at its tick,
    ``stream.origin + k * period``, on this host's clock (the clock of the samples).

    The writes are the server's, out of this host's sight; it says at the end which
    ticks it did not write a row at as sent (``stream.unwritten``: ticks it skipped,
    rows that came after their tick, ticks ramped back after a gap): those rows are
    left out, as a local bus's observer never sees a skipped tick.

    Raises:
        ValueError: the server wrote no frame of the sine.
        TicksMissed: more than ``UNWRITTEN_SHARE`` of the rows were not written as sent.
    """
    if int(stream.stats.as_dict().get("frames", 0)) == 0:
        raise ValueError(f"{frequency:g} Hz: the server wrote no target of the sine")
    unwritten = set(stream.unwritten) & set(range(len(rows)))
    if len(unwritten) > UNWRITTEN_SHARE * len(rows):
        raise TicksMissed(
            f"{frequency:g} Hz: the server did not write {len(unwritten)} of the "
            f"{len(rows)} ticks of the sine as sent (skipped, their targets late, or "
            f"ramped after a gap; at most {UNWRITTEN_SHARE:.0%})"
        )
    return [
        (stream.origin + k * stream.period, x) for k, x in enumerate(rows) if k not in unwritten
    ]


async def _pause_all(bus: Bus, ids: tuple[int, ...]) -> None:
    # Every actuator gets its pause, whatever another's did (a timeout means the pause
    # was written and only its status reply is missing), none held up by another's:
    # the bus's lease table defines and sends it.
    await bus.lease_keeper.stop([f"la:{i}" for i in ids], "pause", who="rig")


async def run_rig(
    bus: Bus,
    plan: RigPlan,
    progress: Progress | None = None,
    *,
    raise_on_abort: bool = True,
) -> RigResult:
    """Run ``plan`` on the LA actuators of ``bus``; every actuator is paused at the end.

    An actuator that does not follow or whose figures cannot be computed does not end
    the run: its failures are in the result (``RigResult.passed``, ``.failures``).

    Args:
        raise_on_abort: when a ceiling trips, raise (True) or return what was measured
            until then, with ``aborted`` saying why (False: the command line writes a
            report of an aborted run).

    Raises:
        RigAborted: a ceiling tripped or an actuator faulted (all paused; the message
            says which, in which test, and why).  Whatever else ends the run (an error,
            cancellation) also pauses every actuator under test before it propagates.
    """
    tell = progress or (lambda _what, _done: None)
    started = time.time()
    t0 = time.monotonic()
    results: dict[int, DeviceResult] = {}
    aborted: str | None = None
    with Sampler(
        bus, plan.ids, max_current_ma=plan.max_current_ma, max_force_g=plan.max_force_g
    ) as sampler:
        rig = _Rig(bus, plan, sampler, tell)
        try:
            for ident in plan.ids:
                results[ident] = DeviceResult(ident)
                await rig.device(ident, results[ident])
            tell("done", 1.0)
        except RigAborted:
            failed = results[ident].failures[-1]
            aborted = f"rig aborted in {failed}; every actuator under test is paused"
            if raise_on_abort:
                raise RigAborted(aborted) from None
        finally:
            sampler.poll(())
            with deferred_interrupts():
                await asyncio.shield(_pause_all(bus, plan.ids))
    return RigResult(
        plan=plan,
        devices=results,
        samples=sampler.samples,
        targets=sampler.targets,
        started=started,
        seconds=time.monotonic() - t0,
        polls=sampler.polls,
        poll_timeouts=sampler.poll_timeouts,
        aborted=aborted,
    )


__all__ += ["RigAborted"]
