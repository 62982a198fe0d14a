"""The options of a bus and of a request: their defaults, their ranges, their checks.

Pure (no asyncio, no clock); ``MOTORBUS_HOST_MARGIN_MS`` is read once, at import.
``Bus`` (``motorbus.bus.bus``) checks its own options at construction and each request's
with ``check_request_options`` before anything is queued: a bad value raises
``LocalProtocolError`` naming the field, the value and what is allowed, nothing sent.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING

from motorbus.bus.schedule import Priority
from motorbus.errors import LocalProtocolError
from motorbus.protocol import families
from motorbus.protocol.base import Family, check_flag, check_int, check_timeout
from motorbus.validation import (
    HOST_MARGIN_MAX_S,
    LATE_GUARD_MAX_S,
    MIN_SPACING_MAX_S,
    RETRIES_MAX,
    check_number,
    check_turnaround,
)

if TYPE_CHECKING:  # the type only: this module stays free of asyncio
    from motorbus.bus.timer import Timer

__all__ = [
    "DEFAULT_HOST_MARGIN_S",
    "DEFAULT_LATE_GUARD_S",
    "DEFAULT_TURNAROUND",
    "MIN_SPACING_S",
    "REQUEST_RETRIES_MAX",
    "REQUEST_TIMEOUT_MAX_S",
    "BusConfig",
    "check_bus_options",
    "check_request_options",
    "check_timer",
]

#: Minimum start-to-start spacing of two frames: "keep the command interval >= 1 ms"
#: (LA manual 3.4.2, docs/protocols.md C.6).
MIN_SPACING_S = 1e-3
#: Worst-case device turnaround, request end to reply start, per family: the registry's
#: ``FamilyInfo.turnaround_s`` (protocol/families.py says where each figure comes from).
DEFAULT_TURNAROUND: Mapping[Family, float] = families.DEFAULT_TURNAROUND


def host_margin_from_env(text: str | None) -> float:
    """``MOTORBUS_HOST_MARGIN_MS`` (``text``; None: unset, 2 ms) in seconds.

    Raises:
        LocalProtocolError: not a number of milliseconds in 0..10000, naming the
            variable (it reached every bus's deadlines, or failed without its name).
    """
    if text is None:
        return 2e-3
    try:
        ms = float(text)
    except ValueError:
        ms = math.nan
    if not 0 <= ms <= HOST_MARGIN_MAX_S * 1e3:  # NaN too
        raise LocalProtocolError(
            f"MOTORBUS_HOST_MARGIN_MS={text!r} is not a host margin: give milliseconds, "
            f"0..{HOST_MARGIN_MAX_S * 1e3:g}",
            field="MOTORBUS_HOST_MARGIN_MS",
            value=text,
        )
    return ms / 1e3


#: Host-side latency allowance added to every deadline: scheduling, the pty or the USB
#: adapter (an FTDI in low-latency mode holds bytes up to 1 ms, docs/platform.md 5).  The
#: demo's LA round trips over a pty to a simulator process on this 2-core machine had a
#: p99 near 2 ms (benchmarks/bench_bus.py measures it), hence 2 ms.  On a loaded or
#: slow host, raise it for every bus at once with ``MOTORBUS_HOST_MARGIN_MS``.
DEFAULT_HOST_MARGIN_S = host_margin_from_env(os.environ.get("MOTORBUS_HOST_MARGIN_MS"))
#: After a timeout, the next request to the same device waits this long, so that the
#: device's late answer (if it comes) arrives before a new question it could be
#: mistaken for.  Requests to other devices are not held.
DEFAULT_LATE_GUARD_S = 20e-3


@dataclass(frozen=True, slots=True)
class BusConfig:
    """Timing policy of one bus (all durations in seconds).

    Frozen: ``Bus`` checks every value when it is built and derives its frame costs
    from them once (``Bus.timing``); give a bus other timing by building another.
    """

    min_spacing: float = MIN_SPACING_S
    host_margin: float = DEFAULT_HOST_MARGIN_S
    turnaround: Mapping[Family, float] = field(
        default_factory=lambda: MappingProxyType(dict(DEFAULT_TURNAROUND))
    )
    retries: int = 1
    late_guard: float = DEFAULT_LATE_GUARD_S
    reconnect: bool = True
    wire_floor: bool = False


def check_bus_options(
    *,
    min_spacing: object,
    host_margin: object,
    turnaround: object,
    retries: object,
    late_guard: object,
    reconnect: object,
    wire_floor: object,
) -> BusConfig:
    """``Bus``'s timing options checked (type, finiteness, range) and frozen together.

    Raises:
        LocalProtocolError: a value out of its range, naming the field and the range.
    """
    given = check_turnaround(turnaround)
    return BusConfig(
        min_spacing=check_number("min_spacing", min_spacing, 0.0, MIN_SPACING_MAX_S, "s"),
        host_margin=check_number("host_margin", host_margin, 0.0, HOST_MARGIN_MAX_S, "s"),
        turnaround=MappingProxyType({**DEFAULT_TURNAROUND, **(given or {})}),
        retries=check_int("retries", retries, 0, RETRIES_MAX),
        late_guard=check_number("late_guard", late_guard, 0.0, LATE_GUARD_MAX_S, "s"),
        reconnect=check_flag("reconnect", reconnect),
        wire_floor=check_flag("wire_floor", wire_floor),
    )


#: Ceiling on a per-request reply budget: far beyond any reply the three manuals
#: describe (the 226-byte 0x3E dump takes 0.24 s at 9600 bit/s), it only refuses nonsense.
REQUEST_TIMEOUT_MAX_S = 3600.0
#: Ceiling on per-request retries, the same as the bus-wide ``retries`` option.
REQUEST_RETRIES_MAX = 10


#: Every priority, built once: the check runs on every submit (the stream's hot path).
_PRIORITIES = frozenset(Priority)


def check_request_options(timeout: object, retries: object, priority: object) -> None:
    """Refuse a bad ``timeout``/``retries``/``priority`` before anything is queued."""
    if timeout is not None:
        check_timeout("timeout", timeout, REQUEST_TIMEOUT_MAX_S)
    if retries is not None and (
        isinstance(retries, bool)
        or not isinstance(retries, int)
        or not 0 <= retries <= REQUEST_RETRIES_MAX
    ):
        raise LocalProtocolError(
            f"retries={retries!r} is out of range: allowed 0..{REQUEST_RETRIES_MAX} or None",
            field="retries",
            value=retries,
        )
    if isinstance(priority, bool) or priority not in _PRIORITIES:
        raise LocalProtocolError(
            f"priority={priority!r} is not allowed: choose one of "
            f"{', '.join(p.name for p in Priority)}",
            field="priority",
            value=priority,
        )


#: What a bus calls on its timer (a :class:`Timer` has them all).
TIMER_METHODS = ("now", "call_at", "call_at_lazily", "hold_arming", "release_arming", "sleep_until")


def check_timer(value: object) -> Timer | None:
    """``value`` if it is a timer (a :class:`Timer`, or anything with its
    ``TIMER_METHODS``) or None; ``LocalProtocolError`` naming it and what it lacks
    otherwise (a bus given one failed only when it opened, or at its first request)."""
    if value is None:
        return None
    missing = [m for m in TIMER_METHODS if not callable(getattr(value, m, None))]
    if missing:
        raise LocalProtocolError(
            f"timer must be a motorbus Timer or None, got {value!r} (without {', '.join(missing)})",
            field="timer",
            value=value,
        )
    return value  # type: ignore[return-value]  # a Timer by its methods
