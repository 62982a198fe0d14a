"""``pacing="prompt"``: no wire time, turnaround 0; half duplex and faults still apply.

Everywhere a simulator is hosted takes the option: ``SimBus``, ``MemorySim.start``,
``PtySim``, ``SimProcess`` and ``motorbus sim --pacing prompt`` (or ``--prompt``).
"""

from __future__ import annotations

import argparse
import asyncio

import pytest
import serial

from motorbus.cli import sim as sim_cli
from motorbus.errors import LocalProtocolError
from motorbus.sim.bus import PACING_MODES, SimBus
from motorbus.sim.faults import FaultConfig
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from motorbus.sim.process import SimProcess
from motorbus.sim.pty import PtySim
from motorbus.sim.quad_stepper import QuadStepperModel
from tests.sim.test_bus import ACK1, BAUD, BYTE, REQ1, TURNAROUND, FakeLA, Ticker, la_reply
from tests.sim.test_bus import la_request as la_req

READ_TIMEOUT_S = 5.0  # an upper bound for a failing test, never a timing assertion


def test_pacing_modes_and_default() -> None:
    assert PACING_MODES == ("wire", "prompt")
    assert SimBus([FakeLA(1)], baud=BAUD).pacing == "wire"


@pytest.mark.parametrize("bad", ["fast", "", None, 1, "Prompt"])
def test_a_bad_pacing_is_refused_naming_the_field_and_choices(bad: object) -> None:
    with pytest.raises(LocalProtocolError, match=r"pacing=.*'wire'.*'prompt'") as info:
        SimBus([FakeLA(1)], baud=BAUD, pacing=bad)  # type: ignore[arg-type]
    assert info.value.field == "pacing"


def test_prompt_still_checks_the_baud() -> None:
    with pytest.raises(LocalProtocolError, match="baud"):
        SimBus([FakeLA(1)], baud=0, pacing="prompt")


def test_prompt_reply_is_due_the_moment_the_request_is_complete() -> None:
    model = FakeLA(1)
    bus = SimBus([model], baud=BAUD, pacing="prompt")
    bus.receive(REQ1, 1.0)
    assert model.heard == [(1.0, REQ1)]  # no request wire time
    assert bus.next_wakeup() == 1.0  # no turnaround, no reply wire time
    assert bus.due_output(1.0) == [ACK1]
    assert bus.next_wakeup() is None
    # The same exchange paced: the reply is due after both wire times and the turnaround.
    paced = SimBus([FakeLA(1)], baud=BAUD)
    paced.receive(REQ1, 1.0)
    assert paced.next_wakeup() == pytest.approx(1.0 + 8 * BYTE + TURNAROUND + 8 * BYTE)


def test_prompt_split_request_completes_with_its_last_chunk() -> None:
    model = FakeLA(1)
    bus = SimBus([model], baud=BAUD, pacing="prompt")
    bus.receive(REQ1[:3], 2.0)
    assert bus.due_output(2.5) == [] and model.heard == []
    bus.receive(REQ1[3:], 3.0)
    assert model.heard == [(3.0, REQ1)]
    assert bus.due_output(3.0) == [ACK1]


def test_prompt_replies_of_several_devices_keep_their_order() -> None:
    one, two = FakeLA(1), FakeLA(2)
    bus = SimBus([one, two], baud=BAUD, pacing="prompt")
    bus.receive(REQ1 + la_req(2), 0.0)
    # One answers the first request at 0.0, the instant the second one arrives: it
    # misses the second (half duplex, counted); two hears both and answers its own.
    assert one.heard == [(0.0, REQ1)]
    assert [r for _, r in two.heard] == [REQ1, la_req(2)]
    assert bus.stats.ignored_while_transmitting == 1
    assert bus.due_output(0.0) == [ACK1, la_reply(2)]


