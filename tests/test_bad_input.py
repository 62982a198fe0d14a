"""Bad input everywhere: every public entry point refuses it before a byte is written.

Each case calls one constructor or method with one argument replaced by an out-of-range,
wrong-typed (str, float, None, bool) or malformed value.  It must raise
``LocalProtocolError`` (a ``ValueError``) whose message names the field and shows the
value, and the bus and the simulated devices must have seen nothing.

The cases are generated from tables: one valid call per entry point, and per argument
the values that must be refused.
"""

from __future__ import annotations

import asyncio
import dataclasses
import inspect
import os
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from motorbus.bus.bus import Bus, BusState, Priority
from motorbus.bus.options import host_margin_from_env
from motorbus.busfile import BusSpec, DeviceSpec
from motorbus.devices.calibration import NamedActuator
from motorbus.devices.la import InspireLA, scan
from motorbus.devices.project_stepper import ProjectStepper
from motorbus.devices.quad_stepper import QuadStepper
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import Command, Family
from motorbus.serve.client import connect
from motorbus.sim.la import LAModel
from motorbus.sim.model import DeviceModel
from motorbus.sim.project_stepper import ProjectStepperModel
from motorbus.sim.quad_stepper import QuadStepperModel
from motorbus.streams import StreamEnded, Streamer
from motorbus.transport.memory import memory_pair
from motorbus.transport.serial import SerialTransport
from tests.helpers import sim_bus
from tests.waiting import eventually
from tests.zygote import run_motorbus

#: Wrong types for an integer (or enum) argument.  ``True`` is refused: it is not a number.
WRONG_INT = ("1", 1.5, None, True)
#: Wrong types for a flag: truthy text or None must never pick a command.
WRONG_FLAG = ("yes", 1.5, None, 0)
#: Wrong values for a duration in seconds that may be left out (None is its default).
WRONG_SECONDS = ("1", True, float("nan"), float("inf"), -1.0, 1e300)
STEPPER_BAUD = 115200

# -- protocol command constructors ------------------------------------------------------------

#: One valid call per command, the extra out-of-range values per field.  Every field of
#: every command class is listed (checked below), so a new field cannot be forgotten.
COMMANDS: dict[type[Any], tuple[dict[str, Any], dict[str, tuple[Any, ...]]]] = {
    la.Control: (
        {"id": 1, "action": la.ControlAction.QUERY_STATUS},
        {"id": (0, 256), "action": (99, -1)},
    ),
    la.MoveTo: ({"id": 1, "position": 5, "reply": True}, {"id": (0, 256), "position": (-1, 2001)}),
    la.Follow: ({"id": 1, "position": 5, "reply": True}, {"id": (0, 256), "position": (-1, 2001)}),
    la.ReadRegister: (
        {"id": 1, "register": la.Register.TARGET},
        {"id": (0, 255), "register": (55, "TARGET")},
    ),
    la.WriteRegister: (
        {"id": 1, "register": la.Register.OVER_CURRENT_LIMIT, "value": 500},
        {"id": (0, 256), "register": (32,), "value": (299, 1501)},
    ),
    la.ReadTable: ({"id": 1, "index": 0, "count": 2}, {"id": (0, 255), "index": (-1, 255)}),
    la.WriteTable: (
        {"id": 1, "index": 0, "data": b"\x01"},
        {"id": (0, 256), "index": (-1, 255), "data": (b"", bytes(254), "ab", None, 5)},
    ),
    la.Broadcast: (
        {"mode": la.BroadcastMode.FOLLOW, "entries": ((1, 5),)},
        {
            "mode": (0xF1, -1),
            "entries": (
                (),
                ((1, 5), (1, 6)),
                ((0, 5),),
                ((1, 2001),),
                tuple((i, 1) for i in range(1, 17)),
                None,
                "x",
            ),
        },
    ),
    ps.AccelAndSpeed: (
        {"step": 1, "accel_hz": 1, "speed_rpm": 1, "motor": 3},
        {"step": (0, 11), "accel_hz": (-1, 65536), "speed_rpm": (-1, 65536), "motor": (0,)},
    ),
    ps.ClearProject: ({"project": 1}, {"project": (0, 5)}),
    ps.DirectionAndStartFrequency: (
        {"step": 1, "direction": ps.RotationDirection.FORWARD, "start_hz": 1, "motor": 3},
        {"step": (0, 11), "direction": (2, -1), "start_hz": (-1, 65536), "motor": (0,)},
    ),
    ps.DistancePerRev: ({"value": 1, "motor": 3}, {"value": (0, 2**24), "motor": (0,)}),
    ps.Home: ({"motor": 3}, {"motor": (0, 256)}),
    ps.JogForward: ({"motor": 3}, {"motor": (0, 256)}),
    ps.JogReverse: ({"motor": 3}, {"motor": (0, 256)}),
    ps.ManualStop: ({"motor": 3}, {"motor": (0, 256)}),
    ps.SingleRun: ({"motor": 3}, {"motor": (0, 256)}),
    ps.MotorSetup: (
        {"subdivision": 1, "step_angle_x100": 180, "motor": 3},
        {"subdivision": (0, 65536), "step_angle_x100": (0, 256), "motor": (0,)},
    ),
    ps.ReadInput: ({"input_number": 1}, {"input_number": (0, 6)}),
    ps.ReadProject: ({"project": 1}, {"project": (0, 5)}),
    ps.RepeatCount: ({"count": 1}, {"count": (-1, 256)}),
    ps.RunDistance: (
        {"step": 1, "distance": 1, "motor": 3},
        {"step": (0, 11), "distance": (-1, 2**24), "motor": (0,)},
    ),
    ps.SaveProject: ({"project": 1}, {"project": (0, 5)}),
    ps.SelectProject: ({"project": 1, "total_steps": 1}, {"project": (0, 5), "total_steps": (11,)}),
    ps.SetMode4: ({"value": 1}, {"value": (-1, 3)}),
    ps.SetOutput: (
        {"port": ps.OutputPort(1), "level": ps.OutputLevel(1)},
        {"port": (0, 6), "level": (2, -1)},
    ),
    ps.SetPowerOnHoming: ({"enabled": True}, {"enabled": ("yes", None, 2)}),
    ps.StartInput: (
        {"step": 1, "input_number": ps.GatingInput(1), "motor": 3},
        {"step": (0, 11), "input_number": (99, -1), "motor": (0,)},
    ),
    ps.StopInput: (
        {"step": 1, "input_number": ps.GatingInput(1), "motor": 3},
        {"step": (0, 11), "input_number": (99, -1), "motor": (0,)},
    ),
    ps.StartProject: ({"project": 1}, {"project": (0, 5)}),
    ps.StepDelay: (
        {"step": 1, "delay_ms": 1, "motor": 3},
        {"step": (0, 11), "delay_ms": (-1, 2**24), "motor": (0,)},
    ),
    ps.StepLoop: (
        {"start": 1, "end": 2, "count": 1},
        {"start": (-1, 11), "end": (-1, 11), "count": (-1, 256)},
    ),
    ps.StepOutput: (
        {"step": 1, "code": ps.StepOutputCode(0), "motor": 3},
        {"step": (0, 11), "code": (99, -1), "motor": (0,)},
    ),
    ps.StopMode: ({"mode": ps.StopBehavior(0), "motor": 3}, {"mode": (2, -1), "motor": (0,)}),
    q.AccelAndSpeed: (
        {"motor": 1, "accel_hz": 1, "speed_rpm": 1},
        {"motor": (0, 5), "accel_hz": (-1, 65536), "speed_rpm": (-1, 65536)},
    ),
    q.DirectionAndStartFrequency: (
        {"motor": 1, "direction": q.RotationDirection(0), "start_hz": 1},
        {"motor": (0, 5), "direction": (2, -1), "start_hz": (-1, 65536)},
    ),
    q.Home: ({"motor": 1, "stop_input": 0}, {"motor": (0, 5), "stop_input": (-1, 14)}),
    q.MotorSetup: (
        {"motor": 1, "subdivision": 1, "step_angle_x100": 180},
        {"motor": (0, 5), "subdivision": (0, 65536), "step_angle_x100": (0, 256)},
    ),
    q.Run: ({"motor": 1}, {"motor": (0, 5)}),
    q.RunPulses: ({"motor": 1, "pulses": 1}, {"motor": (0, 5), "pulses": (-1, 2**24)}),
    q.SetLed: ({"led": 1, "on": True}, {"led": (0, 6), "on": ("yes", None, 1)}),
    q.Stop: ({"motor": 1}, {"motor": (0, 5)}),
}

