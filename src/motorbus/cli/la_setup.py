"""``motorbus la setup`` and ``motorbus la calibrate``: IDs one by one, and a device's range.

``la setup [ID|NAME ...]`` gives each actuator its ID and the bus's baud rate, one at a
time: connect only the next actuator, press Enter; it is found at whichever LA rate it
was set to (19200, 57600, 115200 or 921600 bit/s), paused, given its ID (at once) and
its baud code, saved to flash and read back.  The new rate takes effect at its next
power-up.  An ID listed twice, or one that another actuator already answers to at the
bus's rate, is refused before anything is written; two new actuators answering at once
are too (connect one at a time).  Without IDs the bus file's named devices are set up
in file order.  Nothing is written to any file.

``la calibrate NAME`` finds the range of a named device: slow moves (``--step`` raw
units at a time) to each end within its present soft limits, stopping where it stops
advancing (an end stop, a stall); or takes ``--limits LOW:HIGH``, or the two numbers
typed at the prompt.  It shows the result and, once confirmed (``--yes``: at once),
writes it to the calibration file the device's bus names (``calibration = "..."``),
atomically; ``BusManager.from_toml`` reads it back at start.

Prompts read lines from standard input, so both commands can be scripted; an end of
input at a prompt stops.  Ctrl-C leaves the actuator paused and every file as it was
(exit code 130).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import copy
import dataclasses
import os
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from motorbus import Bus, InspireLA, scan
from motorbus.cli.bus_options import (
    LA_BAUD,
    add_bus_options,
    open_bus,
    resolve_port,
)
from motorbus.cli.ids import parse_ids
from motorbus.cli.main import EXIT_FAILURE, EXIT_OK, CommandFailed, UsageError
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_int

if TYPE_CHECKING:  # the bus file's modules load only for la calibrate (start-up time)
    from motorbus import Calibration, NamedActuator

__all__ = ["register_calibrate", "register_setup", "run_calibrate", "run_setup"]

#: Every LA rate (control table 12), slowest first.
LA_BAUDS = tuple(code.baud for code in la.BaudCode)
#: ``la calibrate``: raw units per step toward an end, and the most a step may take.
STEP_DEFAULT = 20
STEP_TIMEOUT_S = 3.0
#: A step is done when the actuator is within this of its target (raw units); its status
#: is read every STEP_POLL_S, and STILL_POLLS reads without progress mean an end.
STEP_TOLERANCE = 5
STEP_POLL_S = 0.02
STILL_POLLS = 5
#: A range end found at an end stop is kept this far inside it (raw units, 0.5 %).
END_MARGIN = 10
#: Fault flags that mean "pushing against something": the end of the range.
_END_FLAGS = la.ErrorFlags.STALL | la.ErrorFlags.OVER_CURRENT


def register_setup(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``la setup``."""
    p = sub.add_parser(
        "setup",
        help="give actuators their IDs and baud rate, one at a time",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "targets",
        metavar="ID|NAME",
        nargs="*",
        help="the IDs to give, in order (3, 1-4, 2,5), or named devices of the bus file "
        "(default: every named device of the bus)",
    )
    p.add_argument(
        "--search-ids",
        default=f"{la.ID_MIN}-{la.ID_MAX}",
        metavar="IDS",
        help="the IDs an actuator may have now (default 1-254; fewer is faster)",
    )
    p.add_argument("--yes", action="store_true", help="do not wait for Enter at the prompts")
    add_bus_options(p, default_baud=LA_BAUD, json_option=False)
    p.set_defaults(func=run_setup)


