"""The read-only tools on a served bus (``--connect``): ``scan``, ``monitor`` without
``--ids`` and ``doctor``.  The server owns the port, so nothing here opens it: they
start from what the server knows (its ``devices`` query: the devices its bus file or
``--devices`` declares, those that answered its bus, its timing) and ask the devices
through the server, one status query at a time among the application's requests."""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from motorbus.bus.occupancy import command_occupancy
from motorbus.cli.bus_options import served_bus
from motorbus.cli.output import fail, print_json
from motorbus.devices.la import SCAN_BUDGET_MAX_S, SCAN_HOST_ALLOWANCE_S
from motorbus.errors import RemoteProtocolError, ReplyTimeoutError, UsageError
from motorbus.protocol import la

__all__ = ["ServedScan", "known_ids", "run_scan", "scan_served"]


def _query(ident: int) -> la.Control:
    return la.Control(ident, la.ControlAction.QUERY_STATUS)


@dataclass(frozen=True, slots=True)
class ServedScan:
    """What a scan through a server found."""

    declared: tuple[int, ...]
    asked: tuple[int, ...]
    found: tuple[int, ...]
    budget_s: float
    requests: int = 0  # status queries the scan sent
    misses: int = 0  # of those, the ones not answered (timeouts, bad replies)


async def known_ids(bus: Any) -> tuple[int, ...]:
    """The LA IDs the server of ``bus`` knows (declared, or answered it); nothing sent."""
    from motorbus.serve.tools_client import fetch_devices

    return (await fetch_devices(bus)).known_la


async def scan_served(
    bus: Any, ids: Sequence[int] | None, timeout: float | None, passes: int
) -> ServedScan:
    """Status queries through the server to ``ids`` (default: the IDs it knows).

    The per-ID budget (a deadline on the server's bus, from the completed write) is
    ``timeout`` if given, else the status query's wire time and the LA's turnaround on
    the server's bus plus the scan's host allowance, at least ``SCAN_BUDGET_MAX_S``;
    with two passes the IDs that did not answer are asked again with twice that.
    """
    from motorbus.serve.tools_client import fetch_devices

    devices = await fetch_devices(bus)
    asked = tuple(ids) if ids is not None else devices.known_la
    occupancy = command_occupancy(devices.timing, _query(la.ID_MIN))
    floor = occupancy.budget - occupancy.margin + SCAN_HOST_ALLOWANCE_S
    budget = timeout if timeout is not None else max(SCAN_BUDGET_MAX_S, 2 * floor)
    found: set[int] = set()
    remaining = list(asked)
    requests = misses = 0
    for n in range(passes):
        for ident in remaining:
            requests += 1
            try:
                await bus.request(_query(ident), timeout=budget * (1 + n), retries=0)
            except (ReplyTimeoutError, RemoteProtocolError):
                misses += 1
                continue
            found.add(ident)
        remaining = [i for i in remaining if i not in found]
        if not remaining:
            break
    return ServedScan(devices.declared_la, asked, tuple(sorted(found)), budget, requests, misses)


async def run_scan(args: argparse.Namespace, ids: list[int] | None) -> int:
    """``motorbus scan --connect``; 0 if some actuator answered, else 1."""
    if args.port or args.bus_file:
        raise UsageError("--connect uses a served bus: give it without --port or --bus-file")
    if args.baud is None:
        raise UsageError("--baud all reopens the port at each rate: not on a served bus")
    async with served_bus(args.connect, args.bus) as bus:
        result = await scan_served(bus, ids, args.timeout, args.passes)
        where = f"bus {bus.name} at {args.connect}"
    declared = ",".join(str(i) for i in result.declared) or "none"
    print(
        f"scan: {where}: declared la:{declared}; {len(result.asked)} IDs asked through "
        f"the server (budget per ID {result.budget_s * 1e3:.2f} ms), found {len(result.found)}",
        file=sys.stderr,
    )
    found = list(result.found)
    if args.json:
        print_json({"ids": found, "tried": len(result.asked), "declared": list(result.declared)})
    elif found:
        print(",".join(str(i) for i in found))
    if not found:
        why = (
            f"no actuator answered ({len(result.asked)} IDs asked through {where})"
            if result.asked
            else f"the server knows no LA actuator on {where}: give --ids to ask some"
        )
        return fail(args, why, tried=len(result.asked))
    return 0


#: Why the checks of the port itself do not run on a served bus.
PORT_IS_THE_SERVERS = (
    "the port belongs to the server at {where} (motorbus serve owns it); run motorbus doctor "
    "--port on the server's host while the server is stopped for this check"
)


async def diagnose_served(
    bus: Any, endpoint: str, ids: Sequence[int] | None, requests: int, period_s: float
) -> Any:
    """``motorbus doctor --connect``: the read-only checks through the server.

    ``devices`` asks the IDs (default: those the server knows) a status; each one found
    gets ``requests`` more status queries, and ``turnaround la:N`` and ``line`` judge the
    server bus's own counters (every request since it opened, the application's too;
    the line's less the scan's own queries, whose misses are the devices check's).
    The checks of the port, the adapter, the echo, the cycle budget and the host are
    skipped, each saying why: the port is the server's.
    """
    from motorbus.doctor.checks import (
        DeviceScan,
        LineFacts,
        TurnaroundFacts,
        check_devices,
        check_line,
        check_turnaround,
        skipped,
    )
    from motorbus.doctor.report import DoctorReport

    where = f"bus {bus.name} at {endpoint}"
    scan = await scan_served(bus, ids, None, 2)
    timing = (await _devices(bus)).timing
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


async def _devices(bus: Any) -> Any:
    from motorbus.serve.tools_client import fetch_devices

    return await fetch_devices(bus)


async def run_doctor(args: argparse.Namespace, ids: list[int] | None, period_s: float) -> Any:
    """Open the served bus and diagnose it (``diagnose_served``)."""
    if args.port or args.bus_file or args.baud is not None or args.backend is not None:
        raise UsageError(
            "--connect uses a served bus: give it without --port, --bus-file, --baud or --backend"
        )
    if args.fix or args.stream:
        raise UsageError("--fix and --stream change the port or move: not on a served bus")
    async with served_bus(args.connect, args.bus) as bus:
        return await diagnose_served(bus, args.connect, ids, args.requests, period_s)
