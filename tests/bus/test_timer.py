"""Timers: never early, in deadline order, cancellable, leak-free, under both loops.

Behaviour only: lateness is measured by benchmarks/bench_timer.py, never asserted here.
Each test runs its own loop (default asyncio and uvloop) through ``asyncio.Runner``.
"""

from __future__ import annotations

import asyncio
import gc
import random
import sys
import time
import weakref
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from motorbus.bus.timer import (
    LoopTimer,
    Timer,
    TimerfdTimer,
    default_timer,
    timerfd_available,
)
from motorbus.errors import LocalProtocolError
from tests.waiting import eventually

WAIT_S = 5.0  # generous bound for callbacks due within a few milliseconds

LOOPS: list[Any] = [pytest.param(asyncio.new_event_loop, id="asyncio")]
try:
    import uvloop

    LOOPS.append(pytest.param(uvloop.new_event_loop, id="uvloop"))
except ImportError:  # pragma: no cover - uvloop is in the test extras
    pass

TIMERS: list[Any] = [pytest.param(LoopTimer, id="loop")]
if timerfd_available():
    TIMERS.append(pytest.param(TimerfdTimer, id="timerfd"))


def run(loop_factory: Callable[[], asyncio.AbstractEventLoop], coro: Awaitable[None]) -> None:
    with asyncio.Runner(loop_factory=loop_factory) as runner:
        runner.run(asyncio.wait_for(coro, WAIT_S))


@pytest.mark.parametrize("loop_factory", LOOPS)
@pytest.mark.parametrize("timer_cls", TIMERS)
def test_callbacks_never_fire_early_and_run_in_deadline_order(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], timer_cls: type[Timer]
) -> None:
    async def main() -> None:
        timer = timer_cls()
        rng = random.Random(1)
        origin = timer.now()
        # Deadlines from 1 ms in the past to 6 ms ahead, many sharing a value (ties).
        deadlines = [origin + rng.randrange(-10, 60) * 1e-4 for _ in range(300)]
        fired: list[tuple[int, float]] = []
        done = asyncio.get_running_loop().create_future()

        def make(i: int) -> Callable[[], None]:
            def cb() -> None:
                fired.append((i, timer.now()))
                if len(fired) == len(deadlines):
                    done.set_result(None)

            return cb

        for i, d in enumerate(deadlines):
            timer.call_at(d, make(i))
        assert fired == []  # never synchronously, even for past deadlines
        await done
        late = [(i, at - deadlines[i]) for i, at in fired if at < deadlines[i]]
        assert late == []
        order = [i for i, _ in fired]
        assert order == sorted(range(len(deadlines)), key=lambda i: (deadlines[i], i))
        assert timer.pending == 0
        timer.close()

    run(loop_factory, main())


@pytest.mark.parametrize("precise", [True, False], ids=["precise", "not-precise"])
@pytest.mark.parametrize("loop_factory", LOOPS)
@pytest.mark.parametrize("timer_cls", TIMERS)
def test_sleep_until_never_returns_early(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], timer_cls: type[Timer], precise: bool
) -> None:
    async def main() -> None:
        timer = timer_cls()
        origin = timer.now()
        for k in range(1, 101):
            deadline = origin + k * 2e-4  # 200 µs periodic absolute deadlines
            await timer.sleep_until(deadline, precise=precise)
            assert timer.now() >= deadline
        await timer.sleep_until(origin)  # long past: returns after yielding once
        assert timer.pending == 0
        timer.close()

    run(loop_factory, main())


@pytest.mark.parametrize("loop_factory", LOOPS)
@pytest.mark.parametrize("timer_cls", TIMERS)
def test_cancelled_callbacks_never_run_and_do_not_leak(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], timer_cls: type[Timer]
) -> None:
    async def main() -> None:
        timer = timer_cls()
        ran: list[int] = []
        now = timer.now()
        handles = [
            timer.call_at(now + 1e-3 + i * 1e-5, lambda i=i: ran.append(i)) for i in range(100)
        ]
        for h in handles[::2]:
            h.cancel()
            h.cancel()  # idempotent
        assert timer.pending == 50
        assert all(h.cancelled() for h in handles[::2])
        last = asyncio.get_running_loop().create_future()
        timer.call_at(now + 3e-3, lambda: last.set_result(None))
        await last
        assert ran == list(range(1, 100, 2))
        assert timer.pending == 0
        assert len(timer._heap) == 0  # cancelled entries were dropped, not kept
        handles[1].cancel()  # after it ran: harmless
        assert not handles[1].cancelled()
        # A far-future callback that is cancelled leaves nothing behind.
        far = timer.call_at(timer.now() + 3600, lambda: ran.append(-1))
        far.cancel()
        assert timer.pending == 0 and len(timer._heap) == 0
        timer.close()

    run(loop_factory, main())


