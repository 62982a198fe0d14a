"""``motorbus serve``: own the ports, and serve the buses to other programs over Zenoh.

Examples::

    motorbus serve buses.toml                    # every bus of the file
    motorbus serve buses.toml --process arms     # one process group, on its CPUs
    motorbus serve --port /dev/ttyUSB0 --baud 921600 --devices la:1-3 --name arm
    motorbus serve buses.toml --listen tcp/0.0.0.0:7447 --zenoh-config server.json5

Needs the serve extra: pip install 'motorbus[serve]'.  One process owns the ports and
everything that must stay next to the wire (spacing, deadlines, the reassembler,
leases and their safe ends, --guard, real-time mode); programs use the buses with
``motorbus.connect(ENDPOINT)``.  It listens on loopback unless --listen says otherwise
(beyond loopback, give a Zenoh configuration with TLS and access control: docs/serve.md).
When it is ready it prints the endpoint it listens on, on a line of its own (with
port 0, ``--listen tcp/127.0.0.1:0``, the port it was given).

A client's leases end with their safe actions when the client ends, however it ends,
or falls silent for --liveness seconds (default 1).  --watch-only lets clients query,
watch and stop devices, but never move one or change a setting.  Ctrl-C or SIGTERM
ends it (exit code 0) after the safe actions of every lease.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import sys
from typing import Any

from motorbus import BusManager, load_bus_file
from motorbus import run as run_safely
from motorbus.cli.realtime_option import add_realtime_option
from motorbus.errors import LocalProtocolError, UsageError

__all__ = ["EXTRA_MESSAGE", "register", "run"]

EXTRA_MESSAGE = "motorbus serve needs the serve extra: pip install 'motorbus[serve]'"


def register(subparsers: Any) -> None:
    """Add the ``serve`` command."""
    p = subparsers.add_parser(
        "serve",
        help="own the ports and serve the buses to other programs (Zenoh)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("bus_file", nargs="?", help="the bus file to serve (every key honoured)")
    p.add_argument("--process", help="serve this process group of the bus file")
    p.add_argument("--bus", metavar="NAME", help="serve only this bus of the bus file")
    p.add_argument("--port", help="serve one port instead of a bus file")
    p.add_argument("--baud", type=int, help="the port's baud rate (with --port)")
    p.add_argument(
        "--devices", help="devices on --port in the bus file's forms, e.g. la:1-3,quad-stepper"
    )
    p.add_argument("--name", default="bus", help="the bus name of --port (default: bus)")
    p.add_argument("--backend", default="fast", help="serial backend of --port")
    p.add_argument(
        "--host-margin-ms",
        type=float,
        help="host-latency margin of every reply deadline on --port, and on each bus of "
        "the bus file whose table sets none (default: the library's)",
    )
    p.add_argument(
        "--listen",
        default="tcp/127.0.0.1:7447",
        help="the Zenoh endpoint to listen on (default: tcp/127.0.0.1:7447, loopback)",
    )
    p.add_argument("--zenoh-config", help="a Zenoh configuration file (TLS, access control)")
    p.add_argument(
        "--liveness",
        type=float,
        default=1.0,
        help="seconds without a client's heartbeat before its leases end (default 1)",
    )
    p.add_argument(
        "--watch-only",
        action="store_true",
        help="clients may read, watch and stop devices, never move one or change a setting",
    )
    p.add_argument("--guard", action="store_true", help="run the guard process beside the buses")
    add_realtime_option(p)
    p.add_argument(
        "--stop-leased-only",
        action="store_true",
        help="on the way out, stop only the devices clients hold (their leases' safe "
        "actions), not every device the bus lists (a dashboard's own server: watching "
        "sends no motion)",
    )
    p.set_defaults(func=run)


def _manager(args: argparse.Namespace) -> BusManager:
    if args.bus_file and args.port:
        raise UsageError("give a bus file or --port, not both")
    if args.bus_file:
        if args.baud or args.devices:
            raise UsageError("--baud and --devices go with --port; the bus file lists them")
        loaded = load_bus_file(args.bus_file)
        manager = BusManager()
        manager.process = None if args.process is None else loaded.group(args.process)
        specs = loaded.specs_of(args.process)
        for spec in specs:
            if args.bus and spec.name != args.bus:
                continue
            if args.host_margin_ms is not None and "host_margin_ms" not in loaded.given[spec.name]:
                spec = dataclasses.replace(spec, host_margin_ms=args.host_margin_ms)
            manager.add_spec(spec)
        if args.bus and not manager.specs:
            raise UsageError(
                f"--bus {args.bus}: {args.bus_file} has no such bus"
                + (f" in process group {args.process}" if args.process else "")
                + f": choose one of {', '.join(s.name for s in specs)}"
            )
        return manager
    if args.bus:
        raise UsageError("--bus chooses a bus of the bus file; give the bus file")
    if not args.port:
        raise UsageError("give a bus file to serve, or --port (with --baud and --devices)")
    if args.process:
        raise UsageError("--process chooses buses of a bus file; give the bus file")
    if not args.baud:
        raise UsageError("--port needs --baud")
    manager = BusManager()
    manager.add_bus(
        args.name,
        args.port,
        baud=args.baud,
        backend=args.backend,
        devices=_split_devices(args.devices or ""),
        guard=bool(args.guard),
        **({} if args.host_margin_ms is None else {"host_margin_ms": args.host_margin_ms}),
    )
    return manager


def _split_devices(text: str) -> list[str]:
    """``la:1,3,quad-stepper`` -> ``["la:1,3", "quad-stepper"]`` (IDs stay with their la)."""
    out: list[str] = []
    for part in (p.strip() for p in text.split(",") if p.strip()):
        if out and out[-1].startswith("la:") and (part[0].isdigit()):
            out[-1] += "," + part
        else:
            out.append(part)
    return out


def _device_keys(spec: Any) -> list[str]:
    """The device keys a ``BusSpec`` declares (``la:3``, ``project_stepper``, ...)."""
    return [
        key
        for dev in spec.devices
        for key in ([f"la:{i}" for i in dev.ids] if dev.kind == "la" else [dev.kind])
    ]


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus serve``; 0 after Ctrl-C or SIGTERM, 2 without the extra."""
    try:
        import zenoh  # noqa: F401  (only to tell a missing extra from other errors)
    except ImportError:
        print(EXTRA_MESSAGE, file=sys.stderr)
        return 2
    from motorbus.serve import BusServer
    from motorbus.serve.keys import check_liveness
    from motorbus.serve.zconf import check_endpoint, server_config

    # Every server option is checked before a port opens: a bad one sends nothing (the
    # manager's close would pause the devices of a bus that opened).
    check_endpoint("--listen", args.listen)
    check_liveness(args.liveness)
    if args.zenoh_config is not None:
        try:
            server_config(args.listen, args.zenoh_config)
        except LocalProtocolError as err:  # no such file, not JSON5, an unknown key
            raise UsageError(f"--zenoh-config {args.zenoh_config}: {err}") from None
    manager = _manager(args)
    manager.safe_stop = not args.stop_leased_only
    if args.guard:
        for spec in manager.specs.values():
            spec.guard = True

    async def serve() -> None:
        async with manager:
            server = BusServer(
                manager.buses,
                listen=args.listen,
                liveness=args.liveness,
                zenoh_config=args.zenoh_config,
                watch_only=args.watch_only,
                devices={name: _device_keys(spec) for name, spec in manager.specs.items()},
            )
            async with server:
                print(f"serving {', '.join(manager.buses)} on {server.endpoint}", flush=True)
                await asyncio.Event().wait()

    try:
        run_safely(serve())
    except SystemExit as end:
        if end.code not in (130, 143):
            raise
    return 0