def test_prompt_unsolicited_output_is_due_at_its_event_time() -> None:
    ticker = Ticker(1, [0.010, 0.020])
    bus = SimBus([ticker], baud=BAUD, pacing="prompt")
    assert bus.next_wakeup() == 0.010
    assert bus.due_output(0.010) == [la_reply(1, b"\xee")]
    assert bus.next_wakeup() == 0.020
    assert bus.due_output(0.030) == [la_reply(1, b"\xee")]


def test_prompt_half_duplex_a_request_at_the_instant_of_output_is_missed() -> None:
    """A prompt transmission lasts an instant: a request arriving then is not heard."""
    log: list[dict[str, object]] = []
    ticker = Ticker(1, [0.5])
    bus = SimBus([ticker], baud=BAUD, pacing="prompt", log=log.append)
    bus.receive(REQ1, 0.5)  # the ticker's output goes out at 0.5 too
    assert ticker.heard == []
    assert bus.stats.ignored_while_transmitting == 1
    assert log[-1]["fault"] == "half_duplex"
    bus.receive(REQ1, 0.5 + 1e-6)  # an instant later the device listens again
    assert len(ticker.heard) == 1
    assert bus.due_output(1.0) == [la_reply(1, b"\xee"), ACK1]


def test_prompt_late_fault_delays_by_its_extra_delay_only() -> None:
    faults = FaultConfig(late_reply_rate=1.0, late_reply_delay_s=0.05)
    bus = SimBus([FakeLA(1)], baud=BAUD, faults=faults, pacing="prompt")
    bus.receive(REQ1, 1.0)
    assert bus.next_wakeup() == pytest.approx(1.05)
    assert bus.due_output(1.05 - 1e-6) == []
    assert bus.due_output(1.05) == [ACK1]
    assert bus.stats.faults_injected["late"] == 1


def test_prompt_late_device_is_deaf_only_at_its_late_instant() -> None:
    faults = FaultConfig(late_reply_rate=1.0, late_reply_delay_s=0.05)
    model = FakeLA(1)
    bus = SimBus([model], baud=BAUD, faults=faults, pacing="prompt")
    bus.receive(REQ1, 1.0)
    bus.receive(la_req(2), 1.02)  # during the delay: the late device is not talking yet
    assert len(model.heard) == 2 and bus.stats.ignored_while_transmitting == 0
    bus.receive(la_req(2), 1.05)  # while its late reply goes out
    assert len(model.heard) == 2 and bus.stats.ignored_while_transmitting == 1


@pytest.mark.parametrize(
    ("faults", "kind"),
    [
        (FaultConfig(duplicate_reply_rate=1.0), "duplicate"),
        (FaultConfig(garbage_rate=1.0), "garbage"),
        (FaultConfig(silent=True), "silent"),
        (FaultConfig(bit_flip_rate=1.0), "flip"),
    ],
)
def test_prompt_faults_apply(faults: FaultConfig, kind: str) -> None:
    bus = SimBus([FakeLA(1)], baud=BAUD, faults=faults, pacing="prompt")
    bus.receive(REQ1, 0.0)
    out = b"".join(bus.due_output(0.0))
    assert bus.stats.faults_injected[kind] >= 1
    if kind == "duplicate":
        assert out == ACK1 + ACK1
    elif kind == "silent":
        assert out == b""
    else:
        assert out != ACK1 and len(out) >= len(ACK1)


def test_prompt_disconnect_follows_the_schedule() -> None:
    faults = FaultConfig(disconnect_after_s=0.1, reconnect_after_s=0.05, disconnect_count=1)
    bus = SimBus([FakeLA(1)], baud=BAUD, faults=faults, pacing="prompt")
    assert bus.next_wakeup() == pytest.approx(0.1)
    assert [e.value for e in bus.link_events(0.12)] == ["down"]
    bus.receive(REQ1, 0.12)
    assert bus.due_output(0.12) == [] and bus.stats.lost_while_down == len(REQ1)
    assert [e.value for e in bus.link_events(0.2)] == ["up"]
    bus.receive(REQ1, 0.2)
    assert bus.due_output(0.2) == [ACK1]