@pytest.mark.parametrize("loop_factory", LOOPS)
@pytest.mark.parametrize("timer_cls", TIMERS)
def test_cancelling_sleep_until_cleans_up(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], timer_cls: type[Timer]
) -> None:
    async def main() -> None:
        timer = timer_cls()
        sleepers = [asyncio.create_task(timer.sleep_until(timer.now() + 60)) for _ in range(20)]
        await asyncio.sleep(0)
        assert timer.pending == 20
        for task in sleepers:
            task.cancel()
        results = await asyncio.gather(*sleepers, return_exceptions=True)
        assert all(isinstance(r, asyncio.CancelledError) for r in results)
        assert timer.pending == 0
        assert len(timer._heap) == 0
        # wait_for around sleep_until: the timeout cancels the sleep and cleans up too.
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(timer.sleep_until(timer.now() + 60), 0.001)
        assert timer.pending == 0
        timer.close()

    run(loop_factory, main())


@pytest.mark.parametrize("loop_factory", LOOPS)
@pytest.mark.parametrize("timer_cls", TIMERS)
def test_callbacks_may_schedule_and_failures_reach_the_exception_handler(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], timer_cls: type[Timer]
) -> None:
    async def main() -> None:
        timer = timer_cls()
        loop = asyncio.get_running_loop()
        errors: list[BaseException] = []
        loop.set_exception_handler(lambda _loop, ctx: errors.append(ctx["exception"]))
        chain: list[int] = []
        done = loop.create_future()

        def step() -> None:
            chain.append(len(chain))
            if len(chain) < 5:
                timer.call_at(timer.now() + 1e-4, step)
            else:
                done.set_result(None)

        def boom() -> None:
            raise RuntimeError("callback failed")

        timer.call_at(timer.now(), boom)
        timer.call_at(timer.now() + 1e-4, step)
        await done
        assert chain == [0, 1, 2, 3, 4]
        assert [str(e) for e in errors] == ["callback failed"]
        timer.close()

    run(loop_factory, main())


@pytest.mark.parametrize("loop_factory", LOOPS)
@pytest.mark.parametrize("timer_cls", TIMERS)
def test_close_drops_pending_callbacks_and_refuses_new_ones(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], timer_cls: type[Timer]
) -> None:
    async def main() -> None:
        timer = timer_cls()
        handle = timer.call_at(timer.now() + 60, lambda: None)
        timer.close()
        timer.close()
        assert handle.cancelled()
        assert timer.pending == 0
        with pytest.raises(RuntimeError, match="closed"):
            timer.call_at(timer.now(), lambda: None)

    run(loop_factory, main())


@pytest.mark.parametrize("loop_factory", LOOPS)
def test_default_timer_is_one_per_loop(
    loop_factory: Callable[[], asyncio.AbstractEventLoop],
) -> None:
    seen: list[Timer] = []

    async def main() -> None:
        timer = default_timer()
        assert default_timer() is timer
        assert default_timer(asyncio.get_running_loop()) is timer
        expected = "timerfd" if sys.platform.startswith("linux") else "loop"
        assert timer.name == expected
        seen.append(timer)
        timer.close()
        assert default_timer() is not timer  # a closed timer is replaced

    run(loop_factory, main())
    run(loop_factory, main())
    assert seen[0] is not seen[1]