#: The message of a refused register value names the register, not "value".
FIELD_ALIASES = {"value": ("over_current_limit",), "entries": ("id", "position")}


def _wrong_types(valid: Any) -> tuple[Any, ...]:
    return WRONG_FLAG if isinstance(valid, bool) else WRONG_INT


def _constructor_cases() -> list[Any]:
    cases = []
    for cls, (valid, extra) in COMMANDS.items():
        for name in valid:
            wrong = () if name in ("data", "entries") else _wrong_types(valid[name])
            for bad in (*wrong, *extra.get(name, ())):
                cases.append(
                    pytest.param(
                        cls,
                        valid,
                        name,
                        bad,
                        id=f"{cls.__module__[18:]}.{cls.__name__}-{name}={bad!r}",
                    )
                )
    return cases


def test_every_command_class_and_field_is_in_the_table() -> None:
    for module in (la, ps, q):
        for name in module.__all__:
            obj = getattr(module, name)
            if isinstance(obj, type) and issubclass(obj, Command) and dataclasses.is_dataclass(obj):
                # What a caller gives (a cache such as Broadcast's encoded bytes is not).
                fields = {f.name for f in dataclasses.fields(obj) if f.init}
                if not fields:
                    continue  # StopAll, RunAll, Save, StopProject: nothing to get wrong
                assert obj in COMMANDS, f"{module.__name__}.{name} has no bad-input row"
                assert set(COMMANDS[obj][0]) == fields, name


@pytest.mark.parametrize(("cls", "valid", "name", "bad"), _constructor_cases())
def test_command_constructor_refuses(
    cls: type[Any], valid: dict[str, Any], name: str, bad: Any
) -> None:
    cls(**valid)  # the baseline call is fine
    with pytest.raises(LocalProtocolError) as info:
        cls(**{**valid, name: bad})
    assert isinstance(info.value, ValueError)
    message = str(info.value)
    names = (name, *FIELD_ALIASES.get(name, ()))
    assert any(n in message for n in names) or info.value.field in names, message
    if name not in ("entries", "data"):
        assert repr(bad) in message or str(bad) in message, message


# -- device methods, the streamer, the bus ----------------------------------------------------

Call = Callable[[Bus, Any], Awaitable[object]]


async def _sync(value: object) -> object:
    return value


