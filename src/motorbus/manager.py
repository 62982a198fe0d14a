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

Every key is typed and range-checked when the file is loaded, not when it is opened;
nothing is coerced (``"false"`` is not a bool, ``2.7`` is not an integer, ``true`` is
not a number).  A bad key raises ``LocalProtocolError`` on one line naming the file,
the bus (``name`` or ``#index``), the key, the value and what is allowed:

==================  ===============================================================
name                non-empty string, unique (default ``busN``)
url                 non-empty string (required)
baud                integer 300..4000000 (required)
backend             fast | serialx | pyserial-asyncio (rs485 needs fast or
                    pyserial-asyncio)
rs485, remove_echo  true | false (default false)
low_latency         true | false (default true)
min_spacing_ms      finite number 0..100 (default 1; the LA manual asks >= 1 ms)
host_margin_ms      finite number 0..10000 (default 2, 20 for socket:// and rfc2217://)
retries             integer 0..10 (default 1)
la_safe_action      pause | estop | hold (default pause)
guard               true | false (default false): a guard process (``motorbus.guard``,
                    Linux) sends the leased devices' safe action if the program is
                    killed outright; one guard serves every bus of the program
devices             list of strings: ``la:1-15``, ``la:1,4,7`` (IDs 1..254, ranges
                    low-high), ``project-stepper[:motor=N]`` (N a valid motor byte,
                    see ``protocol.project_stepper.check_motor``), ``quad-stepper``
==================  ===============================================================
"""

from __future__ import annotations

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

from motorbus import guard as guard_process
from motorbus import realtime, shutdown
from motorbus.bus.bus import DEFAULT_HOST_MARGIN_S, Bus, Priority
from motorbus.devices.la import InspireLA
from motorbus.devices.project_stepper import ProjectStepper
from motorbus.devices.quad_stepper import QuadStepper
from motorbus.errors import LocalProtocolError, MotorbusError
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol.base import Command, Family, check_flag, check_int
from motorbus.protocol.families import FAMILIES
from motorbus.protocol.ids import IdListError, parse_id_items
from motorbus.shutdown import deferred_interrupts
from motorbus.streams import SafeAction, Streamer
from motorbus.transport.base import Transport
from motorbus.transport.serial import BACKENDS, open_transport
from motorbus.validation import (
    RETRIES_MAX,
    check_baud,
    check_name,
    check_number,
)

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
    "guard",
    "devices",
}


_DEVICE_KINDS = tuple(info.key for info in FAMILIES.values())
_SAFE_ACTIONS = tuple(a.value for a in SafeAction)
#: Range of ``min_spacing_ms`` and ``host_margin_ms`` in a bus file, milliseconds.
MIN_SPACING_MS_MAX = 100.0
HOST_MARGIN_MS_MAX = 10_000.0


@dataclass(frozen=True, slots=True)
class DeviceSpec:
    """A device on a bus: ``kind`` is "la", "project_stepper" or "quad_stepper".

    Checked on construction: LA IDs 1..254 (at least one), the project stepper's motor
    byte by the protocol's own rule (``ps.check_motor``, which ``ManualStop`` applies
    when the manager stops it on the way out).
    """

    kind: str
    ids: tuple[int, ...] = ()
    motor: int = ps.DEFAULT_MOTOR

    def __post_init__(self) -> None:
        if self.kind not in _DEVICE_KINDS:
            raise LocalProtocolError(
                f"kind={self.kind!r} is unknown: choose one of {', '.join(_DEVICE_KINDS)}",
                field="devices",
                value=self.kind,
            )
        ids = tuple(check_int("id", i, la.ID_MIN, la.ID_MAX) for i in self.ids)
        if self.kind == "la" and not ids:
            raise LocalProtocolError("an la device needs at least one ID", field="devices")
        object.__setattr__(self, "ids", ids)
        object.__setattr__(self, "motor", ps.check_motor(self.motor))


def _device_error(item: object, why: str) -> LocalProtocolError:
    return LocalProtocolError(
        f"devices: {item!r}: {why}; forms: la:1-15, la:1,4,7 (IDs {la.ID_MIN}..{la.ID_MAX}), "
        "project-stepper[:motor=N], quad-stepper",
        field="devices",
        value=item,
    )


def parse_devices(items: Sequence[str]) -> list[DeviceSpec]:
    """Parse device strings: ``"la:1-15"``, ``"la:1,4,7"``, ``"project-stepper[:motor=N]"``,
    ``"quad-stepper"``.  Raises ``LocalProtocolError`` naming the bad item."""
    if isinstance(items, str | bytes) or not isinstance(items, Sequence):
        raise LocalProtocolError(
            f"devices must be a list of strings, got {items!r} ({type(items).__name__})",
            field="devices",
            value=items,
        )
    out: list[DeviceSpec] = []
    for item in items:
        if not isinstance(item, str):
            raise _device_error(item, f"a device is a string, not {type(item).__name__}")
        kind, _, rest = item.partition(":")
        kind = kind.strip().replace("_", "-")
        if kind == "la":
            try:  # the shared grammar; empty items ("la:1,") are skipped
                ids = parse_id_items(p for p in rest.split(",") if p.strip())
            except IdListError as err:
                why = f"{err.item!r} is a {err.reason}" if err.problem == "reversed" else err.reason
                raise _device_error(item, why) from None
            if not ids:
                raise _device_error(item, "it lists no IDs")
            out.append(DeviceSpec("la", tuple(ids)))
        elif kind == "project-stepper":
            motor = ps.DEFAULT_MOTOR
            if rest.strip():
                m = re.fullmatch(r"\s*motor\s*=\s*(0[xX][0-9a-fA-F]+|\d+)\s*", rest)
                if not m:
                    raise _device_error(item, "the only option is motor=N")
                try:
                    motor = ps.check_motor(int(m.group(1), 0))
                except LocalProtocolError as err:
                    raise _device_error(item, str(err)) from None
            out.append(DeviceSpec("project_stepper", motor=motor))
        elif kind == "quad-stepper":
            if rest.strip():
                raise _device_error(item, "quad-stepper takes no options")
            out.append(DeviceSpec("quad_stepper"))
        else:
            raise _device_error(item, f"kind {kind!r} is unknown")
    return out


def _check_devices(devices: Sequence[DeviceSpec]) -> list[DeviceSpec]:
    """Refuse an ID listed twice, or a stepper controller listed twice, on one bus."""
    if isinstance(devices, str | bytes) or not isinstance(devices, Sequence):
        raise LocalProtocolError(
            f"devices must be a list of DeviceSpec, got {devices!r}", field="devices"
        )
    bad = [d for d in devices if not isinstance(d, DeviceSpec)]
    if bad:
        raise LocalProtocolError(
            f"devices must be DeviceSpec values, got {bad[0]!r}", field="devices", value=bad[0]
        )
    ids = [i for d in devices for i in d.ids]
    twice = sorted({i for i in ids if ids.count(i) > 1})
    if twice:
        # Two actuators with one ID on a bus answer together (A2-12).
        raise LocalProtocolError(
            f"devices: la ids {twice} are listed twice: each ID once per bus", field="devices"
        )
    kinds = [d.kind for d in devices if d.kind != "la"]
    for kind in sorted(set(kinds)):
        if kinds.count(kind) > 1:
            raise LocalProtocolError(
                f"devices: {kind} is listed twice: at most one per bus", field="devices"
            )
    return list(devices)


def _check_choice(key: str, value: object, allowed: Sequence[str]) -> str:
    if not isinstance(value, str) or value not in allowed:
        raise LocalProtocolError(
            f"{key}={value!r} is not allowed: choose one of {' | '.join(allowed)}",
            field=key,
            value=value,
        )
    return value


def _check_fields(values: Mapping[str, Any]) -> dict[str, Any]:
    """Check the scalar keys of a bus (all but ``devices``); return them in plain types."""
    checks: dict[str, Any] = {
        "name": lambda v: check_name("name", v),
        "url": lambda v: check_name("url", v),
        "baud": lambda v: check_baud("baud", v),
        "backend": lambda v: _check_choice("backend", v, BACKENDS),
        "rs485": lambda v: check_flag("rs485", v),
        "guard": lambda v: check_flag("guard", v),
        "remove_echo": lambda v: check_flag("remove_echo", v),
        "low_latency": lambda v: check_flag("low_latency", v),
        "min_spacing_ms": lambda v: check_number(
            "min_spacing_ms", v, 0.0, MIN_SPACING_MS_MAX, "ms"
        ),
        "host_margin_ms": lambda v: check_number(
            "host_margin_ms", v, 0.0, HOST_MARGIN_MS_MAX, "ms"
        ),
        "retries": lambda v: check_int("retries", v, 0, RETRIES_MAX),
        "la_safe_action": lambda v: _check_choice("la_safe_action", v, _SAFE_ACTIONS),
    }
    out = {key: checks[key](value) for key, value in values.items() if key in checks}
    if out.get("rs485") and out.get("backend") == "serialx":
        raise LocalProtocolError(
            "rs485=true is not supported with backend='serialx' (it has no RS-485 mode): "
            "use backend='fast' or 'pyserial-asyncio'",
            field="rs485",
            value=True,
        )
    return out


def _labelled(where: str, err: LocalProtocolError) -> LocalProtocolError:
    """``err`` with ``where`` (file, bus) in front of its message, field and value kept."""
    return LocalProtocolError(f"{where}: {err}", field=err.field, value=err.value)


@dataclass(slots=True)
class BusSpec:
    """How to open one bus and what is on it (every field checked on construction)."""

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
    guard: bool = False

    def __post_init__(self) -> None:
        values = {key: getattr(self, key) for key in _BUS_KEYS if key != "devices"}
        try:
            checked = _check_fields(values)
            self.devices = _check_devices(self.devices)
        except LocalProtocolError as err:
            raise _labelled(f"bus {self.name!r}", err) from None
        for key, value in checked.items():
            setattr(self, key, value)

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any], index: int = 0) -> BusSpec:
        """Build from one ``[[bus]]`` table; unknown keys are refused by name, every
        value is typed and range-checked (see the module docstring)."""
        name = data.get("name") if isinstance(data, Mapping) else None
        where = f"bus {name!r} (#{index + 1})" if isinstance(name, str) else f"bus #{index + 1}"
        if not isinstance(data, Mapping):
            raise LocalProtocolError(
                f"{where} must be a table of keys, got {data!r}", field="bus", value=data
            )
        unknown = set(data) - _BUS_KEYS
        if unknown:
            raise LocalProtocolError(
                f"{where}: unknown keys {sorted(unknown)}; allowed: {sorted(_BUS_KEYS)}",
                field="bus",
            )
        for key in ("url", "baud"):
            if key not in data:
                raise LocalProtocolError(f"{where}: '{key}' is required", field=key)
        try:
            checked = _check_fields({"name": f"bus{index}", **data})
            devices = _check_devices(parse_devices(data.get("devices", [])))
        except LocalProtocolError as err:
            raise _labelled(where, err) from None
        if "host_margin_ms" not in checked:
            remote = checked["url"].startswith(REMOTE_SCHEMES)
            checked["host_margin_ms"] = (
                REMOTE_HOST_MARGIN_MS if remote else DEFAULT_HOST_MARGIN_S * 1e3
            )
        return cls(devices=devices, **checked)

    def families(self) -> set[Family]:
        """The protocol families its devices speak (all three if none are listed)."""
        return {Family(d.kind) for d in self.devices} or set(Family)


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
        #: Why each bus that failed in the last ``open`` failed (bus name -> error).
        self.open_errors: dict[str, Exception] = {}

    # -- building -----------------------------------------------------------------

    @classmethod
    def from_toml(cls, path: str | Path | None = None, **kwargs: Any) -> BusManager:
        """Load a bus file (see the module docstring); every key is checked here.

        ``path`` defaults to :func:`default_bus_file` (the user's config file).

        Raises:
            LocalProtocolError: the file is not TOML, or a key is unknown, of the wrong
                type or out of range (the message names the file, the bus and the key).
            OSError: the file cannot be read.
        """
        if path is None:
            path = default_bus_file()
            if path is None:
                raise FileNotFoundError("no bus file given and no home directory to look in")
        with open(path, "rb") as fh:
            try:
                data = tomllib.load(fh)
            except tomllib.TOMLDecodeError as err:
                raise LocalProtocolError(f"{path}: not valid TOML: {err}", field="file") from None
        try:
            return cls.from_dict(data, **kwargs)
        except LocalProtocolError as err:
            raise _labelled(str(path), err) from None

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], **kwargs: Any) -> BusManager:
        """Build from parsed TOML: ``{"bus": [{...}, ...]}``; every key is checked here."""
        if not isinstance(data, Mapping):
            raise LocalProtocolError(f"a bus file is a table, got {data!r}", field="bus")
        unknown = sorted(set(data) - {"bus"})
        if unknown:
            raise LocalProtocolError(
                f"unknown top-level keys {unknown}; allowed: ['bus'] ([[bus]] tables)",
                field="bus",
            )
        tables = data.get("bus")
        if not isinstance(tables, list) or not tables:
            raise LocalProtocolError("the bus file needs at least one [[bus]] table", field="bus")
        mgr = cls(**kwargs)
        for i, table in enumerate(tables):
            spec = BusSpec.from_mapping(table, i)
            try:
                mgr.add_spec(spec)
            except LocalProtocolError as err:
                raise _labelled(f"bus {spec.name!r} (#{i + 1})", err) from None
        return mgr

    def add_spec(self, spec: BusSpec, transport: Transport | None = None) -> None:
        """Add a bus; ``transport`` overrides opening ``spec.url`` (e.g. an in-memory link)."""
        if not isinstance(spec, BusSpec):
            raise LocalProtocolError(f"spec must be a BusSpec, got {spec!r}", field="spec")
        if spec.name in self.specs:
            raise LocalProtocolError(
                f"name={spec.name!r} is used twice: each bus needs its own name", field="name"
            )
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
        """
        realtime.on_bus_open()  # a bad MOTORBUS_REALTIME fails before any port opens
        if any(spec.guard for spec in self.specs.values()):
            # Before the buses open (it follows each one); a Python start-up, off the loop.
            await anyio.to_thread.run_sync(guard_process.start_guard)
        self.open_errors = {}
        try:
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
                    # Devices moved outside any lease end like the configured ones.
                    safe_action=spec.la_safe_action,
                )
                self.buses[name] = bus
                phase = (i % PHASE_GROUPS) * PHASE_SPAN_S / PHASE_GROUPS
                self._streamers[name] = Streamer(bus, phase=phase)
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
        shutdown.register_manager(self)

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
        action = SafeAction(spec.la_safe_action)
        plan: list[tuple[DeviceStop, Command[object]]] = []
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

    async def _run_stop_plan(
        self, name: str, plan: list[tuple[DeviceStop, Command[object]]]
    ) -> None:
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


def _describe(cmd: Command[object]) -> str:
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
