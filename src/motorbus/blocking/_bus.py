"""Blocking buses, leases, managers and group reads."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any, Literal, TypeVar, overload

from motorbus import manager as _manager
from motorbus.blocking._devices import InspireLA
from motorbus.blocking._events import EventHub
from motorbus.blocking._proxy import Closing, Proxy, coroutine
from motorbus.blocking._runner import runner
from motorbus.blocking._streams import Streamer
from motorbus.bus import bus as _bus
from motorbus.bus import leases as _leases
from motorbus.bus.bus import Priority
from motorbus.devices import group as _group
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol.base import Command
from motorbus.transport.base import Transport

if TYPE_CHECKING:
    from motorbus.blocking._steppers import ProjectStepper, QuadStepper

__all__ = ["Bus", "BusManager", "BusView", "Lease", "read_statuses"]

R = TypeVar("R")
B = TypeVar("B")


class BusView(Closing, Proxy[B]):
    """What a local :class:`Bus` and a served one (:class:`motorbus.blocking.ServedBus`,
    ``connect(...).bus()``) have alike: requests, group reads, the devices, streams and
    events on them, and ``with``.  The devices and streams take either."""

    @property
    def name(self) -> str:
        """The bus's label (a local bus's default: the transport URL)."""
        name: str = self._any.name
        return name

    @property
    def _any(self) -> Any:
        return self._aio

    @property
    def events(self) -> EventHub:
        """The bus's events (``FaultChanged``, ``ProjectFinished``, ``QuadDone``,
        ``BusStateChanged``, ``StreamGap``): ``with bus.events.subscribe(Kind) as sub:``
        then ``sub.next(timeout=...)`` or ``for event in sub:``."""
        return EventHub._of(self._any.events, self._runner)

    # -- requests ----------------------------------------------------------------------

    def request(
        self,
        cmd: Command[R],
        *,
        timeout: float | None = None,
        retries: int | None = None,
        priority: Priority = Priority.NORMAL,
    ) -> R:
        """Send ``cmd`` and return its decoded reply; see :meth:`motorbus.Bus.request`."""
        result: R = self._runner.call(
            self._any.request(cmd, timeout=timeout, retries=retries, priority=priority)
        )
        return result

    def send(self, cmd: Command[object], *, priority: Priority = Priority.NORMAL) -> None:
        """Send a command that expects no reply; see :meth:`motorbus.Bus.send`."""
        self._runner.call(self._any.send(cmd, priority=priority))

    @overload
    def read_statuses(
        self,
        ids: Iterable[int],
        *,
        on_error: Literal["raise"] = "raise",
        timeout: float | None = None,
    ) -> dict[int, la.Status]: ...

    @overload
    def read_statuses(
        self,
        ids: Iterable[int],
        *,
        on_error: Literal["return"],
        timeout: float | None = None,
    ) -> dict[int, la.Status | Exception]: ...

    def read_statuses(
        self,
        ids: Iterable[int],
        *,
        on_error: Literal["raise", "return"] = "raise",
        timeout: float | None = None,
    ) -> dict[int, la.Status] | dict[int, la.Status | Exception]:
        """The status of every LA in ``ids``, queried at once: ``read_statuses(self, ...)``."""
        if on_error == "return":
            return read_statuses(self, ids, on_error="return", timeout=timeout)
        return read_statuses(self, ids, timeout=timeout)

    # -- devices, streams --------------------------------------------------------------

    def la(self, id: int, *, stroke_mm: float | None = None) -> InspireLA:
        """The LA actuator ``id`` on this bus (``InspireLA(bus, id, stroke_mm=...)``)."""
        return InspireLA(self, id, stroke_mm=stroke_mm)

    def project_stepper(self, *, motor: int = ps.DEFAULT_MOTOR) -> ProjectStepper:
        """The project stepper controller on this bus."""
        from motorbus.blocking._steppers import ProjectStepper

        return ProjectStepper(self, motor=motor)

    def quad_stepper(self) -> QuadStepper:
        """The 4-axis stepper controller on this bus."""
        from motorbus.blocking._steppers import QuadStepper

        return QuadStepper(self)

    def streamer(self, *, phase: float = 0.0, lead: float | None = None) -> Streamer:
        """A new streamer of this bus (``Streamer(bus, phase=..., lead=...)``)."""
        return Streamer(self, phase=phase, lead=lead)


class Bus(BusView[_bus.Bus]):
    """A serial bus, opened now and driven without ``await``: :class:`motorbus.Bus` on a
    thread of its own.

    ``Bus(transport, families=[...], ...)`` takes the arguments of
    :class:`motorbus.Bus`, checks them and opens the port before it returns.  Close it
    with ``close()`` or use it as a context manager: closing runs the same safe ends as
    the asyncio bus's ``async with`` exit (streams stop with their safe action, every
    leased device gets its own, then the port closes), also when the block is left by
    an exception or Ctrl-C, and for a bus still open when the interpreter exits.

    Raises:
        LocalProtocolError: a bad option (nothing is opened).
        OSError: the port cannot open.
    """

    def __init__(self, transport: Transport, **options: Any) -> None:
        self._runner = runner()

        async def open_bus() -> _bus.Bus:
            bus = _bus.Bus(transport, **options)
            await bus.open()
            return bus

        self._aio = self._runner.call(open_bus())
        self._runner.opened()

    # -- what the bus is ---------------------------------------------------------------

    @property
    def state(self) -> _bus.BusState:
        """``BusState.OPEN``, ``LOST`` (reconnecting) or ``CLOSED``."""
        return self._aio.state

    @property
    def closed(self) -> bool:
        """True once the bus is closed."""
        return self._aio.state is _bus.BusState.CLOSED

    @property
    def stats(self) -> Any:
        """The bus's counters (``motorbus.Bus.stats``; read them, do not change them)."""
        return self._aio.stats

    def fetch_stats(self) -> dict[str, Any]:
        """A copy of the bus's counters as plain data (``BusStats.as_dict``): what a
        served bus's ``fetch_stats()`` gives, so a program that reads them this way
        runs on both."""
        return self._runner.call_sync(lambda: dict(self._aio.stats.as_dict()))

    @property
    def leases(self) -> tuple[_leases.LeaseInfo, ...]:
        """Every leased device now: key, owner and the frames of its safe action."""
        return self._runner.call_sync(lambda: self._aio.leases)

    release = coroutine(_bus.Bus.release)

    # -- leases ------------------------------------------------------------------------

    def lease(
        self,
        keys: Iterable[str] | str,
        *,
        owner: str,
        safe_action: str = "pause",
        safe_commands: Iterable[Command[object]] = (),
    ) -> Lease:
        """Hold ``keys`` for ``owner`` from now on (see :meth:`motorbus.Bus.lease`).

        The lease belongs to the calling thread: the motion it sends from now on is the
        lease's.  ``with bus.lease(...):`` releases it with its safe action however the
        block is left.

        Raises:
            LeaseConflictError: another owner holds one of the devices.
            LocalProtocolError: a bad key, owner or action.
        """
        commands = tuple(safe_commands)

        def take() -> _leases.Lease:
            return self._aio.lease(
                keys, owner=owner, safe_action=safe_action, bind=False, safe_commands=commands
            )

        lease = self._runner.call_sync(take)
        # The calling thread's context: every later call from it carries the lease.
        _leases.bind(lease)
        return Lease._of(lease, self._runner)

    # -- closing -----------------------------------------------------------------------

    def close(self) -> None:
        """Stop what runs on the bus safely, then close the port (idempotent).

        A Ctrl-C during the safe stop is raised once the stop is done.
        """
        self._runner.finish(self._aio.close())