def _la_calls() -> dict[str, tuple[Call, tuple[Any, ...]]]:
    def dev(bus: Bus) -> InspireLA:
        return InspireLA(bus, 1)

    return {
        "InspireLA(id)": (lambda b, v: _sync(InspireLA(b, v)), (*WRONG_INT, 0, 255)),
        "move_to(position)": (lambda b, v: dev(b).move_to(v), (*WRONG_INT, -1, 2001)),
        "move_to(reply)": (lambda b, v: dev(b).move_to(5, reply=v), WRONG_FLAG),
        "move_to(wait)": (lambda b, v: dev(b).move_to(5, wait=v), (*WRONG_FLAG, "no")),
        "follow(position)": (lambda b, v: dev(b).follow(v), (*WRONG_INT, -1, 2001)),
        "follow(reply)": (lambda b, v: dev(b).follow(5, reply=v), WRONG_FLAG),
        "read(register)": (lambda b, v: dev(b).read(v), (*WRONG_INT, 55, "TARGET")),
        "write(register)": (lambda b, v: dev(b).write(v, 500), (*WRONG_INT, 32)),
        "write(value)": (
            lambda b, v: dev(b).write(la.Register.OVER_CURRENT_LIMIT, v),
            (*WRONG_INT, 299, 1501),
        ),
        "read_table(index)": (lambda b, v: dev(b).read_table(v, 1), (*WRONG_INT, -1, 255)),
        "read_table(count)": (lambda b, v: dev(b).read_table(0, v), (*WRONG_INT, 0, 254)),
        "write_table(index)": (lambda b, v: dev(b).write_table(v, b"\x01"), (*WRONG_INT, -1)),
        "write_table(data)": (lambda b, v: dev(b).write_table(0, v), (b"", "ab", None, 3)),
        "set_over_current_limit": (
            lambda b, v: dev(b).set_over_current_limit(v),
            (*WRONG_INT, 299, 1501),
        ),
        "set_temperature_limits(over_c)": (
            lambda b, v: dev(b).set_temperature_limits(v, 30.0),
            ("1", None, True, float("nan"), 24.0, 81.0),
        ),
        "set_temperature_limits(recovery_c)": (
            lambda b, v: dev(b).set_temperature_limits(70.0, v),
            ("1", None, True, float("nan"), 19.0, 66.0),
        ),
        "set_baud_code": (lambda b, v: dev(b).set_baud_code(v), (*WRONG_INT, 4, -1)),
        "change_id": (lambda b, v: dev(b).change_id(v), (*WRONG_INT, 0, 255)),
        "change_id(save)": (lambda b, v: dev(b).change_id(2, save=v), (*WRONG_FLAG, "x")),
        "submit(reserved)": (
            lambda b, v: _sync(b.submit(la.Control(1, la.ControlAction.QUERY_STATUS), reserved=v)),
            (*WRONG_FLAG, "yes"),
        ),
        "scan(ids)": (lambda b, v: scan(b, [v]), (*WRONG_INT, 0, 255)),
        "scan(timeout)": (lambda b, v: scan(b, [1], timeout=v), WRONG_SECONDS),
        "follow(actuators)": (
            lambda b, v: _sync(Streamer(b).follow(v, [5])),
            ("1", 1.5, None, True, [], ["x"]),
        ),
        "follow(targets)": (
            lambda b, v: _sync(Streamer(b).follow(dev(b), v)),
            ("1500", None, 1.5, b"\x01"),
        ),
        "follow(period)": (
            lambda b, v: _sync(Streamer(b).follow(dev(b), [5], period=v)),
            ("1", None, True, 0.009, 0.051, float("nan")),
        ),
        "follow(feedback)": (
            lambda b, v: _sync(Streamer(b).follow(dev(b), [5], feedback=v)),
            WRONG_FLAG,
        ),
        "follow(poll_status)": (
            lambda b, v: _sync(Streamer(b).follow(dev(b), [5], poll_status=v)),
            WRONG_FLAG,
        ),
        "follow(safe_action)": (
            lambda b, v: _sync(Streamer(b).follow(dev(b), [5], safe_action=v)),
            ("stop", None, 1),
        ),
        "request(cmd)": (lambda b, v: b.request(v), ("55 AA", None, b"\x55\xaa", q.StopAll())),
        "request(timeout)": (lambda b, v: b.request(la.MoveTo(1, 5), timeout=v), WRONG_SECONDS),
        "request(retries)": (
            lambda b, v: b.request(la.Control(1, la.ControlAction.QUERY_STATUS), retries=v),
            ("1", 1.5, True, -1, 11),
        ),
        "request(priority)": (
            lambda b, v: b.request(la.MoveTo(1, 5), priority=v),
            ("HIGH", 1.5, True, 7),
        ),
    }


