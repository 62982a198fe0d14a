"""``motorbus doctor`` on a served bus (``doctor --connect``): the read-only checks.

The port belongs to the server (``motorbus serve``), so the checks of the port, the
adapter's latency, the echo, the cycle budget and the host do not run here: each is
reported as skipped, saying why.  ``devices`` asks the LA IDs a status through the
server; ``turnaround la:N`` and ``line`` judge the server bus's own counters.  ``bus``
is a served bus (``motorbus.connect(...).bus(name)``: its ``scan``, ``fetch_devices``,
``fetch_stats`` and ``request``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Sequence
from typing import Any

from motorbus.doctor.checks import (
    DeviceScan,
    LineFacts,
    TurnaroundFacts,
    check_devices,
    check_line,
    check_turnaround,
    skipped,
)
from motorbus.doctor.probe import DEFAULT_REQUESTS
from motorbus.doctor.report import DoctorReport
from motorbus.errors import RemoteProtocolError, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol.base import check_int
from motorbus.streams import PERIOD_MAX_S, PERIOD_MIN_S
from motorbus.validation import check_number

__all__ = ["PORT_IS_THE_SERVERS", "diagnose_served"]


def _query(ident: int) -> la.Control:
    return la.Control(ident, la.ControlAction.QUERY_STATUS)


#: Why the checks of the port itself do not run on a served bus.
PORT_IS_THE_SERVERS = (
    "the port belongs to the server at {where} (motorbus serve owns it); run motorbus doctor "
    "--port on the server's host while the server is stopped for this check"
)


async def diagnose_served(
    bus: Any,
    endpoint: str,
    ids: Sequence[int] | None = None,
    *,
    requests: int = DEFAULT_REQUESTS,
    period_s: float = PERIOD_MIN_S,
) -> DoctorReport:
    """``motorbus doctor --connect``: the read-only checks through the server.

    ``devices`` asks the IDs (default: those the server knows) a status; each one found
    gets ``requests`` more status queries, and ``turnaround la:N`` and ``line`` judge the
    server bus's own counters (every request since it opened, the application's too;
    the line's less the scan's own queries, whose misses are the devices check's).
    The checks of the port, the adapter, the echo, the cycle budget and the host are
    skipped, each saying why: the port is the server's.
    """
    check_int("requests", requests, 1, 1000)
    check_number("period", period_s, PERIOD_MIN_S, PERIOD_MAX_S, "s", slack=1e-9)
    if ids is not None:
        ids = [check_int("id", i, la.ID_MIN, la.ID_MAX) for i in ids]
    where = f"bus {bus.name} at {endpoint}"
    scan = await bus.scan(ids)
    timing = (await bus.fetch_devices()).timing
    report = DoctorReport(where, timing.baud, period_s)
    add = report.findings.append
    why = PORT_IS_THE_SERVERS.format(where=endpoint)
    for check in ("port", "latency", "echo"):
        add(skipped(check, why))
    configured = ids is not None or bool(scan.declared)
    add(
        check_devices(
            DeviceScan(timing.baud, scan.asked, configured, scan.found), f"the server's {where}"
        )
    )
    for ident in scan.found:
        for _ in range(requests):
            # A lost or bad reply is counted by the server's bus: its stats say it.
            with contextlib.suppress(ReplyTimeoutError, RemoteProtocolError):
                await bus.request(_query(ident), retries=0)
    stats = await bus.fetch_stats()
    for ident in scan.found:
        key = f"la:{ident}"
        device = stats.get("devices", {}).get(key)
        if not device:
            continue
        latency = device["latency"]
        timeouts, late = int(device["timeouts"]), int(device["late_replies"])
        facts = TurnaroundFacts(
            key=key,
            requests=int(device["requests"]),
            p50=latency["p50_us"] / 1e6,
            p99=latency["p99_us"] / 1e6,
            max=latency["max_us"] / 1e6,
            replies=int(device["replies"]),
            late=late,
            lost=max(0, timeouts - late),
        )
        add(check_turnaround(facts, timing, period_s))
    add(
        check_line(
            LineFacts(
                requests=max(0, int(stats["requests"]) - scan.requests),
                timeouts=max(0, int(stats["timeouts"]) - scan.misses),
                late_replies=int(stats["late_replies"]),
                garbage_bytes=int(stats["garbage_bytes"]),
                unexpected_frames=int(stats["unexpected_frames"]),
                discarded_by_reason=dict(stats.get("discarded_by_reason", {})),
            )
        )
    )
    add(
        skipped(
            "budget",
            "measuring the cycle budget needs the bus to itself; the server's application "
            "streams on it (run motorbus doctor --port on the server's host)",
        )
    )
    add(skipped("host", f"the host checks are of the server's host, not this one ({where})"))
    return report
