"""Many buses in one program: built from code or a TOML file, opened together, stopped safely.

``BusManager`` opens every bus concurrently in an anyio task group, gives each bus a
``Streamer`` whose tick grid is phase-offset from the other buses' (so 32 buses at
100 Hz do not all wake at once), and on the way out - normal exit, exception,
cancellation or Ctrl-C - brings every configured device to its safe state before the
ports close: LA actuators pause (or e-stop, or hold, per bus), project steppers get
"stop project" and their motor stopped, quad steppers "stop all".

A bus file (TOML)::

    [[bus]]
    name = "arm"
    url = "/dev/ttyUSB0"          # any pyserial URL: socket://host:port, rfc2217://...
    baud = 921600
    backend = "fast"              # fast | serialx | pyserial-asyncio
    la_safe_action = "pause"      # pause | estop | hold
    devices = ["la:1-15"]

    [[bus]]
    name = "feeder"
    url = "socket://10.0.0.5:7012"
    baud = 9600
    devices = ["project-stepper:motor=3", "quad-stepper"]
"""

from __future__ import annotations

import contextlib
import enum
import logging
import re
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import anyio

from motorbus import realtime, shutdown
from motorbus.bus.bus import DEFAULT_HOST_MARGIN_S, Bus, Priority
from motorbus.devices.la import InspireLA
from motorbus.devices.project_stepper import ProjectStepper
from motorbus.devices.quad_stepper import QuadStepper
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol.base import Command, Family
from motorbus.shutdown import deferred_interrupts
from motorbus.streams import SafeAction, Streamer
from motorbus.transport.base import Transport
from motorbus.transport.serial import open_transport

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
#: Retries of each safe-stop command (pause, e-stop, stop project, stop all are
#: idempotent: sending one twice is harmless, missing one is not).
SAFE_STOP_RETRIES = 2
#: Ticks of the buses are spread over this span (the shortest stream period)...
PHASE_SPAN_S = 0.010
#: ... in this many phase groups.  Buses of one group share their wake-ups: on this
#: platform a wake-up of its own costs 180-600 us of CPU while tasks sharing one cost
#: 30-90 us each (benchmarks/bench_wakeups.py), so 32 buses in 4
#: groups cost a fraction of 32 separate wake-ups, and the groups still keep the buses
#: from all writing at the same instant.
PHASE_GROUPS = 4

#: Default host margin of a bus reached over the network (ser2net): a TCP hop adds
#: 100-150 us typically but far more under load, and a fresh ser2net connection
#: answers its first request 9-25 ms late (measured by tests/integration).
REMOTE_HOST_MARGIN_MS = 20.0
REMOTE_SCHEMES = ("socket://", "rfc2217://")

_BUS_KEYS = {
    "name",
    "url",
    "baud",
    "backend",
    "rs485",
    "remove_echo",
    "low_latency",
    "min_spacing_ms",
    "host_margin_ms",
    "retries",
    "la_safe_action",
    "devices",
}


@dataclass(frozen=True, slots=True)
class DeviceSpec:
    """A device on a bus: ``kind`` is "la", "project_stepper" or "quad_stepper"."""

    kind: str
    ids: tuple[int, ...] = ()
    motor: int = ps.DEFAULT_MOTOR


