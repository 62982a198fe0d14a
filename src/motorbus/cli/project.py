"""``motorbus project``: program, run and read back the projects of the FF AA project stepper.

Examples::

    motorbus project upload examples/project.toml --port /dev/ttyUSB1
    motorbus project run 1 --timeout 60
    motorbus project read 1 > saved.toml      # the same TOML form upload takes

A project file (TOML)::

    number = 1                 # project 1..4
    subdivision = 8            # microsteps per full step, 1..65535
    step_angle = 1.8           # degrees (0.01 resolution; stored x100, 0.01..2.55)
    distance_per_rev = 1       # user units per revolution, 1..16777215
    repeat = 0                 # 0..254, or "forever"

    [loop]                     # optional: run steps start..end count times in total
    start = 1
    end = 2
    count = 3

    [[step]]                   # 1..10 of these, in order
    distance = 2               # user units, 0..16777215
    direction = "forward"      # or "reverse"
    start_hz = 100             # 0..65535
    accel_hz = 50              # 0..65535
    speed_rpm = 300            # 0..65535
    output = "out1_on"         # none, out1_on..out3_on, all_on, out1_off..out3_off, all_off
    delay_ms = 200             # 0..16777215
    start_input = "none"       # none, in1, in2, in5
    stop_input = "none"

Keys other than these are refused, so a typo is not silently ignored.  Errors name
the file, and the key as written in it (a TOML syntax error also names the line).

"project run" waits for the end of the project (EE DD).  If it does not come within
--timeout seconds the project is stopped (0x5E) and the exit code is 1; with
--keep-running it is left running ("motorbus project stop" ends it).  Ctrl-C stops the
project too, and exits with 130.  "project run" reads the project first and refuses
(exit 1) one that is not valid: cleared, or left by an upload that ended part way.

An upload interrupted part way (Ctrl-C) clears the project on the controller (0x1E,
one frame more, with Ctrl-C deferred while it is sent), says how far it got
("project 1: upload interrupted after 12 of 28 frames; the project on the device is
invalid ...") and exits with 130; "project read" and "project run" then refuse it
until it is uploaded again.  An upload killed outright (SIGKILL, the OOM killer) runs
none of that: with --guard, the guard process sends that clear instead.
"""

from __future__ import annotations

import argparse
import asyncio
import enum
import sys
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from motorbus import ProjectStepper
from motorbus.cli.bus_options import STEPPER_BAUD, add_bus_options, add_guard_option, open_bus
from motorbus.cli.output import print_json, say
from motorbus.cli.values import STEP_ANGLE_SCALE, check_seconds, step_angle_x100
from motorbus.errors import LocalProtocolError
from motorbus.protocol import project_stepper as ps
from motorbus.protocol.base import Family, check_int

__all__ = [
    "project_from_dict",
    "project_from_toml",
    "project_to_dict",
    "project_to_toml",
    "register",
    "run",
]

#: ``--guard`` of ``project upload``: what the guard does for an upload.
UPLOAD_GUARD_HELP = (
    "start a guard process (Linux) that clears the project (0x1E) if the upload is "
    "killed outright part way (SIGKILL, the OOM killer), so that the half-written "
    "project is refused instead of run; see motorbus.runtime.guard"
)
#: ``repeat = "forever"`` is stored as 255 (A.4 0x8E).
REPEAT_FOREVER_NAME = "forever"

_TOP_KEYS = ("number", "subdivision", "step_angle", "distance_per_rev", "repeat", "loop", "step")
_LOOP_KEYS = ("start", "end", "count")
_STEP_KEYS = (
    "distance",
    "direction",
    "start_hz",
    "accel_hz",
    "speed_rpm",
    "output",
    "delay_ms",
    "start_input",
    "stop_input",
)
_REQUIRED_STEP_KEYS = ("distance", "speed_rpm")

E = TypeVar("E", bound=enum.IntEnum)


