"""``motorbus la``: one-shot commands to Inspire LA actuators.

Examples::

    motorbus la status 1 2 3 --port /dev/ttyUSB0
    motorbus la move 1 1500
    motorbus la get 1 over_current_limit
    motorbus la set 1 over_current_limit 800
    motorbus la set-id 1 7 --save

Positions are 0..2000 (0..100 % of the stroke).  Register names are those of
``motorbus.protocol.la.Register`` (case-insensitive); ``la set`` takes the value in the
register's own unit (0.1 degC for the temperature limits).
"""

from __future__ import annotations

import argparse
import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

from motorbus.cli.common import LA_BAUD, add_bus_options, check_ids, open_bus, print_json, say
from motorbus.devices.la import InspireLA
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_int

__all__ = ["STATUS_HEADER", "register", "run", "status_json", "status_row"]

#: Column titles of the status table (``la status`` and ``monitor``).
STATUS_HEADER = "  id  target  position  temp  current   force  errors"
#: Registers whose unit is 0.1 degC (control table 98, 100), printed in degC as well.
_DECI_DEGREES = "0.1 degC"

#: ``la ACTION ID...`` commands that send one CMD_MC control each (manual 3.5.4).
_CONTROLS: dict[str, tuple[str, Callable[[InspireLA], Awaitable[la.Status]]]] = {
    "status": ("query the status (table or JSON)", InspireLA.status),
    "enable": ('"work": enable the power stage', InspireLA.enable),
    "estop": ("emergency stop (power stage off; enable to move again)", InspireLA.estop),
    "pause": ("pause (power stage off; the next move resumes)", InspireLA.pause),
    "clear": ("clear stall, over-current and motor-abnormal faults", InspireLA.clear_fault),
    "save": ("save the control table to flash", InspireLA.save),
}


