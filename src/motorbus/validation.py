"""Argument checks of ``Bus``, ``Streamer`` and the bus file, in one place.

Every check returns the value in its plain Python type (a numpy scalar becomes an
``int`` or a ``float``) or raises ``LocalProtocolError`` naming the field, the value
and what is allowed, before anything reaches a port or a timer.  Rules: bools are not
numbers; text is not a number; NaN and infinity are refused wherever a duration is.

The ranges, and why:

* baud: 300..4,000,000 bit/s.  Every rate the three manuals list (9600 for the
  steppers, up to 921600 for the LA) is inside, with room above for faster adapters;
  below 300 bit/s one 22-byte LA status frame would take most of a second.  Bauds such
  as 1 or 7 are typing mistakes, not serial rates, and 10**12 used to reach the OS.
* min_spacing: 0..1 s (the LA manual asks for >= 1 ms between frames; 0 turns the
  spacing off for devices that need none).
* host_margin: 0..10 s; turnaround: 0..1 s per family; late_guard: 0..2 s (a late
  reply is recognised for 2 s after its timeout, so a longer guard protects nothing).
* retries: 0..10.
* Streamer phase: 0..50 ms (the longest stream period: the grid repeats after it).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import BAUD_MAX as BAUD_MAX
from motorbus.protocol.base import BAUD_MIN as BAUD_MIN
from motorbus.protocol.base import Family, as_real, check_int

__all__ = [
    "BAUD_MAX",
    "BAUD_MIN",
    "HOST_MARGIN_MAX_S",
    "LATE_GUARD_MAX_S",
    "LEAD_MAX_S",
    "MIN_SPACING_MAX_S",
    "PHASE_MAX_S",
    "RETRIES_MAX",
    "TURNAROUND_MAX_S",
    "CheckedRows",
    "check_baud",
    "check_device_bus",
    "check_families",
    "check_name",
    "check_number",
    "check_turnaround",
    "is_scalar",
    "target_id",
    "target_position",
]


class CheckedRows(list[dict[int, int] | None]):
    """Rows of follow targets ``{id: position}`` already checked whole, against limits
    at least as narrow as the stroke (``devices.calibration.limited_targets``): a
    stream takes them without checking each row again (``TargetAdapter.check_rows``)."""


#: Upper bounds of the bus timing options, seconds.
MIN_SPACING_MAX_S = 1.0
HOST_MARGIN_MAX_S = 10.0
TURNAROUND_MAX_S = 1.0
LATE_GUARD_MAX_S = 2.0
#: Most retries a bus (or one request) may be told to make.
RETRIES_MAX = 10
#: Streamer phase offset, seconds: 0 up to the longest follow-mode period (3.5.3).
PHASE_MAX_S = 0.050
#: A served stream's lead, seconds: how far ahead of their ticks its targets travel to
#: the server (and the server's longest ``start_in``).
LEAD_MAX_S = 5.0


def check_number(
    field: str, value: object, lo: float, hi: float, unit: str = "", *, slack: float = 0.0
) -> float:
    """Return ``value`` as a float if it is a finite real number in ``lo..hi``.

    ``slack`` widens the range for rounding only (a float32 0.01 is 0.00999999978).
    """
    number = as_real(value)
    allowed = f"{lo:g}..{hi:g}{' ' + unit if unit else ''}"
    if number is None:
        raise LocalProtocolError(
            f"{field} must be a number {allowed}, got {value!r} ({type(value).__name__})",
            field=field,
            value=value,
        )
    if not math.isfinite(number) or not lo - slack <= number <= hi + slack:
        raise LocalProtocolError(
            f"{field}={value!r}{' ' + unit if unit else ''} is out of range: allowed {allowed} "
            "(a finite number)",
            field=field,
            value=value,
        )
    return number


def check_baud(field: str, value: object) -> int:
    """Return ``value`` if it is an integer serial rate in ``BAUD_MIN..BAUD_MAX``."""
    return check_int(field, value, BAUD_MIN, BAUD_MAX)


def check_name(field: str, value: object, *, optional: bool = False) -> str | None:
    """Return ``value`` if it is a non-empty string (or None when ``optional``)."""
    if value is None and optional:
        return None
    if not isinstance(value, str) or not value.strip():
        raise LocalProtocolError(
            f"{field} must be a non-empty string, got {value!r} ({type(value).__name__})",
            field=field,
            value=value,
        )
    return value


def check_families(value: object) -> frozenset[Family]:
    """Return the families as a frozenset if ``value`` is a non-empty iterable of ``Family``."""
    allowed = ", ".join(f"Family.{f.name}" for f in Family)
    if isinstance(value, str | bytes) or not isinstance(value, Iterable):
        raise LocalProtocolError(
            f"families must be an iterable of {allowed}, got {value!r}",
            field="families",
            value=value,
        )
    items = list(value)
    bad = [f for f in items if not isinstance(f, Family)]
    if bad or not items:
        raise LocalProtocolError(
            f"families={items!r} is not allowed: give at least one of {allowed}",
            field="families",
            value=value,
        )
    return frozenset(items)


def check_turnaround(value: object) -> dict[Family, float] | None:
    """Return ``value`` as ``{Family: seconds}`` if it maps families to 0..1 s (or is None)."""
    if value is None:
        return None
    if not isinstance(value, Mapping):
        raise LocalProtocolError(
            f"turnaround must be a mapping {{Family: seconds}}, got {value!r}",
            field="turnaround",
            value=value,
        )
    out: dict[Family, float] = {}
    for family, seconds in value.items():
        if not isinstance(family, Family):
            raise LocalProtocolError(
                f"turnaround key {family!r} is not a Family: use one of "
                f"{', '.join(f'Family.{f.name}' for f in Family)}",
                field="turnaround",
                value=family,
            )
        out[family] = check_number(
            f"turnaround[{family.name}]", seconds, 0.0, TURNAROUND_MAX_S, "s"
        )
    return out


# -- stream targets ----------------------------------------------------------------------


def is_scalar(item: Any) -> bool:
    """True if a stream item is one number (a numpy scalar or 0-d array included), not a
    row of numbers.  A numpy array has ``__index__`` whatever its shape, so the test is
    "has no length", not "has ``__index__``"."""
    if hasattr(item, "__len__"):
        return getattr(item, "ndim", None) == 0
    return hasattr(item, "__index__") or hasattr(item, "__float__")


def check_device_bus(value: object) -> None:
    """A device's bus: a ``Bus``, or a served one (``motorbus.connect``): anything with a
    ``request`` (an object without one failed at the device's first call)."""
    if not callable(getattr(value, "request", None)):
        raise LocalProtocolError(
            f"bus must be a motorbus Bus (or a served bus from motorbus.connect), got "
            f"{value!r} ({type(value).__name__})",
            field="bus",
            value=value,
        )


def target_position(value: Any, name: str) -> int:
    """A follow target as an int 0..2000 (floats, numpy scalars included, are rounded)."""
    kind = type(value)
    number = value if kind is float or kind is int else as_real(value)
    if number is None and getattr(value, "ndim", None) == 0:
        number = as_real(value.item())  # a 0-d numpy array
    if number is None:
        raise LocalProtocolError(
            f"{name} must be a number {la.POSITION_MIN}..{la.POSITION_MAX}, got {value!r} "
            f"({type(value).__name__})",
            field=name,
            value=value,
        )
    if math.isnan(number) or not la.POSITION_MIN <= number <= la.POSITION_MAX:
        raise LocalProtocolError(
            f"{name}={value} is out of range: allowed {la.POSITION_MIN}..{la.POSITION_MAX}",
            field=name,
            value=value,
        )
    return round(number)


def target_id(value: Any) -> int:
    """An actuator ID used as a key of a target mapping: an integer 1..254."""
    return check_int("targets id", value, la.ID_MIN, la.ID_MAX)
