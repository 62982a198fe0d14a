"""``--realtime[=PRIO]``: real-time mode for a command that talks to a bus.

``add_realtime_option(parser)`` adds the option; giving it asks
:mod:`motorbus.runtime.realtime` for SCHED_FIFO at ``PRIO`` (default 50), locked memory and
garbage-collector control when the command's bus opens.  What the system refuses is
said in one warning line, and the command carries on.  ``MOTORBUS_REALTIME`` does the
same from the environment; the option wins.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any

from motorbus.runtime import realtime

__all__ = ["add_realtime_option", "parse_priority"]


def parse_priority(text: str) -> int:
    """``--realtime=PRIO``: a SCHED_FIFO priority 1..99.

    Raises:
        argparse.ArgumentTypeError: anything else (argparse turns it into a usage error).
    """
    value = text.strip()
    if not value.isdigit() or not realtime.PRIORITY_MIN <= int(value) <= realtime.PRIORITY_MAX:
        raise argparse.ArgumentTypeError(
            f"--realtime={text!r} is out of range: allowed a SCHED_FIFO priority "
            f"{realtime.PRIORITY_MIN}..{realtime.PRIORITY_MAX}"
        )
    return int(value)


class _RealtimeAction(argparse.Action):
    """Stores the priority and asks for real-time mode when the first bus opens."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: str | Sequence[Any] | None,
        option_string: str | None = None,
    ) -> None:
        priority = values if isinstance(values, int) else realtime.DEFAULT_PRIORITY
        setattr(namespace, self.dest, priority)
        realtime.request(priority)


def add_realtime_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--realtime[=PRIO]`` to ``parser`` (no-op if the parser has it already)."""
    if any("--realtime" in a.option_strings for a in parser._actions):
        return
    parser.add_argument(
        "--realtime",
        nargs="?",
        metavar="PRIO",
        type=parse_priority,
        action=_RealtimeAction,
        default=None,
        help=(
            "real-time mode when the bus opens: SCHED_FIFO at PRIO "
            f"(default {realtime.DEFAULT_PRIORITY}), locked memory, no full garbage "
            "collection inside a tick; what the system refuses is logged (docs/realtime.md)"
        ),
    )
