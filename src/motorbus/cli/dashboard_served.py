"""``motorbus dashboard`` on a served bus (docs/dashboard.md, "A served bus").

* ``--connect ENDPOINT [--bus NAME]``: attach to a running ``motorbus serve``; the
  devices to watch are ``--ids``/``--devices`` (a scan is not served yet).
* ``--port ...`` or a bus file: start a ``motorbus serve`` child for those buses on a
  free loopback port, wait for its ready line, attach to it, and end it when the
  dashboard ends (``ServeChild``).  The bus never runs on the dashboard's loop.
* Without the serve extra (Eclipse Zenoh), ``--port`` and bus files fall back to the
  bus in the dashboard's own process, with a one-line warning; ``--connect`` exits 2
  naming the extra.
"""

from __future__ import annotations

import argparse
import asyncio
import socket
import sys
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import cast

from motorbus import Bus, BusManager, scan
from motorbus.busfile import DeviceSpec, parse_devices
from motorbus.cli.bus_options import CLI_HOST_MARGIN_S
from motorbus.cli.ids import parse_ids
from motorbus.cli.scan import SCAN_TIMEOUT_S
from motorbus.dashboard import BusSetup, Dashboard
from motorbus.dashboard.hosts import HostCheck
from motorbus.dashboard.served import ServeChild, ServeChildError, ServedDashboard
from motorbus.errors import UsageError

__all__ = [
    "NO_SERVE_WARNING",
    "PageSettings",
    "Watch",
    "attach",
    "connect_plan",
    "serve_extra",
    "spawn_and_attach",
]

#: The one line printed when --port or a bus file falls back to the bus in this process.
NO_SERVE_WARNING = (
    "motorbus dashboard: warning: the serve extra is not installed "
    "(pip install 'motorbus[serve]'): the bus runs in the dashboard's own process"
)
CONNECT_EXTRA = "--connect needs the serve extra: pip install 'motorbus[serve]'"


def serve_extra() -> bool:
    """Whether Eclipse Zenoh (the ``serve`` extra) is installed."""
    try:
        import zenoh  # noqa: F401
    except ImportError:
        return False
    return True


@dataclass(frozen=True, slots=True)
class PageSettings:
    """Where and how the page is served."""

    host: str
    port: int
    token: str | None
    window: tuple[int, int]
    hosts: HostCheck


@dataclass(slots=True)
class Watch:
    """One served bus to watch: the server's name for it (``None``: the only one), the
    page's (``None``: the same), its devices, and the safe action of what the dashboard
    moves (``None``: the served bus's own)."""

    served: str | None
    shown: str | None
    la_ids: list[int]
    project_motor: int | None = None
    quad: bool = False
    la_safe_action: str | None = None


RunPage = Callable[
    [argparse.Namespace, Dashboard, PageSettings, Callable[[], Awaitable[object]]],
    Awaitable[None],
]


def _device_items(args: argparse.Namespace) -> list[str]:
    items: list[str] = []
    if args.ids:
        items.append("la:" + ",".join(str(i) for i in parse_ids(args.ids)))
    if args.devices:
        items += _split_devices(args.devices)
    return items


def _split_devices(text: str) -> list[str]:
    """``la:1,3,quad-stepper`` -> ``["la:1,3", "quad-stepper"]`` (IDs stay with their la)."""
    out: list[str] = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        if out and out[-1].startswith("la:") and part[0].isdigit():
            out[-1] += "," + part
        else:
            out.append(part)
    return out


def _watch(
    served: str | None,
    shown: str | None,
    devices: Sequence[DeviceSpec],
    la_ids: list[int],
    safe_action: str | None,
) -> Watch:
    project = next((d.motor for d in devices if d.kind == "project_stepper"), None)
    quad = any(d.kind == "quad_stepper" for d in devices)
    return Watch(served, shown, la_ids, project, quad, safe_action)


def connect_plan(args: argparse.Namespace, endpoint: str) -> list[Watch]:
    """What ``--connect`` watches; every option checked before anything connects.

    Raises:
        UsageError: with --port, --bus-file or --process; no devices; no serve extra.
        LocalProtocolError: a bad endpoint or device item.
    """
    if getattr(args, "port", None) or getattr(args, "bus_file", None):
        raise UsageError("--connect uses a served bus: give it without --port or --bus-file")
    if args.process:
        raise UsageError("--process chooses buses of a bus file; --connect uses a served bus")
    if not serve_extra():
        raise UsageError(CONNECT_EXTRA)
    from motorbus.serve.zconf import check_endpoint

    check_endpoint("--connect", endpoint)
    items = _device_items(args)
    if not items:
        raise UsageError(
            "--connect needs the devices to watch: --ids 1-3 or --devices la:1-3,quad-stepper "
            "(a scan is not served yet)"
        )
    devices = parse_devices(items)
    ids = [i for d in devices if d.kind == "la" for i in d.ids]
    return [_watch(args.bus, None, devices, ids, None)]


