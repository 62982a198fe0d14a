"""Many buses in one program: built from code or a TOML file, opened together, stopped safely.

``BusManager`` opens every bus concurrently in an anyio task group, gives each bus a
``Streamer`` whose tick grid is phase-offset from the other buses' (so 32 buses at
100 Hz do not all wake at once), and on the way out - normal exit, exception,
cancellation or Ctrl-C - brings every configured device to its safe state before the
ports close: LA actuators pause (or e-stop, or hold, per bus), project steppers get
"stop project" and their motor stopped, quad steppers "stop all".

The bus file and its schema (every key, its type and range) are
:mod:`motorbus.busfile`, which the command line reads too.  A program that serves one
process group of a bus file (``from_toml(path, process="arms")``) opens that group's
buses only and, while they are open, runs on the group's CPUs.
"""

from __future__ import annotations

import dataclasses
import enum
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Any

import anyio

from motorbus.bus.bus import Bus
from motorbus.busfile import (
    BusSpec,
    DeviceSpec,
    buses_and_groups,
    check_distinct,
    default_bus_file,
    labelled,
    load_bus_file,
    parse_devices,
)
from motorbus.devices.calibration import FULL_STROKE, limited_targets
from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError, MotorbusError
from motorbus.protocol import project_stepper as ps
from motorbus.protocol.base import Command, check_flag
from motorbus.runtime import guard as guard_process
from motorbus.runtime import realtime, shutdown
from motorbus.runtime.process_groups import ProcessGroup, choose_group
from motorbus.runtime.shutdown import deferred_interrupts
from motorbus.streams import SafeAction, Stream, Streamer
from motorbus.transport.base import Transport, check_transport
from motorbus.transport.serial import open_transport

if TYPE_CHECKING:  # loaded on first use: a manager of LA actuators never builds them
    from motorbus.devices.project_stepper import ProjectStepper
    from motorbus.devices.quad_stepper import QuadStepper

__all__ = [
    "BusManager",
    "BusSpec",
    "DeviceSpec",
    "DeviceStop",
    "StopReport",
    "default_bus_file",
    "parse_devices",
]

log = logging.getLogger("motorbus.manager")

#: Longest a safe stop may take on the way out before the ports close anyway.
SAFE_STOP_TIMEOUT_S = 2.0
#: Ticks of the buses are spread over this span (the shortest stream period)...
PHASE_SPAN_S = 0.010
#: ... in this many phase groups.  Buses of one group share their wake-ups: on this
#: platform a wake-up of its own costs 180-600 us of CPU while tasks sharing one cost
#: 30-90 us each (benchmarks/bench_wakeups.py), so 32 buses in 4
#: groups cost a fraction of 32 separate wake-ups, and the groups still keep the buses
#: from all writing at the same instant.
PHASE_GROUPS = 4


@dataclass(slots=True)
class DeviceStop:
    """What the safe stop did for one device: ``outcome`` is "confirmed" (it answered),
    "sent" (a command that has no reply was written), "failed" or "pending"."""

    bus: str
    device: str
    command: str
    outcome: str = "pending"
    detail: str = ""

    def __str__(self) -> str:
        extra = f": {self.detail}" if self.detail else ""
        return f"bus {self.bus}: {self.device} {self.command} {self.outcome}{extra}"


