"""Shared by the examples: use --port if given, else start a built-in simulator."""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator

from motorbus.sim.process import SimProcess


@contextlib.contextmanager
def port_or_simulator(args: argparse.Namespace, devices: list[str], baud: int) -> Iterator[str]:
    """Yield ``args.port``, or the path of a simulator started for ``devices``."""
    if args.port:
        yield args.port
        return
    with SimProcess(devices, baud=baud) as sim:
        print(f"(no --port given: using a simulator on {sim.path})")
        yield sim.path


def parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--port", help="serial port or URL (default: a built-in simulator)")
    return p
