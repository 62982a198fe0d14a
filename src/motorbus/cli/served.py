"""The read-only tools on a served bus (``--connect``): ``scan``, ``monitor`` without
``--ids`` and ``doctor``.  The server owns the port, so nothing here opens it: they
start from what the server knows (its ``devices`` query: the devices its bus file or
``--devices`` declares, those that answered its bus, its timing) and ask the devices
through the server, one status query at a time among the application's requests."""

from __future__ import annotations

import argparse
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
    for n in range(passes):
        for ident in remaining:
            try:
                await bus.request(_query(ident), timeout=budget * (1 + n), retries=0)
            except (ReplyTimeoutError, RemoteProtocolError):
                continue
            found.add(ident)
        remaining = [i for i in remaining if i not in found]
        if not remaining:
            break
    return ServedScan(devices.declared_la, asked, tuple(sorted(found)), budget)


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
