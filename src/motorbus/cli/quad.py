"""``motorbus quad``: the 9-byte FF AA 4-axis stepper controller.

Examples::

    motorbus quad config 1 --subdivision 8 --step-angle 1.8 --pulses 3200 \\
        --direction forward --start-hz 200 --accel 20 --rpm 300 --port /dev/ttyUSB2
    motorbus quad run 1 --timeout 30       # waits for the controller's "done" reply
    motorbus quad stop all
    motorbus quad home 1 --input 3
    motorbus quad led 2 on
    motorbus quad save

Motors are 1..4; LEDs 1..4 (5 = all); home inputs YL1..YL13 (0 = none: homing that
only a stop ends).  "quad run" stops the motor if its done reply does not come within
--timeout seconds (exit code 1); --keep-running leaves it running instead.  Ctrl-C
stops the motor too, and exits with 130.
"""

from __future__ import annotations

import argparse
import asyncio
from typing import Any

from motorbus import QuadStepper
from motorbus.cli.bus_options import STEPPER_BAUD, add_bus_options, add_guard_option, open_bus
from motorbus.cli.output import say
from motorbus.cli.values import check_seconds, step_angle_x100
from motorbus.errors import LocalProtocolError
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import Family, check_int

__all__ = ["register", "run"]

#: ``quad stop all`` stops every motor.
ALL = "all"


def register(subparsers: Any) -> None:
    """Add the ``quad`` command and its sub-commands."""
    parser = subparsers.add_parser(
        "quad",
        help="commands to the 4-axis FF AA stepper controller",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    p = sub.add_parser("run", help="run motor M's configured move")
    p.add_argument("motor", metavar="M", type=int, help="motor 1..4")
    p.add_argument("--no-wait", action="store_true", help="return after the ack, not the done")
    p.add_argument(
        "--timeout",
        type=float,
        default=600.0,
        help="seconds to wait for done; then the motor is stopped (default 600)",
    )
    p.add_argument(
        "--keep-running",
        action="store_true",
        help="on timeout leave the motor running instead of stopping it",
    )
    add_guard_option(p)
    _common(p)
    p = sub.add_parser("stop", help="stop motor M, or all")
    p.add_argument("motor", metavar="M|all", help="motor 1..4 or 'all'")
    _common(p)
    p = sub.add_parser("home", help="home motor M until input YL N")
    p.add_argument("motor", metavar="M", type=int, help="motor 1..4")
    p.add_argument("--input", type=int, required=True, help="stop input 1..13 (0: none)")
    add_guard_option(p)
    _common(p)
    p = sub.add_parser("led", help="switch LED L on or off")
    p.add_argument("led", metavar="L", type=int, help="LED 1..4, 5 = all")
    p.add_argument("state", choices=("on", "off"))
    _common(p)
    _common(sub.add_parser("save", help="save the parameters to flash"))
    p = sub.add_parser("config", help="configure motor M")
    p.add_argument("motor", metavar="M", type=int, help="motor 1..4")
    p.add_argument("--subdivision", type=int, required=True, help="microsteps, 1..65535")
    p.add_argument("--step-angle", type=float, default=1.8, help="degrees (default 1.8)")
    p.add_argument("--pulses", type=int, required=True, help="run length, 0..16777215")
    p.add_argument("--direction", choices=("forward", "reverse"), default="forward")
    p.add_argument("--start-hz", type=int, required=True, help="start frequency, 0..65535 Hz")
    p.add_argument("--accel", type=int, required=True, help="acceleration setting, 0..65535")
    p.add_argument("--rpm", type=int, required=True, help="speed, 0..65535 RPM")
    _common(p)


def _common(parser: argparse.ArgumentParser) -> None:
    add_bus_options(parser, default_baud=STEPPER_BAUD, connect=True)
    parser.set_defaults(func=run)


def _motor(value: object) -> int:
    return check_int("motor", value, q.MOTOR_MIN, q.MOTOR_MAX)


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus quad ACTION``; return the exit code.

    Raises:
        LocalProtocolError: a bad motor, LED, input or setting (before anything is sent).
        MotorbusError, OSError: a timeout, a device error, a port error.
    """
    action: str = args.action
    if action == "stop":
        if args.motor != ALL:
            try:
                args.motor = int(args.motor)
            except ValueError:
                raise LocalProtocolError(
                    f"motor={args.motor!r} is not allowed: choose 1..4 or all", field="motor"
                ) from None
            _motor(args.motor)
    elif action in ("run", "home", "config"):
        _motor(args.motor)
    if action == "run":
        check_seconds("--timeout", args.timeout, 1e-3)
    elif action == "home":
        check_int("--input", args.input, q.STOP_INPUT_NONE, q.STOP_INPUT_MAX)
    elif action == "led":
        check_int("led", args.led, q.LED_MIN, q.LED_ALL)
    elif action == "config":
        args.step_angle_x100 = step_angle_x100("--step-angle", args.step_angle, q.U8_MAX)
        check_int("--subdivision", args.subdivision, q.SUBDIVISION_MIN, q.U16_MAX)
        check_int("--pulses", args.pulses, 0, q.U24_MAX)
        check_int("--start-hz", args.start_hz, 0, q.U16_MAX)
        check_int("--accel", args.accel, 0, q.U16_MAX)
        check_int("--rpm", args.rpm, 0, q.U16_MAX)
    return asyncio.run(_run(args))


async def _run(args: argparse.Namespace) -> int:
    async with open_bus(args, [Family.QUAD_STEPPER]) as bus:
        quad = QuadStepper(bus)
        action: str = args.action
        if action == "run":
            # On timeout run() stops the motor (unless --keep-running) and says so; on
            # Ctrl-C (cancellation) it stops it before the port closes.
            await quad.run(
                args.motor,
                wait=not args.no_wait,
                timeout=args.timeout,
                keep_running=args.keep_running,
            )
            if args.no_wait:
                await quad.release(hold=True)  # asked to start it and leave it running
            what = "started" if args.no_wait else "done"
            say(args, {"motor": args.motor, "result": what}, f"motor {args.motor} {what}")
        elif action == "stop":
            if args.motor == ALL:
                await quad.stop_all()
            else:
                await quad.stop(args.motor)
            what = "all motors" if args.motor == ALL else f"motor {args.motor}"
            say(args, {"motor": args.motor, "stopped": True}, f"{what} stopped")
        elif action == "home":
            await quad.home(args.motor, args.input)
            await quad.release(hold=True)  # homing runs on until its input, as asked
            say(
                args,
                {"motor": args.motor, "input": args.input, "homing": True},
                f"motor {args.motor} homing until YL{args.input}",
            )
        elif action == "led":
            await quad.led(args.led, args.state == "on")
            say(args, {"led": args.led, "on": args.state == "on"}, f"LED {args.led} {args.state}")
        elif action == "save":
            await quad.save()
            say(args, {"saved": True}, "parameters saved")
        elif action == "config":
            await quad.configure(
                args.motor,
                subdivision=args.subdivision,
                step_angle_x100=args.step_angle_x100,
                pulses=args.pulses,
                direction=q.RotationDirection[args.direction.upper()],
                start_hz=args.start_hz,
                accel_hz=args.accel,
                speed_rpm=args.rpm,
            )
            say(
                args,
                {"motor": args.motor, "configured": True},
                f"motor {args.motor} configured (lost at power-off unless `motorbus quad save`)",
            )
    return 0
