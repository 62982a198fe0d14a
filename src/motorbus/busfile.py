"""The bus-file schema: one reader for ``BusManager`` and the command line.

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
    process = "feeders"           # served by the process that opens group "feeders"
    devices = ["project-stepper:motor=3", "quad-stepper"]

    [process.feeders]             # optional: the group's own settings
    cpus = [1]                    # the CPUs the group's process runs on

Every key is typed and range-checked when the file is loaded, not when it is opened;
nothing is coerced (``"false"`` is not a bool, ``2.7`` is not an integer, ``true`` is
not a number).  A bad key raises ``LocalProtocolError`` on one line naming the file,
the bus (``name`` or ``#index``), the key, the value and what is allowed:

==================  ===============================================================
name                non-empty string, unique (default ``busN``)
url                 non-empty string without control characters (required); two
                    buses may not name one port (symlinks such as
                    ``/dev/serial/by-id/...`` are resolved); ``usb:serial=SERIAL``,
                    ``usb:VID:PID`` or ``usb:VID:PID:SERIAL`` (hex VID/PID of 4
                    digits) name a USB adapter, found again at every (re)open
baud                integer 300..4000000 (required), and a rate every listed device
                    family takes: la 19200 | 57600 | 115200 | 921600 (its baud
                    codes), project-stepper 9600 (doc 000 A.1); the quad stepper's
                    manual states none
backend             fast | serialx | pyserial-asyncio (rs485 needs fast or
                    pyserial-asyncio)
rs485, remove_echo  true | false (default false)
low_latency         true | false (default true)
share               true | false (default false: the port opens with an exclusive
                    lock, and another program's open is refused)
guard               true | false (default false: no guard process watches the program)
min_spacing_ms      finite number 0..100 (default 1; the LA manual asks >= 1 ms)
host_margin_ms      finite number 0..10000 (default 2, 20 for socket:// and rfc2217://)
retries             integer 0..10 (default 1)
la_safe_action      pause | estop | hold (default pause)
la_stroke_mm        finite number 1..1000, the LA actuators' stroke in millimetres
                    (``BusManager.la()`` gives them ``stroke_mm``; default none)
devices             list of strings: ``la:1-15``, ``la:1,4,7`` (IDs 1..254, ranges
                    low-high), ``project-stepper[:motor=N]`` (N a valid motor byte,
                    see ``protocol.project_stepper.check_motor``), ``quad-stepper``
process             the process group that serves the bus: 1..32 ASCII letters,
                    digits, ``-`` or ``_`` (default none)
la                  named LA actuators, ``[bus.la.NAME]`` tables: ``id`` (1..254,
                    once per bus; added to ``devices``), and calibration keys
                    (``motorbus.devices.calibration``); a NAME once per file
calibration         file of calibrations by device name, relative to the bus file
                    (``motorbus la calibrate`` writes it); it must exist
==================  ===============================================================

Process groups.  ``process = "arms"`` puts a bus in group ``arms``.  A program that
chooses that group (``BusManager.from_toml(path, process="arms")``, ``motorbus
dashboard --process arms``) opens exactly the group's buses and runs on the group's
CPUs.  A bus without ``process`` is opened only by the programs that choose no group;
those open every bus of the file and pin nothing, as before.  So two group programs
never open one port, and a bus that no running program serves is not an error.  A
group may have a table of its own:

==================  ===============================================================
``[process.NAME]``  NAME a group some ``[[bus]]`` names (a table for a group without
                    buses is refused: it is a typo)
cpus                list of distinct CPU numbers 0..N-1 (N: ``os.cpu_count()`` of the
                    machine loading the file), at least one; on open, every thread of
                    the program runs on them (:func:`motorbus.runtime.realtime.pin`; Linux),
                    and closing the buses gives the threads their CPUs back
==================  ===============================================================

Real-time mode is not a group key: each group's program asks for it on its own
command line (``--realtime``) or environment (``MOTORBUS_REALTIME``), as any other.

A file that is not UTF-8, not TOML, or nested too deeply for the parser is refused
with its name (and the line, where there is one).  TOML has no includes.
"""

from __future__ import annotations

