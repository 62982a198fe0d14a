"""The one background event loop every blocking object runs on.

A daemon thread runs an asyncio loop for the life of the process; a blocking call
hands its coroutine over with ``asyncio.run_coroutine_threadsafe`` and waits for the
result.  The buses, streams and leases on that loop are the asyncio ones, unchanged:
spacing, deadlines, leases and safe ends work exactly as in an asyncio program.

Safe ends (docs/blocking.md):

* ``KeyboardInterrupt`` (Ctrl-C) while a blocking call waits: the call is cancelled,
  every bus and ``BusManager`` open on this loop is closed safely
  (``motorbus.runtime.shutdown.stop_everything``: streams stop, leases get their safe action,
  ports close), then the interrupt is raised again.  A further Ctrl-C during that
  stop is logged and absorbed (the stop takes milliseconds and must finish).
* Interpreter exit (``atexit``): the same stop for whatever is still open.

A served bus's connection (``motorbus.blocking.connect``) is one more thing open on the
loop: the same stop closes it (after the local buses), which ends this client's leases
and streams on the server with their safe actions.
"""

from __future__ import annotations

import asyncio
import atexit
import concurrent.futures
import logging
import threading
from collections.abc import Callable, Coroutine
from typing import Any, Protocol, TypeVar

from motorbus.blocking._signals import protect
from motorbus.errors import BusClosedError, WrongLoopError
from motorbus.runtime.shutdown import STOP_EVERYTHING_TIMEOUT_S, stop_everything

__all__ = ["Runner", "runner"]

log = logging.getLogger("motorbus.blocking")

T = TypeVar("T")

#: Longest slice of one wait for a result: the waiting thread wakes this often (a
#: wait on a lock is not interruptible by Ctrl-C on every platform); a result that
#: comes earlier is returned at once.
WAIT_SLICE_S = 0.25
#: Longest wait for the safe stop after Ctrl-C or at exit (the stop bounds itself at
#: ``STOP_EVERYTHING_TIMEOUT_S``; this is the backstop of the waiting thread).
STOP_WAIT_S = STOP_EVERYTHING_TIMEOUT_S + 5.0


class Closable(Protocol):
    """A connection the runner closes with everything else (a served site)."""

    async def close(self) -> None: ...