def _quad_calls() -> dict[str, tuple[Call, tuple[Any, ...]]]:
    good = {
        "motor": 1,
        "subdivision": 1,
        "step_angle_x100": 180,
        "pulses": 1,
        "direction": 0,
        "start_hz": 1,
        "accel_hz": 1,
        "speed_rpm": 1,
    }
    calls: dict[str, tuple[Call, tuple[Any, ...]]] = {}
    for name, extra in {
        "motor": (0, 5),
        "subdivision": (0, 65536),
        "step_angle_x100": (0, 256),
        "pulses": (-1, 2**24),
        "direction": (2, -1),
        "start_hz": (-1, 65536),
        "accel_hz": (-1, 65536),
        "speed_rpm": (-1, 65536),
    }.items():
        calls[f"configure({name})"] = (
            lambda b, v, name=name: QuadStepper(b).configure(**{**good, name: v}),  # type: ignore[misc]
            (*WRONG_INT, *extra),
        )
    calls.update(
        {
            "run(motor)": (lambda b, v: QuadStepper(b).run(v), (*WRONG_INT, 0, 5)),
            "run(wait)": (lambda b, v: QuadStepper(b).run(1, wait=v), WRONG_FLAG),
            "run(timeout)": (lambda b, v: QuadStepper(b).run(1, timeout=v), WRONG_SECONDS),
            "stop(motor)": (lambda b, v: QuadStepper(b).stop(v), (*WRONG_INT, 0, 5)),
            "home(motor)": (lambda b, v: QuadStepper(b).home(v, 1), (*WRONG_INT, 0, 5)),
            "home(stop_input)": (lambda b, v: QuadStepper(b).home(1, v), (*WRONG_INT, -1, 14)),
            "led(led)": (lambda b, v: QuadStepper(b).led(v, True), (*WRONG_INT, 0, 6)),
            "led(on)": (lambda b, v: QuadStepper(b).led(1, v), WRONG_FLAG),
            "led(wait)": (lambda b, v: QuadStepper(b).led(1, True, wait=v), WRONG_FLAG),
            "led(timeout)": (
                lambda b, v: QuadStepper(b).led(1, True, timeout=v),
                (*WRONG_SECONDS, None),
            ),
        }
    )
    return calls


def _project_calls() -> dict[str, tuple[Call, tuple[Any, ...]]]:
    def dev(bus: Bus) -> ProjectStepper:
        return ProjectStepper(bus)

    numbered = ("read_project", "save_project", "clear_project", "start_project", "run_project")
    calls: dict[str, tuple[Call, tuple[Any, ...]]] = {
        f"{m}(number)": (
            lambda b, v, m=m: getattr(dev(b), m)(v),  # type: ignore[misc]
            (*WRONG_INT, 0, 5),
        )
        for m in numbered
    }
    calls.update(
        {
            "ProjectStepper(motor)": (
                lambda b, v: _sync(ProjectStepper(b, motor=v)),
                (*WRONG_INT, 0, 256),
            ),
            "run_project(timeout)": (lambda b, v: dev(b).run_project(1, timeout=v), WRONG_SECONDS),
            "upload(project)": (lambda b, v: dev(b).upload(v), (None, "1", 1, {"number": 1})),
            "read_input": (lambda b, v: dev(b).read_input(v), (*WRONG_INT, 0, 6)),
            "set_mode4": (lambda b, v: dev(b).set_mode4(v), (*WRONG_INT, -1, 3)),
            "set_stop_mode": (lambda b, v: dev(b).set_stop_mode(v), (*WRONG_INT, 2, -1)),
            "set_output(port)": (lambda b, v: dev(b).set_output(v, True), (*WRONG_INT, 0, 6)),
            "set_output(active)": (lambda b, v: dev(b).set_output(1, v), WRONG_FLAG),
            "set_power_on_homing": (lambda b, v: dev(b).set_power_on_homing(v), WRONG_FLAG),
            "jog(forward)": (lambda b, v: dev(b).jog(forward=v), WRONG_FLAG),
        }
    )
    return calls


def _device_cases() -> list[Any]:
    cases = []
    for family, table in (
        ("la", _la_calls()),
        ("quad", _quad_calls()),
        ("project", _project_calls()),
    ):
        for name, (call, values) in table.items():
            for bad in values:
                cases.append(pytest.param(family, call, bad, id=f"{family}.{name}={bad!r}"))
    return cases


def _models(family: str) -> tuple[list[DeviceModel], int | None]:
    if family == "la":
        return [LAModel(1)], None
    if family == "quad":
        return [QuadStepperModel()], STEPPER_BAUD
    return [ProjectStepperModel()], STEPPER_BAUD


@pytest.mark.parametrize(("family", "call", "bad"), _device_cases())
async def test_device_call_refuses_and_sends_nothing(family: str, call: Call, bad: Any) -> None:
    models, baud = _models(family)
    async with sim_bus(models, baud=baud) as (bus, sim):
        with pytest.raises(LocalProtocolError) as info:
            await call(bus, bad)
        assert isinstance(info.value, ValueError)
        assert info.value.field, str(info.value)
        assert (bus.stats.requests, bus.stats.bytes_out) == (0, 0)
        assert (sim.bus.stats.requests, sim.bus.stats.bytes_in) == (0, 0)


# -- Bus(...) and BusManager -------------------------------------------------------------------

NAN = float("nan")
INF = float("inf")


class _PartTimer:
    """A clock with ``now`` and ``call_at`` only: a bus also holds and lazily calls."""

    def now(self) -> float:
        return 0.0

    def call_at(self, deadline: float, callback: Any) -> None:
        return None

    def __repr__(self) -> str:
        return "_PartTimer()"


BUS_OPTIONS: dict[str, tuple[Any, ...]] = {
    "name": (5, "", b"bus"),
    "families": ([], "la", ["la"], 5, None),
    "min_spacing": (-0.001, 2.0, NAN, INF, "1", None, True),
    "host_margin": (-1.0, 11.0, NAN, INF, -INF, "0.002", None, True),
    "turnaround": (
        {Family.LA: NAN},
        {Family.LA: -0.001},
        {Family.LA: INF},
        {Family.LA: 1.5},
        {Family.LA: "0.001"},
        {Family.LA: True},
        {"la": 0.001},
        0.001,
        [Family.LA],
    ),
    "retries": ("1", 1.5, 2.7, NAN, None, True, -1, 11),
    "late_guard": (NAN, INF, -0.001, 2.5, "0.02", None, True),
    "reconnect": ("yes", 1, 0, None),
    "wire_floor": ("yes", 1, 0, None),
    "safe_action": ("stop", "", "PAUSE", 1, None, True),
    "timer": ("x", 5, [], _PartTimer()),  # made, and failed when the bus opened (or used)
}


