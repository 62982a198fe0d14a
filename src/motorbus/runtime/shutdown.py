"""One shutdown path for every ending: motion stops before the program does.

However a program ends - it returns, raises, is cancelled, gets Ctrl-C once, twice or
three times, or SIGTERM (systemd, ``docker stop``, ``timeout``) or SIGHUP - every open
bus is closed the same way: the streams on it stop first, applying their safe action
(pause or e-stop: nothing of a stream is written after that), a ``BusManager`` brings
every configured device to its safe state, every device still leased (anything that
was moved, ``motorbus.bus.leases``) gets its safe action unless its owner let it go with
``hold``, and only then do the ports close.  A program killed outright (SIGKILL, the
OOM killer) runs none of this: ``motorbus.run(main(), guard=True)`` starts a guard
process (``motorbus.runtime.guard``, Linux) that then sends the leased devices' safe action.

* ``motorbus.run(main())`` is the one-line way in: ``asyncio.run`` with handlers for
  SIGINT, SIGTERM and SIGHUP.  The first signal cancels ``main`` (its ``async with``
  blocks run their safe stops); further signals during the stop are logged and
  ignored, because the stop takes milliseconds and must finish; whatever is still open
  afterwards is closed safely; the program then exits with status 128 + the signal
  number (130 for Ctrl-C, 143 for SIGTERM).  A repeat that comes after the stop, while
  ``asyncio.run`` still tears down, is absorbed as well (one more after that goes to the
  signal's usual disposition, for a teardown that hangs).
* ``install_signal_handlers()`` does the same inside a loop you run yourself.
* Without either, motorbus still protects the ways a plain ``asyncio.run`` program
  would lose its safe stop: while a bus is open, SIGTERM and SIGHUP (if the program has
  not set handlers of its own) close every open bus safely and then end the process as
  the signal would have (status 143 / 129); a second Ctrl-C, which ``asyncio.run``
  raises as ``KeyboardInterrupt`` into whatever runs, is logged and dropped while the
  buses close (the first already ends the program; one more than
  ``STOP_EVERYTHING_TIMEOUT_S`` after it goes through, for a program that ignored the
  cancellation); and the stop paths defer Ctrl-C (``deferred_interrupts``), so one
  that comes during a stop cannot cut it short - it is delivered when the stop is done.

Set ``MOTORBUS_SIGNALS=0`` to keep motorbus from touching signal dispositions at all.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import sys
import threading
import time
import weakref
from collections.abc import Awaitable, Callable, Coroutine, Iterator
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from motorbus.bus.lease_shell import together

if TYPE_CHECKING:
    from types import ModuleType

__all__ = [
    "STOP_SIGNALS",
    "SignalHandlers",
    "deferred_interrupts",
    "install_signal_handlers",
    "run",
    "stop_everything",
    "together",
]

log = logging.getLogger("motorbus.shutdown")

T = TypeVar("T")

#: The signals that end a program and must stop the motion first (those this platform
#: has: Windows has no SIGHUP).
STOP_SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)
#: Signals motorbus handles by itself while a bus is open, if nobody else does.
_AUTO_SIGNALS: tuple[signal.Signals, ...] = tuple(s for s in STOP_SIGNALS if s != signal.SIGINT)
#: Longest the closing of everything may take after a signal (each bus bounds its own
#: safe stop much lower; this is only a backstop).
STOP_EVERYTHING_TIMEOUT_S = 10.0


class _Closable(Protocol):
    async def close(self) -> None: ...


# Open resources and the loop each runs on, in the order they must be closed: managers
# (they stop their devices and close their buses), then any bus still open (its streams
# stop first).
_managers: weakref.WeakKeyDictionary[Any, asyncio.AbstractEventLoop] = weakref.WeakKeyDictionary()
_buses: weakref.WeakKeyDictionary[Any, asyncio.AbstractEventLoop] = weakref.WeakKeyDictionary()


def _enabled() -> bool:
    return os.environ.get("MOTORBUS_SIGNALS", "1").strip() not in ("0", "off", "no", "false")


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


async def stop_everything() -> None:
    """Close every open ``BusManager`` and ``Bus`` of the running loop, safely: the
    managers together, then the buses left together (a silent device on one bus holds
    up no other bus's safe stop).

    Errors are logged and do not stop the others (a ``BaseException`` is raised once
    everything was closed); bounded by ``STOP_EVERYTHING_TIMEOUT_S``.
    """
    loop = asyncio.get_running_loop()
    interrupted: BaseException | None = None
    try:
        async with asyncio.timeout(STOP_EVERYTHING_TIMEOUT_S):
            for group in (_managers, _buses):
                items = [obj for obj, on in list(group.items()) if on is loop]

                def failed(i: int, err: Exception, items: list[Any] = items) -> None:
                    log.error("closing %r on the way out failed: %s", items[i], err)

                first = await together([item.close() for item in items], failed)
                interrupted = interrupted or first
    except TimeoutError:
        log.error("closing everything took over %.0f s; gave up", STOP_EVERYTHING_TIMEOUT_S)
    if interrupted is not None:
        raise interrupted


# -- automatic protection while a bus is open -----------------------------------------------


def _is_asyncio_sigint(handler: object) -> bool:
    """``asyncio.run``'s own Ctrl-C handler (``Runner._on_sigint``, bound in a partial):
    the first Ctrl-C cancels ``main``, a second raises ``KeyboardInterrupt`` at once."""
    func = getattr(handler, "func", None)
    return getattr(func, "__name__", "") == "_on_sigint" and isinstance(
        getattr(func, "__self__", None), asyncio.Runner
    )


class _SigintGuard:
    """Stands in front of ``asyncio.run``'s Ctrl-C handler (``wrapped``) while a bus is
    open.  The first Ctrl-C goes to it (it cancels ``main``, whose ``async with`` blocks
    stop the motion).  A repeat raised ``KeyboardInterrupt`` into whatever ran, which
    could be the stop's own first steps, before ``deferred_interrupts`` held it (a second
    Ctrl-C 3 ms after the first left a stream's actuators unpaused): while the buses
    close it is logged and dropped - the program is ending already.  One that comes more
    than ``STOP_EVERYTHING_TIMEOUT_S`` after the first goes through: a program that
    ignored the cancellation can still be interrupted."""

    def __init__(self, wrapped: Callable[[int, Any], Any]) -> None:
        self.wrapped = wrapped
        self.first: float | None = None  # when the first Ctrl-C came (time.monotonic)

    def __call__(self, signum: int, frame: Any) -> None:
        main = getattr(self.wrapped, "keywords", {}).get("main_task")
        if main is not None and main.done():  # its asyncio.run is over: not ours to hold
            self.wrapped(signum, frame)
            return
        now = time.monotonic()
        if self.first is not None and now - self.first < STOP_EVERYTHING_TIMEOUT_S:
            log.warning("SIGINT again: still stopping the motion safely")
            return
        if self.first is None:
            self.first = now
        self.wrapped(signum, frame)


class _AutoGuard:
    """SIGTERM/SIGHUP handlers installed while buses are open, and a ``_SigintGuard`` in
    front of ``asyncio.run``'s Ctrl-C handler (see the module docstring)."""

    def __init__(self) -> None:
        self.loop: asyncio.AbstractEventLoop | None = None
        self.installed: list[signal.Signals] = []
        self.open_count = 0
        self.stopping = False
        #: The guard in front of ``asyncio.run``'s Ctrl-C handler, until given back.
        self.sigint: _SigintGuard | None = None

    def bus_opened(self) -> None:
        loop = asyncio.get_running_loop()
        if loop is not self.loop:
            # A new loop (a later asyncio.run): the old one took its handlers with it.
            self.loop, self.installed, self.open_count, self.stopping = loop, [], 0, False
        self.open_count += 1
        if not _enabled() or not _in_main_thread():
            return
        handler = signal.getsignal(signal.SIGINT)
        if self.sigint is None and _is_asyncio_sigint(handler):
            self.sigint = _SigintGuard(handler)  # type: ignore[arg-type]
            signal.signal(signal.SIGINT, self.sigint)
        if self.installed:
            return
        for sig in _AUTO_SIGNALS:
            if signal.getsignal(sig) is not signal.SIG_DFL:
                continue  # the program (or install_signal_handlers) handles it
            try:
                loop.add_signal_handler(sig, self._on_signal, sig)
            except (NotImplementedError, RuntimeError, ValueError):
                continue
            self.installed.append(sig)

    def bus_closed(self) -> None:
        self.open_count = max(0, self.open_count - 1)
        if self.open_count or self.stopping:
            return
        self.uninstall()

    def give_back_sigint(self) -> None:
        """No bus is open any more: ``asyncio.run``'s Ctrl-C handler is its own again.
        While a ``deferred_interrupts`` block holds the signals the guard stays, and the
        block's end gives it back (in the main thread only, where handlers are set)."""
        guard = self.sigint
        if guard is None or self.open_count or not _in_main_thread():
            return
        wrapped = guard.wrapped
        if signal.getsignal(signal.SIGINT) is guard:
            signal.signal(signal.SIGINT, wrapped)
            self.sigint = None

    def uninstall(self) -> None:
        self.give_back_sigint()
        loop, installed = self.loop, self.installed
        self.installed = []
        if loop is None or loop.is_closed():
            return
        for sig in installed:
            with contextlib.suppress(Exception):
                loop.remove_signal_handler(sig)

    def _on_signal(self, sig: signal.Signals) -> None:
        if self.stopping:
            log.warning("%s again: still stopping the motion safely", sig.name)
            return
        self.stopping = True
        log.warning("%s: stopping the motion safely before exiting", sig.name)
        assert self.loop is not None
        self.loop.create_task(self._stop_then_die(sig), name=f"motorbus {sig.name} stop")

    async def _stop_then_die(self, sig: signal.Signals) -> None:
        try:
            await stop_everything()
        finally:
            self.uninstall()
            signal.signal(sig, signal.SIG_DFL)
            signal.raise_signal(sig)  # end as the signal would have, now that it is safe


_guard = _AutoGuard()


def _guard_process() -> ModuleType | None:
    """``motorbus.runtime.guard`` if it is loaded: a guard process runs only once something has
    imported it (``guarded``, ``start_guard``), so a program without one never pays its
    import (start-up time of the command line, tests/cli/test_cli_startup.py)."""
    return sys.modules.get("motorbus.runtime.guard")


def register_bus(bus: Any) -> None:
    """A bus opened: protect it (called by ``Bus.open``); a running guard follows it."""
    _buses[bus] = asyncio.get_running_loop()
    _guard.bus_opened()
    guard_process = _guard_process()
    if guard_process is not None:
        guard_process.bus_opened(bus)


def unregister_bus(bus: Any) -> None:
    """A bus closed (called by ``Bus.close``): the guard forgets it."""
    if _buses.pop(bus, None) is not None:
        _guard.bus_closed()
    guard_process = _guard_process()
    if guard_process is not None:
        guard_process.bus_closed(bus)


def register_manager(manager: Any) -> None:
    """A ``BusManager`` opened (called by it)."""
    _managers[manager] = asyncio.get_running_loop()


def unregister_manager(manager: Any) -> None:
    """A ``BusManager`` closed (called by it)."""
    _managers.pop(manager, None)


# -- deferring Ctrl-C during a stop ------------------------------------------------------------

_defer_depth = 0
_deferred: list[int] = []


def _is_loop_noop(handler: object) -> bool:
    # loop.add_signal_handler leaves this Python-level handler; the loop dispatches.
    return getattr(handler, "__name__", "") == "_sighandler_noop"


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Hold SIGINT/SIGTERM/SIGHUP while a safe stop runs; deliver them afterwards.

    asyncio raises ``KeyboardInterrupt`` into whatever runs when a second Ctrl-C comes,
    which would abort a stop half way (some actuators paused, others not).  Inside this
    block such signals are only recorded; when the outermost block ends, the first of
    each is raised again, to the handler that was there before.  Only in the main
    thread (where Python runs signal handlers); nested blocks are fine.
    """
    global _defer_depth
    if not _in_main_thread() or not _enabled():
        yield
        return
    saved: dict[signal.Signals, Any] = {}
    if _defer_depth == 0:
        for sig in STOP_SIGNALS:
            handler = signal.getsignal(sig)
            if not callable(handler) or _is_loop_noop(handler):
                continue  # SIG_DFL/SIG_IGN, or the loop's own handler (ours ignores repeats)
            saved[sig] = handler
            signal.signal(sig, _record)
    _defer_depth += 1
    try:
        yield
    finally:
        _defer_depth -= 1
        if _defer_depth == 0:
            for saved_sig, handler in saved.items():
                signal.signal(saved_sig, handler)
            _guard.give_back_sigint()  # the last bus closed inside this block
            pending = list(dict.fromkeys(_deferred))
            _deferred.clear()
            for signum in pending:
                log.warning("delivering the deferred %s now that the stop is done", _name(signum))
                signal.raise_signal(signum)


def _record(signum: int, frame: object) -> None:
    _deferred.append(signum)
    log.warning("%s during a safe stop: deferred until the stop is done", _name(signum))


def _name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return str(signum)


# -- the helper an application installs --------------------------------------------------------


class SignalHandlers:
    """What ``install_signal_handlers`` set up; ``received`` lists the signals seen."""

    def __init__(self, loop: asyncio.AbstractEventLoop, task: asyncio.Task[Any]) -> None:
        self.loop = loop
        self.task = task
        self.received: list[signal.Signals] = []
        self._signals: list[signal.Signals] = []
        #: Set by ``retire``: the signals are another handler's now; ignore them.
        self._retired = False
        #: Handlers set with ``signal.signal`` where the loop cannot (Windows), and the
        #: dispositions they replaced.
        self._replaced: dict[signal.Signals, Any] = {}

    @property
    def first(self) -> signal.Signals | None:
        """The signal that started the stop, if any."""
        return self.received[0] if self.received else None

    def _on_signal(self, sig: signal.Signals) -> None:
        if self._retired:
            return  # one the loop read before ``retire``: the new handler decides
        self.received.append(sig)
        if len(self.received) == 1:
            log.warning("%s: stopping the motion safely, then exiting", sig.name)
            self.task.cancel()
        else:
            log.warning("%s again: still stopping the motion safely; please wait", sig.name)

    def retire(self) -> None:
        """Stop answering, giving nothing back: for when a handler set with
        ``signal.signal`` has just replaced these (``run``'s ``_LateRepeats``).

        ``uninstall`` gives the signals back through ``loop.remove_signal_handler``,
        which sets the default disposition first: a SIGTERM in the instant before the
        next handler is set would kill the process.  Replacing the handler and then
        retiring leaves no such instant.  asyncio's Unix loop would still do the same
        when it closes (it removes every signal it has a record of), so its records of
        these signals are dropped here, and its wakeup fd with the last of them, as
        ``remove_signal_handler`` does (a signal written to the fd of a closed loop is
        an "Exception ignored" message).  A loop that keeps no such records where they
        can be reached (uvloop) still resets them when it closes."""
        records = getattr(self.loop, "_signal_handlers", None)
        if isinstance(records, dict) and _in_main_thread() and not self.loop.is_closed():
            for sig in self._signals:
                records.pop(sig, None)
            if not records:
                signal.set_wakeup_fd(-1)
        self._retired = True
        self._signals = []
        self._replaced = {}

    def uninstall(self) -> None:
        """Remove the handlers (the previous dispositions come back)."""
        signals, self._signals = self._signals, []
        replaced, self._replaced = self._replaced, {}
        if _in_main_thread():
            for sig, previous in replaced.items():
                signal.signal(sig, previous)
        if self.loop.is_closed():
            return
        for sig in signals:
            with contextlib.suppress(Exception):
                self.loop.remove_signal_handler(sig)


def install_signal_handlers(
    signals: tuple[signal.Signals, ...] = STOP_SIGNALS,
    *,
    task: asyncio.Task[Any] | None = None,
) -> SignalHandlers:
    """Make the first of ``signals`` cancel ``task`` (default: the current task).

    Cancelling it runs its ``async with`` exits, i.e. every safe stop; signals after the
    first are logged and ignored while that happens.  Call from inside the running loop.

    Returns:
        The handlers: ``received`` lists the signals seen, ``uninstall()`` removes them.
    """
    loop = asyncio.get_running_loop()
    owner = task or asyncio.current_task()
    if owner is None:
        raise RuntimeError("install_signal_handlers() needs a task to cancel")
    handlers = SignalHandlers(loop, owner)
    for sig in signals:
        try:
            loop.add_signal_handler(sig, handlers._on_signal, sig)
        except NotImplementedError:
            # Windows' event loops have no add_signal_handler: a plain handler hands the
            # signal to the loop instead (Python runs it in the main thread).
            handlers._replaced[sig] = signal.signal(sig, _handing_to(loop, handlers, sig))
            continue
        handlers._signals.append(sig)
    return handlers


def _handing_to(
    loop: asyncio.AbstractEventLoop, handlers: SignalHandlers, sig: signal.Signals
) -> Callable[[int, object], None]:
    """A ``signal.signal`` handler that passes ``sig`` on to ``handlers`` in ``loop``."""

    def handler(signum: int, frame: object) -> None:
        loop.call_soon_threadsafe(handlers._on_signal, sig)

    return handler


def run(main: Coroutine[Any, Any, T] | Callable[[], Awaitable[T]], *, guard: bool = False) -> T:
    """Run ``main`` like ``asyncio.run``, stopping every motion safely however it ends.

    See the module docstring.  After a signal, raises ``SystemExit(128 + signal)``
    once everything is stopped and closed.

    A program that is killed outright (SIGKILL, the OOM killer, a crash) runs none of
    this.  With ``guard=True`` a guard process (``motorbus.runtime.guard``, Linux) watches the
    program and, if it dies with devices still leased, opens their ports and sends each
    its safe action.  Nothing in software covers a host crash, a power cut or a cut
    cable: keep the hardware e-stop.

    Raises:
        GuardError: ``guard=True`` and the guard cannot start (no pidfds: not Linux).
    """
    state: dict[str, Any] = {}
    # What run() gives back at its end, whatever asyncio.run set up meanwhile.
    before = _dispositions()

    async def runner() -> T:
        handlers = state["h"] = install_signal_handlers()
        try:
            coro = main if asyncio.iscoroutine(main) else main()
            return await coro
        finally:
            with deferred_interrupts():
                await stop_everything()
            state["stopped"] = True
            if handlers.first is not None and before:
                # asyncio.run still has its teardown to do (cancel what is left, close
                # the default executor): a repeated signal there must not turn the exit
                # this one started into a KeyboardInterrupt traceback, or kill it.  The
                # late handlers replace the loop's at once (``retire``).
                state["late"] = _LateRepeats(before)
                handlers.retire()
            else:
                handlers.uninstall()

    from motorbus.runtime.guard import guarded

    with guarded(guard):
        try:
            return asyncio.run(runner())
        except asyncio.CancelledError:
            handlers = state.get("h")
            if handlers is not None and handlers.first is not None:
                raise SystemExit(128 + int(handlers.first)) from None
            raise
        except KeyboardInterrupt:
            # A repeated Ctrl-C in the instant between the loop's close giving SIGINT
            # back (Python's default: KeyboardInterrupt) and _LateRepeats' restore: the
            # stop is done and the program was leaving with the first signal's status.
            handlers = state.get("h")
            if state.get("stopped") and handlers is not None and handlers.first is not None:
                log.warning("%s again while closing: exiting", handlers.first.name)
                raise SystemExit(128 + int(handlers.first)) from None
            raise
        finally:
            late = state.get("late")
            if late is not None:
                late.restore()


def _dispositions() -> dict[signal.Signals, Any]:
    """The stop signals' dispositions now (none where motorbus leaves signals alone)."""
    if not _in_main_thread() or not _enabled():
        return {}
    return {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}


class _LateRepeats:
    """Between the end of a signalled stop and the end of ``run``: stop signals that
    repeat are logged and absorbed, as they were during the stop (the program is already
    on its way out with ``128 + first``); one more after that goes to ``before``'s
    disposition, so that a teardown that hangs can still be interrupted.  ``restore``
    puts ``before`` back (``asyncio.run``'s own SIGINT handler, which it leaves alone
    once replaced, is not restored)."""

    def __init__(self, before: dict[signal.Signals, Any]) -> None:
        self.absorbed: list[int] = []
        self._previous = dict(before)
        for sig in before:
            signal.signal(sig, self._on_signal)

    def _on_signal(self, signum: int, frame: object) -> None:
        if not self.absorbed:
            self.absorbed.append(signum)
            log.warning(
                "%s again: the motion is stopped and the program is closing; "
                "send it once more to stop waiting",
                _name(signum),
            )
            return
        self.restore()
        # os.kill, not raise_signal: the restored handler then runs once this one has
        # returned, where the interrupted code is, not nested inside this handler.
        os.kill(os.getpid(), signum)

    def restore(self) -> None:
        """Give every stop signal its previous disposition back (idempotent)."""
        previous, self._previous = self._previous, {}
        for sig, handler in previous.items():
            # None: a handler set outside Python, which cannot be put back from here.
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