def test_prompt_quad_ack_then_done_reply() -> None:
    """A real model: the LED ack at once, the "done" reply at the model's own time."""
    model = QuadStepperModel()
    bus = SimBus([model], baud=9600, pacing="prompt")
    request = bytes.fromhex("FF AA 00 0C 03 01 00 00 B9")
    bus.receive(request, 0.0)
    assert bus.due_output(0.0) == [bytes.fromhex("FF AA 00 0C 03 00")]
    done = bus.next_wakeup()
    assert done is not None and done > 0.0
    assert bus.due_output(done) == [bytes.fromhex("FF AA 00 0C 03 01")]


async def test_memory_sim_prompt_answers_without_a_timer() -> None:
    """Prompt output is written from inside the host's write delivery: no timer armed."""
    async with MemorySim.start([FakeLA(1)], pacing="prompt") as sim:  # type: ignore[list-item]
        assert sim.bus.pacing == "prompt"
        got = bytearray()
        done = asyncio.get_running_loop().create_future()

        def on_data(data: bytes) -> None:
            got.extend(data)
            if len(got) >= len(ACK1) and not done.done():
                done.set_result(None)

        await sim.transport.open(on_data, lambda exc: None)
        try:
            sim.transport.write(REQ1)
            await asyncio.wait_for(done, READ_TIMEOUT_S)
            assert bytes(got) == ACK1
            assert sim._handle is None  # nothing was scheduled for later
        finally:
            await sim.transport.close()


async def test_memory_sim_refuses_a_bad_pacing_before_serving() -> None:
    with pytest.raises(LocalProtocolError, match="pacing"):
        async with MemorySim.start([FakeLA(1)], pacing="slow"):  # type: ignore[arg-type, list-item]
            pass


def test_pty_sim_prompt_answers_over_a_real_pty() -> None:
    query = bytes.fromhex("55 AA 03 01 04 00 22 2A")
    with (
        PtySim([LAModel(id=1)], pacing="prompt") as sim,
        serial.Serial(sim.path, baudrate=921600, timeout=READ_TIMEOUT_S) as port,
    ):
        assert sim.bus.pacing == "prompt"
        port.write(query)
        reply = port.read(22)
        assert reply[:4] == bytes.fromhex("AA 55 11 01") and len(reply) == 22
    assert sim.error is None and sim.bus.stats.replies == 1


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    sim_cli.add_arguments(parser)
    return parser.parse_args(argv)


def test_cli_pacing_option_and_prompt_shorthand(capsys: pytest.CaptureFixture[str]) -> None:
    assert _parse(["la"]).pacing == "wire"
    assert _parse(["--pacing", "prompt", "la"]).pacing == "prompt"
    assert _parse(["--prompt", "la"]).pacing == "prompt"
    assert _parse(["--pacing", "wire", "la"]).pacing == "wire"
    with pytest.raises(SystemExit):
        _parse(["--pacing", "fast", "la"])
    assert "invalid choice: 'fast'" in capsys.readouterr().err


def test_sim_process_passes_pacing_and_refuses_a_bad_one() -> None:
    assert "--pacing" not in SimProcess(["la"]).args
    args = SimProcess(["la"], pacing="prompt").args
    assert args[args.index("--pacing") + 1] == "prompt"
    with pytest.raises(LocalProtocolError, match="pacing"):
        SimProcess(["la"], pacing="fast")  # type: ignore[arg-type]


def test_sim_process_prompt_child_answers() -> None:
    query = bytes.fromhex("55 AA 03 01 04 00 22 2A")
    with SimProcess(["la:1"], pacing="prompt") as sim:
        with serial.Serial(sim.path, baudrate=921600, timeout=READ_TIMEOUT_S) as port:
            port.write(query)
            assert port.read(22)[:4] == bytes.fromhex("AA 55 11 01")
        summary = sim.stop()
    assert "1 requests, 1 replies" in summary