class Lease(Proxy[_leases.Lease]):
    """A claim on devices: :class:`motorbus.Lease` without ``await``; made by ``Bus.lease``."""

    @property
    def owner(self) -> str:
        """The name given at acquisition."""
        return self._aio.owner

    @property
    def keys(self) -> frozenset[str]:
        """The devices the lease holds now."""
        return self._runner.call_sync(lambda: self._aio.keys)

    @property
    def active(self) -> bool:
        """True until the lease is released."""
        return self._aio.active

    def release(self, *, hold: bool = False, keys: Iterable[str] | None = None) -> None:
        """End the lease (see :meth:`motorbus.Lease.release`); Ctrl-C waits for the
        safe action to go out."""
        wanted = None if keys is None else tuple(keys)
        self._runner.finish(self._aio.release(hold=hold, keys=wanted))

    def __enter__(self) -> Lease:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.release()


class BusManager(Closing, Proxy[_manager.BusManager]):
    """Many buses from a bus file, opened together: :class:`motorbus.BusManager` without
    ``await``.  Make it with :meth:`from_toml` or :meth:`from_dict` (which open every
    bus before they return) or :meth:`open` (a manager you built); closing it stops
    every device safely (``stop_report``), as the asyncio manager does."""

    _views: dict[str, Bus]

    @classmethod
    def open(cls, manager: _manager.BusManager) -> BusManager:
        """Open every bus of ``manager`` (built with ``add_bus``) and return its view.

        Raises:
            OSError, MotorbusError: as :meth:`motorbus.BusManager.open`.
        """
        run = runner()
        run.call(manager.open())
        run.opened()
        proxy = cls._of(manager, run)
        proxy._views = {}
        return proxy

    @classmethod
    def from_toml(
        cls, path: str | Path | None = None, *, process: str | None = None, **kwargs: Any
    ) -> BusManager:
        """Load a bus file (:meth:`motorbus.BusManager.from_toml`) and open its buses."""
        return cls.open(_manager.BusManager.from_toml(path, process=process, **kwargs))

    @classmethod
    def from_dict(
        cls, data: Mapping[str, Any], *, process: str | None = None, **kwargs: Any
    ) -> BusManager:
        """Build from parsed TOML (:meth:`motorbus.BusManager.from_dict`) and open it."""
        return cls.open(_manager.BusManager.from_dict(data, process=process, **kwargs))

    @property
    def stop_report(self) -> _manager.StopReport | None:
        """The last safe stop, device by device (``None`` before the first close)."""
        return self._aio.stop_report

    def bus(self, name: str) -> Bus:
        """The bus called ``name``."""
        view = self._views.get(name)
        if view is None:
            view = self._views[name] = Bus._of(self._aio.bus(name), self._runner)
        return view

    def la(self, bus: str, id: int) -> InspireLA:
        """The LA actuator ``id`` on bus ``bus`` (with the bus's ``la_stroke_mm``)."""
        return InspireLA._on(self.bus(bus), self._aio.la(bus, id))

    def device(self, name: str) -> InspireLA:
        """The actuator the bus file names ``name``, calibrated
        (:meth:`motorbus.BusManager.device`).

        Raises:
            LocalProtocolError: no device of that name (the message lists the names).
        """
        aio = self._aio.device(name)
        return InspireLA._on(self.bus(aio.bus.name), aio)

    def project_stepper(self, bus: str) -> ProjectStepper:
        """The project stepper on bus ``bus`` (its motor byte from the bus spec)."""
        from motorbus.blocking._steppers import ProjectStepper

        return ProjectStepper(self.bus(bus), motor=self._aio.project_stepper(bus).motor)

    def quad_stepper(self, bus: str) -> QuadStepper:
        """The quad stepper on bus ``bus``."""
        from motorbus.blocking._steppers import QuadStepper

        return QuadStepper(self.bus(bus))

    def streamer(self, bus: str) -> Streamer:
        """The streamer of bus ``bus``."""
        return Streamer._on(self.bus(bus), self._runner.call_sync(self._aio.streamer, bus))

    stop_all_devices = coroutine(_manager.BusManager.stop_all_devices)

    def close(self) -> None:
        """Safe-stop every device, then close every bus (see
        :meth:`motorbus.BusManager.close`).  Ctrl-C waits for the stop to finish."""
        self._runner.finish(self._aio.close())


