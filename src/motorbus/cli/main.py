"""The ``motorbus`` command line.

Each command lives in its own module under ``motorbus.cli`` with a ``register``
function that adds its sub-parser.  Only the module of the command on the line is
imported (``motorbus --version`` and ``motorbus --help`` import none): a tool run many
times a day starts in a small fraction of a second, and one command's optional
dependency never breaks another.  The top-level help lists :data:`COMMANDS`, whose
one-line texts tests/cli/test_cli_startup.py checks against each module's ``register``.

Exit codes (documented in docs/cli.md, checked by tests/cli/test_exit_codes.py; with
``--json`` a failure also ends stdout with one object: error, code, command, what it
concerns):
    0  success
    1  the command ran but failed: a reply timeout (a silent ID, also one of several),
       a device error or bad reply, a port that cannot open (missing, forbidden, held by
       another program) or was lost, a project verify
       mismatch, ``scan`` finding nothing, ``stream`` skipping ticks or finding a listed
       actuator silent, a ``project run``/``quad run`` that timed out (stopped unless
       ``--keep-running``)
    2  usage error: bad arguments or bad input - a missing ``--port``, an ID, position,
       register value or setting out of range, an unknown register name, a missing or
       bad project, CSV or bus file, ``la set-id`` onto an ID that answers (nothing was
       sent)
    130 interrupted (Ctrl-C); the hardware commands first bring what they started to a
       safe state (``stream`` pauses its actuators, ``project run`` stops the project,
       ``quad run`` stops the motor).  ``capture`` and ``monitor`` end normally (0) on
       Ctrl-C, which is how an open-ended run ends.

Every error is one line ``motorbus COMMAND: message`` on standard error; ``--debug``
shows the traceback instead.  ``--debug`` and ``--json`` may stand anywhere on the
line, before or after the command.  Output cut short by a closed pipe (``| head``)
ends the command quietly.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

import motorbus
from motorbus.errors import (
    CommandFailed,
    LocalProtocolError,
    MotorbusError,
    PortInUseError,
    ReplyTimeoutError,
    UsageError,
)

__all__ = [
    "EXIT_FAILURE",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_USAGE",
    "CommandFailed",
    "UsageError",
    "main",
]

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130

#: Every command, in help order, with its one-line help; command NAME is registered by
#: ``motorbus.cli.NAME.register``.  The texts are here so that ``motorbus --help`` imports
#: no command module; tests/cli/test_cli_startup.py checks they are each module's own.
COMMANDS: dict[str, str] = {
    "demo": "run every device on built-in simulators (no hardware)",
    "sim": "serve simulated devices on a pseudo-terminal",
    "decode": "describe frames given in hex",
    "scan": "find the LA actuators that answer on a bus",
    "ports": "list the serial ports: USB IDs, serial number, driver, latency timer",
    "doctor": "check a bus: port, adapter, echo, baud, devices, timing, what it can sustain",
    "la": "commands to Inspire LA actuators",
    "stream": "stream a CSV trajectory to LA actuators (follow mode)",
    "monitor": "live table of LA actuator status",
    "project": "program and run the FF AA project stepper",
    "quad": "commands to the 4-axis FF AA stepper controller",
    "capture": "record every frame on a bus as a frame log (listen only)",
    "replay": "print a frame log, or send its requests again through a bus",
    "rig": "characterise LA actuators: step, tracking, latency, repeatability; compare runs",
    "dashboard": "live web page of every bus and device (plots, faults, e-stop)",
    "serve": "own the ports and serve the buses to other programs (Zenoh)",
}

#: Modules that each contribute one command (the command of the same name), in help order.
COMMAND_MODULES = tuple(COMMANDS)


#: Options every command accepts wherever they stand on the line.
GLOBAL_FLAGS = ("--debug", "--json")


class _Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors, under ``--json``, also print the JSON error
    object on standard output (exit code 2, as argparse's); sub-parsers are of this class
    too (argparse makes them of their parent's class)."""

    json_errors = False

    def error(self, message: str) -> NoReturn:
        if self.json_errors:
            from motorbus.cli.output import error_doc, print_json

            command = self.prog.split()[1] if len(self.prog.split()) > 1 else None
            with contextlib.suppress(OSError):
                print_json(error_doc(command, message, EXIT_USAGE))
        super().error(message)


