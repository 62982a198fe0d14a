"""What the dashboard shows, as plain data: fed by observations, read as JSON.

Pure code: no asyncio, no clock, no I/O.  The poller hands it what the bus reports -
every write and accepted reply (``Bus.add_observer``, with the bus's own times), the
bus's events (``bus.events``) and counters (``bus.stats.as_dict()``) - and the server
turns it into JSON for the page: :meth:`DashboardState.snapshot` with every sample
of the last :data:`WINDOW_S` seconds for a viewer that just connected, then, at each
push, only the samples that are new since the previous push (``since=``), so the one
message built per push serves any number of viewers.

Times are the bus clock's (monotonic seconds); the JSON gives them relative to the
state's ``epoch`` (the first observation), in seconds.
"""

from __future__ import annotations

import bisect
import collections
import copy
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from motorbus.bus.events import (
    BusEvent,
    BusStateChanged,
    FaultChanged,
    ProjectFinished,
    QuadDone,
)
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps  # (its names load on first use)
from motorbus.protocol.base import Command, Family

__all__ = [
    "EVENTS_KEPT",
    "GAP_EDGES_MS",
    "REPLY_EDGES_MS",
    "SERIES",
    "WINDOW_S",
    "BusView",
    "DashboardState",
    "Histogram",
    "LAView",
    "columns_of",
    "error_names",
    "with_columns",
]

#: Seconds of samples the plots show (and a new viewer receives).
WINDOW_S = 30.0
#: Seconds over which frames/s is counted.
RATE_WINDOW_S = 1.0
#: Latest events kept per bus.
EVENTS_KEPT = 50
#: Upper bucket edges of the reply-time histogram, milliseconds (the last is open).
REPLY_EDGES_MS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, math.inf)
#: Upper bucket edges of the poll-interval jitter histogram, milliseconds.
GAP_EDGES_MS = (0.1, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, math.inf)
#: The columns of an LA actuator's samples, after ``t`` (units: the protocol's).
SERIES = ("position", "target", "current", "force", "temperature")
#: Mode an LA actuator is in after each control action the bus wrote.
_MODES = {
    la.ControlAction.WORK: "work",
    la.ControlAction.PAUSE: "pause",
    la.ControlAction.ESTOP: "estop",
}


def error_names(errors: int) -> list[str]:
    """The fault bits of an LA status byte by name (``bit4``.. for the undefined ones)."""
    names = [f.name or "" for f in la.ErrorFlags if errors & f]
    names += [f"bit{b}" for b in range(4, 8) if errors & (1 << b)]
    return names


@dataclass(slots=True)
class Histogram:
    """Counts of durations in buckets with fixed upper ``edges`` (milliseconds)."""

    edges: tuple[float, ...]
    counts: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.counts:
            self.counts = [0] * len(self.edges)

    def add(self, ms: float) -> None:
        """Count one duration of ``ms`` milliseconds (a bucket holds values <= its edge)."""
        i = bisect.bisect_left(self.edges, ms)
        self.counts[min(i, len(self.counts) - 1)] += 1

    def to_json(self) -> dict[str, Any]:
        """``{"edges_ms": [...], "counts": [...]}``; the open last edge is ``null``."""
        edges = [None if math.isinf(e) else e for e in self.edges]
        return {"edges_ms": edges, "counts": list(self.counts)}


@dataclass(slots=True)
class LAView:
    """One LA actuator: its latest status, its samples, its mode and faults."""

    id: int
    samples: collections.deque[tuple[int, float, int, int, int, int, int]] = field(
        default_factory=collections.deque
    )  # (seq, t, position, target, current, force, temperature)
    errors: int = 0
    mode: str = "unknown"
    last_reply: float | None = None
    polls: int = 0
    jitter: Histogram = field(default_factory=lambda: Histogram(GAP_EDGES_MS))

    def latest(self) -> dict[str, Any] | None:
        if not self.samples:
            return None
        return dict(zip(SERIES, self.samples[-1][2:], strict=True))


