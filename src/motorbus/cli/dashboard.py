"""``motorbus dashboard``: a live web page of every bus and device, with optional controls.

Examples::

    motorbus dashboard --port /dev/ttyUSB0 --ids 1-3
    motorbus dashboard --bus-file buses.toml --control
    motorbus dashboard --bus-file buses.toml --process arms   # one group, on its CPUs
    motorbus dashboard --port /dev/ttyUSB0 --listen 0.0.0.0:8765   # prints a token URL

Needs the dashboard extra: pip install 'motorbus[dashboard]'.  On start it prints the
page's URL on a line of its own; open it in a browser (a phone works too).  Listening
on every address (--listen 0.0.0.0:PORT) it prints one URL a line instead, each saying
what it is: the machine's host name, each of its addresses, and 127.0.0.1 for this
machine only.  With --port the bus is named by the port as given (/dev/ttyUSB0).  One poller
per bus reads every LA actuator's status in turn (--interval apart), whatever the
number of viewers.  The page is read-only unless started with --control (e-stop, pause,
work, clear fault, move-to inside --window).  It listens on 127.0.0.1 unless --listen
says otherwise; then every request needs the random token printed in the URL.  It
answers only requests addressed to the address it listens on (the Host header; on
127.0.0.1 also "localhost"), which is what keeps a web page of another site from reaching
it through DNS rebinding; --allow-host NAME adds a name it may be reached by.

Without --bus-file it watches one port (--ids, else --devices la:1-3,quad-stepper...,
else a scan); with --bus-file every bus of the file (or --bus NAME), every key honoured;
with --process NAME only that process group's buses, and it runs on the group's CPUs.
--record DIR writes each bus's frame log (motorbus replay reads it) and plots.csv.
Ctrl-C or SIGTERM ends it (exit code 0) after pausing what it moved.

The bus never runs in the dashboard's event loop: with --port or a bus file it starts a
motorbus serve of its own for those buses (loopback, a free port), attaches to it, and
ends it on the way out, however the dashboard ends.  --connect ENDPOINT (--bus NAME
where the server serves several) attaches to a running motorbus serve instead; give
the devices with --ids or --devices (a scan is not served yet).  Without the serve
extra (pip install 'motorbus[serve]') --port and bus files run the bus in the
dashboard's process, after a one-line warning, and --connect exits 2.
"""

from __future__ import annotations

import argparse
import asyncio
import ipaddress
import os
import secrets
import socket
import sys
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from motorbus import BusManager, BusSpec, Family, default_bus_file, load_bus_file, scan
from motorbus import run as run_safely
from motorbus.cli.bus_options import (
    BUS_FILE_ENV,
    CLI_HOST_MARGIN_S,
    LA_BAUD,
    PORT_ENV,
    add_bus_options,
    add_process_option,
    resolve_port,
    with_cli_margin,
)
from motorbus.cli.ids import parse_ids
from motorbus.cli.scan import SCAN_TIMEOUT_S
from motorbus.cli.values import check_seconds
from motorbus.dashboard import BusSetup, Dashboard
from motorbus.dashboard.hosts import LOOPBACK_NAMES, HostCheck
from motorbus.dashboard.served import (
    ServeChild,
    ServeChildError,
    Watch,
    free_loopback_endpoint,
    served_name,
    watch_site,
)
from motorbus.errors import LocalProtocolError, UsageError
from motorbus.protocol import la
from motorbus.runtime import realtime

__all__ = [
    "DEFAULT_LISTEN",
    "EXTRA_MESSAGE",
    "host_check",
    "machine_addresses",
    "page_urls",
    "parse_listen",
    "register",
    "run",
]

#: Where the page is served unless --listen says otherwise.
DEFAULT_LISTEN = "127.0.0.1:8765"
#: What is printed (exit code 2) when aiohttp is not installed.
EXTRA_MESSAGE = "motorbus dashboard needs the dashboard extra: pip install 'motorbus[dashboard]'"
#: Shortest poll round, seconds.
MIN_INTERVAL_S = 0.005
#: WebSocket pushes a second (allowed range).
PUSH_HZ_RANGE = (0.5, 50.0)


