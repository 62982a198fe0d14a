"""Calibration of an LA actuator: its stroke, soft limits, direction, offset and unit.

Pure (no I/O but the calibration file's read and atomic write, no clock).  A
``Calibration`` maps the program's positions onto the actuator's raw 0..2000 and
refuses, before anything is sent, a position outside the soft limits::

    >>> cal = Calibration(stroke_mm=30, limits=(100, 1900), unit="mm")
    >>> cal.to_raw(15.0)
    1000
    >>> cal.from_raw(1900)
    28.5
    >>> cal.to_raw(50, "percent")
    1000

Units:

* ``raw``: the actuator's own 0..2000 (0..100 % of its stroke); direction and offset
  do not apply.  The default, so a program written for raw positions is unchanged.
* ``mm``: millimetres, ``raw * stroke_mm / 2000 + offset_mm`` (``direction =
  "reversed"``: measured from the extended end, ``(2000 - raw) * stroke_mm / 2000 +
  offset_mm``).  Needs ``stroke_mm``.
* ``percent``: 0..100 % of the calibrated range (the soft limits): 0 % is the lower
  limit (``reversed``: the upper one).

Keys of a device's table (bus file ``[bus.la.NAME]`` or its calibration file)::

    stroke_mm  = 30            # finite number 1..1000 (default: the bus's la_stroke_mm)
    limits     = [100, 1900]   # raw positions 0..2000, low < high (default: the whole stroke)
    direction  = "normal"      # normal | reversed
    offset_mm  = 0.0           # finite number -1000..1000 (needs stroke_mm)
    unit       = "mm"          # raw | mm | percent (mm needs stroke_mm)
"""

from __future__ import annotations

import math
import os
import re
import tempfile
import tomllib
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import as_real, check_int
from motorbus.validation import CheckedRows

__all__ = [
    "CALIBRATION_KEYS",
    "DIRECTIONS",
    "FULL_STROKE",
    "UNITS",
    "Calibration",
    "NamedActuator",
    "Positioned",
    "apply_calibration_file",
    "calibrate_buses",
    "check_device_name",
    "check_named",
    "format_calibration_file",
    "limited_targets",
    "parse_named",
    "read_calibration_file",
    "write_calibration_file",
]

#: The units a program may use, and the directions of a calibrated axis.
UNITS = ("raw", "mm", "percent")
DIRECTIONS = ("normal", "reversed")
#: The keys a device's calibration may set.
CALIBRATION_KEYS = ("stroke_mm", "limits", "direction", "offset_mm", "unit")
#: Range of ``stroke_mm`` and ``offset_mm``, millimetres.
STROKE_MM_MIN, STROKE_MM_MAX = 1.0, 1000.0
OFFSET_MM_MAX = 1000.0
#: The limits of an uncalibrated actuator: its whole stroke, raw.
FULL_STROKE = (la.POSITION_MIN, la.POSITION_MAX)
#: Slack for a value at a limit that a unit conversion moved by a rounding error.
_SLACK = 1e-9
DEVICE_NAME_MAX = 64
_NAME = re.compile(rf"[A-Za-z][A-Za-z0-9_-]{{0,{DEVICE_NAME_MAX - 1}}}")


def check_device_name(field_name: str, value: object) -> str:
    """A device name: 1..64 ASCII letters, digits, ``-`` or ``_``, starting with a letter
    (so that it is never mistaken for an ID)."""
    if not isinstance(value, str) or not _NAME.fullmatch(value):
        raise LocalProtocolError(
            f"{field_name}={value!r} is not allowed: a device name is 1..{DEVICE_NAME_MAX} "
            "ASCII letters, digits, '-' or '_', starting with a letter",
            field=field_name,
            value=value,
        )
    return value


def _number(key: str, value: object, lo: float, hi: float, unit: str) -> float:
    number = as_real(value)
    if number is None or not math.isfinite(number) or not lo <= number <= hi:
        raise LocalProtocolError(
            f"{key}={value!r} is out of range: allowed {lo:g}..{hi:g} {unit} (a finite number)",
            field=key,
            value=value,
        )
    return number