def test_timerfd_is_released_with_its_loop() -> None:
    if not timerfd_available():
        pytest.skip("no timerfd on this platform")
    finalizers: list[weakref.finalize[Any, Any]] = []

    async def main() -> None:
        timer = default_timer()
        assert isinstance(timer, TimerfdTimer)
        await timer.sleep_until(timer.now() + 1e-4)
        finalizers.append(timer._finalizer)

    run(asyncio.new_event_loop, main())
    gc.collect()
    # The per-loop cache held the timer weakly through its loop: both are gone and the
    # fd was closed by the finalizer.
    assert not finalizers[0].alive


@pytest.mark.parametrize("loop_factory", LOOPS)
def test_timerfd_tells_the_wake_observer_each_wakeup_and_its_spin(
    loop_factory: Callable[[], asyncio.AbstractEventLoop],
) -> None:
    if not timerfd_available():
        pytest.skip("no timerfd on this platform")
    seen: list[tuple[float, float, float]] = []
    fired: list[float] = []

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=300e-6)
        timer.wake_observer = lambda armed, woke, spun: seen.append((armed, woke, spun))
        deadline = timer.now() + 2e-3
        done = asyncio.get_running_loop().create_future()
        timer.call_at(deadline, lambda: (fired.append(timer.now()), done.set_result(None)))
        await done
        assert len(seen) >= 1
        armed, woke, spun = seen[-1]
        # Armed before the deadline (the spin lead), woken after the armed time; the
        # spin ends at the deadline unless the wake-up itself was late.
        assert 0 < armed <= deadline <= fired[0]
        assert armed <= woke <= spun
        assert spun >= deadline or woke >= deadline
        assert not hasattr(timer, "spin_seconds")  # counted from outside (issue 40)
        timer.close()

    run(loop_factory, main())


def test_timerfd_lead_follows_the_recent_wake_ups() -> None:
    """The spin lead is twice the recent worst wake-up lateness, decaying, within
    [SPIN_LEAD_MIN_S, spin_lead]; with spinning off it is 0."""
    if not timerfd_available():
        pytest.skip("no timerfd on this platform")

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=500e-6)
        assert timer.lead == 500e-6  # cautious before anything was measured
        timer._wake_late = 100e-6
        assert timer.lead == pytest.approx(200e-6)
        timer._wake_late = 10e-6  # prompt wake-ups: the least lead
        assert timer.lead == TimerfdTimer.SPIN_LEAD_MIN_S
        timer._wake_late = 2e-3  # very late ones: never more than spin_lead
        assert timer.lead == 500e-6
        off = TimerfdTimer(spin_lead=0.0)
        assert off.lead == 0.0
        timer.close()
        off.close()

    run(asyncio.new_event_loop, main())


def _wake_up(timer: TimerfdTimer, late: float, *, precise: bool = True, busy: bool = False) -> None:
    """Run the timerfd's expiry as if it had been armed exactly ``late`` ago (its clock
    held still meanwhile: a busy test machine adds no lateness of its own).  The clock is
    read past the timer: its own ``now()`` notes the loop as busy (``_seen``).  ``busy``:
    the loop ran motorbus's work halfway between the arming and the wake-up."""
    now = time.monotonic()
    if busy:
        timer._seen = now - late / 2
    timer._armed_ns = round((now - late) * 1e9)
    timer._armed_precise = precise
    timer.now = lambda: now  # type: ignore[method-assign]
    try:
        timer._on_expiry()
    finally:
        del timer.now


def _settled_timer() -> TimerfdTimer:
    """A timer (500 us longest lead) after 200 prompt wake-ups: at its shortest lead."""
    timer = TimerfdTimer(spin_lead=500e-6)
    for _ in range(200):
        _wake_up(timer, 0.0)
    assert timer.lead == TimerfdTimer.SPIN_LEAD_MIN_S
    return timer


def test_the_lead_follows_the_wake_ups_of_precise_deadlines_only() -> None:
    """A plain deadline (a task's ``sleep_until(precise=False)``, a frame's ``start_by``)
    wakes up wherever the loop is busy: its lateness says nothing of what a precise
    deadline needs, and must not keep the lead (and the spin) up."""
    if not timerfd_available():
        pytest.skip("no timerfd on this platform")

    async def main() -> None:
        timer = _settled_timer()
        for _ in range(50):
            _wake_up(timer, 200e-6, precise=False)
        assert timer.lead == TimerfdTimer.SPIN_LEAD_MIN_S
        _wake_up(timer, 200e-6)  # a precise one that late does raise it
        assert timer.lead == pytest.approx(400e-6)
        timer.close()

    run(asyncio.new_event_loop, main())


