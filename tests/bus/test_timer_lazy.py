"""``Timer.call_at_lazily``: a reply's deadline, watched by the loop's own timer until its
last ``HANDOVER_S`` and by the wake-up source (timerfd) only for that stretch.

What it promises: the same as ``call_at`` (never early, deadline order, cancellable,
nothing after ``close``), and a deadline cancelled before its handover never arms the
timerfd.  Behaviour only: how late a callback runs is benchmarks/bench_timer.py's.
"""

from __future__ import annotations

import asyncio
import math
import random
import time
from collections.abc import Callable

import pytest

import motorbus
from motorbus.bus.timer import LoopTimer, Timer, TimerfdTimer, timerfd_available
from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from tests.bus.test_timer import LOOPS, TIMERS, _record_settimes, run

needs_timerfd = pytest.mark.skipif(not timerfd_available(), reason="needs Linux timerfd")


@pytest.mark.parametrize("loop_factory", LOOPS)
@pytest.mark.parametrize("timer_cls", TIMERS)
def test_lazy_and_plain_deadlines_never_fire_early_and_run_in_deadline_order(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], timer_cls: type[Timer]
) -> None:
    async def main() -> None:
        timer = timer_cls()
        rng = random.Random(7)
        origin = timer.now()
        # Distinct deadlines from 1 ms past to 8 ms ahead: some with their handover past
        # already, most watched by the loop first.  Every other one is lazy.
        steps = rng.sample(range(-10, 80), 60)
        fired: list[tuple[float, float]] = []
        done = asyncio.get_running_loop().create_future()

        def hit(deadline: float) -> Callable[[], None]:
            def callback() -> None:
                fired.append((deadline, timer.now()))
                if len(fired) == len(steps) and not done.done():
                    done.set_result(None)

            return callback

        for i, step in enumerate(steps):
            deadline = origin + step * 1e-4
            schedule = timer.call_at_lazily if i % 2 else timer.call_at
            schedule(deadline, hit(deadline))
        assert timer.pending == len(steps)
        await done
        assert all(ran >= deadline for deadline, ran in fired), "a callback ran early"
        assert [d for d, _ in fired] == sorted(d for d, _ in fired)
        assert timer.pending == 0
        timer.close()

    run(loop_factory, main())