@dataclass(slots=True)
class StopReport:
    """The safe stop of every device of a ``BusManager``, one entry per command."""

    entries: list[DeviceStop] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True only if every device acknowledged its stop or was sent it."""
        return all(e.outcome in ("confirmed", "sent") for e in self.entries)

    def unconfirmed(self) -> list[DeviceStop]:
        """The entries that did not reach their device (failed or never finished)."""
        return [e for e in self.entries if e.outcome not in ("confirmed", "sent")]

    def __str__(self) -> str:
        if self.ok:
            return f"stopped safely: {len(self.entries)} stop commands confirmed or sent"
        bad = self.unconfirmed()
        return "safe stop INCOMPLETE, not confirmed:\n" + "\n".join(f"  {e}" for e in bad)


class BusManager:
    """Opens many buses together, hands out their devices, and stops them safely.

    Use as ``async with BusManager.from_toml("buses.toml") as mgr:`` or build it with
    ``add_bus``.  Devices: ``mgr.la("arm", 3)``, ``mgr.device("gripper")`` (named and
    calibrated in the bus file), ``mgr.project_stepper("feeder")``,
    ``mgr.quad_stepper("feeder")``; streaming: ``mgr.streamer("arm")``, or
    ``mgr.follow(["gripper"], ...)`` in the devices' units within their soft limits.
    """

    def __init__(self, *, safe_stop: bool = True) -> None:
        self.safe_stop = check_flag("safe_stop", safe_stop)
        #: What the last safe stop could not do (empty if every device was reached).
        self.safe_stop_failures: list[str] = []
        #: The last safe stop, device by device (None before the first close).
        self.stop_report: StopReport | None = None
        self.specs: dict[str, BusSpec] = {}
        self.buses: dict[str, Bus] = {}
        self._transports: dict[str, Transport] = {}
        self._streamers: dict[str, Streamer] = {}
        #: Why each bus that failed in the last ``open`` failed (bus name -> error).
        self.open_errors: dict[str, Exception] = {}
        #: The process group of the bus file this manager serves (``from_toml(...,
        #: process=NAME)``); while its buses are open, every thread of the process runs
        #: on the group's ``cpus``.  ``None``: no group, no pinning.
        self.process: ProcessGroup | None = None
        self._pinning: realtime.Pinning | None = None

    # -- building -----------------------------------------------------------------

    @classmethod
    def from_toml(
        cls, path: str | Path | None = None, *, process: str | None = None, **kwargs: Any
    ) -> BusManager:
        """Load a bus file (see :mod:`motorbus.busfile`); every key is checked here.

        Args:
            path: the bus file; default :func:`default_bus_file` (the user's config file).
            process: serve this process group of the file: open only the buses whose
                ``process`` is ``process`` (not the buses of no group), and on
                :meth:`open` run every thread of the process on the group's ``cpus``
                until :meth:`close`.  ``None``: every bus of the file, no pinning.
            **kwargs: passed to the constructor (``safe_stop``).

        Raises:
            LocalProtocolError: the file is not TOML, a key is unknown, of the wrong type
                or out of range (the message names the file, the bus or group and the
                key), or the file has no group ``process`` (the message names its groups).
            OSError: the file cannot be read.
        """
        if path is None:
            path = default_bus_file()
            if path is None:
                raise FileNotFoundError("no bus file given and no home directory to look in")
        bus_file = load_bus_file(path)
        mgr = cls(**kwargs)
        mgr.process = None if process is None else bus_file.group(process)
        for spec in bus_file.specs_of(process):
            mgr.add_spec(spec)
        return mgr

    @classmethod
    def from_dict(
        cls, data: Mapping[str, Any], *, process: str | None = None, **kwargs: Any
    ) -> BusManager:
        """Build from parsed TOML: ``{"bus": [{...}, ...], "process": {...}}``; every key
        is checked here, and two buses may not share a name or a port.  ``process``
        chooses a process group, as in :meth:`from_toml`."""
        specs, groups = buses_and_groups(data)
        mgr = cls(**kwargs)
        if process is not None:
            mgr.process = choose_group(groups, process)
        for spec in specs:
            if process is None or spec.process == process:
                mgr.add_spec(spec)
        return mgr

    def add_spec(self, spec: BusSpec, transport: Transport | None = None) -> None:
        """Add a bus; ``transport`` overrides opening ``spec.url`` (e.g. an in-memory link)."""
        if not isinstance(spec, BusSpec):
            raise LocalProtocolError(f"spec must be a BusSpec, got {spec!r}", field="spec")
        if transport is not None:
            check_transport(transport)  # else it failed only when the manager opened
        try:
            check_distinct(spec, list(self.specs.values()))
        except LocalProtocolError as err:
            raise labelled(f"bus {spec.name!r} (#{len(self.specs) + 1})", err) from None
        self.specs[spec.name] = spec
        if transport is not None:
            self._transports[spec.name] = transport

    def add_bus(
        self,
        name: str,
        url: str,
        *,
        baud: int,
        devices: Sequence[str] = (),
        transport: Transport | None = None,
        **options: Any,
    ) -> None:
        """Add a bus from code; ``options`` are the ``BusSpec`` fields (backend, rs485...)."""
        spec = BusSpec.from_mapping(
            {"name": name, "url": url, "baud": baud, "devices": devices, **options},
            len(self.specs),
        )
        self.add_spec(spec, transport)

    # -- life cycle -----------------------------------------------------------------

    async def __aenter__(self) -> BusManager:
        await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    async def open(self) -> None:
        """Open every bus concurrently; if any fails, close the others and raise.

        What is raised is the first failure (in bus order) that is an ``OSError`` or a
        ``MotorbusError`` - so ``except OSError`` catches a missing port - else the first
        failure; a note on it names its bus, and the failures of the other buses are
        attached as further notes and kept in :attr:`open_errors` (bus name -> error).

        If :attr:`process` gives CPUs, every thread of the process is moved onto them
        first, before the guard starts and any port opens (so what they start runs there
        too); :meth:`close`, or a failed open, gives the threads their CPUs back.  A set
        the kernel refuses raises ``OSError`` naming the group, and nothing is opened.
        """
        realtime.on_bus_open()  # a bad MOTORBUS_REALTIME fails before any port opens
        self._pin()  # before the guard and the ports: what they start runs there too
        try:
            await self._open_buses()
        except BaseException:
            self._unpin()
            raise
        shutdown.register_manager(self)

    def _pin(self) -> None:
        """Run every thread on the process group's CPUs (if it gives any)."""
        group = self.process
        if group is None or group.cpus is None or self._pinning is not None:
            return
        try:
            self._pinning = realtime.pin(group.cpus)
        except OSError as err:
            raise OSError(err.errno, f"process group {group.name!r}: {err.strerror}") from err

    def _unpin(self) -> None:
        if self._pinning is not None:
            self._pinning.restore()
            self._pinning = None

    async def _open_buses(self) -> None:
        if any(spec.guard for spec in self.specs.values()):
            # Before the buses open (it follows each one); a Python start-up, off the loop.
            await anyio.to_thread.run_sync(guard_process.start_guard)
        self.open_errors = {}
        try:
            for i, (name, spec) in enumerate(self.specs.items()):
                transport = self._transports.get(name) or open_transport(
                    spec.url, baudrate=spec.baud, backend=spec.backend, **spec.transport_options()
                )
                bus = Bus(
                    transport,
                    name=name,
                    families=spec.families(),
                    min_spacing=spec.min_spacing_ms / 1e3,
                    host_margin=spec.host_margin_ms / 1e3,
                    retries=spec.retries,
                    # Devices moved outside any lease end like the configured ones.
                    safe_action=spec.la_safe_action,
                )
                self.buses[name] = bus
                phase = (i % PHASE_GROUPS) * PHASE_SPAN_S / PHASE_GROUPS
                self._streamers[name] = _LimitedStreamer(bus, phase=phase)
        except BaseException:
            self.buses.clear()
            self._streamers.clear()
            raise

        async def open_one(name: str, bus: Bus) -> None:
            try:
                await bus.open()
            except Exception as err:  # gathered; cancellation is not
                self.open_errors[name] = err

        try:
            async with anyio.create_task_group() as tg:
                for name, bus in self.buses.items():
                    tg.start_soon(open_one, name, bus)
        except BaseException:  # cancelled while opening: still close what was opened
            with anyio.CancelScope(shield=True):
                await self._close_buses()
            raise
        if self.open_errors:
            with anyio.CancelScope(shield=True):
                await self._close_buses()
            raise self._open_failure()

    def _open_failure(self) -> Exception:
        failed = [(n, self.open_errors[n]) for n in self.specs if n in self.open_errors]
        name, first = next(
            ((n, e) for n, e in failed if isinstance(e, OSError | MotorbusError)), failed[0]
        )
        first.add_note(f"while opening bus {name!r} ({self.specs[name].url})")
        for other, err in failed:
            if other != name:
                first.add_note(
                    f"bus {other!r} ({self.specs[other].url}) failed too: "
                    f"{type(err).__name__}: {err}"
                )
        return first

    async def close(self) -> None:
        """Safe-stop every device (shielded from cancellation, bounded in time), then close.

        Ctrl-C during the stop is deferred until it is done; one device's failure never
        keeps the others from their stop, and the ports always close.  The outcome is in
        ``stop_report`` (and its failures in ``safe_stop_failures``).
        """
        with anyio.CancelScope(shield=True), deferred_interrupts():
            try:
                # Streams end first: a follow target sent after a pause would resume the
                # actuator (manual 3.5.4), undoing the safe stop.
                for streamer in self._streamers.values():
                    try:
                        await streamer.close(safe=False)
                    except Exception as err:
                        log.error("ending the streams failed: %s", err)
                if self.safe_stop and self.buses:
                    await self.stop_all_devices()
            finally:
                await self._close_buses()
                self._unpin()
                shutdown.unregister_manager(self)

    async def _close_buses(self) -> None:
        # Streams were ended by close() (or never started, when open failed); a bus's own
        # close hook stops any stream still running on it.
        async with anyio.create_task_group() as tg:
            for bus in self.buses.values():
                tg.start_soon(self._close_one, bus)

    @staticmethod
    async def _close_one(bus: Bus) -> None:
        try:
            await bus.close()
        except Exception as err:
            log.error("closing bus %s failed: %s", bus.name, err)

    async def stop_all_devices(self) -> StopReport:
        """Bring every configured device to its safe state, all buses in parallel.

        Bounded by ``SAFE_STOP_TIMEOUT_S``; what did not finish is reported as failed.
        Returns the report (also kept in ``stop_report``).
        """
        report = StopReport()
        plans = {name: self._stop_plan(name, report) for name in self.buses}
        with anyio.move_on_after(SAFE_STOP_TIMEOUT_S):
            async with anyio.create_task_group() as tg:
                for name, plan in plans.items():
                    tg.start_soon(self._run_stop_plan, name, plan)
        for entry in report.entries:
            if entry.outcome == "pending":
                entry.outcome = "failed"
                entry.detail = f"not confirmed within {SAFE_STOP_TIMEOUT_S:g} s"
        self.stop_report = report
        self.safe_stop_failures = [str(e) for e in report.unconfirmed()]
        for failure in self.safe_stop_failures:
            log.warning("safe stop: %s", failure)
        return report

    def _stop_plan(self, name: str, report: StopReport) -> list[tuple[DeviceStop, Command[object]]]:
        """The stop commands of every device on bus ``name``, each with its report entry."""
        spec = self.specs[name]
        bus = self.buses[name]
        action = SafeAction(spec.la_safe_action).value
        plan: list[tuple[DeviceStop, Command[object]]] = []
        for dev in spec.devices:
            try:
                # The bus's lease table defines every safe action (the steppers know one
                # way to stop: pause and e-stop both send it).
                keys = [f"la:{i}" for i in dev.ids] if dev.kind == "la" else [dev.kind]
                for key in keys:
                    motor = dev.motor if dev.kind == "project_stepper" else None
                    commands = bus.lease_keeper.safe_commands(
                        key, action if dev.kind == "la" else "pause", motor=motor
                    )
                    for cmd in commands:
                        entry = DeviceStop(name, key, _describe(cmd))
                        report.entries.append(entry)
                        plan.append((entry, cmd))
            except Exception as err:  # one device's bad setting must not stop the others
                report.entries.append(DeviceStop(name, dev.kind, "stop", "failed", str(err)))
        return plan

    async def _run_stop_plan(
        self, name: str, plan: list[tuple[DeviceStop, Command[object]]]
    ) -> None:
        keeper = self.buses[name].lease_keeper
        results = await keeper.send_stop([cmd for _, cmd in plan], who="BusManager")
        for (entry, cmd), result in zip(plan, results, strict=True):
            if isinstance(result, BaseException):
                entry.outcome, entry.detail = "failed", str(result)
            else:
                entry.outcome = "confirmed" if cmd.expects_reply else "sent"

    # -- devices ----------------------------------------------------------------------

    def bus(self, name: str) -> Bus:
        """The bus called ``name`` (the manager open: ``async with`` or ``open()``)."""
        try:
            return self.buses[name]
        except (KeyError, TypeError):
            if isinstance(name, str) and name in self.specs:
                raise LocalProtocolError(
                    f"bus {name!r} is not open: use the manager as `async with mgr:` (or "
                    "await mgr.open()) before asking for its buses and devices",
                    field="bus",
                    value=name,
                ) from None
            raise LocalProtocolError(
                f"no bus named {name!r}; buses: {sorted(self.specs)}", field="bus", value=name
            ) from None

    def la(self, bus: str, id: int) -> InspireLA:
        """The LA actuator ``id`` on bus ``bus`` (with the bus's ``la_stroke_mm``).

        If the bus file names it (``[bus.la.NAME]``), it has its name and calibration
        (soft limits, stroke) but raw units, so a program that addresses actuators by ID
        is unchanged; :meth:`device` gives it with the unit of its calibration.
        """
        handle = self.bus(bus)
        spec = self.specs[bus]
        for named in spec.la:
            if named.id == id:
                cal = dataclasses.replace(named.calibration, unit="raw")
                return InspireLA(handle, id, calibration=cal, name=named.name)
        return InspireLA(handle, id, stroke_mm=spec.la_stroke_mm)

    def device(self, name: str) -> InspireLA:
        """The actuator the bus file names ``name`` (``[bus.la.NAME]``), calibrated: its
        positions are in its calibration's unit (raw, mm or percent) and every move is
        checked against its soft limits before anything is sent.

        Raises:
            LocalProtocolError: no device of that name (the message lists the names).
        """
        for bus, spec in self.specs.items():
            for named in spec.la:
                if named.name == name:
                    return InspireLA(
                        self.bus(bus), named.id, calibration=named.calibration, name=name
                    )
        names = sorted(n.name for spec in self.specs.values() for n in spec.la)
        raise LocalProtocolError(
            f"no device named {name!r}; named devices: {names or 'none'} ([bus.la.NAME] "
            "tables of the bus file)",
            field="device",
            value=name,
        )

    def follow(
        self,
        devices: str | InspireLA | Sequence[str | InspireLA],
        targets: Any,
        *,
        unit: str | None = None,
        **options: Any,
    ) -> Stream:
        """Stream follow targets to named (or any) actuators of one bus, in their units.

        ``devices``: names (:meth:`device`) or actuators; ``targets``: as for
        ``Streamer.follow`` but in ``unit`` (default each device's own), or mappings by
        name.  Every target is checked against its device's soft limits: a sequence
        whole, before the stream starts (nothing sent); a live source item by item (a
        target outside the limits ends the stream with its safe action, unsent).
        ``options`` are those of ``Streamer.follow``.

        Raises:
            LocalProtocolError: an unknown name, devices of several buses, a target
                outside the limits (see above), or a bad option.
        """
        items = [devices] if isinstance(devices, str | InspireLA) else list(devices)
        group = [self.device(d) if isinstance(d, str) else d for d in items]
        if not group:
            raise LocalProtocolError("devices must name at least one device", field="devices")
        buses = sorted({d.bus.name for d in group})
        if len(buses) != 1:
            raise LocalProtocolError(
                f"devices are on buses {buses}: one stream drives one bus", field="devices"
            )
        source = limited_targets(group, targets, unit)
        # Converted and checked here: the streamer's own check would find nothing more.
        return Streamer.follow(self.streamer(buses[0]), group, source, **options)

    def project_stepper(self, bus: str) -> ProjectStepper:
        """The project stepper on bus ``bus`` (its motor byte from the bus spec)."""
        from motorbus.devices.project_stepper import ProjectStepper

        handle = self.bus(bus)  # a bus that is not there is named first
        motor = next(
            (d.motor for d in self.specs[bus].devices if d.kind == "project_stepper"),
            ps.DEFAULT_MOTOR,
        )
        return ProjectStepper(handle, motor=motor)

    def quad_stepper(self, bus: str) -> QuadStepper:
        """The quad stepper on bus ``bus``."""
        from motorbus.devices.quad_stepper import QuadStepper

        return QuadStepper(self.bus(bus))

    def streamer(self, bus: str) -> Streamer:
        """The streamer of bus ``bus`` (phase-offset from the other buses)."""
        self.bus(bus)
        return self._streamers[bus]


class _LimitedStreamer(Streamer):
    """The manager's streamers: the targets of actuators with soft limits narrower than
    the stroke (named devices) are checked against them, in raw units as
    ``Streamer.follow`` takes them (see ``limited_targets``); others pass as before."""

    def follow(
        self, actuators: InspireLA | Sequence[InspireLA], targets: Any, **options: Any
    ) -> Stream:
        group = [actuators] if isinstance(actuators, InspireLA) else actuators
        if isinstance(group, Sequence) and any(
            isinstance(a, InspireLA) and a.calibration.limits != FULL_STROKE for a in group
        ):
            targets = limited_targets(list(group), targets, "raw")
        return super().follow(actuators, targets, **options)


def _describe(cmd: Command[object]) -> str:
    """A stop command as the report names it: ``Control(PAUSE)``, ``StopProject``..."""
    action = getattr(cmd, "action", None)
    name = type(cmd).__name__
    return f"{name}({action.name})" if isinstance(action, enum.Enum) else name
