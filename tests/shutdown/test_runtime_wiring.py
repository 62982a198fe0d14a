"""The process runtime comes with every bus, whoever imports it (issue 40).

The library (bus, devices, streams) never imports ``motorbus.runtime``; it calls the
hooks of ``motorbus.lifecycle``, which ``motorbus``'s package ``__init__`` wires to the
runtime.  A program that imports nothing but the bus's own modules, moves an actuator
and is sent SIGTERM still gets the actuator's safe action before it dies.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

from motorbus import lifecycle
from motorbus.devices.la import InspireLA
from motorbus.protocol import la
from motorbus.sim.la import LAModel, PowerState
from motorbus.sim.process import SimProcess
from tests.helpers import sim_bus
from tests.integration.conftest import SIM_BAUD, SIM_DEVICES, finish, received_frames, start_example

#: Imports the bus's modules only (never ``motorbus.runtime``, never ``motorbus.run``),
#: moves la:2 (the bus's implicit lease) and waits to be killed.
BUS_ONLY_PROGRAM = textwrap.dedent(
    """
    import argparse, asyncio, sys
    from motorbus.bus.bus import Bus
    from motorbus.devices.la import InspireLA
    from motorbus.protocol.base import Family
    from motorbus.transport.serial import open_transport

    def say(when: str) -> None:
        loaded = "motorbus.runtime.hooks" in sys.modules
        print(f"runtime {when}: {loaded}", file=sys.stderr, flush=True)

    async def main(port: str) -> None:
        say("before open")
        async with Bus(open_transport(port, baudrate=921600), families=[Family.LA]) as bus:
            say("after open")
            await InspireLA(bus, 2).move_to(1500, wait=False)
            print("streaming", flush=True)
            await asyncio.sleep(3600)

    p = argparse.ArgumentParser()
    p.add_argument("--port")
    p.add_argument("--baud")
    p.add_argument("--ids")
    asyncio.run(main(p.parse_args().port))
    """
)


def test_a_program_that_only_opens_a_bus_is_stopped_safely_on_sigterm(tmp_path: Path) -> None:
    program = tmp_path / "bus_only.py"
    program.write_text(BUS_ONLY_PROGRAM, encoding="utf-8")
    with SimProcess(SIM_DEVICES, baud=SIM_BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        proc = start_example(sim.path, example=program)
        proc.send_signal(signal.SIGTERM)
        status, out, err = finish(proc)
        frames = received_frames(sim.log_records())
    # Killed by SIGTERM, as the signal would have, after the safe stop.
    assert status == -signal.SIGTERM, (out, err)
    # The program never imported the runtime; opening the bus loaded it.
    assert "runtime before open: False" in err, err
    assert "runtime after open: True" in err, err
    moves = [i for i, f in enumerate(frames) if f[:5] == bytes([0x55, 0xAA, 0x04, 0x02, 0x21])]
    assert moves, frames
    pause = la.Control(2, la.ControlAction.PAUSE).encode()
    assert pause in frames[moves[-1] + 1 :], "no pause to la:2 after its move"


@contextlib.contextmanager
def no_runtime() -> Iterator[None]:
    """No hooks installed and no loader: a library assembled without the runtime."""
    previous = lifecycle.install(None)
    loader = lifecycle._loader
    lifecycle.set_loader(None)
    warned = lifecycle._warned
    lifecycle._warned = False
    try:
        yield
    finally:
        lifecycle.install(previous)
        lifecycle.set_loader(loader)
        lifecycle._warned = warned


async def test_without_a_runtime_the_bus_still_works_and_says_it_is_unprotected(
    caplog: pytest.LogCaptureFixture,
) -> None:
    model = LAModel(2)
    with no_runtime(), caplog.at_level(logging.WARNING, logger="motorbus.lifecycle"):
        async with sim_bus([model], pacing="prompt") as (bus, _):
            await InspireLA(bus, 2).move_to(1500)
            assert model.power_state is PowerState.WORKING
        # The lease's safe action is the bus's own: it goes out at close without a runtime.
        assert model.power_state is PowerState.PAUSED
        assert "motorbus.runtime.hooks" not in _installed_by_now()
    assert [r for r in caplog.records if "no process runtime" in r.getMessage()]


def _installed_by_now() -> str:
    hooks = lifecycle._hooks
    return "" if hooks is None else type(hooks).__module__


async def test_the_hooks_the_runtime_installs_are_what_the_bus_calls() -> None:
    calls: list[tuple[str, object]] = []

    class Recording:
        def bus_opening(self, bus: object) -> None:
            calls.append(("opening", bus))

        def bus_opened(self, bus: object) -> None:
            calls.append(("opened", bus))

        def bus_closed(self, bus: object) -> None:
            calls.append(("closed", bus))

        def deferred_interrupts(self) -> contextlib.AbstractContextManager[None]:
            calls.append(("deferred", None))
            return contextlib.nullcontext()

        def realtime_wanted(self) -> bool:
            return False

        def idle(self, budget_s: float) -> object:
            calls.append(("idle", budget_s))
            return None

    previous = lifecycle.install(Recording())
    try:
        async with sim_bus([LAModel(2)], pacing="prompt") as (bus, _):
            await asyncio.sleep(0)
    finally:
        lifecycle.install(previous)
    assert [c for c in calls if c[0] != "deferred"] == [
        ("opening", bus),
        ("opened", bus),
        ("closed", bus),
    ]
    assert ("deferred", None) in calls  # the close's safe stop runs inside it