def register(subparsers: Any) -> None:
    """Add the ``project`` command and its sub-commands."""
    parser = subparsers.add_parser(
        "project",
        help="program and run the FF AA project stepper",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    p = sub.add_parser("upload", help="program a project from a TOML file")
    p.add_argument("file", metavar="FILE.toml")
    p.add_argument("--no-verify", action="store_true", help="do not read the project back")
    p.add_argument("--no-save", action="store_true", help="do not save it to flash")
    add_guard_option(p, UPLOAD_GUARD_HELP)
    _common(p)
    p = sub.add_parser("run", help="start project N and wait for its end (EE DD)")
    p.add_argument("number", metavar="N", type=int, help="project 1..4")
    p.add_argument(
        "--timeout",
        type=float,
        default=600.0,
        help="seconds to wait for the end; then the project is stopped (default 600)",
    )
    p.add_argument(
        "--keep-running",
        action="store_true",
        help="on timeout leave the project running instead of stopping it",
    )
    add_guard_option(p)
    _common(p)
    for name, text in (
        ("read", "print project N in the TOML form upload takes"),
        ("save", "save project N to flash"),
        ("clear", "clear project N"),
    ):
        p = sub.add_parser(name, help=text)
        p.add_argument("number", metavar="N", type=int, help="project 1..4")
        _common(p)
    _common(sub.add_parser("stop", help="stop the running project"))


def _common(parser: argparse.ArgumentParser) -> None:
    add_bus_options(parser, default_baud=STEPPER_BAUD, connect=True)
    parser.set_defaults(func=run)


# -- the TOML form ---------------------------------------------------------------------


def _unknown_keys(table: Mapping[str, Any], allowed: tuple[str, ...], where: str) -> None:
    extra = sorted(set(table) - set(allowed))
    if extra:
        raise LocalProtocolError(
            f"{where}: key {extra[0]!r} is not allowed: use {', '.join(allowed)}",
            field=extra[0],
        )


def _enum_value(kind: type[E], field: str, value: object) -> E:
    """An enum member from its lower-case name or its integer code."""
    if isinstance(value, str):
        try:
            return kind[value.strip().upper()]
        except KeyError:
            pass
    elif isinstance(value, int) and not isinstance(value, bool):
        try:
            return kind(value)
        except ValueError:
            pass
    names = ", ".join(m.name.lower() for m in kind)
    raise LocalProtocolError(
        f"{field}={value!r} is not allowed: choose one of {names}", field=field, value=value
    )


#: Protocol field names in error messages -> the key a project file uses for them.
_FILE_KEYS = {
    "run_distance": "distance",
    "repeat_count": "repeat",
    "loop_start": "[loop] start",
    "loop_end": "[loop] end",
    "loop_count": "[loop] count",
}


def _as_written(err: LocalProtocolError) -> LocalProtocolError:
    """``err`` with the protocol's field name replaced by the key the file uses."""
    message = str(err)
    for field, key in _FILE_KEYS.items():
        if err.field == field or field in message:
            # "run_distance=1.5 ..." and "run_distance must be an integer ...", after a
            # "step 1: " prefix or not: the file's key, and the file's range for repeat.
            message = message.replace(field, key, 1)
            if field == "repeat_count":
                message = message.replace("0..255", '0..254, or "forever"')
            return LocalProtocolError(message, field=key, value=err.value)
    return err


def _step_from(table: object, n: int) -> ps.StepSpec:
    where = f"step {n}"
    if not isinstance(table, dict):
        raise LocalProtocolError(f"{where} must be a [[step]] table", field="step")
    _unknown_keys(table, _STEP_KEYS, where)
    for key in _REQUIRED_STEP_KEYS:
        if key not in table:
            raise LocalProtocolError(f"{where}: {key} is required", field=key)
    try:
        return ps.StepSpec(
            run_distance=table["distance"],
            direction=_enum_value(
                ps.RotationDirection, "direction", table.get("direction", "forward")
            ),
            start_hz=table.get("start_hz", 0),
            accel_hz=table.get("accel_hz", 0),
            speed_rpm=table["speed_rpm"],
            output=_enum_value(ps.StepOutputCode, "output", table.get("output", "none")),
            delay_ms=table.get("delay_ms", 0),
            start_input=_enum_value(ps.GatingInput, "start_input", table.get("start_input", 0)),
            stop_input=_enum_value(ps.GatingInput, "stop_input", table.get("stop_input", 0)),
        )
    except LocalProtocolError as err:
        named = _as_written(err)
        raise LocalProtocolError(f"{where}: {named}", field=named.field, value=err.value) from err


def project_from_dict(data: Mapping[str, Any]) -> ps.Project:
    """Build a :class:`~motorbus.protocol.project_stepper.Project` from the parsed TOML form.

    Raises:
        LocalProtocolError: a missing or unknown key, or a value out of range (named).
    """
    _unknown_keys(data, _TOP_KEYS, "project")
    for key in ("number", "subdivision", "step_angle", "distance_per_rev", "step"):
        if key not in data:
            raise LocalProtocolError(f"project: {key} is required", field=key)
    steps = data["step"]
    if not isinstance(steps, list):
        raise LocalProtocolError("project: step must be [[step]] tables", field="step")
    check_int("number of steps", len(steps), 1, ps.MAX_STEPS)
    loop = data.get("loop", {})
    if not isinstance(loop, dict):
        raise LocalProtocolError("project: loop must be a [loop] table", field="loop")
    _unknown_keys(loop, _LOOP_KEYS, "loop")
    repeat = data.get("repeat", 0)
    if repeat == REPEAT_FOREVER_NAME:
        repeat = ps.REPEAT_FOREVER
    elif repeat == ps.REPEAT_FOREVER:
        raise LocalProtocolError(
            f'repeat={repeat} is out of range: allowed 0..{ps.REPEAT_FOREVER - 1}, or "forever"',
            field="repeat",
            value=repeat,
        )
    steps_specs = tuple(_step_from(s, n) for n, s in enumerate(steps, start=1))
    try:
        return ps.Project(
            number=data["number"],
            subdivision=data["subdivision"],
            step_angle_x100=step_angle_x100(
                "step_angle", data["step_angle"], ps.MAX_STEP_ANGLE_X100
            ),
            distance_per_rev=data["distance_per_rev"],
            steps=steps_specs,
            loop_start=loop.get("start", 0),
            loop_end=loop.get("end", 0),
            loop_count=loop.get("count", 0),
            repeat_count=repeat,
        )
    except LocalProtocolError as err:
        raise _as_written(err) from err


def project_from_toml(text: str, path: str | Path | None = None) -> ps.Project:
    """Parse a project file's text; ``path``, if given, prefixes every error.

    Raises:
        LocalProtocolError: not TOML (the message names the line), or not a valid
            project (the message names the key as written in the file).
    """
    where = f"{path}: " if path is not None else ""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise LocalProtocolError(f"{where}not valid TOML: {err}", field="file") from err
    try:
        return project_from_dict(data)
    except LocalProtocolError as err:
        if not where:
            raise
        raise LocalProtocolError(f"{where}{err}", field=err.field, value=err.value) from err


def project_to_dict(project: ps.Project) -> dict[str, Any]:
    """The TOML form of ``project`` as a dict (also its ``--json`` form)."""
    out: dict[str, Any] = {
        "number": project.number,
        "subdivision": project.subdivision,
        "step_angle": project.step_angle_x100 / STEP_ANGLE_SCALE,
        "distance_per_rev": project.distance_per_rev,
        "repeat": (
            REPEAT_FOREVER_NAME
            if project.repeat_count == ps.REPEAT_FOREVER
            else project.repeat_count
        ),
    }
    if (project.loop_start, project.loop_end, project.loop_count) != (0, 0, 0):
        out["loop"] = {
            "start": project.loop_start,
            "end": project.loop_end,
            "count": project.loop_count,
        }
    out["step"] = [
        {
            "distance": s.run_distance,
            "direction": s.direction.name.lower(),
            "start_hz": s.start_hz,
            "accel_hz": s.accel_hz,
            "speed_rpm": s.speed_rpm,
            "output": s.output.name.lower(),
            "delay_ms": s.delay_ms,
            "start_input": s.start_input.name.lower(),
            "stop_input": s.stop_input.name.lower(),
        }
        for s in project.steps
    ]
    return out


def _toml_value(value: object) -> str:
    # Only the value types of the project form occur: str, int, float.
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)