def register(subparsers: Any) -> None:
    """Add the ``dashboard`` command."""
    p = subparsers.add_parser(
        "dashboard",
        help="live web page of every bus and device (plots, faults, e-stop)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--ids", help="LA IDs to watch on --port, e.g. 1-3,7 (default: scan)")
    p.add_argument(
        "--devices",
        help="devices on --port as in a bus file, comma list: la:1-3, project-stepper, "
        "quad-stepper",
    )
    p.add_argument(
        "--interval", type=float, default=0.1, help="seconds per poll round (default 0.1)"
    )
    p.add_argument(
        "--listen",
        metavar="HOST:PORT",
        default=DEFAULT_LISTEN,
        help=f"where to serve the page (default {DEFAULT_LISTEN}; port 0: any free port)",
    )
    p.add_argument("--control", action="store_true", help="allow controls (e-stop, move...)")
    p.add_argument(
        "--allow-host",
        metavar="NAME",
        action="append",
        default=[],
        help="a host name the page may be reached by besides the --listen address "
        "(repeatable); requests for any other Host get 403",
    )
    p.add_argument(
        "--window",
        metavar="LO:HI",
        default=f"{la.POSITION_MIN}:{la.POSITION_MAX}",
        help="positions a move-to may target (default the whole stroke)",
    )
    p.add_argument("--record", metavar="DIR", help="record frame logs and plots.csv into DIR")
    p.add_argument("--push-hz", type=float, default=10.0, help="page updates a second (10)")
    add_bus_options(p, default_baud=LA_BAUD, json_option=False, connect=True)
    add_process_option(p)
    p.set_defaults(func=run)


def parse_listen(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:PORT`` for IPv6) into its parts.

    Raises:
        LocalProtocolError: no port, or a port outside 0..65535.
    """
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise LocalProtocolError(
            f"--listen={text!r} is not HOST:PORT with a port 0..65535 (0: any free port)",
            field="--listen",
            value=text,
        )
    return host, int(port)


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def host_check(host: str, allowed: list[str]) -> HostCheck:
    """The ``Host`` names a dashboard listening on ``host`` answers to.

    The listen address itself, the loopback names when it is a loopback address, and
    the names given with ``--allow-host``.  On a wildcard address (0.0.0.0, ::) any IP
    address literal too, and this machine's own names: the page is then reached by
    whichever of the machine's addresses the viewer uses.
    """
    names = [host, *allowed]
    wildcard = host in ("0.0.0.0", "::", "")
    if _is_loopback(host):
        names += LOOPBACK_NAMES
    if wildcard:
        names += [*LOOPBACK_NAMES, socket.gethostname(), socket.getfqdn()]
    for name in allowed:
        if not name.strip() or any(c in name for c in "/ @"):
            raise LocalProtocolError(
                f"--allow-host={name!r} is not a host name (e.g. robot.local)",
                field="--allow-host",
                value=name,
            )
    return HostCheck(names, any_address=wildcard)


#: Listen addresses that mean "every address of this machine".
WILDCARDS = ("0.0.0.0", "::", "")
#: Documentation addresses (RFC 5737, RFC 3849): a UDP socket "connected" to one tells
#: which local address the default route uses, without sending anything.
_PROBE = {socket.AF_INET: "192.0.2.1", socket.AF_INET6: "2001:db8::1"}


def machine_addresses(ipv6: bool) -> list[str]:
    """This machine's addresses another machine may reach it by: the default route's,
    then those its host name resolves to; no loopback or link-local address."""
    families = [socket.AF_INET, socket.AF_INET6] if ipv6 else [socket.AF_INET]
    found: list[str] = []
    for family in families:
        try:
            with socket.socket(family, socket.SOCK_DGRAM) as probe:
                probe.connect((_PROBE[family], 9))  # UDP: no packet leaves
                found.append(str(probe.getsockname()[0]))
        except OSError:
            pass  # no route of this family
        try:
            infos = socket.getaddrinfo(socket.gethostname(), None, family, socket.SOCK_STREAM)
        except OSError:
            infos = []
        found += [str(info[4][0]) for info in infos]
    usable = []
    for text in dict.fromkeys(found):
        address = ipaddress.ip_address(text.split("%")[0])
        if not (address.is_loopback or address.is_link_local or address.is_unspecified):
            usable.append(text)
    return usable


def page_urls(host: str, port: int, token: str | None) -> list[tuple[str, str]]:
    """The URLs the page is opened by, each with what it is (``""`` for the one URL of a
    listen address that is not a wildcard).

    On a wildcard address (``--listen 0.0.0.0:PORT`` or ``[::]:PORT``) the listen address
    is no URL: every other machine needs one of this machine's names or addresses, so
    the host name comes first, then each address, then loopback for this machine.
    """
    query = f"?token={token}" if token else ""

    def url(name: str) -> str:
        shown = f"[{name}]" if ":" in name else name
        return f"http://{shown}:{port}/{query}"

    if host not in WILDCARDS:
        return [(url(host), "")]
    urls = [
        (url(name), "host name")
        for name in dict.fromkeys((socket.getfqdn(), socket.gethostname()))
        if name and name != "localhost" and not name.startswith("localhost.")
    ]
    urls += [(url(a), "address") for a in machine_addresses(ipv6=host == "::")]
    urls.append((url("::1" if host == "::" else "127.0.0.1"), "this machine only"))
    return urls


def _parse_window(text: str) -> tuple[int, int]:
    lo, sep, hi = text.partition(":")
    if not sep or not lo.strip().isdigit() or not hi.strip().isdigit():
        raise LocalProtocolError(
            f"--window={text!r} is not LO:HI positions, e.g. 200:1800", field="--window"
        )
    return int(lo), int(hi)


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus dashboard``; 0 after Ctrl-C or SIGTERM, 2 without the extra."""
    try:
        import aiohttp  # noqa: F401  (only to tell a missing extra from other errors)
    except ImportError:
        print(EXTRA_MESSAGE, file=sys.stderr)
        return 2
    check_seconds("--interval", args.interval, MIN_INTERVAL_S)
    lo, hi = PUSH_HZ_RANGE
    if not lo <= args.push_hz <= hi:
        raise LocalProtocolError(
            f"--push-hz={args.push_hz} is out of range: allowed {lo:g}..{hi:g}",
            field="--push-hz",
            value=args.push_hz,
        )
    host, port = parse_listen(args.listen)
    hosts = host_check(host, args.allow_host)
    window = _parse_window(args.window)
    Dashboard([], window=window)  # checks the window before any port opens
    token = None if _is_loopback(host) else secrets.token_urlsafe(18)
    page = _Page(host, port, token, window, hosts)
    endpoint = getattr(args, "connect", None)
    if endpoint:
        items = _connect_devices(args, endpoint)
        main = _attach(args, page, endpoint, items)
    else:
        manager, wanted, bus_file = _manager(args)
        if _serve_extra():
            main = _spawn_and_attach(args, page, manager, wanted, bus_file)
        else:
            print(NO_SERVE_WARNING, file=sys.stderr, flush=True)
            main = _serve(args, manager, wanted, page)
    try:
        run_safely(main)
    except SystemExit as end:
        if end.code not in (130, 143):  # Ctrl-C and SIGTERM are how a dashboard ends
            raise
    return 0


