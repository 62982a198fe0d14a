"""Two event loops behind the dashboard's one address: the viewers' and the controls'.

The dashboard's own event loop (the "control loop") runs the poller, the bus (or the
served bus's client) and every HTTP request: the page, ``/api/state`` and the controls.
The WebSocket viewers run on a loop of their own, in a thread of its own (the
:class:`ViewerLane`): their handshakes and their snapshots (some 175 kB each) never
take a turn of the control loop.  50 viewers connecting at once held an e-stop's
request in the control loop's queue for tens of milliseconds when they shared it
(``benchmarks/bench_dashboard.py --served``, docs/dashboard.md).  The viewers' thread
also runs at a lower CPU priority (``VIEWER_NICE``), and ``motorbus dashboard`` shortens
the GIL's switch interval, so that the control loop is not kept waiting by it.

One listening socket serves both (the page's WebSocket must be same-origin):
:class:`PageServer` accepts on the control loop, looks at each new connection's request
line without reading it (``MSG_PEEK``) and gives the connection to the viewers' loop
when it asks for ``GET /ws``, else to the control loop's aiohttp server.  The
control loop's responses close their connection (``Connection: close``), so every
request starts a connection of its own and is routed by its own first line: a
WebSocket can never arrive on a connection the control loop holds.

What crosses between the loops: the text of each push (built once on the control
loop, handed to the viewers' loop to send to every viewer) and a new viewer's snapshot
(asked of the control loop, which copies the state at most once per push and never
while an e-stop is in flight; the copy is rendered into JSON on the viewers' thread).
Nothing else is shared but the page's configuration, which is read only.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import threading
import weakref
from collections.abc import Callable, Coroutine
from typing import Any

from aiohttp import web

__all__ = ["PEEK_MAX", "PEEK_TIMEOUT_S", "VIEWER_NICE", "PageServer", "ViewerLane", "route"]

log = logging.getLogger("motorbus.dashboard")

#: Most bytes looked at for a request line; a longer one goes to the control loop
#: (which answers it as aiohttp does).
PEEK_MAX = 2048
#: A new connection that has not sent its request line by then is closed.
PEEK_TIMEOUT_S = 10.0
#: How long a connection whose request line is incomplete waits before another look.
_PEEK_AGAIN_S = 0.005
#: How long accepting pauses after an error such as running out of descriptors.
_ACCEPT_AGAIN_S = 1.0
#: How much lower the viewers' thread's CPU priority is (nice steps; Linux).
VIEWER_NICE = 10
#: Longest wait for the viewers' loop to start or to stop.
_LANE_WAIT_S = 10.0


def _yield_to_the_controls() -> None:
    """This thread (the viewers') at a lower CPU priority than the rest of the process
    (``VIEWER_NICE``, Linux: a nice value is a thread's own), so that when both are
    ready to run the controls' loop gets the CPU first; and never in real-time mode,
    which a thread inherits from the one that starts it (``motorbus dashboard
    --realtime`` puts the controls' thread there).  Where it cannot be, nothing."""
    with contextlib.suppress(AttributeError, OSError):
        if os.sched_getscheduler(0) not in (os.SCHED_OTHER, os.SCHED_BATCH, os.SCHED_IDLE):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(AttributeError, OSError):
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, os.getpriority(os.PRIO_PROCESS, tid) + VIEWER_NICE)


def route(head: bytes) -> str | None:
    """Where a connection goes by the start of its first request: ``"viewers"`` for a
    ``GET /ws`` (query allowed), ``"control"`` for anything else, ``None`` while the
    request line is incomplete."""
    end = head.find(b"\n")
    if end < 0:
        return "control" if len(head) >= PEEK_MAX else None
    parts = head[:end].split()
    if len(parts) >= 2 and parts[0] == b"GET" and parts[1].split(b"?", 1)[0] == b"/ws":
        return "viewers"
    return "control"


class ViewerLane:
    """The WebSocket viewers, on an event loop in a thread of their own.

    ``app`` is the viewers' aiohttp application (the ``/ws`` route and the page's
    checks), built by the caller and set up on the lane's loop.  ``snapshot`` is a
    coroutine function of the control loop giving what renders a new viewer's first
    message (called here, on the lane's thread: the costly part of a snapshot).
    """

    def __init__(
        self, app: web.Application, snapshot: Callable[[], Coroutine[Any, Any, Callable[[], str]]]
    ) -> None:
        self.app = app
        self.viewers: weakref.WeakSet[web.WebSocketResponse] = weakref.WeakSet()
        self._snapshot = snapshot
        self._control: asyncio.AbstractEventLoop | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._thread: threading.Thread | None = None
        self._done: asyncio.Event | None = None
        self._tasks: set[asyncio.Task[Any]] = set()
        #: Viewers whose snapshot is not sent yet, each with the pushes held for it
        #: (``welcome``).
        self._joining: dict[web.WebSocketResponse, list[str]] = {}

    @property
    def count(self) -> int:
        """Viewers connected now, those still being sent their snapshot included (read
        from any thread)."""
        return len(self.viewers) + len(self._joining)

    async def start(self) -> None:
        """Start the lane's thread and its loop; returns once it accepts connections."""
        self._control = asyncio.get_running_loop()
        ready: asyncio.Future[None] = self._control.create_future()

        def started(err: BaseException | None) -> None:
            if not ready.done():
                if err is None:
                    ready.set_result(None)
                else:
                    ready.set_exception(err)

        control = self._control

        def run() -> None:
            _yield_to_the_controls()
            loop = asyncio.new_event_loop()
            self.loop = loop
            try:
                loop.run_until_complete(self._serve(control, started))
            finally:
                loop.close()

        self._thread = threading.Thread(target=run, name="motorbus-dashboard-viewers")
        self._thread.daemon = True
        self._thread.start()
        async with asyncio.timeout(_LANE_WAIT_S):
            await ready

    async def _serve(
        self,
        control: asyncio.AbstractEventLoop,
        started: Callable[[BaseException | None], None],
    ) -> None:
        self._done = asyncio.Event()
        try:
            self._runner = web.AppRunner(self.app, handle_signals=False, access_log=None)
            await self._runner.setup()
        except BaseException as err:
            control.call_soon_threadsafe(started, err)
            raise
        control.call_soon_threadsafe(started, None)
        try:
            await self._done.wait()
        finally:
            for ws in [*self.viewers, *self._joining]:
                with contextlib.suppress(Exception):
                    await ws.close(code=1001, message=b"dashboard closing")
            await self._runner.cleanup()

    async def stop(self) -> None:
        """Close every viewer and end the lane's loop and thread."""
        loop, done, thread = self.loop, self._done, self._thread
        if loop is None or done is None or thread is None:
            return
        with contextlib.suppress(RuntimeError):  # its loop has already ended
            loop.call_soon_threadsafe(done.set)
        await asyncio.to_thread(thread.join, _LANE_WAIT_S)

    # -- called from the control loop --------------------------------------------------

    def adopt(self, conn: socket.socket) -> None:
        """Serve an accepted connection (its request line not yet read) on this lane."""
        loop, runner = self.loop, self._runner
        if loop is None or runner is None or runner.server is None:
            conn.close()
            return
        server = runner.server

        def take() -> None:
            task = loop.create_task(loop.connect_accepted_socket(server, conn))
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

        try:
            loop.call_soon_threadsafe(take)
        except RuntimeError:  # the lane has stopped
            conn.close()

    def broadcast(self, text: str) -> None:
        """Send ``text`` to every viewer (once, built by the caller)."""
        loop = self.loop
        if loop is None or not self.count:
            return
        with contextlib.suppress(RuntimeError):  # the lane has stopped
            loop.call_soon_threadsafe(self._broadcast, text)

    # -- on the lane's loop ------------------------------------------------------------

    def _broadcast(self, text: str) -> None:
        async def send(ws: web.WebSocketResponse) -> None:
            with contextlib.suppress(ConnectionError, RuntimeError):
                await ws.send_str(text)

        for held in self._joining.values():
            held.append(text)
        for ws in list(self.viewers):
            if not ws.closed:
                task = asyncio.get_running_loop().create_task(send(ws))
                self._tasks.add(task)
                task.add_done_callback(self._tasks.discard)

    async def welcome(self, ws: web.WebSocketResponse) -> None:
        """Send a new viewer its snapshot, then every push from the moment it joined;
        from then on it gets the pushes as they go (``viewers``).

        It joins before its snapshot is taken, and a push that goes out while the
        snapshot is taken or sent is held and sent after it, in order: a push is the
        samples since the one before, so a viewer added only once its snapshot was sent
        missed the samples of such a push (seen on a loaded machine).  It may get a
        sample twice, which the page drops by its time.
        """
        held: list[str] = []
        self._joining[ws] = held
        try:
            await ws.send_str(await self.snapshot())
            while held:
                await ws.send_str(held.pop(0))
            self.viewers.add(ws)  # no await since ``held`` was seen empty
        finally:
            del self._joining[ws]

    async def snapshot(self) -> str:
        """A new viewer's first message: taken on the control loop, rendered here."""
        control = self._control
        assert control is not None
        future = asyncio.run_coroutine_threadsafe(self._snapshot(), control)
        render = await asyncio.wrap_future(future)
        return render()


class PageServer:
    """The dashboard's one listening socket: accepts on the control loop and gives each
    connection to the viewers' lane or to ``runner``'s server (see the module)."""

    def __init__(self, runner: web.AppRunner, lane: ViewerLane) -> None:
        self.runner = runner
        self.lane = lane
        self.host = ""
        self.port = 0
        self._sock: socket.socket | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._waiting: dict[socket.socket, float] = {}
        self._tasks: set[asyncio.Task[Any]] = set()

    async def start(self, host: str, port: int) -> None:
        """Listen on ``host:port`` (port 0: any free one; ``self.port`` says which)."""
        self._loop = asyncio.get_running_loop()
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        sock = socket.create_server((host, port), family=family, backlog=128)
        sock.setblocking(False)
        self._sock = sock
        self.host, self.port = host, sock.getsockname()[1]
        self._loop.add_reader(sock.fileno(), self._accept)

    async def close(self) -> None:
        """Stop accepting; close connections not yet routed."""
        sock, loop = self._sock, self._loop
        self._sock = None
        if sock is not None and loop is not None:
            loop.remove_reader(sock.fileno())
            sock.close()
        for conn in list(self._waiting):
            self._drop(conn)

    def _accept(self) -> None:
        sock, loop = self._sock, self._loop
        assert loop is not None
        while sock is not None:
            try:
                conn, _ = sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as err:
                # Out of descriptors, say: the socket stays readable, so stop accepting
                # for a while rather than spin (as asyncio's own servers do).
                log.warning("dashboard: accept failed: %s; accepting again in 1 s", err)
                loop.remove_reader(sock.fileno())
                loop.call_later(_ACCEPT_AGAIN_S, self._listen_again)
                return
            conn.setblocking(False)
            self._waiting[conn] = loop.time() + PEEK_TIMEOUT_S
            loop.add_reader(conn.fileno(), self._look, conn)
            loop.call_later(PEEK_TIMEOUT_S, self._expire, conn)

    def _listen_again(self) -> None:
        if self._sock is not None and self._loop is not None:
            self._loop.add_reader(self._sock.fileno(), self._accept)

    def _expire(self, conn: socket.socket) -> None:
        if conn in self._waiting:  # no request line in PEEK_TIMEOUT_S: a silent client
            self._drop(conn)

    def _drop(self, conn: socket.socket) -> None:
        if self._waiting.pop(conn, None) is not None and self._loop is not None:
            self._loop.remove_reader(conn.fileno())
        conn.close()

    def _look(self, conn: socket.socket) -> None:
        loop = self._loop
        assert loop is not None
        try:
            head = conn.recv(PEEK_MAX, socket.MSG_PEEK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._drop(conn)
            return
        if not head:  # closed before it asked for anything
            self._drop(conn)
            return
        where = route(head)
        deadline = self._waiting.get(conn)
        loop.remove_reader(conn.fileno())
        if where is None:
            # Readable without a whole request line: look again shortly (a peeked byte
            # stays readable, so waiting for readability would spin).
            if deadline is None or loop.time() > deadline:
                self._drop(conn)
            else:
                loop.call_later(_PEEK_AGAIN_S, self._look_again, conn)
            return
        self._waiting.pop(conn, None)
        if where == "viewers":
            self.lane.adopt(conn)
            return
        server = self.runner.server
        if server is None:
            conn.close()
            return
        task = loop.create_task(loop.connect_accepted_socket(server, conn))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def _look_again(self, conn: socket.socket) -> None:
        if conn in self._waiting and self._loop is not None:
            self._loop.add_reader(conn.fileno(), self._look, conn)
