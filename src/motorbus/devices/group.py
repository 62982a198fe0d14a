"""Group reads: the status of many LA actuators in one call, pipelined on the bus.

``await read_statuses(bus, [1, ..., 15])`` submits every status query at once and
gathers the replies: the bus queues them and writes each as soon as the one before
it has been answered (or timed out) and its spacing allows, so the group costs the
wire and the actuators' turnarounds, not one round trip through the caller per ID.
The requests go out in the order given, each with the bus's usual deadline and
retries (a timeout or a garbled reply is retried by the bus before it counts here).

What a silent or garbled actuator gives is chosen with ``on_error``:

* ``"raise"`` (default): once every request has ended, ``GroupReadError`` names the
  IDs that gave no status and why; its ``statuses`` holds those that answered.
* ``"return"``: nothing is raised for them; the mapping holds the error in their
  place (``isinstance(value, Exception)``).

A closed bus, a lost port or a bad argument is never per ID: it is raised as is.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterable
from typing import Literal, overload

from motorbus.bus.bus import Bus, Priority
from motorbus.errors import (
    GroupReadError,
    LocalProtocolError,
    NotSentError,
    RemoteProtocolError,
    ReplyTimeoutError,
)
from motorbus.protocol import la
from motorbus.protocol.base import check_int

__all__ = ["ON_ERROR", "PER_ID_ERRORS", "read_statuses"]

#: The choices of ``read_statuses(on_error=...)``.
ON_ERROR = ("raise", "return")
#: The failures that belong to one actuator (the others are the bus's, raised as is).
PER_ID_ERRORS: tuple[type[Exception], ...] = (ReplyTimeoutError, RemoteProtocolError, NotSentError)


@overload
async def read_statuses(
    bus: Bus,
    ids: Iterable[int],
    *,
    on_error: Literal["raise"] = "raise",
    timeout: float | None = None,
) -> dict[int, la.Status]: ...


@overload
async def read_statuses(
    bus: Bus,
    ids: Iterable[int],
    *,
    on_error: Literal["return"],
    timeout: float | None = None,
) -> dict[int, la.Status | Exception]: ...


async def read_statuses(
    bus: Bus,
    ids: Iterable[int],
    *,
    on_error: str = "raise",
    timeout: float | None = None,
) -> dict[int, la.Status] | dict[int, la.Status | Exception]:
    """Query the status of every actuator in ``ids`` at once; ``{id: Status}`` in that order.

    Args:
        bus: an open bus carrying ``Family.LA``.
        ids: the actuator IDs, 1..254 each, at least one, no repeats.
        on_error: ``"raise"`` or ``"return"`` (see the module docstring).
        timeout: each reply's budget in seconds (default: the bus's own).

    Raises:
        LocalProtocolError: a bad ID list, ``on_error`` or ``timeout``; nothing is sent.
        GroupReadError: ``on_error="raise"`` and some actuators gave no status.
        BusClosedError: the bus is closed or its port was lost.
    """
    wanted = check_ids(ids)
    mode = check_on_error(on_error)
    futures: list[asyncio.Future[la.Status]] = []
    try:
        for ident in wanted:
            query = la.control_frame(ident, la.ControlAction.QUERY_STATUS)
            futures.append(bus.submit(query, timeout=timeout, priority=Priority.NORMAL))
        outcomes = await asyncio.gather(*futures, return_exceptions=True)
    except BaseException:
        for future in futures:
            future.cancel()  # a queued query is dropped; a sent one ends on its deadline
        raise
    results: dict[int, la.Status | Exception] = {}
    failures: dict[int, Exception] = {}
    for ident, outcome in zip(wanted, outcomes, strict=True):
        if isinstance(outcome, PER_ID_ERRORS):
            failures[ident] = outcome
            results[ident] = outcome
        elif isinstance(outcome, BaseException):
            raise outcome
        else:
            results[ident] = outcome
    if mode == "return" or not failures:
        return results
    statuses = {i: s for i, s in results.items() if isinstance(s, la.Status)}
    reasons = "; ".join(f"la:{i}: {err}" for i, err in failures.items())
    raise GroupReadError(
        f"{len(failures)} of {len(wanted)} actuators gave no status "
        f"(IDs {', '.join(str(i) for i in failures)}): {reasons}",
        statuses=dict(statuses),
        failures=failures,
    )


def check_ids(ids: Iterable[int]) -> list[int]:
    """``ids`` as a list of distinct unicast LA IDs (1..254), at least one."""
    if isinstance(ids, str | bytes) or not isinstance(ids, Iterable):
        raise LocalProtocolError(
            f"ids={ids!r} is not allowed: give a list of actuator IDs, 1..{la.ID_MAX}",
            field="ids",
            value=ids,
        )
    wanted = [check_int("ids", i, la.ID_MIN, la.ID_MAX) for i in ids]
    if not wanted:
        raise LocalProtocolError("ids=[] is not allowed: name at least one actuator", field="ids")
    seen: set[int] = set()
    for ident in wanted:
        if ident in seen:
            raise LocalProtocolError(
                f"ids: {ident} is given twice; each actuator is read once", field="ids", value=ident
            )
        seen.add(ident)
    return wanted


def check_on_error(on_error: object) -> str:
    if on_error not in ON_ERROR:
        raise LocalProtocolError(
            f"on_error={on_error!r} is not allowed: one of {', '.join(ON_ERROR)}",
            field="on_error",
            value=on_error,
        )
    return str(on_error)