@dataclass(slots=True)
class BusView:
    """One bus: its state, its traffic, its events and its devices."""

    name: str
    state: str = "closed"
    detail: str = ""
    writes: collections.deque[float] = field(default_factory=collections.deque)
    last_write: float | None = None
    min_gap: float | None = None
    reply_times: Histogram = field(default_factory=lambda: Histogram(REPLY_EDGES_MS))
    events: collections.deque[dict[str, Any]] = field(
        default_factory=lambda: collections.deque(maxlen=EVENTS_KEPT)
    )
    la: dict[int, LAView] = field(default_factory=dict)
    project: dict[str, Any] | None = None
    quad: dict[str, Any] | None = None
    stats: dict[str, Any] = field(default_factory=dict)
    poll_load: float | None = None
    #: The ``motorbus serve`` endpoint the bus is used through (``None``: this process's).
    served: str | None = None
    #: Frames/s from the server's counters (a served bus: the dashboard sees only its own).
    rate: float | None = None
    #: Who holds which device (a served bus): ``[{"key", "owner"}]``.
    leases: list[dict[str, str]] = field(default_factory=list)


class DashboardState:
    """Every bus the dashboard watches.

    Args:
        period: the poll period each actuator is meant to be read at, seconds; its
            jitter histogram counts how far each interval between two replies is from it.
        control: whether the server accepts controls (the page shows them if so).
    """

    def __init__(self, *, period: float, control: bool = False) -> None:
        self.period = period
        self.control = control
        self.buses: dict[str, BusView] = {}
        self.epoch: float | None = None
        self.now = 0.0
        self.seq = 0
        self.recording: str | None = None
        #: The positions a move-to may target (the page's input range).
        self.window: tuple[int, int] = (la.POSITION_MIN, la.POSITION_MAX)

    # -- building -----------------------------------------------------------------

    def add_bus(
        self,
        name: str,
        *,
        la_ids: Iterable[int] = (),
        project_stepper: bool = False,
        quad_stepper: bool = False,
    ) -> BusView:
        """Add a bus and the devices on it (LA IDs; which stepper controllers)."""
        view = self.buses.get(name) or BusView(name)
        self.buses[name] = view
        for i in la_ids:
            view.la.setdefault(i, LAView(i))
        if project_stepper and view.project is None:
            view.project = {"running": None, "last_ee_dd": None, "projects": {}}
        if quad_stepper and view.quad is None:
            view.quad = {"axes": {}, "last_done": None}
        return view

    def _clock(self, t: float) -> float:
        if self.epoch is None:
            self.epoch = t
        self.now = max(self.now, t)
        return t

    def advance(self, now: float) -> None:
        """The bus clock reads ``now``: rates and ages count up to it even when the bus
        is silent (a lost port, nothing to poll)."""
        self._clock(now)

    def _rel(self, t: float | None) -> float | None:
        return _relative(t, self.epoch)

    # -- observations ---------------------------------------------------------------

    def on_write(self, bus: str, cmd: Command[object], at: float) -> None:
        """The bus wrote ``cmd`` (its write completed at ``at``)."""
        self._clock(at)
        view = self.buses[bus]
        if view.last_write is not None:
            gap = at - view.last_write
            view.min_gap = gap if view.min_gap is None else min(view.min_gap, gap)
        view.last_write = at
        view.writes.append(at)
        while view.writes and view.writes[0] < at - RATE_WINDOW_S:
            view.writes.popleft()
        if isinstance(cmd, la.Control) and cmd.action in _MODES:
            self._la(view, cmd.id).mode = _MODES[cmd.action]
        elif isinstance(cmd, la.MoveTo | la.Follow) and cmd.id in view.la:
            # A position command drives an actuator in work (or resumes it from pause).
            self._la(view, cmd.id).mode = "work"
        elif view.project is not None and isinstance(cmd, ps.StartProject):
            view.project["running"] = cmd.project
        elif view.project is not None and isinstance(cmd, ps.StopProject):
            view.project["running"] = None
        elif view.quad is not None and cmd.family is Family.QUAD_STEPPER:
            motor = getattr(cmd, "motor", None)
            if motor is not None:
                axis = view.quad["axes"].setdefault(str(motor), {})
                axis["last_command"] = type(cmd).__name__
                axis["at"] = self._rel(at)

    def on_reply(
        self, bus: str, cmd: Command[object], value: Any, written_at: float, replied_at: float
    ) -> None:
        """The bus accepted ``value``, the reply to ``cmd`` written at ``written_at``."""
        self._clock(replied_at)
        view = self.buses[bus]
        view.reply_times.add((replied_at - written_at) * 1e3)
        if isinstance(value, la.Status) and value.id != 0:
            self.on_status(bus, value, replied_at)
        elif view.project is not None and isinstance(value, ps.ProjectDump):
            view.project["projects"][str(value.project)] = {
                "steps": value.number_of_steps,
                "repeat_count": value.repeat_count,
                "loop": [value.loop_start, value.loop_end, value.loop_count],
            }

    def on_status(self, bus: str, status: la.Status, at: float) -> None:
        """An LA status reply read at ``at``: a sample of the plots, the fault bits."""
        self._clock(at)
        view = self._la(self.buses[bus], status.id)
        if view.last_reply is not None:
            view.jitter.add(abs((at - view.last_reply) - self.period) * 1e3)
        view.last_reply = at
        view.polls += 1
        view.errors = int(status.errors)
        self.seq += 1
        view.samples.append(
            (
                self.seq,
                at,
                status.position,
                status.target,
                status.current,
                status.force,
                status.temperature,
            )
        )
        while view.samples and view.samples[0][1] < at - WINDOW_S:
            view.samples.popleft()

    def on_event(self, event: BusEvent) -> None:
        """A bus event: state changes, faults, ``EE DD``, quad done."""
        view = self.buses.get(event.bus)
        if view is None:
            return
        self._clock(event.time)
        t = self._rel(event.time)
        entry: dict[str, Any] = {"t": t, "kind": type(event).__name__}
        if isinstance(event, BusStateChanged):
            view.state = event.state
            view.detail = event.detail
            entry["text"] = f"bus {event.state}" + (f" ({event.detail})" if event.detail else "")
        elif isinstance(event, FaultChanged):
            self._la(view, event.id).errors = event.after
            now = ", ".join(error_names(event.after)) or "cleared"
            entry["text"] = f"la:{event.id} faults: {now}"
            entry["id"] = event.id
            entry["errors"] = error_names(event.after)
        elif isinstance(event, ProjectFinished):
            entry["text"] = "project stepper: EE DD (project finished)"
            if view.project is not None:
                view.project["running"] = None
                view.project["last_ee_dd"] = t
        elif isinstance(event, QuadDone):
            entry["text"] = f"quad stepper: {event.kind} done (address {event.address})"
            if view.quad is not None:
                view.quad["last_done"] = {"t": t, "kind": event.kind, "address": event.address}
        else:
            entry["text"] = type(event).__name__
        view.events.append(entry)

    def on_note(self, bus: str, at: float, text: str, kind: str = "note") -> None:
        """A line for the bus's event list (a control action, a poll that timed out)."""
        self._clock(at)
        self.buses[bus].events.append({"t": self._rel(at), "kind": kind, "text": text})

    def set_state(self, bus: str, state: str) -> None:
        """The bus's life state when no event said it (``open`` after opening)."""
        self.buses[bus].state = state

    def set_stats(self, bus: str, stats: Mapping[str, Any]) -> None:
        """The bus's counters (``bus.stats.as_dict()``)."""
        self.buses[bus].stats = dict(stats)

    def set_served(self, bus: str, endpoint: str) -> None:
        """The bus is used through the ``motorbus serve`` at ``endpoint``: its frames/s
        come from the server's counters (:meth:`set_rate`), not from the writes seen."""
        self.buses[bus].served = endpoint

    def set_rate(self, bus: str, frames_per_s: float) -> None:
        """Frames/s the server's bus wrote (a served bus)."""
        self.buses[bus].rate = frames_per_s

    def set_leases(self, bus: str, leases: Iterable[tuple[str, str]]) -> None:
        """The devices held on a served bus, as ``(key, owner)``."""
        self.buses[bus].leases = [{"key": key, "owner": owner} for key, owner in leases]

    def set_poll_load(self, bus: str, load: float) -> None:
        """The share of bus time the status polls take (0..1 and beyond: overloaded)."""
        self.buses[bus].poll_load = load

    def _la(self, view: BusView, ident: int) -> LAView:
        dev = view.la.get(ident)
        if dev is None:
            dev = view.la[ident] = LAView(ident)
        return dev

    # -- reading ---------------------------------------------------------------------

    def frames_per_s(self, bus: str) -> float:
        """Frames written in the second before the latest observation or ``advance``
        (a served bus: what its server's counters said last)."""
        view = self.buses[bus]
        if view.served is not None:
            return 0.0 if view.rate is None else round(view.rate, 1)
        writes = view.writes
        return float(sum(1 for t in writes if t >= self.now - RATE_WINDOW_S))

    def snapshot(self, since: int | None = None, *, columns: bool = True) -> dict[str, Any]:
        """The whole state as JSON-ready data.

        Args:
            since: the ``seq`` of the previous snapshot; only samples newer than it are
                included (``None``: every sample of the window, for a new viewer).
            columns: ``False`` leaves each actuator's ``series`` as a copy of its sample
                rows, for :func:`with_columns` to turn into columns later, elsewhere (a
                thread of its own: the copy is the only part that must be taken where
                the state is fed, and the cheap one); nothing in it is changed later.
        """
        return {
            "type": "full" if since is None else "delta",
            "seq": self.seq,
            "t": self._rel(self.now) or 0.0,
            "window_s": WINDOW_S,
            "period_s": self.period,
            "control": self.control,
            "window": list(self.window),
            "recording": self.recording,
            "buses": [self._bus_json(v, since, columns) for v in self.buses.values()],
        }

    def _bus_json(self, view: BusView, since: int | None, columns: bool) -> dict[str, Any]:
        stats = view.stats
        return {
            "name": view.name,
            "state": view.state,
            "detail": view.detail,
            "frames_per_s": self.frames_per_s(view.name),
            "requests": stats.get("requests", 0),
            "timeouts": stats.get("timeouts", 0),
            "late_replies": stats.get("late_replies", 0),
            "garbage_bytes": stats.get("garbage_bytes", 0),
            "poll_load": None if view.poll_load is None else round(view.poll_load, 4),
            "min_write_gap_ms": None
            if view.min_gap is None or view.served is not None
            else round(view.min_gap * 1e3, 3),
            "latency": stats.get("latency", {}),
            "reply_hist": view.reply_times.to_json(),
            "events": list(view.events),
            "la": [
                self._la_json(d, since, columns)
                for d in sorted(view.la.values(), key=lambda d: d.id)
            ],
            # Changed in place as frames come: a snapshot rendered elsewhere takes copies.
            "project": view.project if columns else copy.deepcopy(view.project),
            "quad": view.quad if columns else copy.deepcopy(view.quad),
            "served": view.served,
            "leases": list(view.leases),
        }

    def _la_json(self, dev: LAView, since: int | None, columns: bool) -> dict[str, Any]:
        rows = list(dev.samples) if since is None else [s for s in dev.samples if s[0] > since]
        series: Any = columns_of(rows, self.epoch) if columns else rows
        return {
            "id": dev.id,
            "mode": dev.mode,
            "errors": error_names(dev.errors),
            "latest": dev.latest(),
            "age_s": None if dev.last_reply is None else round(self.now - dev.last_reply, 3),
            "polls": dev.polls,
            "jitter_hist": dev.jitter.to_json(),
            "series": series,
        }


def _relative(t: float | None, epoch: float | None) -> float | None:
    if t is None or epoch is None:
        return None
    return round(t - epoch, 6)


def columns_of(rows: list[tuple[Any, ...]], epoch: float | None) -> dict[str, list[Any]]:
    """An actuator's sample rows as the page's columns (``t`` relative to ``epoch``)."""
    series: dict[str, list[Any]] = {"t": [_relative(r[1], epoch) for r in rows]}
    for k, name in enumerate(SERIES):
        series[name] = [r[2 + k] for r in rows]
    return series


def with_columns(snapshot: dict[str, Any], epoch: float | None) -> dict[str, Any]:
    """``snapshot`` (from ``snapshot(columns=False)``) with its rows turned into columns,
    in place; pure, so it may run in any thread."""
    for bus in snapshot["buses"]:
        for dev in bus["la"]:
            if isinstance(dev["series"], list):
                dev["series"] = columns_of(dev["series"], epoch)
    return snapshot