def register_calibrate(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add ``la calibrate``."""
    p = sub.add_parser(
        "calibrate",
        help="find a named device's range and write its calibration",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("name", metavar="NAME", help="a named device of the bus file ([bus.la.NAME])")
    p.add_argument("--limits", metavar="LOW:HIGH", help="the range in raw units; nothing moves")
    p.add_argument(
        "--step", type=int, default=STEP_DEFAULT, help="raw units per step toward an end (1..200)"
    )
    p.add_argument("--unit", help="the unit programs use for this device: raw | mm | percent")
    p.add_argument("--stroke-mm", type=float, help="the stroke in millimetres (1..1000)")
    p.add_argument("--direction", help="which end is the start: normal | reversed")
    p.add_argument("--offset-mm", type=float, help="millimetres added to every position")
    p.add_argument("--yes", action="store_true", help="write without asking")
    add_bus_options(p, default_baud=LA_BAUD, json_option=False)
    p.set_defaults(func=run_calibrate)


# -- prompts ----------------------------------------------------------------------------------


def _ask(args: argparse.Namespace, prompt: str) -> str:
    """One answer from standard input (lower case); ``--yes`` answers at once, an end of
    input answers "q"."""
    print(prompt, end="", flush=True)
    if args.yes:
        print("(--yes)", flush=True)
        return "y"
    line = sys.stdin.readline()
    if not line:
        print("(end of input)", flush=True)
        return "q"
    if not sys.stdin.isatty():
        print(line.rstrip("\n"), flush=True)  # a scripted answer, shown as typed
    return line.strip().lower()


@asynccontextmanager
async def _bus_at(args: argparse.Namespace, baud: int) -> AsyncIterator[Bus]:
    at = copy.copy(args)
    at.baud = baud
    async with open_bus(at, [Family.LA]) as bus:
        yield bus


async def _pause(bus: Bus, *ids: int) -> None:
    """Pause each ID, whatever happens (an interrupted write leaves it paused)."""
    for ident in dict.fromkeys(ids):
        with contextlib.suppress(Exception):
            await InspireLA(bus, ident).pause()


# -- la setup ---------------------------------------------------------------------------------


def _setup_targets(args: argparse.Namespace) -> list[tuple[int, str]]:
    """``(id, label)`` of each actuator to set up, in order; refuses an ID twice."""
    spec = getattr(args, "bus_spec", None)
    named = {n.name: n.id for n in spec.la} if spec is not None else {}
    items = args.targets or list(named)
    if not items:
        raise UsageError("give the IDs to set up (e.g. 1-4), or name devices in the bus file")
    out: list[tuple[int, str]] = []
    for item in items:
        if item in named:
            out.append((named[item], f"la:{named[item]} ({item})"))
        elif item[:1].isalpha():
            raise UsageError(
                f"{item!r} is no named device of the bus: named are {sorted(named) or 'none'}"
            )
        else:
            out += [(i, f"la:{i}") for i in parse_ids(item, "ID")]
    ids = [i for i, _ in out]
    twice = sorted({i for i in ids if ids.count(i) > 1})
    if twice:
        raise LocalProtocolError(
            f"ID {twice[0]} is listed twice: each actuator needs its own ID", field="ID"
        )
    return out


def run_setup(args: argparse.Namespace) -> int:
    """Run ``la setup``: 0 if every actuator was set up, 1 if not (skipped, quit, failed)."""
    resolve_port(args)
    baud = args.baud
    if baud not in LA_BAUDS:
        raise LocalProtocolError(
            f"--baud={baud!r} is not an LA rate: allowed {' | '.join(map(str, LA_BAUDS))}",
            field="--baud",
            value=baud,
        )
    targets = _setup_targets(args)
    search = parse_ids(args.search_ids, "--search-ids")
    earlier: set[tuple[int, int]] = set()  # (rate, ID) of the actuators set up so far
    set_up: list[str] = []
    answer = ""
    for n, (ident, label) in enumerate(targets, 1):
        while answer != "q":
            answer = _ask(
                args,
                f"[{n}/{len(targets)}] connect only the actuator for {label}, then press "
                "Enter (s: skip, q: quit): ",
            )
            if answer in ("q", "s"):
                break
            why = _setup_one(args, ident, label, baud, search, earlier)
            if why is None:
                set_up.append(label)
                break
            print(f"  {why}", flush=True)
            if args.yes:
                break
        if answer == "q":
            break
    print(f"set up {len(set_up)} of {len(targets)}: {', '.join(set_up) or 'none'}", flush=True)
    if set_up:
        print(
            f"power the actuators off and on: they answer at {baud} bit/s from their next "
            "power-up (motorbus scan lists them)",
            flush=True,
        )
    return EXIT_OK if len(set_up) == len(targets) else EXIT_FAILURE


def _setup_one(
    args: argparse.Namespace,
    ident: int,
    label: str,
    baud: int,
    search: list[int],
    earlier: set[tuple[int, int]],
) -> str | None:
    """Find the one actuator connected, give it ``ident`` and ``baud``; None, or why not."""
    found = asyncio.run(_search(args, baud, search))
    if not found:
        return (
            f"no actuator answers (IDs {args.search_ids} at {', '.join(map(str, LA_BAUDS))} "
            "bit/s): check its power and wiring, then press Enter to look again"
        )
    if len(found) > 1:
        shown = ", ".join(f"la:{i} at {b}" for b, i in found)
        return f"{len(found)} actuators answer ({shown}): connect only the one for {label}"
    ((rate, old),) = found
    print(f"  found la:{old} at {rate} bit/s", flush=True)
    if (rate, old) in earlier:
        # The actuator set up before, still connected, looks just like this.
        question = (
            f"  la:{old} at {rate} bit/s is how an actuator was just set up: a new one? [y/N]: "
        )
        if _ask(args, question) not in ("y", "yes"):
            return f"nothing written: disconnect the actuator set up as la:{old}"
    asyncio.run(_write_id_and_baud(args, rate, old, ident, baud, label))
    earlier.update({(rate, ident), (baud, ident)})
    print(
        f"  {label}: was la:{old} at {rate} bit/s; ID {ident} and baud {baud} saved and read "
        f"back{'' if rate == baud else ' (the new rate takes effect at its next power-up)'}",
        flush=True,
    )
    return None


async def _search(args: argparse.Namespace, baud: int, search: list[int]) -> list[tuple[int, int]]:
    """``(rate, ID)`` of every actuator that answers, the bus's rate first."""
    found: list[tuple[int, int]] = []
    for rate in (baud, *(b for b in LA_BAUDS if b != baud)):
        async with _bus_at(args, rate) as bus:
            found += [(rate, i) for i in await scan(bus, search)]
    return found


async def _write_id_and_baud(
    args: argparse.Namespace, rate: int, old: int, ident: int, baud: int, label: str
) -> None:
    """Pause, write the ID (at once) and the baud code, save, read both back."""
    code = next(c for c in la.BaudCode if c.baud == baud)
    async with _bus_at(args, rate) as bus:
        try:
            actuator = InspireLA(bus, old)
            await actuator.pause()  # nothing moves while it is set up
            if old != ident:
                actuator = await actuator.change_id(ident)
            if rate != baud:
                await actuator.set_baud_code(code)
            await actuator.save()
            got = (await actuator.read(la.Register.ID), await actuator.read(la.Register.BAUD))
            if got != (ident, int(code)):
                raise CommandFailed(
                    f"{label}: read back ID {got[0]}, baud code {got[1]} after saving ID "
                    f"{ident}, code {int(code)} ({baud} bit/s)"
                )
        finally:
            await _pause(bus, ident, old)


# -- la calibrate -----------------------------------------------------------------------------


def _named_device(args: argparse.Namespace) -> tuple[Path, str, NamedActuator]:
    """The bus file, the bus and the named device ``args.name``; sets ``--bus``."""
    from motorbus import default_bus_file, load_bus_file
    from motorbus.cli.bus_options import BUS_FILE_ENV

    given = args.bus_file or os.environ.get(BUS_FILE_ENV)
    path = Path(given) if given else default_bus_file()
    if path is None or not path.is_file():
        raise UsageError(f"--bus-file {path}: no such file (la calibrate needs a bus file)")
    bus_file = load_bus_file(path, missing_calibration_ok=True)
    for spec in bus_file.specs:
        for named in spec.la:
            if named.name == args.name and args.bus in (None, spec.name):
                if spec.calibration is None:
                    raise UsageError(
                        f"{path}: bus {spec.name!r} names no calibration file: add "
                        f'calibration = "{spec.name}.cal.toml" to its [[bus]] table (la '
                        "calibrate writes there, never into the bus file)"
                    )
                args.bus_file, args.bus = str(path), spec.name
                return Path(spec.calibration), spec.name, named
    names = sorted(n.name for s in bus_file.specs for n in s.la)
    raise UsageError(f"{path} names no device {args.name!r}: named are {names or 'none'}")


def _limits_text(text: str) -> tuple[int, int]:
    from motorbus import Calibration

    parts = text.replace(":", " ").split()
    try:
        values = [int(p) for p in parts]
    except ValueError:
        values = []
    if len(values) != 2:
        raise LocalProtocolError(
            f"limits={text!r} is not allowed: two raw positions LOW:HIGH, 0..2000",
            field="limits",
            value=text,
        )
    return Calibration(limits=(values[0], values[1])).limits


def run_calibrate(args: argparse.Namespace) -> int:
    """Run ``la calibrate``: 0 once written (or declined), 1 if the device failed."""
    from motorbus import Calibration, write_calibration_file

    cal_path, _, named = _named_device(args)
    resolve_port(args)
    check_int("--step", args.step, 1, 200)
    keys = {
        k: v
        for k, v in (
            ("unit", args.unit),
            ("stroke_mm", args.stroke_mm),
            ("direction", args.direction),
            ("offset_mm", args.offset_mm),
        )
        if v is not None
    }
    base = Calibration.from_table(keys, named.calibration)  # bad values: exit 2, unsent
    if args.limits is not None:
        limits = _limits_text(args.limits)
    else:
        limits = asyncio.run(_find_range(args, named, base))
    while True:
        cal = Calibration.from_table({"limits": list(limits)}, base)
        shown = ""
        if cal.stroke_mm is not None:
            lo, hi = cal.limits_in("mm")
            shown = f" ({lo:g}..{hi:g} mm)"
        print(
            f"{args.name}: limits {list(cal.limits)} raw{shown}, direction {cal.direction}, "
            f"unit {cal.unit}",
            flush=True,
        )
        answer = _ask(args, f"write this to {cal_path}? [y/N, or type LOW HIGH]: ")
        if answer in ("y", "yes"):
            break
        if answer[:1].isdigit():
            try:
                limits = _limits_text(answer)
            except LocalProtocolError as err:
                print(f"  {err}", flush=True)
            continue
        print("nothing written", flush=True)
        return EXIT_OK
    write_calibration_file(cal_path, args.name, cal)
    print(f"written to {cal_path}: {args.name} is calibrated from the next start", flush=True)
    return EXIT_OK


async def _find_range(
    args: argparse.Namespace, named: NamedActuator, base: Calibration
) -> tuple[int, int]:
    """Move slowly to each end within ``base``'s limits; return where it stopped."""
    async with open_bus(args, [Family.LA]) as bus:
        # Raw units within the present limits: the library refuses any target outside.
        within = dataclasses.replace(base, unit="raw")
        actuator = InspireLA(bus, named.id, calibration=within, name=named.name)
        try:
            await actuator.enable()
            start = (await actuator.status()).position
            lo, hi = base.limits
            print(f"{named.name}: at {start}; finding its ends within {lo}..{hi}", flush=True)
            if not lo <= start <= hi:
                nearest = min(max(start, lo), hi)
                print(f"  outside its limits: moving to {nearest} first", flush=True)
                await actuator.move_to(nearest, wait=True, timeout=STEP_TIMEOUT_S * 10)
            low = await _seek(actuator, lo, -args.step)
            high = await _seek(actuator, hi, args.step)
        finally:
            await _pause(bus, named.id)
    if not low < high:
        raise CommandFailed(f"{named.name}: found no range (both ends at {low})")
    return low, high


async def _seek(actuator: InspireLA, limit: int, step: int) -> int:
    """Step toward ``limit``; return where the actuator stopped advancing (an end stop:
    :data:`END_MARGIN` inside it), or ``limit``."""
    position = (await actuator.status()).position
    low, high = actuator.calibration.limits
    while position != limit:
        target = max(limit, position + step) if step < 0 else min(limit, position + step)
        target = min(max(target, low), high)  # never outside the present limits
        arrived, at, why = await _step(actuator, target)
        if not arrived:
            await actuator.clear_fault()  # a stall against the end: clear it, move on
            end = min(max(at - END_MARGIN if step > 0 else at + END_MARGIN, low), high)
            print(f"  {why} at {at} (target {target}): an end; {end} with the margin", flush=True)
            return end
        position = target
    print(f"  reached {limit}", flush=True)
    return limit


async def _step(actuator: InspireLA, target: int) -> tuple[bool, int, str]:
    """One move: (arrived, where it is, why it stopped short)."""
    await actuator.move_to(target)
    clock = actuator.bus.timer
    deadline = clock.now() + STEP_TIMEOUT_S
    last: int | None = None
    still = 0
    while True:
        await clock.sleep_until(clock.now() + STEP_POLL_S)
        status = await actuator.status()
        if status.errors & _END_FLAGS:
            return False, status.position, status.errors.name or "a fault"
        if abs(status.position - target) <= STEP_TOLERANCE:
            return True, status.position, ""
        still = still + 1 if last is not None and abs(status.position - last) <= 1 else 0
        if still >= STILL_POLLS or clock.now() > deadline:
            return False, status.position, "stopped"
        last = status.position