def test_every_bus_option_is_in_the_table() -> None:
    options = set(inspect.signature(Bus).parameters) - {"transport"}
    assert options == set(BUS_OPTIONS)


@pytest.mark.parametrize("transport", [None, "memory://x", 5], ids=repr)
def test_bus_refuses_what_is_not_a_transport(transport: Any) -> None:
    # Bus(None) failed with an AttributeError on the transport's URL.
    with pytest.raises(LocalProtocolError, match=r"^transport must be a motorbus Transport"):
        Bus(transport)


@pytest.mark.parametrize(
    ("option", "bad"),
    [pytest.param(k, v, id=f"{k}={v!r}") for k, values in BUS_OPTIONS.items() for v in values],
)
async def test_bus_constructor_refuses(option: str, bad: Any) -> None:
    host, _peer = memory_pair()
    with pytest.raises(LocalProtocolError, match=option):
        Bus(host, **{option: bad})
    assert not host.is_open


@pytest.mark.parametrize("turnaround", [NAN, -0.997])
async def test_bus_refuses_a_nan_or_negative_turnaround_before_any_request(
    turnaround: float,
) -> None:
    # A NaN turnaround used to fail the first request and hang the later ones (and leave a
    # NaN deadline in the loop-wide timer); a negative one timed out "within -997 ms".
    host, _peer = memory_pair()
    with pytest.raises(LocalProtocolError, match=r"turnaround\[LA\]=.* is out of range"):
        Bus(host, turnaround={Family.LA: turnaround})


@pytest.mark.parametrize("late_guard", [NAN, -0.001])
async def test_bus_refuses_a_nan_or_negative_late_guard(late_guard: float) -> None:
    host, _peer = memory_pair()
    with pytest.raises(LocalProtocolError, match=r"late_guard=.* is out of range: allowed 0\.\.2"):
        Bus(host, late_guard=late_guard)


async def test_bus_refuses_text_for_a_duration_with_a_named_error() -> None:
    host, _peer = memory_pair()
    with pytest.raises(LocalProtocolError, match=r"min_spacing must be a number 0\.\.1 s, got '1'"):
        Bus(host, min_spacing="1")  # type: ignore[arg-type]


@pytest.mark.parametrize("start_by", [NAN, "1", True], ids=repr)
async def test_submit_refuses_a_start_by_that_is_no_time_and_the_bus_goes_on(
    start_by: Any,
) -> None:
    # A NaN start_by was taken: its timer callback then failed (NaN to an integer
    # deadline) and every later request on the bus hung.
    model = LAModel(1)
    async with sim_bus([model]) as (bus, sim):
        query = la.Control(1, la.ControlAction.QUERY_STATUS)
        held = bus.submit(query)  # a frame holds the bus: the next one would wait
        with pytest.raises(LocalProtocolError, match=r"start_by must be a time in seconds"):
            bus.submit(query, start_by=start_by)
        await held
        assert sim.bus.stats.requests == 1
        assert (await bus.request(query)).id == 1


BAD_RELEASE_KEYS: tuple[Any, ...] = (["LA:1"], ["la:0"], "bogus", 5, ["project_stepper"], [1])


@pytest.mark.parametrize("keys", BAD_RELEASE_KEYS, ids=repr)
async def test_release_refuses_keys_that_name_no_device_here(keys: Any) -> None:
    # A malformed key used to be let go of silently: release() returned, la:1 stayed
    # held and was not paused, and the program believed it had stopped it.
    model = LAModel(1)
    async with sim_bus([model]) as (bus, sim):
        await InspireLA(bus, 1).move_to(1200)
        sent = sim.bus.stats.requests
        with pytest.raises(LocalProtocolError, match=r"key"):
            await bus.release(keys)
        lease = bus.lease("la:2", owner="rig")
        if keys != ["project_stepper"]:  # well formed: a lease's table knows no families
            with pytest.raises(LocalProtocolError, match=r"key"):
                await lease.release(keys=keys)
        assert lease.active and "la:2" in lease.keys
        assert bus.lease_keeper.table.owner_of("la:1") == "program"
        assert sim.bus.stats.requests == sent  # nothing sent
        await lease.release(hold=True)
        await bus.release(["la:1"])  # a good key still works: la:1 is paused
        assert bus.lease_keeper.table.owner_of("la:1") is None
        assert sim.bus.stats.requests == sent + 1


#: Each streamer option, a bad value and the range its error names.  ``lead`` may be
#: None (the default: a served bus's own); ``phase`` may not.
STREAMER_OPTIONS = [
    *(("phase", v, "0..0.05 s") for v in (NAN, INF, -INF, "x", "0.001", None, True, -0.001, 0.051)),
    *(("lead", v, "0..5 s") for v in (NAN, INF, -INF, "0.1", True, -0.001, 5.001)),
]