def parse_devices(items: Sequence[str]) -> list[DeviceSpec]:
    """Parse device strings: ``"la:1-15"``, ``"la:1,4,7"``, ``"project-stepper[:motor=N]"``,
    ``"quad-stepper"``.  Raises ``LocalProtocolError`` naming the bad item."""
    out: list[DeviceSpec] = []
    for item in items:
        kind, _, rest = str(item).partition(":")
        kind = kind.strip().replace("_", "-")
        if kind == "la":
            ids: list[int] = []
            for part in filter(None, rest.split(",")):
                m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+))?\s*", part)
                if not m:
                    raise LocalProtocolError(
                        f"device {item!r}: {part!r} is not an ID or a range like 1-15",
                        field="devices",
                    )
                lo = int(m.group(1))
                hi = int(m.group(2) or lo)
                for i in (lo, hi):
                    if not la.ID_MIN <= i <= la.ID_MAX:
                        raise LocalProtocolError(
                            f"device {item!r}: id={i} is out of range: allowed 1..254",
                            field="devices",
                        )
                ids.extend(range(lo, hi + 1))
            if not ids:
                raise LocalProtocolError(
                    f"device {item!r} lists no IDs: write la:1-15 or la:1,4,7", field="devices"
                )
            out.append(DeviceSpec("la", tuple(ids)))
        elif kind == "project-stepper":
            motor = ps.DEFAULT_MOTOR
            if rest:
                m = re.fullmatch(r"\s*motor\s*=\s*(\d+)\s*", rest)
                if not m:
                    raise LocalProtocolError(
                        f"device {item!r}: options are 'motor=N'", field="devices"
                    )
                motor = int(m.group(1))
            out.append(DeviceSpec("project_stepper", motor=motor))
        elif kind == "quad-stepper":
            out.append(DeviceSpec("quad_stepper"))
        else:
            raise LocalProtocolError(
                f"device {item!r}: kind {kind!r} is unknown: use la:IDS, project-stepper or "
                "quad-stepper",
                field="devices",
            )
    return out