@needs_timerfd
def test_a_lazy_deadline_cancelled_before_its_handover_never_arms_the_timerfd(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        later = timer.call_at(timer.now() + 1.0, lambda: None)
        await asyncio.sleep(0)  # the far deadline armed
        armed = _record_settimes(timer, monkeypatch)
        # A handover 200 ms after the write: a window a loaded VM keeps.
        timer._handover_s, timer.LAZY_WITHIN_S = 0.05, 0.3
        ran: list[bool] = []
        now = timer.now()
        reply_deadline = timer.call_at_lazily(now + 0.25, lambda: ran.append(True), now=now)
        assert reply_deadline._watch is not None and timer.pending == 2
        await asyncio.sleep(0.002)  # the reply came: well before the handover
        reply_deadline.cancel()
        assert reply_deadline.cancelled() and timer.pending == 1
        await asyncio.sleep(0.27)  # past the cancelled deadline
        assert armed == [] and ran == []
        later.cancel()
        timer.close()

    run(asyncio.new_event_loop, main())


@needs_timerfd
def test_a_lazy_deadline_left_to_run_is_armed_for_its_last_stretch_only(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        armed = _record_settimes(timer, monkeypatch)
        # A handover 10 ms from now, 50 ms before the deadline: windows a loaded VM keeps.
        timer._handover_s, timer.LAZY_WITHIN_S = 0.05, 0.2
        fired = asyncio.get_running_loop().create_future()
        handed_over: list[float] = []
        on_handover = timer._on_handover
        timer._on_handover = lambda h: (handed_over.append(timer.now()), on_handover(h))  # type: ignore[method-assign]
        now = timer.now()
        deadline = now + 0.06
        timer.call_at_lazily(deadline, lambda: fired.set_result(timer.now()), now=now)
        await asyncio.sleep(0)
        assert armed == []  # the loop's timer watches it until its handover
        ran = await fired
        assert ran >= deadline
        if handed_over[0] < deadline:
            assert armed == [math.ceil(deadline * 1e9)]  # then the timerfd, at the deadline
        else:  # the loop was held up past the deadline itself: it ran at once, unarmed
            assert armed == []
        timer.close()

    run(asyncio.new_event_loop, main())


@needs_timerfd
def test_a_lazy_deadline_cancelled_after_its_handover_does_not_run() -> None:
    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        timer._handover_s = 0.05  # room to cancel between the handover and the deadline
        ran: list[bool] = []
        now = timer.now()
        handle = timer.call_at_lazily(now + 0.055, lambda: ran.append(True), now=now)
        assert handle._watch is not None
        # The handover as the loop's watch (or a wake-up) makes it, not waited for: a
        # loaded machine can hold the loop past the deadline itself, and the deadline
        # then rightly runs at once (test_a_loop_held_up_past_the_handover_...).
        timer._take_watched(now + 0.01)  # past its handover (5 ms), before the deadline
        assert handle._watch is None and timer.pending == 1
        handle.cancel()
        assert timer.pending == 0
        await asyncio.sleep(0.06)  # past the deadline
        assert ran == [] and handle.cancelled()
        timer.close()

    run(asyncio.new_event_loop, main())


@needs_timerfd
def test_closing_before_the_handover_drops_a_lazy_deadline() -> None:
    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        ran: list[bool] = []
        now = timer.now()
        handle = timer.call_at_lazily(now + 0.005, lambda: ran.append(True), now=now)
        watch = handle._watch
        assert watch is not None
        timer.close()
        assert timer.pending == 0 and handle.cancelled() and watch.cancelled()
        await asyncio.sleep(0.02)  # past the handover and the deadline
        assert ran == []

    run(asyncio.new_event_loop, main())


@pytest.mark.parametrize("loop_factory", LOOPS)
@pytest.mark.parametrize("timer_cls", TIMERS)
def test_where_the_loop_cannot_watch_it_a_lazy_call_is_a_plain_one(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], timer_cls: type[Timer]
) -> None:
    """Only a timerfd timer on asyncio's own loop (whose clock is ``time.monotonic``)
    hands the first part to the loop."""

    async def main() -> None:
        timer = timer_cls()
        now = timer.now()
        watched = timer.call_at_lazily(now + 0.006, lambda: None, now=now)
        on_asyncio = type(asyncio.get_running_loop()).__module__.startswith("asyncio")
        assert (watched._watch is not None) is (timer_cls is TimerfdTimer and on_asyncio)
        # Past the window asyncio's rounding can add a millisecond; within the handover
        # there is nothing to watch: both plain calls.
        window = timer._handover_s + timer.LAZY_WITHIN_S
        far = timer.call_at_lazily(now + window + 0.001, lambda: None, now=now)
        near = timer.call_at_lazily(now + timer._handover_s, lambda: None, now=now)
        assert far._watch is None and near._watch is None
        watched.cancel()
        far.cancel()
        near.cancel()
        timer.close()

    run(loop_factory, main())


@needs_timerfd
def test_behind_an_earlier_deadline_a_lazy_call_is_a_plain_one(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With an earlier deadline pending, the timerfd stays armed for that one: the
    deadline goes straight into the heap, and its cancel re-arms nothing either."""

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        timer.LAZY_WITHIN_S = 0.2  # the reply deadline is one the loop would watch...
        # 150 ms ahead: a loaded VM's loop turn does not reach it.
        tick = timer.call_at(timer.now() + 0.15, lambda: None)
        await asyncio.sleep(0)
        armed = _record_settimes(timer, monkeypatch)
        reply_deadline = timer.call_at_lazily(timer.now() + 0.16, lambda: None)
        assert reply_deadline._watch is None and timer.pending == 2  # ...but for the tick
        reply_deadline.cancel()
        await asyncio.sleep(0)
        assert armed == []
        tick.cancel()
        await asyncio.sleep(0)
        now = timer.now()
        alone = timer.call_at_lazily(now + 0.16, lambda: None, now=now)
        assert alone._watch is not None  # with nothing earlier: watched
        alone.cancel()
        timer.close()

    run(asyncio.new_event_loop, main())


@needs_timerfd
def test_a_loop_held_up_past_the_handover_keeps_deadline_and_scheduling_order() -> None:
    """The loop's timer that should hand a deadline over comes late (the loop was busy):
    the deadline still runs before a later one of the heap, and after an equal one
    scheduled before it, before an equal one scheduled after it."""

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        order: list[str] = []
        done = asyncio.get_running_loop().create_future()
        now = timer.now()
        lazy = timer.call_at_lazily(now + 0.009, lambda: order.append("lazy"))
        assert lazy._watch is not None
        timer.call_at(now + 0.009, lambda: order.append("tie, after"))
        timer.call_at(now + 0.011, lambda: order.append("later"))
        timer.call_at(now + 0.011, lambda: done.set_result(None))
        await asyncio.sleep(0)  # the timerfd armed for the heap's earliest
        time.sleep(0.03)  # the loop held up past every deadline, handover and all
        await done
        assert order == ["lazy", "tie, after", "later"]
        timer.close()

    run(asyncio.new_event_loop, main())


@needs_timerfd
def test_a_deadline_whose_handover_falls_inside_a_wake_up_runs_in_order() -> None:
    """A callback of a wake-up takes long (or the thread is descheduled): a watched
    deadline whose handover fell meanwhile runs before a later one of the same wake-up."""

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        order: list[str] = []
        done = asyncio.get_running_loop().create_future()
        now = timer.now()
        watched = timer.call_at_lazily(now + 0.005, lambda: order.append("watched"), now=now)
        assert watched._watch is not None
        timer.call_at(now + 0.001, lambda: (order.append("slow"), time.sleep(0.008)))
        timer.call_at(now + 0.0055, lambda: order.append("later"))
        timer.call_at(now + 0.0055, lambda: done.set_result(None))
        await done
        assert order == ["slow", "watched", "later"]
        timer.close()

    run(asyncio.new_event_loop, main())


@needs_timerfd
def test_with_a_spin_lead_the_handover_comes_before_the_fd_must_fire(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """In real-time mode the fd fires a spin lead before a precise deadline: the loop
    hands the deadline over that much earlier, so the fd is never armed in the past."""

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0005)
        timer._handover_s += 0.048  # a handover 10 ms from now, as a loaded VM keeps it
        timer.LAZY_WITHIN_S = 0.2
        armings: list[tuple[int, int]] = []
        real = timer._api.set_absolute_ns
        monkeypatch.setattr(
            timer._api,
            "set_absolute_ns",
            lambda fd, ns: (armings.append((ns, time.monotonic_ns())), real(fd, ns)),
        )
        fired = asyncio.get_running_loop().create_future()
        deadline = timer.now() + 0.0605
        handle = timer.call_at_lazily(deadline, lambda: fired.set_result(timer.now()))
        assert handle._watch is not None
        assert await fired >= deadline
        ns, when = armings[0]
        assert ns > when  # armed ahead: its spin starts where it should
        assert ns <= math.ceil(deadline * 1e9)
        timer.close()

    run(asyncio.new_event_loop, main())


def test_a_nan_deadline_is_refused_as_by_call_at() -> None:
    async def main() -> None:
        timer = TimerfdTimer() if timerfd_available() else LoopTimer()
        with pytest.raises(LocalProtocolError, match="deadline"):
            timer.call_at_lazily(float("nan"), lambda: None)
        assert timer.pending == 0
        timer.close()

    run(asyncio.new_event_loop, main())


@needs_timerfd
async def test_requests_answered_in_time_do_not_arm_the_bus_timer(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A status request whose reply comes well before its deadline arms nothing: its
    deadline never reaches the timerfd (two ``timerfd_settime`` a request before)."""
    timer = TimerfdTimer(spin_lead=0.0)
    sim_timer = LoopTimer()  # the simulated devices' replies: not the bus's timerfd
    models = [LAModel(1)]
    sim_start = MemorySim.start(models, timer=sim_timer)  # type: ignore[arg-type]
    # A host margin that puts the handover ~50 ms after each write (the window widened to
    # watch it): the simulated reply, on the loop's timer, comes well before.
    timer.LAZY_WITHIN_S = 0.2
    async with sim_start as sim:
        bus_start = motorbus.Bus(
            sim.transport, families=[motorbus.Family.LA], timer=timer, host_margin=0.05
        )
        async with bus_start as bus:
            la = InspireLA(bus, 1)
            await la.status()
            armed = _record_settimes(timer, monkeypatch)
            answered_in_time = 0
            for _ in range(10):
                await asyncio.sleep(0.003)  # past the 1 ms spacing: no wait for it
                before, asked = len(armed), timer.now()
                await la.status()
                # A loaded machine can hold the loop past a handover (~50 ms after the
                # write): that request's deadline is then rightly armed.  Count the rest.
                if timer.now() - asked < 0.04:
                    answered_in_time += 1
                    assert len(armed) == before, [n / 1e9 for n in armed]
            assert answered_in_time > 0
    timer.close()
    sim_timer.close()
