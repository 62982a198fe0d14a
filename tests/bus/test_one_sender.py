"""One place sends a safe action: the bus's lease table (issue 40).

Every ending asks ``bus.lease_keeper`` - a lease's end and the bus's close
(``end_all``), a stream's end, ``BusManager.stop_all_devices``, the rig, the dashboard -
and none builds stop frames of its own; the guard process takes the frames the table
publishes (``bus.leases``).  The checks below record what reaches the table's one
sender (``LeaseKeeper.send_stop``), and read the source for any other sender.
"""

from __future__ import annotations

import ast
import asyncio
from collections.abc import Iterator, Sequence
from pathlib import Path

import pytest

from motorbus.bus.lease_shell import LeaseKeeper, SafeStopper
from motorbus.devices.la import InspireLA
from motorbus.errors import BusClosedError, LocalProtocolError, ReplyTimeoutError
from motorbus.manager import BusManager
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q
from motorbus.protocol.base import Command
from motorbus.rig.runner import _pause_all
from motorbus.runtime.guard import _devices
from motorbus.sim.la import LAModel, PowerState
from motorbus.sim.memory import MemorySim
from motorbus.streams import Streamer
from tests.helpers import sim_bus
from tests.waiting import eventually

SRC = Path(__file__).resolve().parents[2] / "src" / "motorbus"


@pytest.fixture
def sent(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[tuple[str, list[Command[object]]]]]:
    """Every call of the lease table's sender: (who, commands)."""
    calls: list[tuple[str, list[Command[object]]]] = []
    original = LeaseKeeper.send_stop

    async def recording(
        self: LeaseKeeper, commands: Sequence[Command[object]], *, who: str
    ) -> list[object]:
        calls.append((who, list(commands)))
        return await original(self, commands, who=who)

    monkeypatch.setattr(LeaseKeeper, "send_stop", recording)
    yield calls


def pause(ident: int) -> la.Control:
    return la.Control(ident, la.ControlAction.PAUSE)


async def test_a_stream_s_end_asks_the_lease_table(
    sent: list[tuple[str, list[Command[object]]]],
) -> None:
    models = [LAModel(1), LAModel(2)]
    async with sim_bus(models, pacing="prompt") as (bus, _):
        actuators = [InspireLA(bus, 1), InspireLA(bus, 2)]
        stream = Streamer(bus).follow(
            actuators, lambda t, s: [800, 900], period=0.01, safe_action="estop"
        )
        await eventually(lambda: len(models[0].received) >= 2, "targets at la:1")
        await stream.stop()
        assert all(m.power_state is PowerState.ESTOPPED for m in models)
    streams = [cmds for who, cmds in sent if who.startswith("stream")]
    assert streams == [
        [la.Control(1, la.ControlAction.ESTOP), la.Control(2, la.ControlAction.ESTOP)]
    ]


async def test_a_lease_s_end_at_close_asks_the_lease_table(
    sent: list[tuple[str, list[Command[object]]]],
) -> None:
    async with sim_bus([LAModel(3)], pacing="prompt") as (bus, _):
        await InspireLA(bus, 3).move_to(1200)
    assert ("a lease ended", [pause(3)]) in sent


async def test_the_manager_s_stop_asks_the_lease_table(
    sent: list[tuple[str, list[Command[object]]]],
) -> None:
    async with MemorySim.start([LAModel(1), LAModel(2)], pacing="prompt") as sim:
        mgr = BusManager()
        mgr.add_bus(
            "arm",
            "memory://arm",
            baud=921600,
            devices=["la:1-2"],
            transport=sim.transport,
            host_margin_ms=50,
            la_safe_action="estop",
        )
        async with mgr:
            report = await mgr.stop_all_devices()
    assert [e.outcome for e in report.entries] == ["confirmed", "confirmed"]
    manager = [cmds for who, cmds in sent if who == "BusManager"]
    assert manager[0] == [
        la.Control(1, la.ControlAction.ESTOP),
        la.Control(2, la.ControlAction.ESTOP),
    ]


async def test_the_rig_s_pause_asks_the_lease_table(
    sent: list[tuple[str, list[Command[object]]]],
) -> None:
    async with sim_bus([LAModel(1), LAModel(2)], pacing="prompt") as (bus, _):
        await _pause_all(bus, (1, 2))
    assert ("rig", [pause(1), pause(2)]) in sent


