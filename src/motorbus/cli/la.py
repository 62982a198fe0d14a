"""``motorbus la``: one-shot commands to Inspire LA actuators.

Examples::

    motorbus la status 1-3 --port /dev/ttyUSB0      # or: 1 2 3, 1,2,3
    motorbus la move 1 1500
    motorbus la get 1 over_current_limit
    motorbus la set 1 over_current_limit 800
    motorbus la set 1 baud 115200                 # a rate, or its code 0..3
    motorbus la set-id 1 7 --save
    motorbus la setup 1-4 --port /dev/ttyUSB0      # one actuator at a time, any baud
    motorbus la calibrate gripper --bus-file arm.toml

Positions are 0..2000 (0..100 % of the stroke).  Register names are those of
motorbus.protocol.la.Register (case-insensitive); "la set" takes the value in the
register's own unit (0.1 °C for the temperature limits).  A command to several IDs
reports every one of them; one that does not answer gets a "timeout" row and the
exit code is 1.  "la set-id" refuses an ID that another actuator already answers
to (two actuators on one ID answer together), unless --force.
"""

from __future__ import annotations

import argparse
import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

from motorbus import Bus, InspireLA
from motorbus.cli.bus_options import LA_BAUD, add_bus_options, add_guard_option, open_bus
from motorbus.cli.ids import add_ids_argument, check_ids, parse_id_args
from motorbus.cli.main import EXIT_FAILURE, EXIT_OK, UsageError
from motorbus.cli.output import fail, plural, print_json, say
from motorbus.errors import LocalProtocolError, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_int

__all__ = [
    "STATUS_HEADER",
    "baud_code",
    "format_value",
    "register",
    "run",
    "status_json",
    "status_row",
    "timeout_row",
]

#: Column titles of the status table (``la status`` and ``monitor``).
STATUS_HEADER = "  id  target  position   temp  current   force  errors"
#: Registers whose unit is 0.1 degC (control table 98, 100), printed in °C as well.
_DECI_DEGREES = "0.1 degC"
#: What a row of an ID that did not answer says.
TIMEOUT_TEXT = "timeout (no reply)"

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
        add_ids_argument(p)
        _common(p)
    p = sub.add_parser("move", help="positioning move to POS (0..2000)")
    p.add_argument("id", metavar="ID", type=int, help="actuator ID 1..254")
    p.add_argument("position", metavar="POS", type=int, help="target position 0..2000")
    p.add_argument("--no-reply", action="store_true", help="send 0x03 (no status reply)")
    add_guard_option(p)
    _common(p)
    p = sub.add_parser("get", help="read a control-table register")
    p.add_argument("id", metavar="ID", type=int, help="actuator ID 1..254")
    p.add_argument("register", metavar="REGISTER", help=_register_help())
    _common(p)
    p = sub.add_parser("set", help="write a control-table register")
    p.add_argument("id", metavar="ID", type=int, help="actuator ID 1..254")
    p.add_argument("register", metavar="REGISTER", help=_register_help())
    p.add_argument(
        "value", metavar="VALUE", type=int, help="value in the register's unit (baud: rate or code)"
    )
    _common(p)
    p = sub.add_parser("set-id", help="give actuator OLD the ID NEW (effective at once)")
    p.add_argument("old", metavar="OLD", type=int, help="present ID 1..254")
    p.add_argument("new", metavar="NEW", type=int, help="new ID 1..254 (must not answer yet)")
    p.add_argument("--save", action="store_true", help="save to flash so the ID survives power")
    p.add_argument("--force", action="store_true", help="change the ID even if NEW already answers")
    _common(p)
    from motorbus.cli import la_setup

    la_setup.register_setup(sub)
    la_setup.register_calibrate(sub)


def _common(parser: argparse.ArgumentParser) -> None:
    add_bus_options(parser, default_baud=LA_BAUD, connect=True)
    parser.set_defaults(func=run)