async def attach(
    args: argparse.Namespace,
    page: PageSettings,
    watches: list[Watch],
    endpoint: str,
    run_page: RunPage,
    until: Callable[[], Awaitable[object]] | None = None,
) -> None:
    """Connect to the server at ``endpoint`` and serve the page of ``watches`` until
    ``until()`` returns (default: until Ctrl-C or SIGTERM)."""
    import motorbus

    async with motorbus.connect(endpoint, name="dashboard") as site:
        setups = []
        for w in watches:
            bus = site.bus(w.served)
            setups.append(
                BusSetup(
                    cast(Bus, bus),
                    list(w.la_ids),
                    w.project_motor,
                    w.quad,
                    w.la_safe_action or bus.safe_action,
                    name=w.shown,
                )
            )
        dash = ServedDashboard(
            setups,
            endpoint=endpoint,
            period=args.interval,
            control=args.control,
            window=page.window,
        )
        await run_page(args, dash, page, until or asyncio.Event().wait)


def free_loopback_endpoint() -> str:
    """A Zenoh endpoint on a loopback port that is free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _chunk(url: str) -> str:
    """A served bus name (one key chunk) for the port ``url``: ``/dev/ttyUSB0`` ->
    ``dev_ttyUSB0``."""
    out = "".join(c if c.isalnum() or c in "_.-" else "_" for c in url).strip("_")
    return out or "bus"


async def _scan_missing(
    manager: BusManager, wanted: dict[str, list[int] | None]
) -> dict[str, list[int]]:
    """The LA IDs of every bus; the buses whose devices are not given are scanned here,
    before the server opens them (a scan is not served yet)."""
    out = {name: ids for name, ids in wanted.items() if ids is not None}
    if len(out) == len(wanted):
        return out
    async with manager:
        for name, bus in manager.buses.items():
            if name not in out:
                out[name] = await scan(bus, timeout=SCAN_TIMEOUT_S)
    return out


def serve_plan(
    args: argparse.Namespace,
    manager: BusManager,
    wanted: dict[str, list[int]],
    bus_file: Path | None,
    endpoint: str,
) -> tuple[list[str], list[Watch]]:
    """The ``motorbus serve`` arguments for the dashboard's buses, and what to watch."""
    margin_ms = f"{CLI_HOST_MARGIN_S * 1e3:g}"
    # The dashboard's contract: an actuator it never commanded gets nothing on exit.
    argv = ["--stop-leased-only"]
    if bus_file is not None:
        argv += [str(bus_file), "--listen", endpoint, "--host-margin-ms", margin_ms]
        if args.process:
            argv += ["--process", args.process]
        if args.bus:
            argv += ["--bus", args.bus]
        watches = [
            _watch(name, None, spec.devices, wanted[name], spec.la_safe_action)
            for name, spec in manager.specs.items()
        ]
        return argv, watches
    ((name, spec),) = manager.specs.items()
    served = _chunk(spec.url)
    argv += ["--port", spec.url, "--baud", str(spec.baud), "--backend", spec.backend]
    argv += ["--name", served, "--listen", endpoint]
    argv += ["--host-margin-ms", f"{spec.host_margin_ms:g}"]
    items = _device_items(args)
    if items:
        argv += ["--devices", ",".join(items)]
    return argv, [_watch(served, name, spec.devices, wanted[name], spec.la_safe_action)]


async def spawn_and_attach(
    args: argparse.Namespace,
    page: PageSettings,
    manager: BusManager,
    wanted: dict[str, list[int] | None],
    bus_file: Path | None,
    run_page: RunPage,
) -> None:
    """Start a ``motorbus serve`` child for the dashboard's buses, attach to it, and
    end it (SIGTERM: its safe ends) when the dashboard ends, however it ends."""
    ids = await _scan_missing(manager, wanted)
    endpoint = free_loopback_endpoint()
    argv, watches = serve_plan(args, manager, ids, bus_file, endpoint)
    child = ServeChild(argv)
    try:
        await child.start()
        print(
            f"motorbus serve (pid {child.pid}) owns the port(s) and serves them at {endpoint}",
            file=sys.stderr,
            flush=True,
        )

        async def until() -> None:
            code = await child.wait()
            raise ServeChildError(
                f"motorbus serve (pid {child.pid}), the dashboard's bus server, ended with "
                f"status {code}; its messages are above"
            )

        await attach(args, page, watches, endpoint, run_page, until)
    finally:
        await child.stop()
