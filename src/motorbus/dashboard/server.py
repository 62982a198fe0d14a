"""The dashboard's web server (aiohttp): one page, one WebSocket feed, the control API.

* ``GET /`` - the page: one self-contained HTML file shipped in the package
  (``static/index.html``: inline CSS and JS, plots drawn on canvas; nothing from a CDN).
  Its Content-Security-Policy lets it talk to this server only.
* ``GET /ws`` - a WebSocket: a full snapshot on connect, then ``push_hz`` times a
  second the state with only the new samples.  One message is built per push and sent
  to every viewer, so viewers never add bus traffic: the pollers run whether or not
  anyone watches.  The viewers run on an event loop of their own (``lanes.py``), so a
  burst of them never holds up a control or the poller.
* ``GET /api/state`` - the full snapshot as JSON.
* ``POST /api/estop|pause|work|clear_fault`` (JSON ``{"bus": .., "id": ..}``, both
  optional: all buses, a bus, one actuator), ``POST /api/move`` (``{"bus", "id",
  "position", "confirm": true}``, inside the position window), ``POST /api/record``
  (``{"on": true|false}``): only when the dashboard was started with control; else
  403 and nothing is sent.

With a ``token`` (given when listening beyond 127.0.0.1), every request needs it, as
``?token=`` or the ``X-Motorbus-Token`` header.  A browser request from a page of
another origin (its ``Origin`` header) is refused: the WebSocket and the controls only
answer this server's own page.

Every request, the page's included, must name in its ``Host`` header one of the names
the server answers to (``allowed_hosts``: the address it listens on, and the names the
user allowed); anything else gets 403 before any handler runs.  This is what stops DNS
rebinding: a page of ``attacker.example`` whose name the attacker re-points at 127.0.0.1
is same-origin with itself, so the ``Origin`` check alone lets it through, but its
requests carry ``Host: attacker.example``.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import importlib.resources
import json
import logging
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from motorbus.dashboard.hosts import LOOPBACK_NAMES, HostCheck
from motorbus.dashboard.lanes import PageServer, ViewerLane
from motorbus.dashboard.runtime import ControlError, Dashboard
from motorbus.errors import LocalProtocolError

__all__ = [
    "CSP",
    "DASHBOARD_KEY",
    "LANE_KEY",
    "TOKEN_HEADER",
    "make_app",
    "page",
    "serve_page",
]

log = logging.getLogger("motorbus.dashboard")

DASHBOARD_KEY = web.AppKey("dashboard", Dashboard)
LANE_KEY = web.AppKey("viewers", ViewerLane)
_CONFIG = web.AppKey("config", dict)
#: Header that may carry the access token (else ``?token=``).
TOKEN_HEADER = "X-Motorbus-Token"
#: The page may load nothing and talk to nothing but this server.
CSP = (
    "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; "
    "connect-src 'self'; img-src 'self' data:; base-uri 'none'; form-action 'none'; "
    "frame-ancestors 'none'"
)
_ACTIONS = ("estop", "pause", "work", "clear_fault")


class _EmergencyGate:
    """Telemetry waits while an e-stop is on its way: a new viewer's snapshot and the
    pushes are held until every e-stop in flight has its answer, so building them does
    not take the control loop's turns the e-stop needs."""

    def __init__(self) -> None:
        self.in_flight = 0
        self.clear = asyncio.Event()
        self.clear.set()

    @contextlib.contextmanager
    def emergency(self) -> Iterator[None]:
        self.in_flight += 1
        self.clear.clear()
        try:
            yield
        finally:
            self.in_flight -= 1
            if not self.in_flight:
                self.clear.set()

    async def wait(self) -> None:
        if not self.clear.is_set():
            await self.clear.wait()


_GATE = web.AppKey("gate", _EmergencyGate)


def page() -> str:
    """The dashboard page (the packaged ``static/index.html``)."""
    return (
        importlib.resources.files("motorbus.dashboard")
        .joinpath("static/index.html")
        .read_text(encoding="utf-8")
    )