def project_to_toml(project: ps.Project) -> str:
    """The TOML text of ``project``, in the form ``project upload`` reads back."""
    data = project_to_dict(project)
    lines = [f"# motorbus project {project.number}"]
    for key, value in data.items():
        if key not in ("loop", "step"):
            lines.append(f"{key} = {_toml_value(value)}")
    if "loop" in data:
        lines += ["", "[loop]"] + [f"{k} = {_toml_value(v)}" for k, v in data["loop"].items()]
    for step in data["step"]:
        lines += ["", "[[step]]"] + [f"{k} = {_toml_value(v)}" for k, v in step.items()]
    return "\n".join(lines) + "\n"


# -- running -----------------------------------------------------------------------------


def run(args: argparse.Namespace) -> int:
    """Run ``motorbus project ACTION``; return the exit code.

    Raises:
        LocalProtocolError: a bad file, project number or timeout (nothing is sent).
        OSError: the file cannot be read, or the port cannot open.
        MotorbusError: a timeout, a verify mismatch, a device error.
    """
    project: ps.Project | None = None
    if args.action == "upload":
        path = Path(args.file)
        project = project_from_toml(path.read_text(encoding="utf-8"), path)
    elif args.action != "stop":
        check_int("project", args.number, 1, ps.MAX_PROJECT)
    if args.action == "run":
        check_seconds("--timeout", args.timeout, 1e-3)
    return asyncio.run(_run(args, project))