@pytest.mark.parametrize(
    ("field", "value", "allowed"),
    STREAMER_OPTIONS,
    ids=[f"{f}={v!r}" for f, v, _ in STREAMER_OPTIONS],
)
async def test_streamer_refuses_a_bad_option(field: str, value: Any, allowed: str) -> None:
    host, _peer = memory_pair()
    bus = Bus(host)
    with pytest.raises(LocalProtocolError, match=field) as info:
        Streamer(bus, **{field: value})
    assert info.value.field == field and allowed in str(info.value)


async def test_a_local_streamer_takes_a_lead_it_has_no_use_for() -> None:
    """``lead`` is a served bus's (how far ahead its targets travel); a local streamer
    checks it and goes on, so a program moves between the two unchanged."""
    host, _peer = memory_pair()
    assert isinstance(Streamer(Bus(host), lead=0.3), Streamer)


async def test_streamer_refuses_what_is_not_a_bus() -> None:
    with pytest.raises(LocalProtocolError, match="bus must be a Bus"):
        Streamer("memory://arm")  # type: ignore[arg-type]


FOLLOW_PERIODS = (NAN, INF, "0.02", None, True, 0.005, 0.0501, -0.02)


@pytest.mark.parametrize("period", FOLLOW_PERIODS, ids=[repr(p) for p in FOLLOW_PERIODS])
async def test_follow_refuses_bad_period_and_sends_nothing(period: Any) -> None:
    async with sim_bus([LAModel(1)]) as (bus, sim):
        streamer = Streamer(bus)
        with pytest.raises(LocalProtocolError, match="period") as info:
            streamer.follow(InspireLA(bus, 1), [1000] * 3, period=period)
        assert "0.01..0.05 s" in str(info.value)
        assert streamer.streams == []
        assert (bus.stats.requests, sim.bus.stats.bytes_in) == (0, 0)
        await streamer.close()


BAD_TARGET_ITEMS: tuple[Any, ...] = (
    {"1": 1000},  # a text ID used to become int("1")
    {1.7: 1000},  # ... and 1.7 became ID 1
    {True: 1000},
    ["1000"],  # a text position used to be parsed by float()
    "1000",  # ... and a text row was split into characters
    [None],
    [NAN],
    [True],
)


@pytest.mark.parametrize("item", BAD_TARGET_ITEMS, ids=[repr(i) for i in BAD_TARGET_ITEMS])
async def test_a_sequence_with_a_bad_row_is_refused_at_follow(item: Any) -> None:
    # A sequence is all there at follow(): it is checked whole, so a bad row far into
    # it refuses the stream before its first frame, naming the row (it used to end the
    # stream at that row's tick, having moved the actuator through the rows before).
    model = LAModel(1)
    async with sim_bus([model]) as (bus, _sim):
        streamer = Streamer(bus)
        rows = [1000, 1100, item, 1200]
        with pytest.raises(LocalProtocolError, match=r"^targets row 2 \(of 4\): ") as info:
            streamer.follow(InspireLA(bus, 1), rows, period=0.01)
        assert "nothing sent" in str(info.value)
        assert streamer.streams == []
        assert bus.lease_keeper.table.owner_of("la:1") is None  # nothing taken
        assert model.received == []
        await streamer.close()


class _LabelTable:
    """A table indexed by column label, as a pandas DataFrame is: a length, no rows."""

    dtypes = ("float64",)  # a DataFrame's: data held, so checked at follow

    def __len__(self) -> int:
        return 3

    def __getitem__(self, key: object) -> object:
        raise KeyError(key)


async def test_a_table_whose_rows_cannot_be_read_is_refused_at_follow() -> None:
    model = LAModel(1)
    async with sim_bus([model]) as (bus, _sim):
        streamer = Streamer(bus)
        with pytest.raises(LocalProtocolError, match=r"row 0 \(of 3\) could not be read"):
            streamer.follow(InspireLA(bus, 1), _LabelTable(), period=0.01)
        assert streamer.streams == [] and model.received == []
        await streamer.close()


async def test_set_targets_refuses_a_bad_sequence_and_the_stream_goes_on() -> None:
    model = LAModel(1)
    async with sim_bus([model]) as (bus, _sim):
        streamer = Streamer(bus)
        stream = streamer.follow(InspireLA(bus, 1), lambda t, statuses: 900, period=0.01)
        await eventually(lambda: stream.stats.ticks >= 2, "two ticks")
        with pytest.raises(LocalProtocolError, match=r"^targets row 1 \(of 3\): .*2001"):
            stream.set_targets([1000, 2001, 1000])
        ticks = stream.stats.ticks
        await eventually(lambda: stream.stats.ticks >= ticks + 2, "two more ticks")
        assert not stream.done
        assert {t for _, _, t in model.received} == {900}  # the old source, unchanged
        await streamer.close()


@pytest.mark.parametrize("item", BAD_TARGET_ITEMS, ids=[repr(i) for i in BAD_TARGET_ITEMS])
async def test_a_bad_target_from_a_function_ends_the_stream_before_it_is_sent(item: Any) -> None:
    # A function's targets exist only at their tick: checked there, and the first bad
    # one ends the stream unsent.
    model = LAModel(1)
    async with sim_bus([model]) as (bus, _sim):
        streamer = Streamer(bus)
        stream = streamer.follow(InspireLA(bus, 1), lambda t, statuses: item, period=0.01)
        with pytest.raises(StreamEnded) as info:
            await asyncio.wait_for(stream.wait(), 5)
        assert isinstance(info.value.__cause__, LocalProtocolError)
        assert "targets" in str(info.value.__cause__) or "target" in str(info.value.__cause__)
        assert [cmd for _, cmd, _ in model.received] == []
        await streamer.close()


