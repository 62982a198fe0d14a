"""The ``motorbus`` command line.

Each command lives in its own module under ``motorbus.cli`` with a ``register``
function that adds its sub-parser; commands are imported when the parser is built,
so one command's optional dependency never breaks another.

Exit codes (documented in README):
    0  success
    1  the command ran but failed: a reply timeout (a silent ID), a device error or bad
       reply, a port that cannot open or was lost, a project verify mismatch, ``scan``
       finding nothing, ``stream`` skipping ticks
    2  usage error: bad arguments or bad input - a missing ``--port``, an ID, position,
       register value or setting out of range, an unknown register name, a bad project or
       CSV file (nothing was sent)
    130 interrupted (Ctrl-C); the hardware commands first bring what they started to a
       safe state (``stream`` pauses its actuators, ``project run`` stops the project,
       ``quad run`` stops the motor).  ``capture`` and ``monitor`` end normally (0) on
       Ctrl-C, which is how an open-ended run ends.

Every error is one line ``motorbus COMMAND: message`` on standard error; ``--debug``
shows the traceback instead.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from motorbus.errors import LocalProtocolError, MotorbusError

__all__ = ["EXIT_FAILURE", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_USAGE", "main"]

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

#: Modules that each contribute one or more commands, in help order.
COMMAND_MODULES = (
    "demo",
    "sim",
    "decode",
    "scan",
    "la",
    "stream",
    "monitor",
    "project",
    "quad",
    "capture",
)


class UsageError(MotorbusError):
    """Bad command-line input; reported as one line with exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    """The top-level parser with every command registered."""
    parser = argparse.ArgumentParser(
        prog="motorbus",
        description="Drive buses of serial motion devices (Inspire LA actuators, FF AA steppers).",
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(f"motorbus.cli.{name}")
        except ModuleNotFoundError as err:
            if err.name and err.name.startswith("motorbus.cli"):
                continue  # command not built yet in this checkout
            raise
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.debug else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        code: int = func(args)
        return code
    except KeyboardInterrupt:
        print("motorbus: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except (LocalProtocolError, UsageError, ValueError) as err:
        if args.debug:
            raise
        print(f"motorbus {args.command}: {err}", file=sys.stderr)
        return EXIT_USAGE
    except (MotorbusError, OSError) as err:
        if args.debug:
            raise
        print(f"motorbus {args.command}: {err}", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":
    raise SystemExit(main())