@overload
def read_statuses(
    bus: BusView[Any],
    ids: Iterable[int],
    *,
    on_error: Literal["raise"] = "raise",
    timeout: float | None = None,
) -> dict[int, la.Status]: ...


@overload
def read_statuses(
    bus: BusView[Any],
    ids: Iterable[int],
    *,
    on_error: Literal["return"],
    timeout: float | None = None,
) -> dict[int, la.Status | Exception]: ...


def read_statuses(
    bus: BusView[Any],
    ids: Iterable[int],
    *,
    on_error: Literal["raise", "return"] = "raise",
    timeout: float | None = None,
) -> dict[int, la.Status] | dict[int, la.Status | Exception]:
    """The status of every LA in ``ids``, queried at once and pipelined on the bus:
    :func:`motorbus.read_statuses` in one blocking call.

    Raises:
        LocalProtocolError: a bad ID list or option; nothing is sent.
        GroupReadError: ``on_error="raise"`` and some actuators gave no status.
    """
    wanted = _group.check_ids(ids)  # checked here, in the caller's thread
    if on_error == "return":
        return bus._runner.call(
            _group.read_statuses(bus._any, wanted, on_error="return", timeout=timeout)
        )
    _group.check_on_error(on_error)
    return bus._runner.call(_group.read_statuses(bus._any, wanted, timeout=timeout))