def make_app(
    dash: Dashboard,
    *,
    token: str | None = None,
    push_hz: float = 10.0,
    record_dir: Path | None = None,
    hosts: HostCheck | None = None,
) -> web.Application:
    """The aiohttp application serving ``dash``.

    Args:
        dash: the started (or to be started) dashboard.
        token: the access token every request must carry (``None``: none needed).
        push_hz: WebSocket pushes a second.
        record_dir: where the record button writes (default ``./motorbus-recording``).
        hosts: the ``Host`` names answered (default: the loopback names only).
    """
    config = {
        "token": token,
        "push_hz": push_hz,
        "record_dir": record_dir or Path("motorbus-recording"),
        "page": page(),
        "hosts": hosts if hosts is not None else HostCheck(LOOPBACK_NAMES),
    }
    gate = _EmergencyGate()

    async def snapshot() -> Callable[[], str]:  # on the control loop, for the lane
        await gate.wait()
        return dash.viewer_snapshot().text  # a copy: rendered on the viewers' thread

    viewers = web.Application(middlewares=[_guard])
    viewers[_CONFIG] = config
    viewers.router.add_get("/ws", _ws)
    lane = ViewerLane(viewers, snapshot)
    viewers[LANE_KEY] = lane

    app = web.Application(middlewares=[_guard])
    app[DASHBOARD_KEY] = dash
    app[LANE_KEY] = lane
    app[_GATE] = gate
    app[_CONFIG] = config
    app.router.add_get("/", _index)
    app.router.add_get("/api/state", _state)
    for action in _ACTIONS:
        app.router.add_post(f"/api/{action}", _make_action(action))
    app.router.add_post("/api/move", _move)
    app.router.add_post("/api/record", _record)
    app.cleanup_ctx.append(_run_lane)
    app.cleanup_ctx.append(_pusher)
    return app


@contextlib.asynccontextmanager
async def serve_page(app: web.Application, host: str, port: int) -> AsyncIterator[PageServer]:
    """Serve ``app`` (from :func:`make_app`) on ``host:port`` (port 0: a free one,
    ``.port`` says which) until the block ends: its viewers on their own loop, all else
    on this one (``lanes.PageServer``)."""
    runner = web.AppRunner(app, handle_signals=False, access_log=None)
    await runner.setup()  # starts the viewers' lane and the pusher
    server = PageServer(runner, app[LANE_KEY])
    try:
        await server.start(host, port)
        yield server
    finally:
        await server.close()
        await runner.cleanup()


def _same_origin(request: web.Request) -> bool:
    origin = request.headers.get("Origin")
    if origin is None:
        return True  # not a browser page's request (curl, a script, the tests)
    return origin in (f"http://{request.host}", f"https://{request.host}")


@web.middleware
async def _guard(
    request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
) -> web.StreamResponse:
    try:
        response = await _checked(request, handler)
    except web.HTTPException as exc:
        exc.force_close()
        raise
    if isinstance(response, web.Response):
        # One request a connection: the next one (a WebSocket too) starts a connection
        # of its own, which the page server routes by its request line (lanes.py).
        response.force_close()
    return response


async def _checked(
    request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
) -> web.StreamResponse:
    host = request.headers.get("Host")
    if not request.app[_CONFIG]["hosts"].allows(host):
        log.warning(
            "dashboard: refused %s %s for Host %r (not a name this dashboard answers to)",
            request.method,
            request.path,
            host,
        )
        return web.json_response(
            {
                "error": f"Host {host!r} is not a name this dashboard answers to; "
                "start it with --allow-host NAME to allow a name"
            },
            status=403,
        )
    token = request.app[_CONFIG]["token"]
    if token is not None:
        given = request.headers.get(TOKEN_HEADER) or request.query.get("token") or ""
        if not hmac.compare_digest(given.encode(), token.encode()):
            return web.json_response({"error": "a valid access token is required"}, status=401)
    if request.path != "/" and not _same_origin(request):
        log.warning(
            "dashboard: refused %s %s from origin %s",
            request.method,
            request.path,
            request.headers.get("Origin"),
        )
        return web.json_response({"error": "cross-origin request refused"}, status=403)
    return await handler(request)


async def _index(request: web.Request) -> web.Response:
    return web.Response(
        text=request.app[_CONFIG]["page"],
        content_type="text/html",
        headers={"Content-Security-Policy": CSP, "Cache-Control": "no-store"},
    )


async def _state(request: web.Request) -> web.Response:
    return web.Response(text=request.app[DASHBOARD_KEY].message(), content_type="application/json")


async def _ws(request: web.Request) -> web.WebSocketResponse:
    # No permessage-deflate, though browsers offer it: one snapshot goes to every viewer,
    # and deflating it once per viewer (a 175 kB snapshot, 50 viewers at once) took the
    # CPU the e-stop and the bus's host needed (benchmarks/bench_dashboard.py --served).
    # On the viewers' lane (lanes.py); the snapshot comes from the control loop.
    lane = request.app[LANE_KEY]
    ws = web.WebSocketResponse(heartbeat=20.0, compress=False)
    await ws.prepare(request)
    await lane.welcome(ws)
    try:
        async for msg in ws:  # viewers only listen; anything they send is ignored
            if msg.type == WSMsgType.ERROR:
                break
    finally:
        lane.viewers.discard(ws)
    return ws