def register(subparsers: Any) -> None:
    """Add the ``la`` command and its sub-commands."""
    parser = subparsers.add_parser(
        "la",
        help="commands to Inspire LA actuators",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    for name, (text, _) in _CONTROLS.items():
        p = sub.add_parser(name, help=text, description=text)
        p.add_argument("ids", metavar="ID", type=int, nargs="+", help="actuator ID 1..254")
        _common(p)
    p = sub.add_parser("move", help="positioning move to POS (0..2000)")
    p.add_argument("id", metavar="ID", type=int, help="actuator ID 1..254")
    p.add_argument("position", metavar="POS", type=int, help="target position 0..2000")
    p.add_argument("--no-reply", action="store_true", help="send 0x03 (no status reply)")
    _common(p)
    p = sub.add_parser("get", help="read a control-table register")
    p.add_argument("id", metavar="ID", type=int, help="actuator ID 1..254")
    p.add_argument("register", metavar="REGISTER", help=_register_help())
    _common(p)
    p = sub.add_parser("set", help="write a control-table register")
    p.add_argument("id", metavar="ID", type=int, help="actuator ID 1..254")
    p.add_argument("register", metavar="REGISTER", help=_register_help())
    p.add_argument("value", metavar="VALUE", type=int, help="value in the register's unit")
    _common(p)
    p = sub.add_parser("set-id", help="give actuator OLD the ID NEW (effective at once)")
    p.add_argument("old", metavar="OLD", type=int, help="present ID 1..254")
    p.add_argument("new", metavar="NEW", type=int, help="new ID 1..254")
    p.add_argument("--save", action="store_true", help="save to flash so the ID survives power")
    _common(p)


def _common(parser: argparse.ArgumentParser) -> None:
    add_bus_options(parser, default_baud=LA_BAUD)
    parser.set_defaults(func=run)


def _register_help() -> str:
    return "register name: " + ", ".join(r.name.lower() for r in la.Register)


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus la ACTION``; return the exit code (0, or 1 if a device did not answer).

    Raises:
        LocalProtocolError: a bad ID, position, register or value (before anything is sent).
        MotorbusError, OSError: a timeout, a device error, a port error.
    """
    # Check everything before the port opens: bad input must send nothing.
    action: str = args.action
    if action in _CONTROLS:
        check_ids(args.ids)
    elif action == "move":
        check_ids([args.id])
        check_int("position", args.position, la.POSITION_MIN, la.POSITION_MAX)
    elif action in ("get", "set"):
        check_ids([args.id])
        reg = la.Register.by_name(args.register)
        if action == "set":
            reg.check_value(args.value)
    elif action == "set-id":
        check_int("old id", args.old, la.ID_MIN, la.ID_MAX)
        check_int("new id", args.new, la.ID_MIN, la.ID_MAX)
    return asyncio.run(_run(args))


async def _run(args: argparse.Namespace) -> int:
    async with open_bus(args, [Family.LA]) as bus:
        action: str = args.action
        if action in _CONTROLS:
            _, method = _CONTROLS[action]
            statuses = [await method(InspireLA(bus, i)) for i in args.ids]
            _print_statuses(statuses, args.json, brief=action != "status")
        elif action == "move":
            status = await InspireLA(bus, args.id).move_to(args.position, reply=not args.no_reply)
            if status is None:
                say(args, {"id": args.id, "target": args.position, "reply": False}, "sent")
            else:
                _print_statuses([status], args.json, brief=False)
        elif action == "get":
            reg = la.Register.by_name(args.register)
            value = await InspireLA(bus, args.id).read(reg)
            if args.json:
                doc = {"id": args.id, "register": reg.name.lower(), "value": value}
                print_json({**doc, "unit": _unit(reg)})
            else:
                print(f"la:{args.id} {reg.name.lower()} = {format_value(reg, value)}")
        elif action == "set":
            reg = la.Register.by_name(args.register)
            await InspireLA(bus, args.id).write(reg, args.value)
            say(
                args,
                {"id": args.id, "register": reg.name.lower(), "value": args.value},
                f"la:{args.id} {reg.name.lower()} set to {format_value(reg, args.value)}",
            )
        elif action == "set-id":
            await InspireLA(bus, args.old).change_id(args.new, save=args.save)
            saved = " and saved" if args.save else " (not saved: lost at power-off)"
            say(
                args,
                {"old": args.old, "new": args.new, "saved": args.save},
                f"la:{args.old} is now la:{args.new}{saved}",
            )
    return 0


def _unit(reg: la.Register) -> str:
    return reg.value.unit


def format_value(reg: la.Register, value: int) -> str:
    """A register value with its unit, e.g. ``800 mA`` or ``800 (80.0 degC)``."""
    unit = _unit(reg)
    if unit == _DECI_DEGREES:
        return f"{value} ({value / 10:.1f} degC)"
    return f"{value} {unit}".rstrip()


def _error_names(status: la.Status) -> list[str]:
    names = [f.name.lower() for f in la.ErrorFlags if f.name and f in status.errors]
    undefined = int(status.errors) & ~int(la.KNOWN_ERROR_BITS)
    if undefined:
        names.append(f"0x{undefined:02X}")  # undefined bits are shown raw (A2-19)
    return names


def status_json(status: la.Status) -> dict[str, Any]:
    """A status as a JSON object (units in the key names)."""
    return {
        "id": status.id,
        "target": status.target,
        "position": status.position,
        "temperature_c": status.temperature,
        "current_ma": status.current,
        "force_g": status.force,
        "errors": _error_names(status),
    }


def status_row(status: la.Status) -> str:
    """A status as one row under :data:`STATUS_HEADER`."""
    errors = ",".join(_error_names(status)) or "-"
    return (
        f"  {status.id:3d}  {status.target:6d}  {status.position:8d}  {status.temperature:3d}C"
        f"  {status.current:5d}mA  {status.force:5d}g  {errors}"
    )


def _print_statuses(statuses: list[la.Status], as_json: bool, *, brief: bool) -> None:
    if as_json:
        for s in statuses:
            print_json(status_json(s))
        return
    if brief:
        for s in statuses:
            print(f"la:{s.id} ok")
        return
    print(STATUS_HEADER)
    for s in statuses:
        print(status_row(s))