def test_a_wake_up_the_loop_may_have_held_up_does_not_move_the_lead() -> None:
    """The loop ran motorbus's work after the fd was armed (another bus's reply, a
    stream's task: they read the timer's clock), so the wake-up may have waited for that
    work: its lateness is the loop's, not the kernel's, and it is no sample of what the
    lead is for.  Late, it does not raise the lead; prompt, it does not lower it (a bus
    waiting out its spacing handles the reply just after the arming, and the next,
    idle wake-up still needs the lead).  Wake-ups with the loop idle since the arming
    move it as before."""
    if not timerfd_available():
        pytest.skip("no timerfd on this platform")

    async def main() -> None:
        timer = _settled_timer()
        for _ in range(20):
            _wake_up(timer, 300e-6, busy=True)
        assert timer.lead == TimerfdTimer.SPIN_LEAD_MIN_S
        timer._seen = time.monotonic() - 1.0  # idle since long before the arming
        _wake_up(timer, 200e-6)
        assert timer.lead == pytest.approx(400e-6)
        for _ in range(100):
            _wake_up(timer, 10e-6, busy=True)
        assert timer.lead == pytest.approx(400e-6)
        timer._seen = 0.0
        for _ in range(20):  # idle and prompt: the lead comes down
            _wake_up(timer, 0.0)
        assert timer.lead < 0.7 * 400e-6
        timer.close()

    run(asyncio.new_event_loop, main())


def test_the_timers_clock_notes_that_the_loop_was_busy() -> None:
    """Every ``now()`` of a timerfd timer is a moment the loop ran motorbus's work."""
    if not timerfd_available():
        pytest.skip("no timerfd on this platform")

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=500e-6)
        before = timer._seen
        t = timer.now()
        assert timer._seen == t > before
        timer.close()

    run(asyncio.new_event_loop, main())


def test_one_very_late_wake_up_raises_the_lead_once_not_for_hundreds_of_wake_ups() -> None:
    """A wake-up far later than any lead covers (the loop was busy) counts as no more
    than half the longest lead: the next prompt wake-ups bring the lead down at once,
    where an unclipped 30 ms sample held it at its maximum for ~250 wake-ups."""
    if not timerfd_available():
        pytest.skip("no timerfd on this platform")

    async def main() -> None:
        timer = _settled_timer()
        _wake_up(timer, 30e-3)
        assert timer.lead == 500e-6  # cautious after the outlier ...
        for _ in range(20):
            _wake_up(timer, 0.0)
        assert timer.lead < 0.7 * 500e-6  # ... but only briefly
        timer.close()

    run(asyncio.new_event_loop, main())


@pytest.mark.parametrize("loop_factory", LOOPS)
def test_cancelling_the_earliest_callback_rearms_instead_of_waking_for_nothing(
    loop_factory: Callable[[], asyncio.AbstractEventLoop],
) -> None:
    """A reply deadline cancelled by its reply must not leave the timerfd armed for it:
    that wake-up would find nothing to do (and costs far more than re-arming)."""
    if not timerfd_available():
        pytest.skip("no timerfd on this platform")

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        woken: list[float] = []
        timer.wake_observer = lambda armed, woke, spun: woken.append(woke)
        later = timer.call_at(timer.now() + 1.0, lambda: None)
        soon = timer.call_at(timer.now() + 0.002, lambda: None)
        soon.cancel()
        await asyncio.sleep(0.02)  # well past the cancelled deadline
        assert woken == []
        assert timer.pending == 1
        later.cancel()
        timer.close()

    run(loop_factory, main())