def _manager(
    args: argparse.Namespace,
) -> tuple[BusManager, dict[str, list[int] | None], Path | None]:
    """The buses to watch, per bus the LA IDs (``None``: scan for them), and the bus
    file they come from (``None``: --port)."""
    port_given = bool(getattr(args, "port", None) or os.environ.get(PORT_ENV))
    bus_file = getattr(args, "bus_file", None) or os.environ.get(BUS_FILE_ENV)
    if args.process and port_given:
        raise UsageError("--process chooses buses of the bus file; --port names one: give one")
    if args.process and not bus_file:
        bus_file = default_bus_file()
        if bus_file is None or not bus_file.is_file():
            raise UsageError(f"--process {args.process}: no bus file: give --bus-file")
    from_file = Path(bus_file) if bus_file and not port_given else None
    if bus_file and not port_given:
        if args.ids or args.devices:
            raise UsageError("--ids and --devices go with --port; the bus file lists devices")
        loaded = load_bus_file(bus_file)
        manager = BusManager(safe_stop=False)
        # --process: its CPUs while the buses are open.
        manager.process = None if args.process is None else loaded.group(args.process)
        specs = loaded.specs_of(args.process)
        for spec in specs:
            if args.bus and spec.name != args.bus:
                continue
            # As every command: the table's host margin if it sets one, else the CLI's.
            manager.add_spec(with_cli_margin(spec, loaded.given[spec.name]))
        if not manager.specs:
            among = f"process group {args.process} of " if args.process else ""
            raise UsageError(
                f"--bus {args.bus}: {among}{bus_file} has no such bus: "
                f"choose one of {', '.join(s.name for s in specs)}"
            )
    else:
        url = resolve_port(args)
        devices: list[str] = []
        if args.ids:
            devices.append("la:" + ",".join(str(i) for i in parse_ids(args.ids)))
        if args.devices:
            devices += [d.strip() for d in _split_devices(args.devices)]
        manager = BusManager(safe_stop=False)
        manager.add_bus(  # every device item is checked here, before the port opens
            url,
            url,
            baud=args.baud,
            backend=args.backend,
            devices=devices,
            host_margin_ms=CLI_HOST_MARGIN_S * 1e3,
        )
    wanted: dict[str, list[int] | None] = {}
    for name, spec in manager.specs.items():
        ids = [i for d in spec.devices if d.kind == "la" for i in d.ids]
        scan_it = not spec.devices and Family.LA in spec.families()
        wanted[name] = None if scan_it else ids
    return manager, wanted, from_file


