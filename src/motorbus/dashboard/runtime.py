"""The dashboard's engine: one poller per bus, the controls, the recording.

Each bus gets exactly one poller, whatever the number of viewers: it reads the status
of every LA actuator in turn at ``Priority.BACKGROUND`` (so every other request goes
first), one round every ``period`` seconds, as ``motorbus monitor`` does.  What the
page shows comes from the bus itself - its observer (every write and accepted reply,
with the bus's own times), its events and its counters - so a status read by anyone
on the bus counts, and the viewers only ever read :class:`DashboardState`.

Controls (only when the server allows them) go through the same buses: e-stop at
``Priority.EMERGENCY``, the others at ``Priority.HIGH``.  On :meth:`Dashboard.stop`
every actuator the dashboard set in motion (a move, a "work") gets its bus's safe
action (``la_safe_action``: pause, e-stop or hold); an actuator it never commanded
gets nothing, so watching sends no motion of its own on start or exit.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import logging
import threading
from collections.abc import Awaitable, Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from motorbus.bus.bus import Bus, BusState, Priority
from motorbus.bus.events import BusEvent, Subscription
from motorbus.dashboard.record import Recorder
from motorbus.dashboard.state import DashboardState, with_columns
from motorbus.errors import ControlError, MotorbusError
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol.base import Command, check_int
from motorbus.validation import check_number

__all__ = [
    "ACTIONS",
    "PROJECTS",
    "STOP_TIMEOUT_S",
    "BusSetup",
    "ControlError",
    "Dashboard",
    "ViewerSnapshot",
]

log = logging.getLogger("motorbus.dashboard")

#: Project numbers of the project stepper (doc 000 A.4: projects 1..4).
PROJECTS = (1, 2, 3, 4)
#: Allowed poll round, seconds.
PERIOD_MIN_S = 0.001
PERIOD_MAX_S = 3600.0
#: Longest the safe stop on the way out may take before the buses close anyway.
STOP_TIMEOUT_S = 2.0
#: Control actions on LA actuators and the priority each is sent at.
ACTIONS: dict[str, tuple[la.ControlAction, Priority]] = {
    "estop": (la.ControlAction.ESTOP, Priority.EMERGENCY),
    "pause": (la.ControlAction.PAUSE, Priority.HIGH),
    "work": (la.ControlAction.WORK, Priority.HIGH),
    "clear_fault": (la.ControlAction.CLEAR_FAULT, Priority.HIGH),
}


@dataclass(slots=True)
class BusSetup:
    """One bus the dashboard watches and what is on it.

    Attributes:
        bus: the bus (opened by the caller, closed by the caller).
        la_ids: the LA actuators to poll.
        project_motor: the project stepper's motor byte, ``None`` if there is none.
        quad: whether a quad stepper controller is on the bus.
        la_safe_action: what an actuator the dashboard moved gets on the way out.
        name: the name the page shows (default: the bus's own name).
    """

    bus: Bus
    la_ids: list[int] = field(default_factory=list)
    project_motor: int | None = None
    quad: bool = False
    la_safe_action: str = "pause"
    name: str | None = None

    @property
    def shown(self) -> str:
        """The bus's name on the page."""
        return self.name if self.name is not None else self.bus.name


class _Observer:
    """Feeds one bus's writes and replies to the state and the recorder."""

    def __init__(self, dash: Dashboard, name: str) -> None:
        self.dash = dash
        self.name = name

    def on_write(self, cmd: Command[object], at: float) -> None:
        self.dash.state.on_write(self.name, cmd, at)
        if self.dash.recorder is not None:
            self.dash.recorder.on_write(self.name, cmd, at)

    def on_reply(
        self, cmd: Command[object], value: Any, written_at: float, replied_at: float
    ) -> None:
        self.dash.state.on_reply(self.name, cmd, value, written_at, replied_at)
        if self.dash.recorder is not None:
            self.dash.recorder.on_reply(self.name, cmd, value, replied_at)


class ViewerSnapshot:
    """A new viewer's full snapshot: copied where the state lives, rendered (columns,
    JSON) once, by whoever asks first, in any thread."""

    def __init__(self, data: dict[str, Any], epoch: float | None) -> None:
        self._data: dict[str, Any] | None = data
        self._epoch = epoch
        self._text: str | None = None
        self._lock = threading.Lock()

    def text(self) -> str:
        with self._lock:
            if self._text is None:
                assert self._data is not None
                self._text = "".join(json_pieces(with_columns(self._data, self._epoch)))
                self._data = None
            return self._text


def json_pieces(value: Any) -> Iterator[str]:
    """``json.dumps(value, separators=(",", ":"))`` in pieces: one ``json.dumps`` per
    list of plain values (a plot's column), the objects and lists around them here.

    One ``json.dumps`` of a whole snapshot holds the GIL for milliseconds (C code
    never offers it), and the thread that renders a new viewer's snapshot shares the
    process with the loop that sends e-stops: in pieces, that loop can take the GIL
    between two columns."""
    if isinstance(value, dict) and all(isinstance(key, str) for key in value):
        yield "{"
        for n, (key, item) in enumerate(value.items()):
            yield ("," if n else "") + json.dumps(key) + ":"
            yield from json_pieces(item)
        yield "}"
    elif isinstance(value, list) and any(isinstance(v, dict | list) for v in value):
        yield "["
        for n, item in enumerate(value):
            if n:
                yield ","
            yield from json_pieces(item)
        yield "]"
    else:
        yield json.dumps(value, separators=(",", ":"))


class Dashboard:
    """The pollers, controls and recording of every watched bus.

    Args:
        setups: the buses (open) and their devices.
        period: seconds between two status reads of one actuator (the poll round).
        control: accept controls (else every control raises ``PermissionError``).
        window: the positions a move-to may target, inclusive.
    """

    def __init__(
        self,
        setups: Iterable[BusSetup],
        *,
        period: float = 0.1,
        control: bool = False,
        window: tuple[int, int] = (la.POSITION_MIN, la.POSITION_MAX),
    ) -> None:
        self.setups = {s.shown: s for s in setups}
        self.period = check_number("period", period, PERIOD_MIN_S, PERIOD_MAX_S, "s")
        self.control = control
        lo, hi = window
        check_int("window low", lo, la.POSITION_MIN, la.POSITION_MAX)
        check_int("window high", hi, lo, la.POSITION_MAX)
        self.window = (lo, hi)
        self.state = DashboardState(period=period, control=control)
        self.state.window = self.window
        self.recorder: Recorder | None = None
        self.moved: set[tuple[str, int]] = set()
        #: Poll rounds completed per bus (every LA actuator read once a round).
        self.rounds: dict[str, int] = dict.fromkeys(self.setups, 0)
        self._observers: dict[str, _Observer] = {}
        self._subs: list[Subscription[BusEvent]] = []
        #: The full snapshot new viewers get until the next push (see ``viewer_snapshot``).
        self._viewer_snapshot: ViewerSnapshot | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._hooks: dict[str, Callable[[], Awaitable[None]]] = {}
        for name, s in self.setups.items():
            self.state.add_bus(
                name,
                la_ids=s.la_ids,
                project_stepper=s.project_motor is not None,
                quad_stepper=s.quad,
            )

    # -- life -----------------------------------------------------------------------

    async def start(self) -> None:
        """Observe every bus and start its poller (the buses are open)."""
        for name, s in self.setups.items():
            self._observers[name] = _Observer(self, name)
            sub = s.bus.events.subscribe(BusEvent)
            self._subs.append(sub)
            loop = asyncio.get_running_loop()
            self._tasks.append(
                loop.create_task(self._events(name, sub), name=f"dashboard events {name}")
            )
            self._tasks.append(loop.create_task(self._poll(s), name=f"dashboard poller {name}"))
            self._attach(name, s)

    def _attach(self, name: str, s: BusSetup) -> None:
        """Watch a bus of this process: its observer, its close path, its poll load."""
        bus = s.bus
        self.state.set_state(name, bus.state.value)
        bus.add_observer(self._observers[name])
        # However the program ends (a signal closing every bus, say), the bus's close
        # path stops what the dashboard moved on it before the port closes.
        hook = self._hooks[name] = self._close_hook(name)
        bus.add_close_hook(hook)
        if s.la_ids:
            cost = bus.occupancy(la.Control(s.la_ids[0], la.ControlAction.QUERY_STATUS))
            self.state.set_poll_load(name, len(s.la_ids) * cost.answered / self.period)

    def _detach(self) -> None:
        """Undo :meth:`_attach` on every bus."""
        for name, hook in self._hooks.items():
            self.setups[name].bus.remove_close_hook(hook)
        self._hooks.clear()
        for name, observer in self._observers.items():
            self.setups[name].bus.remove_observer(observer)

    async def _request(
        self,
        name: str,
        cmd: Command[object],
        priority: Priority,
        retries: int | None = None,
    ) -> Any:
        """``cmd`` on bus ``name`` (its observer tells the state and the recorder)."""
        return await self.setups[name].bus.request(cmd, priority=priority, retries=retries)

    def _is_open(self, name: str) -> bool:
        return self.setups[name].bus.state is BusState.OPEN

    def _stats(self, name: str) -> dict[str, Any]:
        return self.setups[name].bus.stats.as_dict()

    def _port(self, name: str) -> str:
        return self.setups[name].bus.transport.url

    async def stop(self) -> None:
        """Stop polling; give every actuator the dashboard moved its bus's safe action."""
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        self._tasks.clear()
        for sub in self._subs:
            sub.close()
        self._subs.clear()
        await self.safe_stop()
        self._detach()
        self._observers.clear()
        self.stop_recording()

    async def safe_stop(self, bus: str | None = None) -> None:
        """Send the safe action of its bus to every actuator the dashboard moved (on
        ``bus`` only, if given); bounded by ``STOP_TIMEOUT_S``."""
        moved = sorted(m for m in self.moved if bus is None or m[0] == bus)
        keys: dict[str, list[str]] = {}
        for name, ident in moved:
            keys.setdefault(name, []).append(f"la:{ident}")
        self.moved.difference_update(moved)
        if not keys:
            return

        async def stop(name: str) -> None:
            # The bus's lease table defines and sends the safe action (failures logged).
            s = self.setups[name]
            try:
                await s.bus.lease_keeper.stop(keys[name], s.la_safe_action, who="dashboard")
            except Exception as err:
                log.error("safe stop on %s failed: %s", name, err)

        try:
            async with asyncio.timeout(STOP_TIMEOUT_S):
                await asyncio.gather(*(stop(name) for name in keys))
        except TimeoutError:
            log.error("safe stop not confirmed within %.0f s", STOP_TIMEOUT_S)

    def _close_hook(self, name: str) -> Callable[[], Awaitable[None]]:
        async def hook() -> None:
            await self.safe_stop(name)

        return hook

    # -- the poller -------------------------------------------------------------------

    async def _events(self, name: str, sub: Subscription[BusEvent]) -> None:
        async for event in sub:
            if event.bus != name:  # a bus shown by another name than its own
                event = dataclasses.replace(event, bus=name)
            self.state.on_event(event)

    async def _poll(self, s: BusSetup) -> None:
        name = s.shown
        loop = asyncio.get_running_loop()
        if s.project_motor is not None:
            for number in PROJECTS:  # the project list, once: what the page shows
                with contextlib.suppress(MotorbusError):
                    await self._request(name, ps.ReadProject(number), Priority.BACKGROUND)
        if not s.la_ids:
            return
        queries = [la.Control(i, la.ControlAction.QUERY_STATUS) for i in s.la_ids]
        next_round = loop.time()
        while True:
            for cmd in queries:
                try:
                    await self._request(name, cmd, Priority.BACKGROUND, 0)
                except MotorbusError as err:
                    # A silent actuator or a lost port must not end the poller; the
                    # bus counts timeouts, its events tell the state changes.
                    log.debug("dashboard poll of la:%d on %s: %s", cmd.id, name, err)
                    if not self._is_open(name):
                        await asyncio.sleep(self.period)
            self.rounds[name] += 1
            next_round += self.period
            now = loop.time()
            if next_round < now:
                next_round = now  # overloaded: poll back to back, never catch up in a burst
            await asyncio.sleep(next_round - now)

    # -- reading ----------------------------------------------------------------------

    def message(self, since: int | None = None) -> str:
        """The state as one JSON text (``since``: only the samples after that ``seq``)."""
        self._refresh()
        return json.dumps(self.state.snapshot(since), separators=(",", ":"))

    def _refresh(self) -> None:
        for name, s in self.setups.items():
            self.state.set_stats(name, self._stats(name))
            self.state.advance(s.bus.timer.now())

    def viewer_snapshot(self) -> ViewerSnapshot:
        """The full snapshot for a viewer that just connected: taken once per push.

        The snapshot is some 0.2-0.4 MB of JSON with five actuators' samples.  Built
        anew for each of 50 viewers connecting at once, it held the bus's event loop for
        over a second, polls and e-stops included; built once, it still held this loop
        for ~10 ms, in the way of an e-stop posted among them.  So every viewer that
        connects between two pushes gets the snapshot the first of them asked for, and
        here only its copy is taken (the samples' rows, a C-level copy each); turning
        the rows into columns and JSON (:meth:`ViewerSnapshot.text`) is for the caller,
        on the viewers' own thread.  It is never older than the last push, and the next
        push sends the samples since the previous one, so a viewer misses nothing (it
        may get a sample twice, which the page drops by its time).
        """
        if self._viewer_snapshot is None:
            self._refresh()
            data = self.state.snapshot(columns=False)
            self._viewer_snapshot = ViewerSnapshot(data, self.state.epoch)
        return self._viewer_snapshot

    def for_new_viewer(self) -> str:
        """:meth:`viewer_snapshot` as its JSON text."""
        return self.viewer_snapshot().text()

    def pushed(self) -> None:
        """A push went out (or would have): the next new viewer gets a fresh snapshot."""
        self._viewer_snapshot = None

    # -- controls -----------------------------------------------------------------------

    def _targets(self, bus: str | None, ident: int | None) -> list[tuple[str, int | None]]:
        if bus is None:
            if ident is not None:
                raise ControlError("id needs a bus: give bus and id", field="bus")
            return [(name, None) for name in self.setups]
        if bus not in self.setups:
            raise ControlError(
                f"bus={bus!r} is not watched: choose one of {', '.join(self.setups)}",
                field="bus",
                value=bus,
            )
        if ident is not None and ident not in self.state.buses[bus].la:
            known = ", ".join(str(i) for i in sorted(self.state.buses[bus].la)) or "none"
            raise ControlError(
                f"id={ident!r} is not an LA actuator on bus {bus!r}: known IDs {known}",
                field="id",
                value=ident,
            )
        return [(bus, ident)]

    def _check_control(self) -> None:
        if not self.control:
            raise PermissionError("the dashboard was started without --control")

    async def act(
        self, action: str, bus: str | None = None, ident: int | None = None, *, source: str = "?"
    ) -> list[dict[str, Any]]:
        """Apply ``action`` (estop, pause, work, clear_fault) to one actuator, a bus, or all.

        An e-stop or pause of a whole bus also stops its stepper controllers.  Returns
        one outcome per command.  Raises ``PermissionError`` without control,
        ``ControlError`` for an unknown action, bus or ID (nothing sent).
        """
        self._check_control()
        if action not in ACTIONS:
            raise ControlError(
                f"action={action!r} is unknown: choose one of {', '.join(ACTIONS)}",
                field="action",
                value=action,
            )
        sub, priority = ACTIONS[action]
        plan: list[tuple[str, Command[object], Priority, str]] = []
        stops = action in ("estop", "pause")
        for name, one in self._targets(bus, ident):
            s = self.setups[name]
            keeper = s.bus.lease_keeper
            ids = [one] if one is not None else sorted(self.state.buses[name].la)
            for i in ids:
                key = f"la:{i}"
                # A stop is the safe action as the bus's lease table defines it.
                cmds = keeper.safe_commands(key, action) if stops else (la.Control(i, sub),)
                plan.extend((name, cmd, priority, key) for cmd in cmds)
            if one is None and stops:
                # The steppers' stop, likewise.
                if s.project_motor is not None:
                    key = "project_stepper"
                    for cmd in keeper.safe_commands(key, motor=s.project_motor):
                        plan.append((name, cmd, priority, key))
                if s.quad:
                    for cmd in keeper.safe_commands("quad_stepper"):
                        plan.append((name, cmd, priority, "quad_stepper"))
        where = f"{bus}/la:{ident}" if ident is not None else (bus or "all buses")
        log.warning("dashboard control %s on %s from %s", action, where, source)
        for name in {p[0] for p in plan}:
            now = self.setups[name].bus.timer.now()
            self.state.on_note(name, now, f"{action} {where} (from {source})", "control")
        if action == "work":  # the power stage on: the actuator may drive to its target
            self.moved.update(
                (name, cmd.id) for name, cmd, _, _ in plan if isinstance(cmd, la.Control)
            )
        if len(plan) == 1:  # one actuator: no task to start and join (an e-stop's path)
            return [await self._send(*plan[0])]
        results = await asyncio.gather(*(self._send(*p) for p in plan))
        return list(results)

    async def move_to(self, bus: str, ident: int, position: int, *, source: str = "?") -> Any:
        """Move one actuator to ``position`` inside the window; returns the outcome."""
        self._check_control()
        self._targets(bus, ident)
        lo, hi = self.window
        if isinstance(position, bool) or not isinstance(position, int) or not lo <= position <= hi:
            raise ControlError(
                f"position={position!r} is out of range: allowed {lo}..{hi} (the window)",
                field="position",
                value=position,
            )
        log.warning("dashboard control move %s/la:%d to %d from %s", bus, ident, position, source)
        now = self.setups[bus].bus.timer.now()
        self.state.on_note(bus, now, f"move la:{ident} to {position} (from {source})", "control")
        self.moved.add((bus, ident))
        return await self._send(bus, la.MoveTo(ident, position), Priority.HIGH, f"la:{ident}")

    async def _send(
        self, name: str, cmd: Command[object], priority: Priority, device: str
    ) -> dict[str, Any]:
        out: dict[str, Any] = {"bus": name, "device": device, "command": type(cmd).__name__}
        try:
            await self._request(name, cmd, priority)
        except MotorbusError as err:
            out.update(ok=False, error=str(err))
        else:
            out["ok"] = True
        return out

    # -- recording ------------------------------------------------------------------------

    def start_recording(self, folder: Path) -> list[str]:
        """Start writing the frame logs and ``plots.csv`` into ``folder``; returns the files."""
        self.stop_recording()
        buses = {
            name: (frozenset(s.bus.families), s.bus.baudrate, self._port(name))
            for name, s in self.setups.items()
        }
        t0 = next(iter(self.setups.values())).bus.timer.now() if self.setups else 0.0
        self.recorder = Recorder(folder, buses, t0)
        self.state.recording = str(folder)
        return [str(p) for p in self.recorder.paths]

    def stop_recording(self) -> None:
        """Close the recording, if one runs."""
        if self.recorder is not None:
            self.recorder.close()
            self.recorder = None
        self.state.recording = None