SERIAL_BAUDS = (0, 1, 7, 299, 4_000_001, 10**12, 9600.0, "9600", True)


@pytest.mark.parametrize("baud", SERIAL_BAUDS, ids=[repr(b) for b in SERIAL_BAUDS])
def test_serial_transport_refuses_implausible_bauds(baud: Any) -> None:
    # 10**12 used to reach the OS ("signed integer is greater than maximum"); 1 and 7
    # were accepted.
    with pytest.raises(LocalProtocolError, match="baudrate") as info:
        SerialTransport("/dev/ttyUSB0", baudrate=baud)
    assert "300..4000000" in str(info.value)
    assert SerialTransport("/dev/ttyUSB0", baudrate=300).baudrate == 300


@pytest.mark.parametrize("option", ["rs485", "remove_echo", "low_latency"])
@pytest.mark.parametrize("bad", ["false", 0, 1, None], ids=repr)
def test_serial_transport_refuses_flags_that_are_not_bools(option: str, bad: Any) -> None:
    # rs485="false" used to turn RS-485 on.
    with pytest.raises(LocalProtocolError, match=f"{option} must be True or False"):
        SerialTransport("/dev/ttyUSB0", baudrate=9600, **{option: bad})


MANAGER_BUS = {"name": "arm", "url": "memory://arm", "baud": 921600}


@pytest.mark.parametrize("bad", (*WRONG_FLAG, "no"), ids=repr)
def test_manager_refuses_a_safe_stop_that_is_no_bool(bad: Any) -> None:
    # "no" is truthy: it kept the safe stop it was meant to turn off.
    with pytest.raises(LocalProtocolError, match=r"safe_stop must be True or False"):
        BusManager(safe_stop=bad)


MANAGER_CASES: list[tuple[str, dict[str, Any]]] = [
    ("baud", {"baud": 0}),
    ("baud", {"baud": "921600"}),
    ("baud", {"baud": True}),
    ("baud", {"baud": None}),
    ("baud", {"baud": 1.5}),
    ("la_safe_action", {"la_safe_action": "explode"}),
    ("unknown", {"speed": 3}),
]


@pytest.mark.parametrize(
    ("field", "change"), MANAGER_CASES, ids=[f"{f}-{c}" for f, c in MANAGER_CASES]
)
def test_manager_from_dict_and_add_bus_refuse(field: str, change: dict[str, Any]) -> None:
    table = {**MANAGER_BUS, **change}
    with pytest.raises(LocalProtocolError, match=field if field != "unknown" else "speed"):
        BusManager.from_dict({"bus": [table]})
    mgr = BusManager()
    options = {k: v for k, v in table.items() if k not in ("name", "url", "baud")}
    with pytest.raises(LocalProtocolError):
        mgr.add_bus("arm", "memory://arm", baud=table["baud"], **options)
    assert mgr.buses == {} and mgr.specs == {}


@pytest.mark.parametrize("data", [{}, {"bus": []}, {"bus": "x"}, {"bus": [{"url": "x"}]}])
def test_manager_from_dict_refuses_malformed(data: dict[str, Any]) -> None:
    with pytest.raises(LocalProtocolError):
        BusManager.from_dict(data)


@pytest.mark.parametrize("devices", [["la:0"], ["la:x"], ["printer"], ["la:255"]])
def test_manager_refuses_bad_device_lists(devices: list[str]) -> None:
    with pytest.raises(LocalProtocolError):
        BusManager().add_bus("arm", "memory://arm", baud=921600, devices=devices)


# -- the command line --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv",
    [["decode", "ZZ"], ["demo", "--seconds", "0"]],
    ids=["decode-ZZ", "demo-seconds-0"],
)
def test_cli_usage_errors_exit_2_with_one_line(argv: list[str]) -> None:
    done = run_motorbus(argv)
    assert done.returncode == 2, done
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert lines[0].startswith(f"motorbus {argv[0]}: "), lines
    assert done.stdout == ""


def test_priority_values_are_accepted_as_ints() -> None:
    # The check must not refuse the documented IntEnum values given as plain ints.
    assert [int(p) for p in Priority] == [0, 1, 2, 3]


@pytest.mark.parametrize("text", ["abc", "-5", "nan", "20000", ""], ids=repr)
def test_a_bad_host_margin_in_the_environment_is_refused_naming_the_variable(text: str) -> None:
    # "abc" failed as a bare "could not convert string to float" when motorbus.bus was
    # first imported; "nan" and "-5" failed every Bus() for an argument not given.
    with pytest.raises(LocalProtocolError, match=r"^MOTORBUS_HOST_MARGIN_MS=.*0\.\.10000") as info:
        host_margin_from_env(text)
    assert info.value.field == "MOTORBUS_HOST_MARGIN_MS"
    assert (host_margin_from_env("5"), host_margin_from_env(None)) == (0.005, 0.002)


def test_the_command_line_names_a_bad_host_margin_in_one_line() -> None:
    done = run_motorbus(
        ["la", "status", "1", "--port", "/dev/null"],
        {**os.environ, "MOTORBUS_HOST_MARGIN_MS": "abc"},
    )
    assert done.returncode == 2, done
    assert done.stderr.strip().splitlines() == [
        "motorbus: MOTORBUS_HOST_MARGIN_MS='abc' is not a host margin: give milliseconds, 0..10000"
    ]