import os
import re
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from motorbus.bus.bus import DEFAULT_HOST_MARGIN_S
from motorbus.devices.calibration import (
    NamedActuator,
    calibrate_buses,
    check_named,
    parse_named,
)
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol.base import Family, check_flag, check_int
from motorbus.protocol.families import FAMILIES, STEPPER_DEFAULT_BAUD
from motorbus.protocol.ids import IdListError, parse_id_items
from motorbus.runtime.process_groups import (
    ProcessGroup,
    check_group_name,
    check_group_table,
    choose_group,
)
from motorbus.streams import SafeAction
from motorbus.transport.serial import BACKENDS
from motorbus.transport.usb import is_usb_url, parse_usb_url
from motorbus.transport.usb import port_identity as port_identity
from motorbus.validation import RETRIES_MAX, check_baud, check_name, check_number

__all__ = [
    "BUS_KEYS",
    "BusFile",
    "BusSpec",
    "DeviceSpec",
    "ProcessGroup",
    "buses_and_groups",
    "check_distinct",
    "default_bus_file",
    "family_baud_rates",
    "labelled",
    "load_bus_file",
    "parse_devices",
    "port_identity",
    "read_bus_toml",
    "specs_from_dict",
]

#: Every key a ``[[bus]]`` table may set.
BUS_KEYS = frozenset(
    {
        "name",
        "url",
        "baud",
        "backend",
        "rs485",
        "remove_echo",
        "low_latency",
        "share",
        "guard",
        "min_spacing_ms",
        "host_margin_ms",
        "retries",
        "la_safe_action",
        "la_stroke_mm",
        "devices",
        "process",
        "la",
        "calibration",
    }
)
#: Range of ``min_spacing_ms`` and ``host_margin_ms`` in a bus file, milliseconds.
MIN_SPACING_MS_MAX = 100.0
HOST_MARGIN_MS_MAX = 10_000.0
#: Default host margin of a bus reached over the network (ser2net): a TCP hop adds
#: 100-150 us typically but far more under load, and a fresh ser2net connection
#: answers its first request 9-25 ms late (measured by tests/integration).
REMOTE_HOST_MARGIN_MS = 20.0
REMOTE_SCHEMES = ("socket://", "rfc2217://")

_DEVICE_KINDS = tuple(info.key for info in FAMILIES.values())
_SAFE_ACTIONS = tuple(a.value for a in SafeAction)
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def family_baud_rates(family: Family) -> tuple[int, ...] | None:
    """The line speeds a family's devices take, bit/s; ``None`` if its manual states none.

    LA: the four rates of its baud code (control table 12, ``la.BaudCode``; what
    ``motorbus la set baud`` writes).  Project stepper: 9600 8N1, the only rate doc 000
    A.1 gives.  Quad stepper: doc 001 states none (A1-01), so any plausible rate.
    """
    if family is Family.LA:
        return tuple(sorted(code.baud for code in la.BaudCode))
    if family is Family.PROJECT_STEPPER:
        return (STEPPER_DEFAULT_BAUD,)
    return None


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
        if isinstance(self.ids, str | bytes) or not isinstance(self.ids, Iterable):
            msg = f"ids must be a list of IDs {la.ID_MIN}..{la.ID_MAX}, got {self.ids!r}"
            raise LocalProtocolError(msg, field="devices", value=self.ids)
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


def _listed(values: object, key: str, kind: type) -> list[Any]:
    """``values`` (a bus's ``devices`` or ``la``) as a list of ``kind``; refused, naming
    ``key``, if it is no list of them (``None`` raised a bare ``TypeError``)."""
    if isinstance(values, str | bytes) or not isinstance(values, Sequence):
        raise LocalProtocolError(
            f"{key} must be a list of {kind.__name__}, got {values!r}", field=key, value=values
        )
    bad = [v for v in values if not isinstance(v, kind)]
    if bad:
        raise LocalProtocolError(
            f"{key} must be {kind.__name__} values, got {bad[0]!r}", field=key, value=bad[0]
        )
    return list(values)


def _check_devices(devices: Sequence[DeviceSpec]) -> list[DeviceSpec]:
    """Refuse an ID listed twice, or a stepper controller listed twice, on one bus."""
    devices = _listed(devices, "devices", DeviceSpec)
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


def _check_url(value: object) -> str:
    """A non-empty string with no control character (a NUL never reaches ``open``)."""
    url = check_name("url", value)
    assert url is not None
    bad = _CONTROL.search(url)
    if bad:
        raise LocalProtocolError(
            f"url={url!r} has the control character {bad.group()!r} at {bad.start()}: "
            "must be a device path or URL of printable characters",
            field="url",
            value=url,
        )
    if is_usb_url(url):
        parse_usb_url(url)  # the adapter need not be plugged in yet: only the form
    return url