def _split_devices(text: str) -> list[str]:
    """``la:1,3,quad-stepper`` -> ``["la:1,3", "quad-stepper"]`` (IDs stay with their la)."""
    out: list[str] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if out and out[-1].startswith("la:") and (part[0].isdigit()):
            out[-1] += "," + part
        else:
            out.append(part)
    return out


async def _serve(
    args: argparse.Namespace,
    manager: BusManager,
    wanted: dict[str, list[int] | None],
    page: _Page,
) -> None:
    """The bus in this process, on this loop: only without the serve extra."""
    async with manager:
        setups = []
        for name, bus in manager.buses.items():
            spec = manager.specs[name]
            ids = wanted[name]
            if ids is None:
                ids = await scan(bus, timeout=SCAN_TIMEOUT_S)
            project = next((d.motor for d in spec.devices if d.kind == "project_stepper"), None)
            quad = any(d.kind == "quad_stepper" for d in spec.devices)
            setups.append(BusSetup(bus, list(ids), project, quad, spec.la_safe_action))
        dash = Dashboard(setups, period=args.interval, control=args.control, window=page.window)
        await _run_page(args, dash, page, asyncio.Event().wait)


async def _run_page(
    args: argparse.Namespace,
    dash: Dashboard,
    page: _Page,
    until: Callable[[], Awaitable[object]],
) -> None:
    """Serve ``dash`` on the page's address until ``until()`` returns or Ctrl-C or
    SIGTERM cancels us; then stop it (its safe stop) and the page."""
    from motorbus.dashboard.server import make_app, serve_page

    # The viewers' thread and this loop share the GIL; a thread waiting for it gets it
    # after the interpreter's switch interval (5 ms by default), each time: an e-stop's
    # request needs it several times on its way while a burst of viewers is served.
    sys.setswitchinterval(min(sys.getswitchinterval(), GIL_SWITCH_S))
    record = Path(args.record) if args.record else None
    app = make_app(
        dash, token=page.token, push_hz=args.push_hz, record_dir=record, hosts=page.hosts
    )
    async with serve_page(app, page.host, page.port) as server:
        try:
            await dash.start()
            # --realtime / MOTORBUS_REALTIME: this thread (the controls' loop, where an
            # e-stop is handled) in real-time mode, ahead of the viewers' thread (which
            # drops it, dashboard/lanes.py) and of every other program's.  Where the bus
            # is in this process its open has applied it already; a served bus opens none.
            realtime.on_bus_open()
            if record is not None:
                dash.start_recording(record)
            for url, what in page_urls(page.host, server.port, page.token):
                print(f"{url}  ({what})" if what else url, flush=True)
            for name, s in dash.setups.items():
                listed = ", ".join(map(str, s.la_ids)) or "none"
                print(f"bus {name}: LA {listed}", file=sys.stderr, flush=True)
            await until()
        finally:
            await dash.stop()


#: The dashboard process's GIL switch interval, seconds (see ``_run_page``).
GIL_SWITCH_S = 0.0002


# -- the bus in a motorbus serve (docs/dashboard.md, "A served bus") ---------------------

#: The one line printed when --port or a bus file falls back to the bus in this process.
NO_SERVE_WARNING = (
    "motorbus dashboard: warning: the serve extra is not installed "
    "(pip install 'motorbus[serve]'): the bus runs in the dashboard's own process"
)


@dataclass(frozen=True, slots=True)
class _Page:
    """Where and how the page is served."""

    host: str
    port: int
    token: str | None
    window: tuple[int, int]
    hosts: HostCheck


def _serve_extra() -> bool:
    try:
        import zenoh  # noqa: F401  (only to tell whether the serve extra is there)
    except ImportError:
        return False
    return True