async def _run_lane(app: web.Application) -> AsyncIterator[None]:
    lane = app[LANE_KEY]
    await lane.start()
    yield
    await lane.stop()


async def _pusher(app: web.Application) -> AsyncIterator[None]:
    """One task for every viewer: build one message per push, send it to all."""
    dash = app[DASHBOARD_KEY]
    lane = app[LANE_KEY]
    period = 1.0 / app[_CONFIG]["push_hz"]

    async def push() -> None:
        loop = asyncio.get_running_loop()
        since = dash.state.seq
        next_push = loop.time()
        while True:
            # Absolute deadlines: the push rate does not sag with the number of viewers.
            next_push = max(next_push + period, loop.time())
            await asyncio.sleep(next_push - loop.time())
            await app[_GATE].wait()
            if dash.recorder is not None:
                dash.recorder.flush()
            dash.pushed()
            if not lane.count:
                since = dash.state.seq
                continue
            text = dash.message(since)
            since = dash.state.seq
            lane.broadcast(text)

    task = asyncio.get_running_loop().create_task(push(), name="dashboard pusher")
    yield
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


def _source(request: web.Request) -> str:
    return f"{request.remote or '?'} ({request.headers.get('User-Agent', '?')[:60]})"


async def _body(request: web.Request) -> dict[str, Any]:
    if not request.can_read_body:
        return {}
    try:
        doc = await request.json()
    except (ValueError, json.JSONDecodeError) as err:
        raise web.HTTPBadRequest(
            text=json.dumps({"error": f"body is not JSON: {err}"}), content_type="application/json"
        ) from None
    if not isinstance(doc, dict):
        raise web.HTTPBadRequest(
            text=json.dumps({"error": "body must be a JSON object"}),
            content_type="application/json",
        )
    return doc


def _refused(err: Exception, status: int) -> web.Response:
    return web.json_response({"error": str(err)}, status=status)


def _ident(doc: dict[str, Any]) -> int | None:
    ident = doc.get("id")
    if ident is None:
        return None
    if isinstance(ident, bool) or not isinstance(ident, int):
        raise ControlError(f"id={ident!r} must be an integer ID", field="id", value=ident)
    return ident


def _make_action(action: str) -> Callable[[web.Request], Awaitable[web.Response]]:
    async def handler(request: web.Request) -> web.Response:
        dash = request.app[DASHBOARD_KEY]
        if not dash.control:
            return _refused(PermissionError("read-only: start with --control to allow this"), 403)
        doc = await _body(request)
        try:
            bus = doc.get("bus")
            if bus is not None and not isinstance(bus, str):
                raise ControlError(f"bus={bus!r} must be a bus name", field="bus", value=bus)
            ident = _ident(doc)
            with request.app[_GATE].emergency() if action == "estop" else contextlib.nullcontext():
                results = await dash.act(action, bus, ident, source=_source(request))
        except LocalProtocolError as err:
            return _refused(err, 400)
        return web.json_response({"action": action, "results": results})

    return handler


async def _move(request: web.Request) -> web.Response:
    dash = request.app[DASHBOARD_KEY]
    if not dash.control:
        return _refused(PermissionError("read-only: start with --control to allow this"), 403)
    doc = await _body(request)
    if doc.get("confirm") is not True:
        return _refused(ValueError('a move needs "confirm": true'), 400)
    try:
        bus, ident = doc.get("bus"), _ident(doc)
        if not isinstance(bus, str) or ident is None:
            raise ControlError("a move needs bus and id", field="bus")
        result = await dash.move_to(bus, ident, doc.get("position"), source=_source(request))  # type: ignore[arg-type]
    except LocalProtocolError as err:
        return _refused(err, 400)
    return web.json_response({"action": "move", "results": [result]})


async def _record(request: web.Request) -> web.Response:
    dash = request.app[DASHBOARD_KEY]
    if not dash.control:
        return _refused(PermissionError("read-only: start with --control (or use --record)"), 403)
    doc = await _body(request)
    if doc.get("on", True):
        files = dash.start_recording(request.app[_CONFIG]["record_dir"])
        return web.json_response({"recording": True, "files": files})
    dash.stop_recording()
    return web.json_response({"recording": False})