@pytest.mark.parametrize(
    ("given", "field"),
    [
        ({"config_file": 5}, "config_file"),
        ({"config_file": "/nonexistent/zenoh.json5"}, "config_file"),
        ({"name": "x" * 65}, "name"),
        ({"name": 5}, "name"),
    ],
    ids=["config-int", "config-missing", "name-long", "name-int"],
)
def test_connect_refuses_bad_arguments_when_called(given: dict[str, Any], field: str) -> None:
    # The asyncio client took them and failed at open() with a raw TypeError or Zenoh's
    # "No such file or directory" (the blocking one checked them already).
    with pytest.raises(LocalProtocolError) as bad:
        connect("tcp/127.0.0.1:7447", **given)
    assert bad.value.field == field


@pytest.mark.parametrize("make", [InspireLA, QuadStepper, ProjectStepper], ids=lambda c: c.__name__)
@pytest.mark.parametrize("bus", [None, "arm", 5], ids=repr)
def test_a_device_refuses_what_is_not_a_bus_when_made(make: Any, bus: Any) -> None:
    # They were made, and failed with an AttributeError at their first call.
    args = (bus, 1) if make is InspireLA else (bus,)
    with pytest.raises(LocalProtocolError, match=r"^bus must be a motorbus Bus") as info:
        make(*args)
    assert info.value.field == "bus"


async def test_the_manager_names_an_unknown_bus_and_one_not_open_yet() -> None:
    mgr = BusManager()
    mgr.add_bus("arm", "memory://arm-bad-input", baud=921600, devices=["la:1"])
    with pytest.raises(LocalProtocolError, match=r"no bus named 'nope'; buses: \['arm'\]"):
        mgr.project_stepper("nope")  # a bare KeyError: 'nope' before
    with pytest.raises(LocalProtocolError, match=r"bus 'arm' is not open: use the manager as"):
        mgr.la("arm", 1)  # "no bus named 'arm'; buses: ['arm']" before


def test_manager_refuses_a_transport_that_is_not_one_when_the_bus_is_added() -> None:
    # It was taken, and the manager's open failed with an AttributeError on 'baudrate'.
    with pytest.raises(LocalProtocolError, match=r"^transport must be a motorbus Transport"):
        BusManager().add_bus("arm", "memory://arm", baud=921600, transport="x")  # type: ignore[arg-type]


def test_a_named_actuator_refuses_a_calibration_that_is_not_one_when_made() -> None:
    # It was made, and refused only when the manager handed out the device.
    with pytest.raises(LocalProtocolError, match=r"^calibration='x': not a Calibration"):
        NamedActuator("grip", 1, calibration="x")  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: DeviceSpec("la", ids=5), r"^ids must be a list of IDs 1\.\.254, got 5"),
        (
            lambda: BusSpec(name="a", url="memory://a", baud=921600, devices=None),
            r"^bus 'a': devices must be a list of DeviceSpec, got None",
        ),
        (
            lambda: BusSpec(name="a", url="memory://a", baud=921600, la=5),
            r"^bus 'a': la must be a list of NamedActuator, got 5",
        ),
    ],
    ids=["device-ids-int", "bus-devices-none", "bus-la-int"],
)
def test_bus_specs_refuse_lists_that_are_not_lists(make: Any, message: str) -> None:
    # Each raised a bare "TypeError: ... is not iterable".
    with pytest.raises(LocalProtocolError, match=message):
        make()


async def test_wait_state_refuses_a_state_or_timeout_that_is_none() -> None:
    # "closed" raised an AttributeError (no .value); a negative or NaN timeout reached
    # asyncio.  The value of a state is taken as the state.
    async with sim_bus([LAModel(1)]) as (bus, _sim):
        with pytest.raises(LocalProtocolError, match=r"^state='shut' is not a bus state"):
            await bus.wait_state("shut")  # type: ignore[arg-type]
        with pytest.raises(LocalProtocolError, match=r"^timeout=-1 is out of range"):
            await bus.wait_state(BusState.LOST, timeout=-1)
        with pytest.raises(LocalProtocolError, match=r"^timeout=nan is out of range"):
            await bus.wait_state(BusState.LOST, timeout=NAN)
        await bus.wait_state("open")  # type: ignore[arg-type]  # already: returns at once


@pytest.mark.parametrize(
    "given", [5, la.Control(1, la.ControlAction.PAUSE)], ids=["int", "one-command-unlisted"]
)
async def test_a_lease_refuses_safe_commands_that_are_no_list(given: Any) -> None:
    # A bare TypeError ("not iterable") before; nothing is taken either way.
    async with sim_bus([LAModel(1)]) as (bus, sim):
        with pytest.raises(LocalProtocolError, match=r"^safe_commands must be a list"):
            bus.lease("la:1", owner="rig", safe_commands=given)
        assert bus.lease_keeper.table.owner_of("la:1") is None
        assert sim.bus.stats.requests == 0


class _Computed:
    """Rows computed on access, a billion of them: checked whole, follow would hang."""

    def __len__(self) -> int:
        return 10**9

    def __getitem__(self, k: int) -> list[int]:
        return [1000 + k % 2]


async def test_a_sequence_that_computes_its_rows_is_checked_at_each_tick_not_at_follow() -> None:
    model = LAModel(1)
    async with sim_bus([model]) as (bus, _sim):
        streamer = Streamer(bus)
        stream = streamer.follow(InspireLA(bus, 1), _Computed(), period=0.01)  # at once
        await eventually(lambda: len(model.received) >= 3, "three computed rows sent")
        await stream.stop()
        assert {t for _, _, t in model.received} <= {1000, 1001}
        await streamer.close()