def _device_items(args: argparse.Namespace) -> list[str]:
    items: list[str] = []
    if args.ids:
        items.append("la:" + ",".join(str(i) for i in parse_ids(args.ids)))
    if args.devices:
        items += _split_devices(args.devices)
    return items


def _connect_devices(args: argparse.Namespace, endpoint: str) -> list[str]:
    """What ``--connect`` watches, checked before anything connects (the device items
    against the served bus's baud rate once connected, before anything is sent)."""
    if getattr(args, "port", None) or getattr(args, "bus_file", None):
        raise UsageError("--connect uses a served bus: give it without --port or --bus-file")
    if args.process:
        raise UsageError("--process chooses buses of a bus file; --connect uses a served bus")
    if not _serve_extra():
        raise UsageError("--connect needs the serve extra: pip install 'motorbus[serve]'")
    import motorbus

    motorbus.connect(endpoint)  # checks the endpoint; connects nothing
    items = _device_items(args)
    if not items:
        raise UsageError(
            "--connect needs the devices to watch: --ids 1-3 or --devices la:1-3,quad-stepper "
            "(a scan is not served yet)"
        )
    return items


async def _attach(
    args: argparse.Namespace,
    page: _Page,
    endpoint: str,
    watch: list[str] | list[Watch],
    until: Callable[[], Awaitable[object]] | None = None,
) -> None:
    """Connect to the server at ``endpoint`` and serve the page of ``watch`` (the
    ``--connect`` device items, or the buses of the dashboard's own server) until
    ``until()`` returns (default: until Ctrl-C or SIGTERM)."""
    import motorbus

    async with motorbus.connect(endpoint, name="dashboard") as site:
        watches: list[Watch] = []
        for w in watch:
            if isinstance(w, Watch):
                watches.append(w)
                continue
            bus = site.bus(args.bus)  # the LocalProtocolError names the served buses
            table = {"name": bus.name, "url": endpoint, "baud": bus.baudrate, "devices": watch}
            devices = BusSpec.from_mapping(table).devices
            ids = [i for d in devices if d.kind == "la" for i in d.ids]
            watches = [Watch.of(args.bus, None, devices, ids, None)]
            break
        dash = watch_site(
            site,
            watches,
            endpoint=endpoint,
            period=args.interval,
            control=args.control,
            window=page.window,
        )
        await _run_page(args, dash, page, until or asyncio.Event().wait)


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


def _serve_plan(
    args: argparse.Namespace,
    manager: BusManager,
    wanted: dict[str, list[int]],
    bus_file: Path | None,
    endpoint: str,
) -> tuple[list[str], list[Watch]]:
    """The ``motorbus serve`` arguments for the dashboard's buses, and what to watch."""
    # The dashboard's contract: an actuator it never commanded gets nothing on exit.
    argv = ["--stop-leased-only", "--listen", endpoint]
    if args.realtime is not None:
        argv.append(f"--realtime={args.realtime}")  # the bus's timing is kept there
    if bus_file is not None:
        argv += [str(bus_file), "--host-margin-ms", f"{CLI_HOST_MARGIN_S * 1e3:g}"]
        if args.process:
            argv += ["--process", args.process]
        if args.bus:
            argv += ["--bus", args.bus]
        watches = [
            Watch.of(name, None, spec.devices, wanted[name], spec.la_safe_action)
            for name, spec in manager.specs.items()
        ]
        return argv, watches
    ((name, spec),) = manager.specs.items()
    served = served_name(spec.url)
    argv += ["--port", spec.url, "--baud", str(spec.baud), "--backend", spec.backend]
    argv += ["--name", served, "--host-margin-ms", f"{spec.host_margin_ms:g}"]
    items = _device_items(args)
    if items:
        argv += ["--devices", ",".join(items)]
    return argv, [Watch.of(served, name, spec.devices, wanted[name], spec.la_safe_action)]


async def _spawn_and_attach(
    args: argparse.Namespace,
    page: _Page,
    manager: BusManager,
    wanted: dict[str, list[int] | None],
    bus_file: Path | None,
) -> None:
    """Start a ``motorbus serve`` child for the dashboard's buses, attach to it, and
    end it (SIGTERM: its safe ends) when the dashboard ends, however it ends."""
    ids = await _scan_missing(manager, wanted)
    endpoint = free_loopback_endpoint()
    argv, watches = _serve_plan(args, manager, ids, bus_file, endpoint)
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

        await _attach(args, page, endpoint, watches, until)
    finally:
        await child.stop()
