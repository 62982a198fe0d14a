"""``scan --connect`` and ``doctor --connect``: the read-only tools on a served bus.

The server owns the port, so nothing here opens it: they start from what the server
knows (``ServedBus.fetch_devices``: the devices its bus file or ``--devices`` declares,
those that answered its bus, its timing) and ask the devices through the server, one
status query at a time among the application's requests (``ServedBus.scan``,
``motorbus.diagnose_served``)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

from motorbus import diagnose_served
from motorbus.cli.bus_options import served_bus
from motorbus.cli.output import fail, print_json
from motorbus.errors import UsageError

__all__ = ["run_doctor", "run_scan"]


async def run_scan(args: argparse.Namespace, ids: list[int] | None) -> int:
    """``motorbus scan --connect``; 0 if some actuator answered, else 1."""
    if args.port or args.bus_file:
        raise UsageError("--connect uses a served bus: give it without --port or --bus-file")
    if args.baud is None:
        raise UsageError("--baud all reopens the port at each rate: not on a served bus")
    async with served_bus(args.connect, args.bus) as bus:
        if getattr(args, "baud_given", False) and args.baud != bus.baudrate:
            raise UsageError(
                f"--baud {args.baud}: the served bus {bus.name} runs at {bus.baudrate} bit/s "
                "(its server's port); a scan through it cannot change that"
            )
        served: Any = bus
        result = await served.scan(ids, timeout=args.timeout, passes=args.passes)
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


async def run_doctor(args: argparse.Namespace, ids: list[int] | None, period_s: float) -> Any:
    """``motorbus doctor --connect``: the served bus's read-only checks (a report)."""
    if args.port or args.bus_file or args.baud is not None or args.backend is not None:
        raise UsageError(
            "--connect uses a served bus: give it without --port, --bus-file, --baud or --backend"
        )
    if args.fix or args.stream:
        raise UsageError("--fix and --stream change the port or move: not on a served bus")
    async with served_bus(args.connect, args.bus) as bus:
        return await diagnose_served(
            bus, args.connect, ids, requests=args.requests, period_s=period_s
        )