def _record_settimes(timer: TimerfdTimer, monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The absolute times (ns) ``timer`` arms its timerfd for from now on, in a list."""
    armed: list[int] = []
    real = timer._api.set_absolute_ns
    monkeypatch.setattr(
        timer._api, "set_absolute_ns", lambda fd, ns: (armed.append(ns), real(fd, ns))
    )
    return armed


@pytest.mark.parametrize("loop_factory", LOOPS)
def test_a_hold_rearms_once_at_its_release_and_callbacks_stay_on_time(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Deadlines scheduled and cancelled inside ``hold_arming`` (a reply that frees the
    bus and schedules the next write) re-arm the timerfd once, at the release, for the
    earliest deadline then; callbacks scheduled inside callbacks likewise.  Nothing runs
    early or is lost, and a cancelled deadline does not wake the loop."""
    if not timerfd_available():
        pytest.skip("no timerfd on this platform")

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        armed = _record_settimes(timer, monkeypatch)
        fired: list[tuple[str, float, float]] = []
        done = asyncio.get_running_loop().create_future()

        def fire(name: str, deadline: float) -> Callable[[], None]:
            def callback() -> None:
                fired.append((name, deadline, timer.now()))
                if name == "last" and not done.done():
                    done.set_result(None)

            return callback

        now = timer.now()
        timer.hold_arming()
        dropped = timer.call_at(now + 0.001, fire("dropped", now + 0.001))
        first = now + 0.004
        timer.call_at(first, fire("first", first))
        timer.call_at(now + 0.002, fire("second", now + 0.002))
        dropped.cancel()
        assert armed == []  # nothing armed while held
        timer.release_arming()
        assert armed == []  # ... nor before the loop's current turn is over
        await asyncio.sleep(0)
        assert len(armed) == 1  # one re-arm, for the earliest deadline left
        assert armed[0] / 1e9 == pytest.approx(now + 0.002, abs=1e-6)

        # Inside a callback: what it schedules and cancels re-arms once, after it.
        def chain() -> None:
            t = timer.now()
            timer.call_at(t + 0.003, fire("last", t + 0.003))
            timer.call_at(t + 0.001, fire("gone", t + 0.001)).cancel()

        timer.call_at(now + 0.005, chain)
        await done
        assert [name for name, _, _ in fired] == ["second", "first", "last"]
        assert all(ran >= deadline for _, deadline, ran in fired)
        timer.close()

    run(loop_factory, main())


@pytest.mark.parametrize("loop_factory", LOOPS)
def test_one_loop_turn_re_arms_the_timerfd_once_for_all_its_changes(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Deadlines scheduled and cancelled by the callbacks of one loop turn (a timer
    wake-up that resolves a task's sleep, the task that then sends a request and arms its
    reply deadline) re-arm the timerfd once, after them: a re-arm for a deadline near
    enough to reprogram the CPU's timer costs a VM tens of µs (bench_pieces.py)."""
    if not timerfd_available():
        pytest.skip("no timerfd on this platform")

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        armed = _record_settimes(timer, monkeypatch)
        loop = asyncio.get_running_loop()
        now = timer.now()
        far = timer.call_at(now + 1.0, lambda: None)
        await asyncio.sleep(0)
        assert len(armed) == 1  # armed for the only deadline, one turn later
        ran: list[float] = []
        done = loop.create_future()

        def turn() -> None:  # three changes of the earliest deadline in one callback ...
            t = timer.now()
            timer.call_at(t + 0.001, lambda: None).cancel()
            timer.call_at(t + 0.004, lambda: None)
            timer.call_at(t + 0.002, lambda: (ran.append(timer.now()), done.set_result(t)))

        def same_turn() -> None:  # ... and one more from another callback of that turn
            timer.call_at(timer.now() + 0.003, lambda: None)

        loop.call_soon(turn)
        loop.call_soon(same_turn)
        await asyncio.sleep(0)
        await asyncio.sleep(0)
        assert len(armed) == 2  # one re-arm for the whole turn ...
        asked = await done
        assert armed[1] / 1e9 == pytest.approx(asked + 0.002, abs=1e-6)  # ... at its earliest
        assert ran[0] >= asked + 0.002  # never early
        far.cancel()
        timer.close()

    run(loop_factory, main())


@pytest.mark.skipif(not timerfd_available(), reason="needs Linux timerfd")
@pytest.mark.parametrize("loop_factory", LOOPS)
def test_a_wake_up_that_leaves_nothing_queued_re_arms_before_it_returns(
    loop_factory: Callable[[], asyncio.AbstractEventLoop], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A stream's tick callback arms the next tick and leaves nothing else to run: the
    timerfd is re-armed before the wake-up returns, without a loop turn of its own (an
    epoll_wait a tick, issue 40).  A wake-up whose callbacks queued work (a task to
    resume) re-arms after that work, once, as before."""

    async def main() -> None:
        timer = TimerfdTimer(spin_lead=0.0)
        loop = asyncio.get_running_loop()
        armed = _record_settimes(timer, monkeypatch)
        real_wake = timer._wake
        #: For each wake-up: the loop's queue after it, a re-arm queued, arms during it.
        wakes: list[tuple[int, bool, int]] = []

        def wake(now: float | None = None) -> None:
            before = len(armed)
            real_wake(now)
            ready = len(timer._ready) if timer._ready is not None else -1
            wakes.append((ready, timer._flush_queued, len(armed) - before))

        monkeypatch.setattr(timer, "_wake", wake)
        ticks: list[float] = []

        def tick(queue_work: bool) -> None:
            ticks.append(timer.now())
            if len(ticks) % 5:
                timer.call_at(timer.now() + 0.005, lambda: tick(queue_work))
            if queue_work:
                loop.call_soon(lambda: None)

        for queue_work in (False, True):
            wakes.clear()
            first = len(ticks)
            timer.call_at(timer.now() + 0.005, lambda q=queue_work: tick(q))  # type: ignore[misc]
            await eventually(lambda f=first: len(ticks) >= f + 5, "five ticks", poll=0.1)  # type: ignore[misc]
            if timer._ready is None:  # another loop: always the queued re-arm
                assert all(queued for _, queued, _ in wakes), wakes
            elif not queue_work:
                clean = [w for w in wakes if w[0] == 0]  # (a poll of eventually may join)
                assert len(clean) >= 3, wakes
                assert all(not queued and arms == 1 for _, queued, arms in clean[:-1]), wakes
            else:
                assert all(queued and arms == 0 for _, queued, arms in wakes[:-1]), wakes
        timer.close()

    run(loop_factory, main())


@pytest.mark.skipif(not timerfd_available(), reason="needs Linux timerfd")
async def test_the_timerfd_timer_spins_only_where_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 40: no spin by default; real-time mode or MOTORBUS_TIMER_SPIN_US asks for it."""
    from motorbus.runtime import realtime

    monkeypatch.delenv("MOTORBUS_TIMER_SPIN_US", raising=False)
    monkeypatch.delenv(realtime.ENV_VAR, raising=False)
    monkeypatch.setattr(realtime._process, "requested", None)
    monkeypatch.setattr(realtime._process, "applied", None)
    monkeypatch.setattr(realtime._gc, "active", False)
    timers = []
    try:
        plain = TimerfdTimer()
        timers.append(plain)
        assert plain.lead == 0.0
        spins: list[float] = []
        plain.wake_observer = lambda armed, woke, spun: spins.append(spun - woke)
        deadline = plain.now() + 0.002
        await plain.sleep_until(deadline)
        assert spins and all(s == 0.0 for s in spins)
        monkeypatch.setenv(realtime.ENV_VAR, "1")  # asked for: the next timer spins
        asked = TimerfdTimer()
        timers.append(asked)
        assert asked.lead >= TimerfdTimer.SPIN_LEAD_MIN_S
        monkeypatch.setenv("MOTORBUS_TIMER_SPIN_US", "0")  # ... unless told not to
        off = TimerfdTimer()
        timers.append(off)
        assert off.lead == 0.0
    finally:
        for t in timers:
            t.close()


async def test_a_nan_deadline_is_refused_and_the_timer_goes_on() -> None:
    # A NaN deadline sat in the heap, where no comparison orders it, and failed when the
    # timer armed for it: nothing after it ran.
    timer = default_timer()
    with pytest.raises(LocalProtocolError, match="deadline must be a time"):
        timer.call_at(float("nan"), lambda: None)
    with pytest.raises(LocalProtocolError, match="deadline must be a time"):
        await timer.sleep_until(float("nan"))
    ran: list[bool] = []
    timer.call_at(timer.now() + 0.001, lambda: ran.append(True))
    await eventually(lambda: ran == [True], "the next deadline's callback")
