"""``motorbus sim``: serve simulated devices on a pseudo-terminal until interrupted.

Example::

    motorbus sim --link /tmp/ttyLA la:1-3
    /dev/pts/7 /tmp/ttyLA

The first line of standard output is the slave device path, followed by the link if
one was asked for; point any serial client at either.  SIGINT or SIGTERM stops the
simulator, which prints a one-line summary and exits with status 0.

``--log FILE`` appends a frame log (docs/frame-log.md) to FILE: a header line, then one
JSON line per frame either way.  ``--tap PATH`` opens a second, listen-only pty linked
at PATH that carries a copy of every byte both ways, so that a sniffer can listen::

    motorbus sim --link /tmp/ttyLA --tap /tmp/ttyLA.tap la:1-3 &
    motorbus capture --port /tmp/ttyLA.tap --family la --out session.jsonl
"""

from __future__ import annotations

import argparse
import signal
import sys
from typing import Any

from motorbus.errors import LocalProtocolError
from motorbus.sim.bus import PACING_MODES, SimStats
from motorbus.sim.faults import FaultConfig
from motorbus.sim.pty import PtySim
from motorbus.sim.spec import parse_device_specs

__all__ = ["add_arguments", "main", "register", "run", "summary"]

#: Exit status for bad arguments, as argparse uses.
EXIT_USAGE = 2
#: How often the main thread checks that the sim thread is still alive (s).
_LIVENESS_PERIOD_S = 0.5
_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}
#: ... and SIGUSR1: the next device (``--one-at-a-time``).
_WAITED = _STOP_SIGNALS | {signal.SIGUSR1}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``sim`` options and the DEVICE arguments to ``parser``."""
    parser.add_argument(
        "devices",
        metavar="DEVICE",
        nargs="+",
        help="device spec: la, la:1-15, la:1,4,7, project-stepper[:motor=3], quad-stepper "
        "(options are key=value items of the model)",
    )
    parser.add_argument("--link", metavar="PATH", help="create a symlink PATH to the pty")
    parser.add_argument(
        "--baud",
        type=int,
        help="emulated wire rate in bit/s (default 921600 for LA only, else 9600)",
    )
    parser.add_argument(
        "--faults",
        metavar="SPEC",
        default="",
        help="faults, e.g. drop=0.01,flip=0.001,garbage=0.02,late=0.01:0.05,dup=0.01,"
        "silent,silent=2:3,disconnect=5:1",
    )
    parser.add_argument(
        "--pacing",
        choices=PACING_MODES,
        default="wire",
        help="wire: deliver replies when their last byte would arrive at the baud (default); "
        "prompt: answer the moment a request is complete, no wire time, turnaround 0 "
        "(a USB-CDC device or a TCP bridge)",
    )
    parser.add_argument(
        "--prompt",
        dest="pacing",
        action="store_const",
        const="prompt",
        help="shorthand for --pacing prompt",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of turnarounds and faults")
    parser.add_argument(
        "--log", metavar="FILE", help="append a frame log (one JSON line per frame) to FILE"
    )
    parser.add_argument(
        "--tap",
        metavar="PATH",
        help="also serve a listen-only pty, linked at PATH, carrying a copy of every byte "
        "both ways (for motorbus capture --port PATH)",
    )
    parser.add_argument(
        "--spin",
        action="store_true",
        help="busy-poll the port: precise arrival timestamps for timing measurements, "
        "at the cost of a whole CPU core",
    )
    parser.add_argument(
        "--echo",
        action="store_true",
        help="send every byte the host writes straight back, as a half-duplex RS-485 "
        "adapter that hears itself (motorbus doctor finds it)",
    )
    parser.add_argument(
        "--device-bauds",
        action="store_true",
        help="each LA actuator hears only at its own rate (la:1,baud_code=0 is a 19200 "
        "bit/s actuator), as actuators set to different rates on one line",
    )
    parser.add_argument(
        "--one-at-a-time",
        action="store_true",
        help="connect only the first DEVICE; each SIGUSR1 unplugs it and plugs in the next, "
        "powered up afresh (as a user connects actuators one by one; IDs may repeat)",
    )
    parser.add_argument(
        "--strict-baud",
        action="store_true",
        help="devices ignore the host while it has the port at another rate than --baud, "
        "as a UART at the wrong rate would",
    )


def register(subparsers: Any) -> None:
    """Add the ``sim`` command to an ``argparse`` subparsers object (``add_subparsers()``)."""
    parser = subparsers.add_parser(
        "sim",
        help="serve simulated devices on a pseudo-terminal",
        description="Serve simulated devices on a pseudo-terminal until SIGINT or SIGTERM.",
    )
    add_arguments(parser)
    parser.set_defaults(func=run)


def summary(stats: SimStats) -> str:
    """Return the one-line summary printed when the simulator stops."""
    faults = " ".join(f"{k}={v}" for k, v in stats.faults_injected.items() if v) or "none"
    return (
        f"motorbus sim: {stats.requests} requests, {stats.replies} replies, "
        f"{stats.unsolicited} unsolicited, {stats.ignored_while_transmitting} missed while "
        f"transmitting, {stats.discarded_bytes} bytes discarded; faults: {faults}"
    )


def run(args: argparse.Namespace) -> int:
    """Serve the devices in ``args`` until SIGINT/SIGTERM; return the exit status.

    Returns 0 after a signal, 2 for a bad device or fault spec, 1 if the simulator
    thread fails.
    """
    try:
        one_at_a_time = getattr(args, "one_at_a_time", False)
        models = parse_device_specs(args.devices, distinct_ids=not one_at_a_time)
        faults = FaultConfig.parse(args.faults or "")
    except LocalProtocolError as err:
        print(f"motorbus sim: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    # Block the stop signals before the sim thread exists, so that it inherits the mask
    # and only this thread takes them, synchronously, with sigtimedwait.
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, _WAITED)
    try:
        try:
            sim = PtySim(
                models,
                baud=args.baud,
                faults=faults,
                seed=args.seed,
                link=args.link,
                log_file=args.log,
                spin=getattr(args, "spin", False),
                tap=getattr(args, "tap", None),
                pacing=getattr(args, "pacing", "wire"),
                echo=getattr(args, "echo", False),
                strict_baud=getattr(args, "strict_baud", False),
                device_bauds=getattr(args, "device_bauds", False),
                one_at_a_time=one_at_a_time,
            ).start()
        except (OSError, LocalProtocolError) as err:
            print(f"motorbus sim: error: {err}", file=sys.stderr)
            return EXIT_USAGE
        try:
            line = sim.path if sim.link is None else f"{sim.path} {sim.link}"
            print(line, flush=True)
            if sim.tap is not None:
                tap = f"motorbus sim: tap on {sim.tap_path} ({sim.tap})"
                print(tap, file=sys.stderr, flush=True)
            while (got := signal.sigtimedwait(_WAITED, _LIVENESS_PERIOD_S)) is None or (
                got.si_signo == signal.SIGUSR1
            ):
                if got is not None:
                    plugged = sim.next_device()
                    said = "none (that was the last)" if plugged is None else f"#{plugged + 1}"
                    print(f"motorbus sim: connected device {said}", file=sys.stderr, flush=True)
                if not sim.running:
                    print(f"motorbus sim: error: simulator stopped: {sim.error}", file=sys.stderr)
                    return 1
        finally:
            sim.stop()
        print(summary(sim.bus.stats), flush=True)
        return 0
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m motorbus.cli.sim`` (the same options as ``motorbus sim``)."""
    parser = argparse.ArgumentParser(prog="motorbus sim", description=__doc__)
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