def _choice(key: str, value: object, allowed: tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in allowed:
        raise LocalProtocolError(
            f"{key}={value!r} is not allowed: choose one of {' | '.join(allowed)}",
            field=key,
            value=value,
        )
    return value


def _limits(value: object) -> tuple[int, int]:
    bad = LocalProtocolError(
        f"limits={_shown(value)} is not allowed: two integer raw positions [low, high], "
        f"{la.POSITION_MIN} <= low < high <= {la.POSITION_MAX} (the whole stroke)",
        field="limits",
        value=value,
    )
    if isinstance(value, str | bytes) or not isinstance(value, list | tuple) or len(value) != 2:
        raise bad
    try:
        low, high = (check_int("limits", v, la.POSITION_MIN, la.POSITION_MAX) for v in value)
    except LocalProtocolError:
        raise bad from None
    if not low < high:
        raise bad
    return low, high


def _shown(value: object) -> str:
    return repr(list(value)) if isinstance(value, tuple) else repr(value)


@dataclass(frozen=True, slots=True)
class Calibration:
    """How positions of one actuator map to its raw 0..2000, and where it may go.

    Every field is checked on construction (``LocalProtocolError`` naming the key, the
    value and what is allowed).  The default is the identity: raw units, the whole
    stroke, no offset.
    """

    stroke_mm: float | None = None
    limits: tuple[int, int] = FULL_STROKE
    direction: str = "normal"
    offset_mm: float = 0.0
    unit: str = "raw"

    def __post_init__(self) -> None:
        if self.stroke_mm is not None:
            stroke = _number("stroke_mm", self.stroke_mm, STROKE_MM_MIN, STROKE_MM_MAX, "mm")
            object.__setattr__(self, "stroke_mm", stroke)
        object.__setattr__(self, "limits", _limits(self.limits))
        _choice("direction", self.direction, DIRECTIONS)
        offset = _number("offset_mm", self.offset_mm, -OFFSET_MM_MAX, OFFSET_MM_MAX, "mm")
        object.__setattr__(self, "offset_mm", offset)
        _choice("unit", self.unit, UNITS)
        for key, needs in (("offset_mm", offset != 0.0), ("unit", self.unit == "mm")):
            if needs and self.stroke_mm is None:
                value = self.offset_mm if key == "offset_mm" else self.unit
                raise LocalProtocolError(
                    f"{key}={value!r} needs stroke_mm (the actuator's stroke in mm, "
                    f"{STROKE_MM_MIN:g}..{STROKE_MM_MAX:g})",
                    field=key,
                    value=value,
                )

    @classmethod
    def from_table(cls, table: Mapping[str, Any], base: Calibration | None = None) -> Calibration:
        """``base`` (default: the identity) with the keys ``table`` sets; unknown keys are
        refused by name."""
        if not isinstance(table, Mapping):
            raise LocalProtocolError(
                f"a calibration is a table of keys, got {table!r}", field="calibration"
            )
        unknown = sorted(set(table) - set(CALIBRATION_KEYS))
        if unknown:
            raise LocalProtocolError(
                f"unknown keys {unknown}; allowed: {list(CALIBRATION_KEYS)}",
                field=unknown[0],
                value=table[unknown[0]],
            )
        values = (base or cls()).as_table()
        values.update(table)
        return cls(**values)

    def as_table(self) -> dict[str, Any]:
        """The keys of this calibration, as a calibration file stores them."""
        table: dict[str, Any] = {"limits": list(self.limits), "direction": self.direction}
        if self.stroke_mm is not None:
            table["stroke_mm"] = self.stroke_mm
        table["offset_mm"] = self.offset_mm
        table["unit"] = self.unit
        return table

    def _unit(self, unit: str | None, device: str) -> str:
        chosen = self.unit if unit is None else _choice("unit", unit, UNITS)
        if chosen == "mm" and self.stroke_mm is None:
            raise LocalProtocolError(
                f"{device} has no stroke_mm: give InspireLA(bus, ID, stroke_mm=...), or "
                "stroke_mm in its calibration, to use millimetres",
                field="stroke_mm",
            )
        return chosen

    def from_raw(self, raw: float, unit: str | None = None, *, device: str = "la") -> float:
        """A raw position (0..2000) in ``unit`` (default: this calibration's)."""
        chosen = self._unit(unit, device)
        if chosen == "raw":
            return float(raw)
        if chosen == "percent":
            low, high = self.limits
            share = (raw - low) / (high - low)
            return 100.0 * (1.0 - share if self.direction == "reversed" else share)
        assert self.stroke_mm is not None
        along = la.POSITION_MAX - raw if self.direction == "reversed" else raw
        return along * self.stroke_mm / la.POSITION_MAX + self.offset_mm

    def limits_in(self, unit: str | None = None, *, device: str = "la") -> tuple[float, float]:
        """The soft limits in ``unit``, lower value first."""
        a, b = (self.from_raw(r, unit, device=device) for r in self.limits)
        return (a, b) if a <= b else (b, a)

    def to_raw(
        self, value: object, unit: str | None = None, *, device: str = "la", whole: bool = False
    ) -> int:
        """``value`` in ``unit`` (default: this calibration's) as the nearest raw position
        (``whole``: a raw position must be an integer, as the device API takes it).

        Raises:
            LocalProtocolError: not a finite number, or outside the soft limits; the
                message names ``device``, the value, the unit and the limits.
        """
        chosen = self._unit(unit, device)
        key = "position" if chosen == "raw" else chosen
        number = as_real(value)
        fraction = isinstance(value, bool) or not hasattr(value, "__index__")
        if whole and chosen == "raw" and fraction:
            raise LocalProtocolError(
                f"{device}: position must be an integer (raw units 0..2000), got {value!r}; "
                "nothing sent",
                field=key,
                value=value,
            )
        if number is None or not math.isfinite(number):
            raise LocalProtocolError(
                f"{device}: {key} must be a finite number, got {value!r}; nothing sent",
                field=key,
                value=value,
            )
        lo, hi = self.limits_in(chosen, device=device)
        span = max(abs(lo), abs(hi), 1.0) * _SLACK
        if not lo - span <= number <= hi + span:
            raw_lo, raw_hi = self.limits
            raise LocalProtocolError(
                f"{device}: {key}={value!r} is out of range: allowed {lo:g}..{hi:g}"
                f"{'' if chosen == 'raw' else ' ' + ('%' if chosen == 'percent' else 'mm')} "
                f"(its soft limits, raw {raw_lo}..{raw_hi}); nothing sent",
                field=key,
                value=value,
            )
        if chosen == "raw":
            raw = float(number)
        elif chosen == "percent":
            low, high = self.limits
            share = number / 100.0
            raw = low + (high - low) * (1.0 - share if self.direction == "reversed" else share)
        else:
            assert self.stroke_mm is not None
            along = (number - self.offset_mm) * la.POSITION_MAX / self.stroke_mm
            raw = la.POSITION_MAX - along if self.direction == "reversed" else along
        return min(self.limits[1], max(self.limits[0], round(raw)))


@dataclass(frozen=True, slots=True)
class NamedActuator:
    """An LA actuator a bus file names: ``[bus.la.NAME]`` with its ``id`` and calibration."""

    name: str
    id: int
    calibration: Calibration = field(default_factory=Calibration)

    def __post_init__(self) -> None:
        check_device_name("name", self.name)
        check_int("id", self.id, la.ID_MIN, la.ID_MAX)
        if not isinstance(self.calibration, Calibration):  # else refused only at mgr.device
            raise LocalProtocolError(
                f"calibration={self.calibration!r}: not a Calibration",
                field="calibration",
                value=self.calibration,
            )


def _labelled(where: str, err: LocalProtocolError) -> LocalProtocolError:
    return LocalProtocolError(f"{where}: {err}", field=err.field, value=err.value)


def parse_named(tables: object, stroke_mm: float | None = None) -> tuple[NamedActuator, ...]:
    """The ``[bus.la.NAME]`` tables of a bus: each an ``id`` and the keys of a
    ``Calibration`` (whose ``stroke_mm`` defaults to ``stroke_mm``, the bus's)."""
    if not isinstance(tables, Mapping):
        raise LocalProtocolError(
            f"la={tables!r} is not allowed: name actuators in [bus.la.NAME] tables (id = N)",
            field="la",
            value=tables,
        )
    named: list[NamedActuator] = []
    for name, table in tables.items():
        try:
            check_device_name("name", name)
            if not isinstance(table, Mapping) or "id" not in table:
                raise LocalProtocolError(
                    f"{table!r} is not allowed: a table with id = {la.ID_MIN}..{la.ID_MAX}",
                    field="id",
                )
            keys = {k: v for k, v in table.items() if k != "id"}
            cal = Calibration.from_table(keys, Calibration(stroke_mm=stroke_mm))
            named.append(NamedActuator(name, table["id"], cal))
        except LocalProtocolError as err:
            raise _labelled(f"la.{name}", err) from None
    return tuple(named)


def check_named(named: Sequence[NamedActuator]) -> dict[int, str]:
    """Refuse two names for one ID on a bus; return ID -> name."""
    by_id: dict[int, str] = {}
    for n in named:
        if not isinstance(n, NamedActuator):
            raise LocalProtocolError(f"la must hold NamedActuator values, got {n!r}", field="la")
        if n.id in by_id:
            raise LocalProtocolError(
                f"la.{n.name}: id={n.id} is the ID of la.{by_id[n.id]} too: each ID once per bus",
                field="id",
                value=n.id,
            )
        by_id[n.id] = n.name
    return by_id


def apply_calibration_file(
    path: Path, named: Sequence[NamedActuator], missing_ok: bool = False
) -> tuple[NamedActuator, ...]:
    """``named`` with the calibration the file at ``path`` keeps for each of them (its
    keys replace the bus file's).  An entry that names none of them is refused (a typo).

    Raises:
        LocalProtocolError: a bad file or entry, naming the file, the device, the key,
            the value and what is allowed; a missing file unless ``missing_ok``.
    """
    try:
        entries = read_calibration_file(path)
    except FileNotFoundError:
        if missing_ok:
            return tuple(named)
        raise LocalProtocolError(
            f"calibration={str(path)!r}: no such file (motorbus la calibrate NAME writes it)",
            field="calibration",
            value=str(path),
        ) from None
    names = {n.name for n in named}
    unknown = sorted(set(entries) - names)
    if unknown:
        raise LocalProtocolError(
            f"{path}: [{unknown[0]}] names no device of the buses that use this file: "
            f"named are {sorted(names) or 'none'} ([bus.la.NAME] tables)",
            field=unknown[0],
        )
    out = []
    for n in named:
        if n.name in entries:
            try:
                n = NamedActuator(
                    n.name, n.id, Calibration.from_table(entries[n.name], n.calibration)
                )
            except LocalProtocolError as err:
                raise _labelled(f"{path}: [{n.name}]", err) from None
        out.append(n)
    return tuple(out)


def calibrate_buses(
    buses: Sequence[tuple[str, str | None, tuple[NamedActuator, ...]]], missing_ok: bool = False
) -> list[tuple[NamedActuator, ...]]:
    """The named actuators of each bus ``(name, calibration file, named)`` of a bus file,
    with the calibration each file keeps for them.

    Raises:
        LocalProtocolError: a name used on two buses, or a bad calibration file (see
            :func:`apply_calibration_file`).
    """
    seen: dict[str, str] = {}
    files: dict[str, list[int]] = {}
    for index, (bus, path, named) in enumerate(buses):
        for n in named:
            if n.name in seen:
                raise LocalProtocolError(
                    f"bus {bus!r}: la.{n.name} is a device of bus {seen[n.name]!r} too: "
                    "each name once per file",
                    field="la",
                    value=n.name,
                )
            seen[n.name] = bus
        if path is not None:
            files.setdefault(path, []).append(index)
    out = [named for _, _, named in buses]
    for path, users in files.items():
        merged = iter(
            apply_calibration_file(Path(path), [n for i in users for n in out[i]], missing_ok)
        )
        for i in users:
            out[i] = tuple(next(merged) for _ in out[i])
    return out


class Positioned(Protocol):
    """What :func:`limited_targets` needs of a device (``InspireLA`` has it)."""

    id: int
    name: str
    calibration: Calibration


def limited_targets(devices: Sequence[Positioned], source: Any, unit: str | None = None) -> Any:
    """A stream's target source in ``unit`` (default: each device's own) made raw, every
    target checked against its device's soft limits.

    An item is a position (one device), one position per device in order, or a mapping
    by ID or name; it becomes ``{id: raw}``.  A sequence is converted whole here, so a
    target outside the limits is refused before the stream starts (nothing sent); an
    iterator, async iterator or function is converted item by item, and a target
    outside the limits ends the stream (with its safe action) before it is sent.
    """
    by_key: dict[object, Positioned] = {}
    for d in devices:
        by_key[d.id] = by_key[d.name] = d

    def convert(item: Any) -> dict[int, int] | None:
        if item is None:
            return None
        if isinstance(item, Mapping):
            pairs = [(_device(by_key, k), v) for k, v in item.items()]
        elif isinstance(item, int | float) or not hasattr(item, "__len__"):
            if len(devices) != 1:
                raise LocalProtocolError(
                    f"a single target was given for {len(devices)} devices; give one per "
                    "device or a mapping {name: position}",
                    field="targets",
                )
            pairs = [(devices[0], item)]
        else:
            values = item.tolist() if hasattr(item, "tolist") else list(item)
            if len(values) != len(devices):
                raise LocalProtocolError(
                    f"targets has {len(values)} values for {len(devices)} devices",
                    field="targets",
                )
            pairs = list(zip(devices, values, strict=True))
        return {d.id: d.calibration.to_raw(v, unit, device=d.name) for d, v in pairs}

    if isinstance(source, str | bytes):
        return source  # refused by the stream, as text
    if isinstance(source, Sequence) or (
        hasattr(source, "__len__") and hasattr(source, "__getitem__")
    ):
        return CheckedRows([convert(item) for item in source])
    if hasattr(source, "__anext__"):
        return _converted_async(source, convert)
    if hasattr(source, "__next__") or (hasattr(source, "__iter__") and not callable(source)):
        return (convert(item) for item in source)
    if callable(source):
        return lambda t, statuses: convert(source(t, statuses))
    return source  # refused by the stream, naming its kind


async def _converted_async(
    source: AsyncIterator[Any], convert: Callable[[Any], dict[int, int] | None]
) -> AsyncIterator[dict[int, int] | None]:
    async for item in source:
        yield convert(item)


def _device(by_key: Mapping[object, Positioned], key: object) -> Positioned:
    try:
        return by_key[key]
    except (KeyError, TypeError):
        raise LocalProtocolError(
            f"targets name {key!r}, which this stream does not drive "
            f"(it drives {sorted({d.name for d in by_key.values()})})",
            field="targets",
            value=key,
        ) from None


def read_calibration_file(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The tables of a calibration file, by device name.

    Raises:
        LocalProtocolError: not UTF-8, not TOML, or an entry that is not a table (the
            message names the file).
        OSError: the file cannot be read (``FileNotFoundError`` if it is missing).
    """
    raw = Path(path).read_bytes()
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise LocalProtocolError(f"{path}: not UTF-8 text", field="calibration") from None
    except tomllib.TOMLDecodeError as err:
        raise LocalProtocolError(f"{path}: not valid TOML: {err}", field="calibration") from None
    for name, table in data.items():
        if not isinstance(table, dict):
            raise LocalProtocolError(
                f"{path}: {name}={table!r} is not allowed: each entry is a [NAME] table of a "
                "named device",
                field=name,
                value=table,
            )
    return data


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return "[" + ", ".join(_toml_value(v) for v in value) + "]"


def format_calibration_file(entries: Mapping[str, Mapping[str, Any]]) -> str:
    """The text of a calibration file holding ``entries`` (device name -> keys)."""
    lines = [
        "# Calibration of named LA actuators (motorbus la calibrate writes this file;",
        "# the bus file that names it reads it). Keys: docs/guide/calibrate.md",
    ]
    for name in sorted(entries):
        lines += ["", f"[{check_device_name('name', name)}]"]
        lines += [f"{key} = {_toml_value(value)}" for key, value in entries[name].items()]
    return "\n".join(lines) + "\n"


def write_calibration_file(path: str | os.PathLike[str], name: str, cal: Calibration) -> None:
    """Write ``name``'s calibration into the file at ``path``, keeping its other entries.

    Atomic: the new text goes to a temporary file beside it, which is flushed to disk
    and renamed over the old one; an interrupted write leaves the old file as it was.
    """
    target = Path(path)
    try:
        entries = read_calibration_file(target)
    except FileNotFoundError:
        entries = {}
    entries[name] = cal.as_table()
    text = format_calibration_file(entries)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
