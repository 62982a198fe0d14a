"""The shutdown helpers themselves (the exit paths end to end: tests/integration/)."""

from __future__ import annotations

import asyncio
import functools
import os
import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from typing import Any

import pytest

from motorbus.runtime import shutdown
from motorbus.runtime.shutdown import deferred_interrupts, install_signal_handlers


def test_ctrl_c_inside_a_safe_stop_is_delivered_after_it() -> None:
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    steps: list[str] = []
    try:
        with pytest.raises(KeyboardInterrupt), deferred_interrupts():
            signal.raise_signal(signal.SIGINT)  # a second Ctrl-C, mid-stop
            steps.append("the stop went on")
            with deferred_interrupts():  # nested stop paths defer as one
                signal.raise_signal(signal.SIGINT)
                steps.append("inner stop done")
            steps.append("outer stop done")
        assert steps == ["the stop went on", "inner stop done", "outer stop done"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


def test_nothing_is_deferred_when_no_signal_comes() -> None:
    with deferred_interrupts():
        pass
    assert shutdown._deferred == []


async def test_the_first_signal_cancels_the_task_and_later_ones_are_only_counted() -> None:
    started = asyncio.Event()

    async def main() -> None:
        handlers = install_signal_handlers((signal.SIGUSR1,))
        started.set()
        try:
            await asyncio.sleep(30)
        finally:
            # The safe stop runs here; more signals must not cut it short.
            os.kill(os.getpid(), signal.SIGUSR1)
            await asyncio.sleep(0.05)
            handlers.uninstall()
            assert handlers.received == [signal.SIGUSR1, signal.SIGUSR1]

    task = asyncio.create_task(main())
    await started.wait()
    os.kill(os.getpid(), signal.SIGUSR1)
    with pytest.raises(asyncio.CancelledError):
        await asyncio.wait_for(task, 5)


def test_motorbus_run_ends_a_signalled_program_with_128_plus_the_signal() -> None:
    async def main() -> None:
        asyncio.get_running_loop().call_later(0.05, os.kill, os.getpid(), signal.SIGHUP)
        await asyncio.sleep(30)

    with pytest.raises(SystemExit) as ended:
        shutdown.run(main())
    assert ended.value.code == 128 + signal.SIGHUP


def test_without_loop_signal_handlers_run_falls_back_to_signal_signal(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Windows' event loops have no add_signal_handler: Ctrl-C must still stop safely."""

    def unsupported(*args: object) -> None:
        raise NotImplementedError

    monkeypatch.setattr(asyncio.AbstractEventLoop, "add_signal_handler", unsupported)
    monkeypatch.setattr(asyncio.SelectorEventLoop, "add_signal_handler", unsupported)
    previous = signal.getsignal(signal.SIGTERM)

    async def main() -> None:
        asyncio.get_running_loop().call_later(0.05, os.kill, os.getpid(), signal.SIGTERM)
        await asyncio.sleep(30)

    with pytest.raises(SystemExit) as ended:
        shutdown.run(main())
    assert ended.value.code == 128 + signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is previous  # the fallback handler is removed


_KEEP: list[object] = []  # async generators asyncio.run's teardown, not the GC, closes


def _signals_in_teardown(times: int) -> Any:
    """A main() that gets Ctrl-C, leaving an async generator that sends ``times`` more
    Ctrl-C as asyncio.run's teardown closes it: after the stop, before run() returns.
    (Not for a KeyboardInterrupt raised there: on CPython 3.11 one raised inside an
    async generator's aclose in the teardown left a later ast.parse failing with "AST
    constructor recursion depth mismatch".)"""

    async def closing() -> AsyncIterator[None]:
        try:
            while True:
                yield
        finally:
            for _ in range(times):
                signal.raise_signal(signal.SIGINT)

    async def main() -> None:
        gen = closing()
        _KEEP.append(gen)
        await gen.__anext__()
        asyncio.get_running_loop().call_later(0.05, os.kill, os.getpid(), signal.SIGINT)
        await asyncio.sleep(30)

    return main()


#: A plain ``asyncio.run`` program whose bus gets Ctrl-C twice before its main task has
#: been given the first one's cancellation (what a loaded machine does to two Ctrl-C a few
#: ms apart); ``asyncio.run``'s handler raised ``KeyboardInterrupt`` for the second at
#: once, into whatever ran, the bus's own stop included.
TWO_CTRL_C_AT_ONCE = """
import asyncio, signal
from motorbus.bus.bus import Bus
from motorbus.protocol.base import Family
from motorbus.transport.memory import memory_pair

def handler_name():
    return type(signal.getsignal(signal.SIGINT)).__name__

async def main():
    host, peer = memory_pair(baudrate=921600)
    try:
        async with Bus(host, families=[Family.LA]):
            print("open:", handler_name(), flush=True)
            ctrl_c = signal.getsignal(signal.SIGINT)
            ctrl_c(signal.SIGINT, None)  # the first: asyncio cancels main
            ctrl_c(signal.SIGINT, None)  # the second, before main has run on
            print("the second was held", flush=True)
            await asyncio.sleep(5)  # the cancellation comes here
    finally:
        print("closed:", handler_name(), flush=True)

try:
    asyncio.run(main())
except KeyboardInterrupt:
    print("KeyboardInterrupt", flush=True)
"""


def test_a_second_ctrl_c_before_main_runs_on_is_held_while_the_bus_closes() -> None:
    out = subprocess.run(
        [sys.executable, "-c", TWO_CTRL_C_AT_ONCE], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:-1] == [
        "open: _SigintGuard",  # motorbus's guard in front of asyncio's handler
        "the second was held",
        "closed: partial",  # asyncio's own handler back once the bus closed
        "KeyboardInterrupt",  # the program ends as Ctrl-C ends an asyncio.run program
    ], out.stderr
    assert "SIGINT again: still stopping the motion safely" in out.stderr


#: The last bus closes inside an outer ``deferred_interrupts`` block (a manager's close):
#: the guard can only be given back when the block ends.
CLOSED_INSIDE_A_DEFERRAL = """
import asyncio, signal
from motorbus.bus.bus import Bus
from motorbus.protocol.base import Family
from motorbus.runtime.shutdown import deferred_interrupts
from motorbus.transport.memory import memory_pair

def handler_name():
    return type(signal.getsignal(signal.SIGINT)).__name__

async def main():
    host, peer = memory_pair(baudrate=921600)
    bus = Bus(host, families=[Family.LA])
    await bus.open()
    print("open:", handler_name())
    with deferred_interrupts():
        await bus.close()
        print("inside:", handler_name())
    print("after:", handler_name())

asyncio.run(main())
"""


def test_the_ctrl_c_guard_is_given_back_after_a_deferral_the_last_bus_closed_in() -> None:
    # Left in place with nothing behind it, the guard broke every later Ctrl-C of the
    # process (a TypeError in place of KeyboardInterrupt: seen in a test worker).
    out = subprocess.run(
        [sys.executable, "-c", CLOSED_INSIDE_A_DEFERRAL], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:-1] == [
        "open: _SigintGuard",
        "inside: function",  # the deferral's recorder
        "after: partial",  # asyncio.run's own handler again
    ], out.stderr


def test_the_guard_holds_repeats_only_while_its_asyncio_run_runs() -> None:
    loop = asyncio.new_event_loop()
    try:
        for done, passed in ((False, [2]), (True, [2, 2])):
            main = loop.create_future()
            if done:
                main.set_result(None)
            calls: list[int] = []

            def handler(signum: int, frame: Any, main_task: Any, calls: list[int]) -> None:
                calls.append(signum)

            guard = shutdown._SigintGuard(functools.partial(handler, main_task=main, calls=calls))
            guard(signal.SIGINT, None)
            guard(signal.SIGINT, None)
            assert calls == passed, done
    finally:
        loop.close()


def test_a_repeated_ctrl_c_after_the_stop_still_exits_with_the_first_signals_status() -> None:
    """Once the stop is done, asyncio.run still tears down (cancels what is left, closes
    async generators and its executor).  A second Ctrl-C there used to escape as a
    KeyboardInterrupt traceback (a stress run of tests/integration/test_exit_paths.py);
    it waits, as one during the stop does."""
    previous = signal.getsignal(signal.SIGINT)
    try:
        _exits_with_the_first_signals_status(_signals_in_teardown(1))
    finally:
        _KEEP.clear()
    assert signal.getsignal(signal.SIGINT) is previous  # given back


def _exits_with_the_first_signals_status(main: Any) -> None:
    """``shutdown.run(main)`` ends with ``SystemExit(128 + SIGINT)``, not a
    KeyboardInterrupt and not a return."""
    try:
        shutdown.run(main)
    except SystemExit as ended:
        assert ended.code == 128 + signal.SIGINT
    except KeyboardInterrupt:
        pytest.fail("a Ctrl-C after the stop escaped run() as KeyboardInterrupt")
    else:
        pytest.fail("run() returned after a signal")


def test_a_ctrl_c_as_the_loop_gives_sigint_back_still_exits_with_the_first_status(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Between the loop's close giving SIGINT back (Python's default, which raises
    KeyboardInterrupt) and run() restoring the dispositions it found, a repeated Ctrl-C
    raised a KeyboardInterrupt out of run() (seen once under load, as a traceback and
    no "stopped safely"): the stop was done, so it exits with the first signal's
    status."""
    probe = asyncio.new_event_loop()
    loop_class = type(probe)
    probe.close()
    close = loop_class.close

    def close_then_ctrl_c(self: asyncio.AbstractEventLoop) -> None:
        close(self)
        raise KeyboardInterrupt  # what default_int_handler does in that instant

    monkeypatch.setattr(loop_class, "close", close_then_ctrl_c)

    async def main() -> None:
        asyncio.get_running_loop().call_later(0.05, os.kill, os.getpid(), signal.SIGINT)
        await asyncio.sleep(30)

    previous = signal.getsignal(signal.SIGINT)
    try:
        _exits_with_the_first_signals_status(main())
    finally:
        signal.signal(signal.SIGINT, previous)


#: A program stopped by a SIGTERM, whose repeats ``{probe}`` (code that runs first) sends
#: at the instant a test chooses.
_REPEATED_SIGTERM = """
import asyncio, os, signal
from motorbus.runtime import shutdown
{probe}
async def main():
    asyncio.get_running_loop().call_later(0.05, os.kill, os.getpid(), signal.SIGTERM)
    await asyncio.sleep(30)

shutdown.run(main())
"""


def _stopped_by_sigterm_with_repeats(probe: str) -> str:
    """Run ``_REPEATED_SIGTERM`` with ``probe``; it exited 143 with a repeat absorbed.
    Returns its standard error."""
    program = _REPEATED_SIGTERM.format(probe=probe)
    done = subprocess.run([sys.executable, "-c", program], capture_output=True, text=True,
                          timeout=60)  # fmt: skip
    assert done.returncode == 128 + signal.SIGTERM, (done.returncode, done.stderr[-2000:])
    assert "the motion is stopped and the program is closing" in done.stderr
    return done.stderr


def test_a_sigterm_as_the_stop_hands_the_signals_over_does_not_kill_the_program() -> None:
    """The loop's handlers used to be removed (the default disposition: death) before
    the late ones were set: a repeated SIGTERM in that instant killed a program whose
    stop was done, before it could exit 143 or print its report (seen once on a loaded
    run of tests/integration/test_exit_paths.py).  Now the late handlers replace the
    loop's with no instant in between."""
    _stopped_by_sigterm_with_repeats(
        """
class Probe(shutdown._LateRepeats):
    def __init__(self, before):
        os.kill(os.getpid(), signal.SIGTERM)  # as the handover starts
        super().__init__(before)
        os.kill(os.getpid(), signal.SIGTERM)  # and as it ends: absorbed

shutdown._LateRepeats = Probe
"""
    )


def test_a_sigterm_as_the_loop_closes_does_not_kill_the_program() -> None:
    """asyncio's Unix loop gives every signal it has a record of back to its default
    disposition when it closes: SIGTERM's kills.  A repeated SIGTERM just after asyncio.run
    closed the loop killed a program whose stop was done (a third Ctrl-C there printed a
    traceback, seen with six test workers).  The loop no longer holds records of the
    signals once the late handlers have them."""
    err = _stopped_by_sigterm_with_repeats(
        """
probe = asyncio.new_event_loop()
loop_class = type(probe)
probe.close()
close = loop_class.close

def close_then_sigterm(self):
    close(self)
    os.kill(os.getpid(), signal.SIGTERM)

loop_class.close = close_then_sigterm
"""
    )
    assert "wakeup fd" not in err and "Traceback" not in err, err


def test_a_third_ctrl_c_still_interrupts_a_teardown() -> None:
    """A teardown that hangs must not trap the user: the repeat after the absorbed one
    goes to the disposition run() found, and everything is given back."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        late = shutdown._LateRepeats({signal.SIGINT: signal.default_int_handler})
        signal.raise_signal(signal.SIGINT)  # absorbed: the program is already closing
        assert late.absorbed == [signal.SIGINT]
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)
            for _ in range(1000):  # the restored handler runs at the next check
                pass
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, previous)


class _Interrupt(BaseException):
    """Not an Exception: what a close might raise that is not an error of its own."""


async def test_stop_everything_closes_the_buses_even_after_a_manager_raised() -> None:
    closed: list[str] = []

    class Manager:
        async def close(self) -> None:
            closed.append("manager")
            raise _Interrupt

    class Bus:
        async def close(self) -> None:
            closed.append("bus")
            shutdown.unregister_bus(self)

    manager, bus = Manager(), Bus()
    shutdown.register_manager(manager)
    shutdown.register_bus(bus)
    try:
        with pytest.raises(_Interrupt):
            await shutdown.stop_everything()
    finally:
        shutdown.unregister_manager(manager)
        shutdown.unregister_bus(bus)
    assert closed == ["manager", "bus"]  # the bus's close ran before _Interrupt came out