@dataclass(slots=True)
class BusSpec:
    """How to open one bus and what is on it."""

    name: str
    url: str
    baud: int
    devices: list[DeviceSpec] = field(default_factory=list)
    backend: str = "fast"
    rs485: bool = False
    remove_echo: bool = False
    low_latency: bool = True
    min_spacing_ms: float = 1.0
    host_margin_ms: float = DEFAULT_HOST_MARGIN_S * 1e3
    retries: int = 1
    la_safe_action: str = "pause"

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], index: int = 0) -> BusSpec:
        """Build from one ``[[bus]]`` table; unknown keys are refused by name."""
        unknown = set(data) - _BUS_KEYS
        if unknown:
            raise LocalProtocolError(
                f"bus #{index + 1}: unknown keys {sorted(unknown)}; allowed: {sorted(_BUS_KEYS)}",
                field="bus",
            )
        for key in ("url", "baud"):
            if key not in data:
                raise LocalProtocolError(f"bus #{index + 1}: '{key}' is required", field=key)
        baud = data["baud"]
        if isinstance(baud, bool) or not isinstance(baud, int) or baud <= 0:
            raise LocalProtocolError(
                f"bus #{index + 1}: baud={baud!r} must be a positive integer", field="baud"
            )
        safe = data.get("la_safe_action", "pause")
        if safe not in {a.value for a in SafeAction}:
            raise LocalProtocolError(
                f"bus #{index + 1}: la_safe_action={safe!r}: choose pause, estop or hold",
                field="la_safe_action",
            )
        devices = parse_devices(list(data.get("devices", [])))
        ids = [i for d in devices for i in d.ids]
        twice = sorted({i for i in ids if ids.count(i) > 1})
        if twice:
            # Two actuators with one ID on a bus answer together (A2-12).
            raise LocalProtocolError(
                f"bus #{index + 1}: la ids {twice} are listed twice: each ID once per bus",
                field="devices",
            )
        kinds = [d.kind for d in devices if d.kind != "la"]
        for kind in set(kinds):
            if kinds.count(kind) > 1:
                raise LocalProtocolError(
                    f"bus #{index + 1}: {kind} is listed twice: at most one per bus",
                    field="devices",
                )
        return cls(
            name=str(data.get("name", f"bus{index}")),
            url=str(data["url"]),
            baud=baud,
            devices=devices,
            backend=str(data.get("backend", "fast")),
            rs485=bool(data.get("rs485", False)),
            remove_echo=bool(data.get("remove_echo", False)),
            low_latency=bool(data.get("low_latency", True)),
            min_spacing_ms=float(data.get("min_spacing_ms", 1.0)),
            host_margin_ms=float(
                data.get(
                    "host_margin_ms",
                    REMOTE_HOST_MARGIN_MS
                    if str(data["url"]).startswith(REMOTE_SCHEMES)
                    else DEFAULT_HOST_MARGIN_S * 1e3,
                )
            ),
            retries=int(data.get("retries", 1)),
            la_safe_action=safe,
        )

    def families(self) -> set[Family]:
        """The protocol families its devices speak (all three if none are listed)."""
        kinds = {
            "la": Family.LA,
            "project_stepper": Family.PROJECT_STEPPER,
            "quad_stepper": Family.QUAD_STEPPER,
        }
        return {kinds[d.kind] for d in self.devices} or set(Family)


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
    ``add_bus``.  Devices: ``mgr.la("arm", 3)``, ``mgr.project_stepper("feeder")``,
    ``mgr.quad_stepper("feeder")``; streaming: ``mgr.streamer("arm")``.
    """

    def __init__(self, *, safe_stop: bool = True) -> None:
        self.safe_stop = safe_stop
        #: What the last safe stop could not do (empty if every device was reached).
        self.safe_stop_failures: list[str] = []
        #: The last safe stop, device by device (None before the first close).
        self.stop_report: StopReport | None = None
        self.specs: dict[str, BusSpec] = {}
        self.buses: dict[str, Bus] = {}
        self._transports: dict[str, Transport] = {}
        self._streamers: dict[str, Streamer] = {}

    # -- building -----------------------------------------------------------------

    @classmethod
    def from_toml(cls, path: str | Path | None = None, **kwargs: Any) -> BusManager:
        """Load a bus file (see the module docstring); default: :func:`default_bus_file`."""
        if path is None:
            path = default_bus_file()
            if path is None:
                raise FileNotFoundError("no bus file given and no home directory to look in")
        with open(path, "rb") as fh:
            try:
                data = tomllib.load(fh)
            except tomllib.TOMLDecodeError as err:
                raise LocalProtocolError(f"{path}: not valid TOML: {err}", field="file") from err
        return cls.from_dict(data, **kwargs)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], **kwargs: Any) -> BusManager:
        """Build from parsed TOML: ``{"bus": [{...}, ...]}``."""
        tables = data.get("bus")
        if not isinstance(tables, list) or not tables:
            raise LocalProtocolError("the bus file needs at least one [[bus]] table", field="bus")
        mgr = cls(**kwargs)
        for i, table in enumerate(tables):
            mgr.add_spec(BusSpec.from_mapping(table, i))
        return mgr

    def add_spec(self, spec: BusSpec, transport: Transport | None = None) -> None:
        """Add a bus; ``transport`` overrides opening ``spec.url`` (e.g. an in-memory link)."""
        if spec.name in self.specs:
            raise LocalProtocolError(f"bus name {spec.name!r} is used twice", field="name")
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
            {"name": name, "url": url, "baud": baud, "devices": list(devices), **options},
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
        """Open every bus concurrently; if one fails, close the others and raise."""
        realtime.on_bus_open()  # a bad MOTORBUS_REALTIME fails before any port opens
        for i, (name, spec) in enumerate(self.specs.items()):
            transport = self._transports.get(name) or open_transport(
                spec.url,
                baudrate=spec.baud,
                backend=spec.backend,
                rs485=spec.rs485,
                remove_echo=spec.remove_echo,
                low_latency=spec.low_latency,
            )
            bus = Bus(
                transport,
                name=name,
                families=spec.families(),
                min_spacing=spec.min_spacing_ms / 1e3,
                host_margin=spec.host_margin_ms / 1e3,
                retries=spec.retries,
            )
            self.buses[name] = bus
            phase = (i % PHASE_GROUPS) * PHASE_SPAN_S / PHASE_GROUPS
            self._streamers[name] = Streamer(bus, phase=phase)
        try:
            async with anyio.create_task_group() as tg:
                for bus in self.buses.values():
                    tg.start_soon(bus.open)
        except BaseException:
            await self._close_buses()
            raise
        shutdown.register_manager(self)

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
                shutdown.unregister_manager(self)

    async def _close_buses(self) -> None:
        for streamer in self._streamers.values():
            with contextlib.suppress(Exception):
                await streamer.close(safe=False)
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

    def _stop_plan(self, name: str, report: StopReport) -> list[tuple[DeviceStop, Command]]:
        """The stop commands of every device on bus ``name``, each with its report entry."""
        spec = self.specs[name]
        bus = self.buses[name]
        action = SafeAction(spec.la_safe_action)
        plan: list[tuple[DeviceStop, Command]] = []
        for dev in spec.devices:
            devices: list[Any]
            try:
                if dev.kind == "la":
                    devices = [InspireLA(bus, i) for i in dev.ids]
                elif dev.kind == "project_stepper":
                    devices = [ProjectStepper(bus, motor=dev.motor)]
                else:
                    devices = [QuadStepper(bus)]
                for device in devices:
                    key = f"la:{device.id}" if dev.kind == "la" else dev.kind
                    commands = (
                        device.safe_stop_commands(action)
                        if dev.kind == "la"
                        else device.safe_stop_commands()
                    )
                    for cmd in commands:
                        entry = DeviceStop(name, key, _describe(cmd))
                        report.entries.append(entry)
                        plan.append((entry, cmd))
            except Exception as err:  # one device's bad setting must not stop the others
                report.entries.append(DeviceStop(name, dev.kind, "stop", "failed", str(err)))
        return plan

    async def _run_stop_plan(self, name: str, plan: list[tuple[DeviceStop, Command]]) -> None:
        bus = self.buses[name]
        for entry, cmd in plan:
            try:
                await bus.request(cmd, priority=Priority.EMERGENCY, retries=SAFE_STOP_RETRIES)
            except Exception as err:
                entry.outcome, entry.detail = "failed", str(err)
            else:
                entry.outcome = "confirmed" if cmd.expects_reply else "sent"

    # -- devices ----------------------------------------------------------------------

    def bus(self, name: str) -> Bus:
        """The bus called ``name``."""
        try:
            return self.buses[name]
        except KeyError:
            raise LocalProtocolError(
                f"no bus named {name!r}; buses: {sorted(self.specs)}", field="bus"
            ) from None

    def la(self, bus: str, id: int) -> InspireLA:
        """The LA actuator ``id`` on bus ``bus``."""
        return InspireLA(self.bus(bus), id)

    def project_stepper(self, bus: str) -> ProjectStepper:
        """The project stepper on bus ``bus`` (its motor byte from the bus spec)."""
        motor = next(
            (d.motor for d in self.specs[bus].devices if d.kind == "project_stepper"),
            ps.DEFAULT_MOTOR,
        )
        return ProjectStepper(self.bus(bus), motor=motor)

    def quad_stepper(self, bus: str) -> QuadStepper:
        """The quad stepper on bus ``bus``."""
        return QuadStepper(self.bus(bus))

    def streamer(self, bus: str) -> Streamer:
        """The streamer of bus ``bus`` (phase-offset from the other buses)."""
        self.bus(bus)
        return self._streamers[bus]


def _describe(cmd: Command) -> str:
    """A stop command as the report names it: ``Control(PAUSE)``, ``StopProject``..."""
    action = getattr(cmd, "action", None)
    name = type(cmd).__name__
    return f"{name}({action.name})" if isinstance(action, enum.Enum) else name


def default_bus_file() -> Path | None:
    """The user's bus file: ``$XDG_CONFIG_HOME/motorbus/buses.toml`` (default
    ``~/.config/motorbus/buses.toml``), whether or not it exists; ``None`` without a home.

    ``BusManager.from_toml()`` without a path and the command line read it.
    """
    import os

    base = os.environ.get("XDG_CONFIG_HOME")
    if not base:
        try:
            base = str(Path.home() / ".config")
        except RuntimeError:
            return None
    return Path(base) / "motorbus" / "buses.toml"