async def test_the_table_defines_every_family_s_safe_action() -> None:
    async with sim_bus([LAModel(1)], pacing="prompt") as (bus, _):
        keeper = bus.lease_keeper
        assert keeper.safe_commands("la:1", "estop") == (la.Control(1, la.ControlAction.ESTOP),)
        assert keeper.safe_commands("la:1", "hold") == ()
        with pytest.raises(LocalProtocolError, match="carries la") as err:
            keeper.safe_commands("quad_stepper")
        assert err.value.field == "key"
        with pytest.raises(LocalProtocolError, match="action"):
            keeper.safe_commands("la:1", "brake")
        # The guard process sends what the table publishes, frame for frame.
        lease = bus.lease(["la:1"], owner="me", safe_action="estop")
        (device,) = _devices(bus.leases)
        assert device.safe_frames == tuple(
            c.encode() for c in keeper.safe_commands("la:1", "estop")
        )
        await lease.release(hold=True)


async def test_the_steppers_safe_actions_are_the_table_s_too() -> None:
    from motorbus.protocol.base import Family
    from motorbus.sim.quad_stepper import QuadStepperModel

    async with sim_bus([QuadStepperModel()], pacing="prompt") as (bus, _):
        assert bus.families == frozenset({Family.QUAD_STEPPER})
        assert bus.lease_keeper.safe_commands("quad_stepper") == (q.StopAll(),)
    keeper = LeaseKeeper(
        "x", frozenset({Family.PROJECT_STEPPER}), "pause", _no_request, lambda: "open"
    )
    assert keeper.safe_commands("project_stepper", motor=0x02) == (
        ps.StopProject(),
        ps.ManualStop(motor=0x02),
    )


def _quad_keeper(request: object, state: str = "open") -> tuple[LeaseKeeper, list[Command[object]]]:
    from motorbus.protocol.base import Family

    sent: list[Command[object]] = []

    async def recorded(cmd: Command[object], **kwargs: object) -> object:
        sent.append(cmd)
        return await request(cmd)  # type: ignore[operator]

    keeper = LeaseKeeper("x", frozenset({Family.QUAD_STEPPER}), "pause", recorded, lambda: state)
    return keeper, sent


async def test_an_ending_s_stop_falls_back_to_stop_all_when_the_motor_s_stop_fails() -> None:
    async def stop_fails(cmd: Command[object]) -> object:
        if isinstance(cmd, q.Stop):
            raise ReplyTimeoutError("no answer")
        return None

    keeper, sent = _quad_keeper(stop_fails)
    tried = await keeper.stop_shielded((q.Stop(2),), (q.StopAll(),), who="test")
    assert [type(c).__name__ for c in sent] == ["Stop", "StopAll"]
    assert len(tried) == 2 and tried[1] == [None]


async def test_an_ending_s_stop_is_owed_while_the_port_is_lost() -> None:
    keeper, sent = _quad_keeper(_no_request, state="lost")
    tried = await keeper.stop_shielded((q.Stop(2),), (q.StopAll(),), who="test")
    assert sent == [] and keeper.owed == [q.Stop(2)]  # sent the moment the port is back
    [[owed]] = tried
    assert isinstance(owed, BusClosedError) and "owed" in str(owed)


async def test_an_ending_s_stop_runs_to_its_end_when_cancelled_and_then_says_so() -> None:
    release = asyncio.Event()

    async def slow(cmd: Command[object]) -> object:
        await release.wait()
        return None

    keeper, sent = _quad_keeper(slow)
    task = asyncio.create_task(keeper.stop_shielded((q.Stop(2),), (q.StopAll(),), who="t"))
    await asyncio.sleep(0)
    await asyncio.sleep(0)
    task.cancel()
    await asyncio.sleep(0)
    task.cancel()  # twice
    await asyncio.sleep(0)
    assert not task.done()
    release.set()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert sent == [q.Stop(2)]  # sent, and no stop all needed


async def _no_request(cmd: Command[object], **kwargs: object) -> object:
    raise AssertionError("nothing is sent here")


# -- nothing else sends a safe stop ------------------------------------------------------


def _calls(path: Path) -> Iterator[ast.Call]:
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Call):
            yield node


def test_no_module_but_the_lease_table_sends_safe_stops() -> None:
    table = SRC / "bus" / "lease_shell.py"
    bad = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).as_posix()
        if path == table or rel.startswith(("protocol/", "sim/")):
            continue
        for call in _calls(path):
            text = ast.unparse(call)
            func = ast.unparse(call.func)
            # The table's private sender, or a stop frame built by hand.
            if func.endswith("send_together"):
                bad.append(f"{rel}: {text}")
            if func.endswith("Control") and (
                "ControlAction.PAUSE" in text or "ControlAction.ESTOP" in text
            ):
                bad.append(f"{rel}: {text}")
            # The safe actions' definition, read anywhere but in the devices' "as
            # values" methods (InspireLA.safe_stop_commands ...).
            if func.endswith("safety.safe_stop_commands") and not rel.startswith("devices/"):
                bad.append(f"{rel}: {text}")
    assert bad == []


#: Where ``bus.lease_keeper`` is a local bus's ``LeaseKeeper`` only: the bus itself, and
#: the local streamer (a served bus's ``Streamer(bus)`` is its own, ``served_streamer``).
LOCAL_ONLY = ("bus/", "streams.py")