def _json_errors(parser: argparse.ArgumentParser) -> None:
    """Have ``parser`` and every sub-parser print argument errors as JSON too."""
    if isinstance(parser, _Parser):
        parser.json_errors = True
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in dict.fromkeys(action.choices.values()):
                _json_errors(child)


def version() -> str:
    """The motorbus version (``motorbus.__version__``, which tests check against the
    installed metadata; reading the metadata would cost ``--version`` 30 ms of imports)."""
    return motorbus.__version__


def build_parser(only: str | None = "") -> argparse.ArgumentParser:
    """The top-level parser.

    Args:
        only: ``""`` (the default): every command registered from its module.  A command
            name: only that command's module is imported and registered; the others get a
            sub-parser with their one-line help from :data:`COMMANDS`, enough for the
            top-level help and for argparse to name the choices.  ``None``: no command
            module is imported at all (``motorbus --help``, ``--version``, a typo).
    """
    parser = _Parser(
        prog="motorbus",
        description="Drive buses of serial motion devices (Inspire LA actuators, FF AA steppers).",
    )
    parser.add_argument("--version", action="version", version=f"motorbus {version()}")
    # Both are taken out of the line before parsing (see main); these entries document them.
    parser.add_argument(
        "--debug",
        action="store_true",
        default=argparse.SUPPRESS,
        help="show tracebacks and debug logs (anywhere on the line)",
    )
    parser.add_argument(
        "--json",
        action="store_true",
        default=argparse.SUPPRESS,
        help="print JSON instead of text, for the commands that print data (anywhere on the line)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        if only == "" or name == only:
            # A command whose module does not import is a broken install: say so, never
            # leave the command out of the help as if it did not exist.
            module = importlib.import_module(f"motorbus.cli.{name}")
            module.register(sub)
        else:
            sub.add_parser(name, help=COMMANDS.get(name), add_help=False)
    _plain_help(parser)
    return parser


def _plain_text(text: str | None) -> str | None:
    """Help text without reST markup: ``literal`` -> literal, ``Example::`` -> ``Example:``."""
    if text is None:
        return None
    return text.replace("``", "").replace("::\n", ":\n")


def _plain_help(parser: argparse.ArgumentParser) -> None:
    """Strip reST markup from every description and help text (commands reuse docstrings)."""
    parser.description = _plain_text(parser.description)
    parser.epilog = _plain_text(parser.epilog)
    for action in parser._actions:
        if action.help is not None and action.help is not argparse.SUPPRESS:
            action.help = _plain_text(action.help)
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                choice.help = _plain_text(choice.help)
            for child in dict.fromkeys(action.choices.values()):
                _plain_help(child)


def _split_global_flags(argv: Sequence[str]) -> tuple[list[str], set[str]]:
    """Take ``--debug``/``--json`` out of ``argv`` wherever they stand (not after ``--``)."""
    rest: list[str] = []
    flags: set[str] = set()
    for n, arg in enumerate(argv):
        if arg == "--":
            rest.extend(argv[n:])
            break
        if arg in GLOBAL_FLAGS:
            flags.add(arg)
        else:
            rest.append(arg)
    return rest, flags


def _command_of(argv: Sequence[str]) -> str | None:
    """The command named on the line, if any: the first word that is not an option (the
    top-level options take no value), or ``None`` (``--help``, ``--version``, a typo)."""
    for arg in argv:
        if arg != "--" and not arg.startswith("-"):
            return arg if arg in COMMANDS else None
    return None


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit code."""
    rest, flags = _split_global_flags(sys.argv[1:] if argv is None else argv)
    try:
        parser = build_parser(only=_command_of(rest))
    except LocalProtocolError as err:  # the environment, read as the commands load
        print(f"motorbus: {err}", file=sys.stderr)
        return EXIT_USAGE
    if "--json" in flags:
        _json_errors(parser)
    args = parser.parse_args(rest)
    args.debug = "--debug" in flags
    if "--json" in flags:
        if not hasattr(args, "json"):
            parser.error(f"--json: motorbus {args.command} prints no data to put in JSON")
        args.json = True
    logging.basicConfig(
        level=logging.DEBUG if args.debug else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    func = getattr(args, "func", None)
    if func is None:
        parser.print_help()
        return EXIT_USAGE
    try:
        with _guarded(getattr(args, "guard", False)):  # --guard: see motorbus.runtime.guard
            code: int = func(args)
        sys.stdout.flush()  # a closed pipe shows here, inside the handler below
        return code
    except KeyboardInterrupt:
        return _failed(args, EXIT_INTERRUPTED, "interrupted")
    except BrokenPipeError:
        # ``motorbus replay f.jsonl | head``: the reader has all it wanted.  Point
        # stdout at /dev/null so the interpreter's final flush does not complain.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK
    except FileNotFoundError as err:
        if args.debug:
            raise
        name = err.filename if err.filename is not None else err
        return _failed(args, EXIT_USAGE, f"no such file: {name}", file=name)
    except (LocalProtocolError, UsageError, ValueError) as err:
        if args.debug:
            raise
        concerns: dict[str, object] = {}
        if isinstance(err, LocalProtocolError) and err.field is not None:
            concerns = {"field": err.field, "value": err.value}
        return _failed(args, EXIT_USAGE, str(err), **concerns)
    except ReplyTimeoutError as err:
        if args.debug:
            raise
        return _failed(args, EXIT_FAILURE, f"{err}{_timeout_hint(args)}", port=_port_of(args))
    except (MotorbusError, OSError) as err:
        if args.debug:
            raise
        message = f"{err}{_port_in_use_hint(err, args)}"
        return _failed(args, EXIT_FAILURE, message, port=_port_of(args))


def _failed(args: argparse.Namespace, code: int, message: str, **concerns: object) -> int:
    """Report a failure (one line on stderr; with --json one JSON object on stdout)."""
    from motorbus.cli.output import fail

    with contextlib.suppress(BrokenPipeError):
        fail(args, message, code=code, **concerns)
    return code


def _port_of(args: argparse.Namespace) -> str | None:
    """The port the command was given (``--port``, a bus file's, ``replay --to``)."""
    port = getattr(args, "port", None) or getattr(args, "to", None)
    return port if isinstance(port, str) else None


def _guarded(enabled: bool) -> contextlib.AbstractContextManager[object]:
    """``motorbus.runtime.guard.guarded(enabled)``, imported only for ``--guard``
    (start-up time)."""
    if not enabled:
        return contextlib.nullcontext()
    from motorbus.runtime.guard import guarded

    return guarded(True)


#: Commands that only watch a bus: on a port another program holds, what to do instead.
_WATCH_INSTEAD = (
    " - to watch a bus another program drives, listen on a tap (a second adapter on "
    "the RS-485 line, or `motorbus sim --tap PATH` for a simulator) with `motorbus "
    "monitor --listen --port TAP` or `motorbus capture --port TAP`, or have that "
    "program read the statuses itself "
    "(Streamer.follow(..., poll_status=True))"
)


def _port_in_use_hint(err: BaseException, args: argparse.Namespace) -> str:
    """For ``monitor`` and ``capture`` on a port in use: where to look instead."""
    if args.command not in ("monitor", "capture"):
        return ""
    seen: BaseException | None = err
    while seen is not None:
        if isinstance(seen, PortInUseError):
            return _WATCH_INSTEAD
        seen = seen.__cause__
    return ""


def _timeout_hint(args: argparse.Namespace) -> str:
    """What to check when a device is silent: its ID and the baud rate (not after a run)."""
    baud = getattr(args, "baud", None)
    if baud is None or getattr(args, "action", None) == "run":
        return ""
    ids = "the ID (motorbus scan lists the IDs that answer)" if args.command == "la" else ""
    check = " and ".join(x for x in (ids, f"--baud {baud}") if x)
    return f" - check {check}"


if __name__ == "__main__":
    raise SystemExit(main())