def _check_path(key: str, value: object) -> str:
    path = check_name(key, value)
    if path is None or _CONTROL.search(path):
        raise LocalProtocolError(
            f"{key}={value!r} is not allowed: a file path of printable characters",
            field=key,
            value=value,
        )
    return path


def _check_named(named: Sequence[NamedActuator], devices: list[DeviceSpec]) -> list[DeviceSpec]:
    """``devices`` with the named IDs it leaves out (so the safe stop reaches them)."""
    listed = {i for d in devices for i in d.ids}
    extra = tuple(i for i in check_named(named) if i not in listed)
    return [*devices, DeviceSpec("la", extra)] if extra else devices


def _check_baud_for(baud: int, devices: Sequence[DeviceSpec]) -> None:
    """Refuse a rate one of the bus's device families does not take."""
    for kind in dict.fromkeys(d.kind for d in devices):
        family = Family(kind)
        rates = family_baud_rates(family)
        if rates is not None and baud not in rates:
            name = FAMILIES[family].spec_name
            raise LocalProtocolError(
                f"baud={baud!r} is not a rate of the {name} devices on this bus: "
                f"allowed {' | '.join(map(str, rates))}",
                field="baud",
                value=baud,
            )


def _check_fields(values: Mapping[str, Any]) -> dict[str, Any]:
    """Check the scalar keys of a bus (all but ``devices``); return them in plain types."""
    checks: dict[str, Any] = {
        "name": lambda v: check_name("name", v),
        "url": _check_url,
        "baud": lambda v: check_baud("baud", v),
        "backend": lambda v: _check_choice("backend", v, BACKENDS),
        "rs485": lambda v: check_flag("rs485", v),
        "remove_echo": lambda v: check_flag("remove_echo", v),
        "low_latency": lambda v: check_flag("low_latency", v),
        "share": lambda v: check_flag("share", v),
        "guard": lambda v: check_flag("guard", v),
        "min_spacing_ms": lambda v: check_number(
            "min_spacing_ms", v, 0.0, MIN_SPACING_MS_MAX, "ms"
        ),
        "host_margin_ms": lambda v: check_number(
            "host_margin_ms", v, 0.0, HOST_MARGIN_MS_MAX, "ms"
        ),
        "retries": lambda v: check_int("retries", v, 0, RETRIES_MAX),
        "la_safe_action": lambda v: _check_choice("la_safe_action", v, _SAFE_ACTIONS),
        "la_stroke_mm": lambda v: (
            None if v is None else check_number("la_stroke_mm", v, 1.0, 1000.0, "mm")
        ),
        "process": lambda v: None if v is None else check_group_name("process", v),
        "calibration": lambda v: None if v is None else _check_path("calibration", v),
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


def labelled(where: str, err: LocalProtocolError) -> LocalProtocolError:
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
    share: bool = False
    guard: bool = False
    min_spacing_ms: float = 1.0
    host_margin_ms: float = DEFAULT_HOST_MARGIN_S * 1e3
    retries: int = 1
    la_safe_action: str = "pause"
    la_stroke_mm: float | None = None
    #: The process group that serves this bus (``None``: every program that opens the
    #: file without choosing a group).
    process: str | None = None
    #: Named, calibrated LA actuators (``[bus.la.NAME]`` tables).
    la: tuple[NamedActuator, ...] = ()
    #: The calibration file the bus names (resolved against the bus file's folder on load).
    calibration: str | None = None

    def __post_init__(self) -> None:
        values = {key: getattr(self, key) for key in BUS_KEYS if key not in ("devices", "la")}
        try:
            checked = _check_fields(values)
            self.la = tuple(_listed(self.la, "la", NamedActuator))
            self.devices = _check_devices(
                _check_named(self.la, _listed(self.devices, "devices", DeviceSpec))
            )
            _check_baud_for(checked["baud"], self.devices)
        except LocalProtocolError as err:
            raise labelled(f"bus {self.name!r}", err) from None
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
        unknown = set(data) - BUS_KEYS
        if unknown:
            raise LocalProtocolError(
                f"{where}: unknown keys {sorted(unknown)}; allowed: {sorted(BUS_KEYS)}",
                field="bus",
            )
        for key in ("url", "baud"):
            if key not in data:
                raise LocalProtocolError(f"{where}: '{key}' is required", field=key)
        try:
            checked = _check_fields({"name": f"bus{index}", **data})
            named = parse_named(data.get("la", {}), checked.get("la_stroke_mm"))
            devices = _check_devices(_check_named(named, parse_devices(data.get("devices", []))))
            _check_baud_for(checked["baud"], devices)
        except LocalProtocolError as err:
            raise labelled(where, err) from None
        if "host_margin_ms" not in checked:
            remote = checked["url"].startswith(REMOTE_SCHEMES)
            checked["host_margin_ms"] = (
                REMOTE_HOST_MARGIN_MS if remote else DEFAULT_HOST_MARGIN_S * 1e3
            )
        return cls(devices=devices, la=named, **checked)

    def families(self) -> set[Family]:
        """The protocol families its devices speak (all three if none are listed)."""
        return {Family(d.kind) for d in self.devices} or set(Family)

    def transport_options(self) -> dict[str, Any]:
        """The ``open_transport`` options this bus sets (baud and backend apart)."""
        return {
            "rs485": self.rs485,
            "remove_echo": self.remove_echo,
            "low_latency": self.low_latency,
            "share": self.share,
        }


def check_distinct(spec: BusSpec, others: Sequence[BusSpec]) -> None:
    """Refuse ``spec`` if a bus of ``others`` has its name or its port.

    Two buses on one port read each other's replies (half of the requests fail), so a
    bus file may not name a port twice, however it is spelled.
    """
    for other in others:
        if other.name == spec.name:
            raise LocalProtocolError(
                f"name={spec.name!r} is used twice: each bus needs its own name", field="name"
            )
    port = port_identity(spec.url)
    for other in others:
        if port_identity(other.url) == port:
            same = "" if other.url == spec.url else f" (both are {port!r})"
            raise LocalProtocolError(
                f"url={spec.url!r} is the port of bus {other.name!r}{same}: one bus per "
                "port is allowed - list all its devices on that bus",
                field="url",
                value=spec.url,
            )


def _groups_from_dict(data: Mapping[str, Any], specs: Sequence[BusSpec]) -> dict[str, ProcessGroup]:
    """The process groups the buses name, each with its ``[process.NAME]`` table's keys."""
    named: dict[str, list[str]] = {}
    for spec in specs:
        if spec.process is not None:
            named.setdefault(spec.process, []).append(spec.name)
    tables = data.get("process", {})
    if not isinstance(tables, Mapping):
        raise LocalProtocolError(
            f"process={tables!r} is not allowed at the top level: a group's settings are a "
            "[process.NAME] table (cpus = [...]); a bus names its group in its [[bus]] table",
            field="process",
            value=tables,
        )
    cpus: dict[str, frozenset[int] | None] = {}
    for name, table in tables.items():
        try:
            cpus[name] = check_group_table(name, table, named)
        except LocalProtocolError as err:
            raise labelled(f"[process.{name}]", err) from None
    return {name: ProcessGroup(name, tuple(buses), cpus.get(name)) for name, buses in named.items()}


def specs_from_dict(data: Mapping[str, Any]) -> list[BusSpec]:
    """The buses of parsed TOML ``{"bus": [{...}, ...]}``; every key checked here, and
    no two buses with one name or one port."""
    return buses_and_groups(data)[0]


def buses_and_groups(
    data: Mapping[str, Any], *, base: Path | None = None, missing_calibration_ok: bool = False
) -> tuple[list[BusSpec], dict[str, ProcessGroup]]:
    """The buses of parsed TOML, and the process groups they name (with their
    ``[process.NAME]`` tables); every key of both checked here, and each bus's
    calibration file read (relative paths from ``base``, default the working folder;
    a missing one is refused unless ``missing_calibration_ok``)."""
    if not isinstance(data, Mapping):
        raise LocalProtocolError(f"a bus file is a table, got {data!r}", field="bus")
    unknown = sorted(set(data) - {"bus", "process"})
    if unknown:
        raise LocalProtocolError(
            f"unknown top-level keys {unknown}; allowed: ['bus', 'process'] ([[bus]] and "
            "[process.NAME] tables)",
            field="bus",
        )
    tables = data.get("bus")
    if not isinstance(tables, list) or not tables:
        one = " (it has [bus]: write [[bus]], a list of buses)" if isinstance(tables, dict) else ""
        raise LocalProtocolError(f"the bus file needs at least one [[bus]] table{one}", field="bus")
    specs: list[BusSpec] = []
    for i, table in enumerate(tables):
        spec = BusSpec.from_mapping(table, i)
        try:
            check_distinct(spec, specs)
        except LocalProtocolError as err:
            raise labelled(f"bus {spec.name!r} (#{i + 1})", err) from None
        specs.append(spec)
    _calibrate(specs, base or Path.cwd(), missing_calibration_ok)
    return specs, _groups_from_dict(data, specs)


def _calibrate(specs: Sequence[BusSpec], base: Path, missing_ok: bool) -> None:
    """Refuse a device name used twice in a file; merge each calibration file in."""
    for spec in specs:
        if spec.calibration is not None:
            spec.calibration = str(base / Path(spec.calibration).expanduser())
    buses = [(s.name, s.calibration, s.la) for s in specs]
    for spec, named in zip(specs, calibrate_buses(buses, missing_ok), strict=True):
        spec.la = named


@dataclass(frozen=True, slots=True)
class BusFile:
    """A loaded bus file: its buses in file order, and the keys each table set."""

    path: Path
    specs: tuple[BusSpec, ...]
    #: bus name -> the keys its table sets (the rest are defaults).
    given: Mapping[str, frozenset[str]]
    #: The process groups its buses name, in file order.
    groups: Mapping[str, ProcessGroup] = field(default_factory=dict)

    def names(self) -> list[str]:
        return [s.name for s in self.specs]

    def group(self, name: str) -> ProcessGroup:
        """The process group called ``name``.

        Raises:
            LocalProtocolError: no such group (the message names the file and its groups).
        """
        try:
            return choose_group(self.groups, name)
        except LocalProtocolError as err:
            raise labelled(str(self.path), err) from None

    def specs_of(self, group: str | None) -> tuple[BusSpec, ...]:
        """The buses the program serving ``group`` opens: that group's, or every bus for
        ``None``."""
        if group is None:
            return self.specs
        self.group(group)
        return tuple(s for s in self.specs if s.process == group)

    def spec(self, name: str) -> BusSpec:
        """The bus called ``name``."""
        for spec in self.specs:
            if spec.name == name:
                return spec
        raise LocalProtocolError(
            f"{self.path} has no bus {name!r}: choose one of {', '.join(self.names())}",
            field="bus",
            value=name,
        )


def read_bus_toml(path: str | Path) -> dict[str, Any]:
    """Parse a bus file's TOML; errors name the file (and the line where there is one).

    Raises:
        LocalProtocolError: not UTF-8, not TOML, or nested too deeply.
        OSError: the file cannot be read.
    """
    raw = Path(path).read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as err:
        line = raw.count(b"\n", 0, err.start) + 1
        raise LocalProtocolError(
            f"{path}: line {line}: not UTF-8 text (byte 0x{raw[err.start]:02x} at offset "
            f"{err.start}): a bus file must be UTF-8",
            field="file",
        ) from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise LocalProtocolError(f"{path}: not valid TOML: {err}", field="file") from None
    except RecursionError:
        raise LocalProtocolError(
            f"{path}: not valid TOML: arrays or tables nested too deeply for the parser "
            "(a bus file needs two levels)",
            field="file",
        ) from None


def load_bus_file(path: str | Path, *, missing_calibration_ok: bool = False) -> BusFile:
    """Read and check a bus file (see the module docstring), and the calibration files it
    names (a missing one is refused unless ``missing_calibration_ok``).

    Raises:
        LocalProtocolError: naming the file, the bus, the key, the value and what is
            allowed, or the file and line for text that is not UTF-8 or not TOML.
        OSError: the file cannot be read.
    """
    data = read_bus_toml(path)
    try:
        specs, groups = buses_and_groups(
            data, base=Path(path).parent, missing_calibration_ok=missing_calibration_ok
        )
    except LocalProtocolError as err:
        raise labelled(str(path), err) from None
    tables = data["bus"]
    given = {spec.name: frozenset(table) for spec, table in zip(specs, tables, strict=True)}
    return BusFile(Path(path), tuple(specs), given, groups)


def default_bus_file() -> Path | None:
    """The user's bus file: ``$XDG_CONFIG_HOME/motorbus/buses.toml`` (default
    ``~/.config/motorbus/buses.toml``), whether or not it exists; ``None`` without a home.

    ``BusManager.from_toml()`` without a path and the command line read it.
    """
    base = os.environ.get("XDG_CONFIG_HOME")
    if not base:
        try:
            base = str(Path.home() / ".config")
        except RuntimeError:
            return None
    return Path(base) / "motorbus" / "buses.toml"