async def _run(args: argparse.Namespace, project: ps.Project | None) -> int:
    async with open_bus(args, [Family.PROJECT_STEPPER]) as bus:
        stepper = ProjectStepper(bus)
        action: str = args.action
        if project is not None:
            try:
                await stepper.upload(project, save=not args.no_save, verify=not args.no_verify)
            except asyncio.CancelledError as err:
                if err.args:  # "project 1: upload interrupted after 12 of 28 frames; ..."
                    print(f"motorbus project: {err.args[0]}", file=sys.stderr)
                raise
            done = ["uploaded"] + ([] if args.no_save else ["saved"])
            done += [] if args.no_verify else ["verified"]
            say(
                args,
                {"project": project.number, "steps": len(project.steps), "result": done},
                f"project {project.number} ({len(project.steps)} steps) {', '.join(done)}",
            )
        elif action == "run":
            # A cleared or half-uploaded project is refused before anything moves.
            await stepper.check_project(args.number)
            # On timeout run_project stops the project (unless --keep-running) and says
            # so; on Ctrl-C (cancellation) it stops it before the port closes.
            await stepper.run_project(
                args.number, timeout=args.timeout, keep_running=args.keep_running
            )
            say(args, {"project": args.number, "finished": True}, f"project {args.number} done")
        elif action == "read":
            stored = await stepper.check_project(args.number)
            if args.json:
                print_json(project_to_dict(stored))
            else:
                print(project_to_toml(stored), end="")
        elif action == "save":
            await stepper.save_project(args.number)
            say(args, {"project": args.number, "saved": True}, f"project {args.number} saved")
        elif action == "clear":
            await stepper.clear_project(args.number)
            say(args, {"project": args.number, "cleared": True}, f"project {args.number} cleared")
        elif action == "stop":
            await stepper.stop_project()
            say(args, {"stopped": True}, "project stopped")
    return 0