def _register_help() -> str:
    return "register name: " + ", ".join(r.name.lower() for r in la.Register)


def baud_code(value: object) -> int:
    """The baud code to write for ``la set ID baud VALUE``: a code 0..3 or its rate in bit/s.

    Raises:
        LocalProtocolError: neither; the message lists every code with its rate.
    """
    if isinstance(value, int) and not isinstance(value, bool):
        for code in la.BaudCode:
            if value in (int(code), code.baud):
                return int(code)
    allowed = ", ".join(f"{int(c)} ({c.baud} bit/s)" for c in la.BaudCode)
    raise LocalProtocolError(
        f"baud={value!r} is not allowed: give a code or its rate: {allowed}",
        field="baud",
        value=value,
    )


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus la ACTION``; return the exit code (0, or 1 if a device did not answer).

    Raises:
        LocalProtocolError: a bad ID, position, register or value (before anything is sent).
        MotorbusError, OSError: a timeout, a device error, a port error.
    """
    # Check everything before the port opens: bad input must send nothing.
    action: str = args.action
    if action in _CONTROLS:
        args.ids = parse_id_args(args.ids)
    elif action == "move":
        check_ids([args.id])
        check_int("position", args.position, la.POSITION_MIN, la.POSITION_MAX)
    elif action in ("get", "set"):
        check_ids([args.id])
        reg = la.Register.by_name(args.register)
        if action == "set":
            if reg is la.Register.BAUD:
                args.value = baud_code(args.value)
            reg.check_value(args.value)
    elif action == "set-id":
        check_int("old id", args.old, la.ID_MIN, la.ID_MAX)
        check_int("new id", args.new, la.ID_MIN, la.ID_MAX)
        if args.new == args.old:
            raise LocalProtocolError(
                f"new id={args.new} is the present ID: nothing to change", field="new id"
            )
    return asyncio.run(_run(args))


async def _answers(bus: Bus, ident: int) -> bool:
    try:
        await InspireLA(bus, ident).status()
    except ReplyTimeoutError:
        return False
    return True


async def _run(args: argparse.Namespace) -> int:
    async with open_bus(args, [Family.LA]) as bus:
        action: str = args.action
        if action in _CONTROLS:
            return await _run_control(args, bus)
        if action == "move":
            actuator = InspireLA(bus, args.id)
            status = await actuator.move_to(args.position, reply=not args.no_reply)
            # A one-shot move ends on purpose: the actuator keeps its target after exit.
            await actuator.release(hold=True)
            if status is None:
                say(args, {"id": args.id, "target": args.position, "reply": False}, "sent")
            else:
                _print_statuses([status], args.json, brief=False)
        elif action == "get":
            reg = la.Register.by_name(args.register)
            value = await InspireLA(bus, args.id).read(reg)
            if args.json:
                doc: dict[str, Any] = {"id": args.id, "register": reg.name.lower(), "value": value}
                doc["unit"] = _unit(reg)
                if reg is la.Register.BAUD and value in set(la.BaudCode):
                    doc["baud"] = la.BaudCode(value).baud
                print_json(doc)
            else:
                print(f"la:{args.id} {reg.name.lower()} = {format_value(reg, value)}")
        elif action == "set":
            reg = la.Register.by_name(args.register)
            actuator = InspireLA(bus, args.id)
            await actuator.write(reg, args.value)
            await actuator.release(hold=True)  # a target written is a move kept on purpose
            note = _set_note(reg, args.id, args.value)
            doc = {"id": args.id, "register": reg.name.lower(), "value": args.value}
            say(
                args,
                {**doc, "note": note} if note else doc,
                f"la:{args.id} {reg.name.lower()} set to {format_value(reg, args.value)}"
                + (f": {note}" if note else ""),
            )
        elif action == "set-id":
            # Two actuators with one ID answer together and garble each other (A2-12):
            # look before writing.  The look is a status query; nothing is written.
            if not args.force and await _answers(bus, args.new):
                raise UsageError(
                    f"new id={args.new} already answers on {bus.name}: nothing written "
                    f"(pick a free ID - motorbus scan lists the taken ones - or add --force)"
                )
            await InspireLA(bus, args.old).change_id(args.new, save=args.save)
            saved = " and saved" if args.save else " (not saved: lost at power-off)"
            say(
                args,
                {"old": args.old, "new": args.new, "saved": args.save},
                f"la:{args.old} is now la:{args.new}{saved}",
            )
    return EXIT_OK


async def _run_control(args: argparse.Namespace, bus: Bus) -> int:
    """One control to every listed ID; a silent ID gets a timeout row, the others go on."""
    _, method = _CONTROLS[args.action]
    if len(args.ids) == 1:
        # One ID: its error (with the frame sent and the time waited) is the whole answer.
        status = await method(InspireLA(bus, args.ids[0]))
        _print_statuses([status], args.json, brief=args.action != "status")
        return EXIT_OK
    results: list[la.Status | int] = []
    for ident in args.ids:
        try:
            results.append(await method(InspireLA(bus, ident)))
        except ReplyTimeoutError:
            results.append(ident)
    _print_statuses(results, args.json, brief=args.action != "status")
    silent = [r for r in results if isinstance(r, int)]
    if not silent:
        return EXIT_OK
    return fail(
        args,
        f"{plural(len(silent), 'actuator')} of {len(results)} did not answer "
        f"({', '.join(f'la:{i}' for i in silent)}): check the IDs (motorbus scan lists "
        f"the ones that answer) and --baud {args.baud}",
        code=EXIT_FAILURE,
        port=args.port,
        ids=silent,
    )


def _unit(reg: la.Register) -> str:
    return reg.value.unit


def format_value(reg: la.Register, value: int) -> str:
    """A register value with its unit: ``800 mA``, ``800 (80.0 °C)``, ``921600 (code 3)``."""
    unit = _unit(reg)
    if reg is la.Register.BAUD:
        if value in set(la.BaudCode):
            return f"{la.BaudCode(value).baud} (code {value})"
        return f"code {value} (undefined: codes 0..3 are documented)"
    if unit == _DECI_DEGREES:
        return f"{value} ({value / 10:.1f} °C)"
    return f"{value} {unit}".rstrip()


def _set_note(reg: la.Register, ident: int, value: int) -> str:
    """When a register written with ``la set`` takes effect, and how to keep it."""
    if reg is la.Register.BAUD:
        baud = la.BaudCode(value).baud if value in set(la.BaudCode) else value
        return (
            f"takes effect only after `motorbus la save {ident}` and a power cycle "
            f"(then use --baud {baud})"
        )
    if reg in (la.Register.TARGET, la.Register.FORCE_ZERO):
        return ""  # a motion command and a one-shot action: nothing to keep
    return f"effective now, lost at power-off unless `motorbus la save {ident}`"


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
        f"  {status.id:3d}  {status.target:6d}  {status.position:8d}  {status.temperature:3d}°C"
        f"  {status.current:5d}mA  {status.force:5d}g  {errors}"
    )


def timeout_row(ident: int) -> str:
    """The row of an ID that did not answer, under :data:`STATUS_HEADER`."""
    return f"  {ident:3d}  {TIMEOUT_TEXT}"


def _print_statuses(statuses: list[la.Status | int], as_json: bool, *, brief: bool) -> None:
    """Print statuses; an ``int`` is the ID of an actuator that did not answer."""
    if as_json:
        for s in statuses:
            print_json({"id": s, "error": "timeout"} if isinstance(s, int) else status_json(s))
        return
    if brief:
        for s in statuses:
            print(f"la:{s} {TIMEOUT_TEXT}" if isinstance(s, int) else f"la:{s.id} ok")
        return
    print(STATUS_HEADER)
    for s in statuses:
        print(timeout_row(s) if isinstance(s, int) else status_row(s))