def _lease_keeper_uses(path: Path) -> Iterator[str]:
    """The names read off ``<something>.lease_keeper`` in ``path``, and off a local
    ``keeper`` (``keeper = self.bus.lease_keeper``)."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(node, ast.Attribute):
            continue
        owner = node.value
        if (isinstance(owner, ast.Attribute) and owner.attr == "lease_keeper") or (
            isinstance(owner, ast.Name) and owner.id == "keeper"
        ):
            yield node.attr


def test_what_the_devices_and_tools_ask_of_the_sender_a_served_bus_has_too() -> None:
    # A served bus's sender of safe actions is a SafeStopper, not a LeaseKeeper: a
    # device that asked the local keeper for more (stop_shielded, once) raised
    # AttributeError on a served bus instead of stopping the motion.
    missing = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).as_posix()
        if rel.startswith(LOCAL_ONLY):
            continue
        for name in _lease_keeper_uses(path):
            if not hasattr(SafeStopper, name):
                missing.append(f"{rel}: lease_keeper.{name}")
    assert missing == []
    assert list(_lease_keeper_uses(SRC / "devices" / "quad_stepper.py"))  # it sees them


#: Stop frames of the steppers (and the upload's clear), by constructor name.
STEPPER_STOPS = ("StopProject", "ManualStop", "Stop", "StopAll", "ClearProject")
#: The methods that send one as the user's own command (``motorbus project stop``,
#: ``QuadStepper.stop``): not an ending, so not the lease table's.
USER_COMMANDS = {
    ("devices/project_stepper.py", "stop_project"),
    ("devices/project_stepper.py", "stop"),
    ("devices/project_stepper.py", "clear_project"),
    ("devices/quad_stepper.py", "stop"),
    ("devices/quad_stepper.py", "stop_all"),
}


def _stepper_stops_sent(path: Path, rel: str) -> Iterator[str]:
    """``x.request(<a stepper stop>(...))`` or ``x.submit(...)`` calls outside the
    user-command methods."""
    for func in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if not isinstance(func, ast.AsyncFunctionDef | ast.FunctionDef):
            continue
        if (rel, func.name) in USER_COMMANDS:
            continue
        for call in ast.walk(func):
            if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute)):
                continue
            if (rel, call.func.attr) in USER_COMMANDS and ast.unparse(call.func.value) == "self":
                # A user's stop command, called from an ending: the keeper's job.
                yield f"{rel}:{func.name}: {ast.unparse(call)}"
                continue
            if call.func.attr not in ("request", "submit", "send", "prepare") or not call.args:
                continue
            first = call.args[0]
            if isinstance(first, ast.Call) and ast.unparse(first.func).endswith(STEPPER_STOPS):
                yield f"{rel}:{func.name}: {ast.unparse(call)}"


def test_no_ending_sends_a_stepper_stop_of_its_own() -> None:
    # Issue 40: the run stops of both steppers and the upload's clear go through the
    # lease keeper; only the user's own stop commands send them directly.
    bad = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).as_posix()
        if rel.startswith(("protocol/", "sim/")) or rel == "bus/lease_shell.py":
            continue
        bad.extend(_stepper_stops_sent(path, rel))
    assert bad == []


def test_the_stepper_check_sees_a_stop_sent_from_an_ending(tmp_path: Path) -> None:
    sample = tmp_path / "sample.py"
    sample.write_text(
        "async def _stop_after(self):\n"
        "    await self.bus.request(ps.StopProject(), priority=Priority.EMERGENCY)\n"
        "async def stop_project(self):\n"
        "    await self.bus.request(ps.StopProject())\n"
        "async def _abandon(self):\n"
        "    await self.stop_project()\n",
        encoding="utf-8",
    )
    found = list(_stepper_stops_sent(sample, "devices/project_stepper.py"))
    assert [f.split(": ")[0] for f in found] == [
        "devices/project_stepper.py:_stop_after",
        "devices/project_stepper.py:_abandon",
    ]


def test_the_source_check_sees_a_hand_built_stop(tmp_path: Path) -> None:
    sample = tmp_path / "sample.py"
    sample.write_text(
        "la.Control(1, la.ControlAction.PAUSE)\nsend_together(bus.request, [])\n",
        encoding="utf-8",
    )
    funcs = [ast.unparse(c.func) for c in _calls(sample)]
    assert "la.Control" in funcs and "send_together" in funcs


async def test_a_cancellation_that_comes_as_the_stop_ends_is_still_delivered() -> None:
    from motorbus.bus.lease_shell import finish_shielded

    fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
    task = asyncio.create_task(finish_shielded(fut))
    await asyncio.sleep(0)
    fut.set_result(None)  # the stop ends, and in the same loop step the caller is cancelled
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