class Runner:
    """An asyncio loop on a daemon thread of its own, and the blocking calls into it."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        #: Served connections open on the loop (``track``), closed by ``stop_everything``.
        self.connections: dict[int, Closable] = {}
        self._connections_lock = threading.Lock()
        self._started = threading.Event()
        self.thread = threading.Thread(target=self._main, name="motorbus-blocking", daemon=True)
        self.closed = False
        self.thread.start()
        self._started.wait()

    def _main(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.call_soon(self._started.set)
        try:
            self.loop.run_forever()
        finally:
            self.loop.close()

    def opened(self) -> None:
        """A bus opened: make the safe stop at exit the first exit handler to run.

        ``atexit`` runs its handlers last registered first, and what a bus opens may
        register its own (the timer's ``weakref.finalize`` closes its file descriptor at
        exit): the stop must run while everything it needs is still there.
        """
        atexit.unregister(self.shutdown)
        atexit.register(self.shutdown)

    def track(self, connection: Closable) -> None:
        """Close ``connection`` with everything else on Ctrl-C, at exit, on SIGTERM."""
        with self._connections_lock:
            self.connections[id(connection)] = connection

    def untrack(self, connection: Closable) -> None:
        """``connection`` was closed by its owner."""
        with self._connections_lock:
            self.connections.pop(id(connection), None)

    def in_loop_thread(self) -> bool:
        return threading.current_thread() is self.thread

    def call(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run ``coro`` on the loop and return its result (or raise its error).

        A ``KeyboardInterrupt`` while waiting cancels it, stops everything open on the
        loop safely, then is raised again.

        Raises:
            WrongLoopError: called from the loop's own thread (a target callback, an
                event handler): waiting there would wait forever.
            BusClosedError: the loop has shut down (the interpreter is exiting).
        """
        future = self._submit(coro)
        try:
            return _wait(future)
        except KeyboardInterrupt:
            future.cancel()
            log.warning("KeyboardInterrupt: stopping the motion safely")
            self.stop_everything()
            raise

    def call_sync(self, fn: Callable[..., T], *args: Any) -> T:
        """Run the plain function ``fn(*args)`` on the loop's thread (objects that belong
        to the loop are touched there only) and return its result."""

        async def apply() -> T:
            return fn(*args)

        return self.call(apply())

    def finish(self, coro: Coroutine[Any, Any, T]) -> T:
        """Run a safe stop (a close): wait for it to end, whatever comes meanwhile.

        A ``KeyboardInterrupt`` during the stop is logged and raised only once the stop
        is done, so that it cannot cut the stop short.
        """
        future = self._submit(coro)
        interrupted: KeyboardInterrupt | None = None
        while True:
            try:
                result = _wait(future)
                break
            except KeyboardInterrupt as err:
                interrupted = interrupted or err
                log.warning("KeyboardInterrupt again: still stopping the motion safely")
        if interrupted is not None:
            raise interrupted
        return result

    def stop_everything(self) -> None:
        """Close every bus and ``BusManager`` open on this loop, safely, then every
        served connection; errors logged."""
        if self.closed:
            return
        with self._connections_lock:
            connections = list(self.connections.values())
            self.connections.clear()
        try:
            self.finish(_bounded(_stop_all(connections), STOP_WAIT_S))
        except Exception as err:
            log.error("stopping everything failed: %s", err)

    def shutdown(self) -> None:
        """Stop everything safely, then end the loop and its thread (at exit)."""
        if self.closed:
            return
        try:
            self.stop_everything()
        finally:
            self.closed = True
            self.loop.call_soon_threadsafe(self.loop.stop)
            self.thread.join(STOP_WAIT_S)

    def _submit(self, coro: Coroutine[Any, Any, T]) -> concurrent.futures.Future[T]:
        if self.in_loop_thread():
            coro.close()
            raise WrongLoopError(
                "a blocking motorbus call from the bus thread itself (a target callback or "
                "an event handler) would wait forever: use the asyncio API there"
            )
        if self.closed or self.loop.is_closed():
            coro.close()
            raise BusClosedError("motorbus's background loop has shut down")
        # The task runs in a copy of the calling thread's context, so an explicit lease
        # the caller holds (``motorbus.bus.leases.bind``) owns the motion it sends.
        return asyncio.run_coroutine_threadsafe(coro, self.loop)


def _wait(future: concurrent.futures.Future[T]) -> T:
    while True:
        try:
            return future.result(timeout=WAIT_SLICE_S)
        except concurrent.futures.TimeoutError:
            if future.done():
                raise  # the coroutine's own TimeoutError
            continue


async def _stop_all(connections: list[Closable]) -> None:
    """The local buses' safe stop, then each served connection closed (the server ends
    its leases and streams with their safe actions)."""
    try:
        await stop_everything()
    finally:
        for connection in connections:
            try:
                await connection.close()
            except Exception as err:
                log.error("closing %r on the way out failed: %s", connection, err)


async def _bounded(coro: Coroutine[Any, Any, None], seconds: float) -> None:
    async with asyncio.timeout(seconds):
        await coro


_lock = threading.Lock()
_runner: Runner | None = None


def runner() -> Runner:
    """The process's runner, started on first use (and stopped safely at exit, or on
    SIGTERM or SIGHUP: ``motorbus.blocking._signals``)."""
    global _runner
    with _lock:
        if _runner is None or _runner.closed:
            _runner = Runner()
            atexit.register(_runner.shutdown)
        current = _runner
    protect(_stop_current)
    return current


def _stop_current() -> None:
    current = _runner
    if current is not None:
        current.stop_everything()
