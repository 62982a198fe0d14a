"""SimBus: wire timing, half duplex, unsolicited output, routing; MemorySim on the loop."""

from __future__ import annotations

import asyncio
import random
from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motorbus.protocol.base import Family, sum8
from motorbus.sim.bus import SimBus
from motorbus.sim.faults import FaultConfig
from motorbus.sim.memory import MemorySim
from motorbus.sim.model import DeviceModel
from motorbus.sim.timing import BITS_PER_BYTE, wire_time

BAUD = 921600
BYTE = BITS_PER_BYTE / BAUD
TURNAROUND = 100e-6


def la_request(dev: int, sub: int = 0x22) -> bytes:
    """An LA CMD_MC request (8 bytes), e.g. the status query 55 AA 03 01 04 00 22 2A."""
    body = bytes([0x03, dev, 0x04, 0x00, sub])
    return b"\x55\xaa" + body + bytes([sum8(body)])


def la_reply(dev: int, payload: bytes = b"\x00") -> bytes:
    body = bytes([len(payload) + 2, dev, 0x04, 0x00]) + payload
    return b"\xaa\x55" + body + bytes([sum8(body)])


class FakeLA(DeviceModel):
    """Answers requests addressed to its ID with a reply of ``reply_len`` payload bytes."""

    family = Family.LA

    def __init__(self, dev: int, *, payload_len: int = 1) -> None:
        self.dev = dev
        self.payload_len = payload_len
        self.heard: list[tuple[float, bytes]] = []

    def handle(self, request: bytes, now: float) -> list[bytes]:
        self.heard.append((now, request))
        if request[3] != self.dev:
            return []
        return [la_reply(self.dev, bytes(self.payload_len))]

    def turnaround(self, rng: random.Random) -> float:
        return TURNAROUND


class Ticker(FakeLA):
    """Sends an unsolicited frame at each time in ``events``."""

    def __init__(self, dev: int, events: list[float]) -> None:
        super().__init__(dev)
        self.events = sorted(events)
        self.polled: list[float] = []

    def poll(self, now: float) -> list[bytes]:
        self.polled.append(now)
        out = []
        while self.events and self.events[0] <= now:
            self.events.pop(0)
            out.append(la_reply(self.dev, b"\xee"))
        return out

    def next_event_time(self) -> float | None:
        return self.events[0] if self.events else None


class Stuck(FakeLA):
    """A broken model: always claims an event in the past, never produces one."""

    def next_event_time(self) -> float | None:
        return 0.0


REQ1 = la_request(1)
ACK1 = la_reply(1)


def test_wire_time_matches_the_protocol_digest_table() -> None:
    assert wire_time(22, 921600) == pytest.approx(238.7e-6, abs=1e-7)
    assert wire_time(11, 9600) == pytest.approx(11.458e-3, abs=1e-6)
    assert wire_time(0, 9600) == 0.0


@pytest.mark.parametrize("bad", [0, -1, 9600.0, True])
def test_wire_time_refuses_a_bad_baud(bad: object) -> None:
    with pytest.raises(ValueError, match="baud"):
        wire_time(1, bad)  # type: ignore[arg-type]


def test_reply_is_delivered_after_request_wire_time_turnaround_and_reply_wire_time() -> None:
    model = FakeLA(1)
    bus = SimBus([model], baud=BAUD)
    bus.receive(REQ1, 1.0)
    end_of_request = 1.0 + 8 * BYTE
    due = end_of_request + TURNAROUND + len(ACK1) * BYTE
    assert model.heard == [(end_of_request, REQ1)]
    assert bus.next_wakeup() == due
    assert bus.due_output(due - 1e-9) == []
    assert bus.due_output(due) == [ACK1]
    assert bus.next_wakeup() is None
    assert (bus.stats.requests, bus.stats.replies, bus.stats.bytes_out) == (1, 1, 8)


def test_requests_in_one_chunk_end_at_their_own_last_byte() -> None:
    one, two = FakeLA(1), FakeLA(2)
    bus = SimBus([one, two], baud=BAUD)
    bus.receive(REQ1 + la_request(2), 0.0)
    assert [t for t, _ in one.heard] == [8 * BYTE, 16 * BYTE]
    # Replies share the line toward the host: the second waits for the first.
    first_due = 8 * BYTE + TURNAROUND + 8 * BYTE
    second_due = max(16 * BYTE + TURNAROUND, first_due) + 8 * BYTE
    assert bus.next_wakeup() == first_due
    assert bus.due_output(first_due) == [ACK1]
    assert bus.due_output(second_due) == [la_reply(2)]


def test_host_bytes_queue_behind_bytes_still_on_the_wire() -> None:
    model = FakeLA(1)
    bus = SimBus([model], baud=BAUD)
    bus.receive(REQ1[:4], 0.0)
    bus.receive(REQ1[4:], 0.0)  # written at once: sent back to back
    assert model.heard == [(8 * BYTE, REQ1)]


def test_garbage_before_a_request_is_discarded_and_counted() -> None:
    log: list[dict[str, object]] = []
    model = FakeLA(1)
    bus = SimBus([model], baud=BAUD, log=log.append)
    bus.receive(b"\x00\x13" + REQ1, 0.0)
    assert bus.stats.discarded_bytes == 2
    assert model.heard == [(10 * BYTE, REQ1)]
    assert log[0] == {
        "t": 2 * BYTE,
        "dir": "rx",
        "hex": "00 13",
        "family": None,
        "fault": "discarded: garbage",
    }
    assert log[1] == {
        "t": 10 * BYTE,
        "dir": "rx",
        "hex": "55 AA 03 01 04 00 22 2A",
        "family": "la",
        "fault": None,
    }


def test_every_model_of_the_family_hears_every_request() -> None:
    models = [FakeLA(i) for i in (1, 2, 3)]
    bus = SimBus(models, baud=BAUD)
    bus.receive(la_request(2), 0.0)
    assert [len(m.heard) for m in models] == [1, 1, 1]
    assert bus.due_output(1.0) == [la_reply(2)]


def test_a_device_that_is_transmitting_does_not_hear_a_request() -> None:
    log: list[dict[str, object]] = []
    model = FakeLA(1, payload_len=100)  # a 107-byte reply: long on the wire
    bus = SimBus([model], baud=BAUD, log=log.append)
    bus.receive(REQ1, 0.0)
    reply_start = 8 * BYTE + TURNAROUND
    # Sent so that it is on the wire while the reply is: not heard.
    bus.receive(REQ1, reply_start)
    assert len(model.heard) == 1
    assert bus.stats.ignored_while_transmitting == 1
    assert log[-1]["fault"] == "half_duplex"
    assert bus.due_output(1.0) == [la_reply(1, bytes(100))]


def test_a_request_during_the_turnaround_is_heard() -> None:
    model = FakeLA(1)
    bus = SimBus([model], baud=BAUD)
    bus.receive(REQ1, 0.0)
    bus.receive(b"", 0.0)
    # Ends before the first reply starts (8 bytes + 100 us turnaround): heard.
    bus.receive(REQ1[:0] + la_request(2), 8 * BYTE)
    assert len(model.heard) == 2
    assert bus.stats.ignored_while_transmitting == 0


def test_unsolicited_output_is_delivered_after_its_wire_time_in_time_order() -> None:
    a = Ticker(1, [0.010, 0.030])
    b = Ticker(2, [0.020])
    bus = SimBus([a, b], baud=BAUD)
    frame_time = len(la_reply(1, b"\xee")) * BYTE
    assert bus.next_wakeup() == 0.010
    assert bus.due_output(0.010) == []
    assert bus.next_wakeup() == 0.010 + frame_time
    out = bus.due_output(0.050)
    assert out == [la_reply(1, b"\xee"), la_reply(2, b"\xee"), la_reply(1, b"\xee")]
    assert a.polled == [0.010, 0.030] and b.polled == [0.020]
    assert bus.stats.unsolicited == 3
    assert bus.next_wakeup() is None


def test_unsolicited_output_due_before_a_request_goes_first() -> None:
    ticker = Ticker(2, [0.0])
    bus = SimBus([FakeLA(1), ticker], baud=BAUD)
    bus.receive(REQ1, 0.0)
    assert bus.due_output(1.0) == [la_reply(2, b"\xee"), ACK1]
    # The ticker was transmitting while the request was on the wire.
    assert ticker.heard == []
    assert bus.stats.ignored_while_transmitting == 1


def test_a_stuck_model_does_not_hang_the_core() -> None:
    bus = SimBus([Stuck(1)], baud=BAUD)
    assert bus.due_output(5.0) == []
    wake = bus.next_wakeup()
    assert wake is not None and wake > 5.0 - 1e-9


def test_models_of_another_family_are_not_asked() -> None:
    class Stepper(FakeLA):
        family = Family.QUAD_STEPPER

    stepper = Stepper(1)
    bus = SimBus([FakeLA(1), stepper], baud=BAUD)
    bus.receive(REQ1, 0.0)
    assert stepper.heard == []


@settings(max_examples=60)
@given(st.lists(st.integers(min_value=1, max_value=23), max_size=12), st.integers(0, 2**16))
def test_how_the_host_bytes_are_split_does_not_change_the_outcome(
    cuts: list[int], seed: int
) -> None:
    stream = b"\x01" + REQ1 + la_request(2) + b"\xaa\x55" + la_request(3)
    points = sorted({c % len(stream) for c in cuts} - {0})

    def run(chunks: list[bytes]) -> tuple[list[bytes], list[tuple[float, bytes]]]:
        models = [FakeLA(i) for i in (1, 2, 3)]
        bus = SimBus(models, baud=BAUD, seed=seed, faults=FaultConfig(garbage_rate=0.5))
        for chunk in chunks:
            bus.receive(chunk, 0.0)
        return bus.due_output(1.0), models[0].heard

    pieces = [stream[a:b] for a, b in zip([0, *points], [*points, len(stream)], strict=True)]
    whole = run([stream])
    split = run(pieces)
    assert split[0] == whole[0]
    assert [r for _, r in split[1]] == [r for _, r in whole[1]]
    for (t1, _), (t2, _) in zip(split[1], whole[1], strict=True):
        assert t1 == pytest.approx(t2, abs=1e-12)


# -- MemorySim ----------------------------------------------------------------------


async def _exchange(sim: MemorySim, request: bytes, expect_len: int) -> bytes:
    got = bytearray()
    done = asyncio.get_running_loop().create_future()

    def on_data(data: bytes) -> None:
        got.extend(data)
        if len(got) >= expect_len and not done.done():
            done.set_result(None)

    def on_lost(exc: BaseException | None) -> None:
        if not done.done():
            done.set_exception(ConnectionError(exc))

    await sim.transport.open(on_data, on_lost)
    try:
        sim.transport.write(request)
        await asyncio.wait_for(done, 5.0)
    finally:
        await sim.transport.close()
    return bytes(got)


@pytest.mark.parametrize("delivery", ["whole", "bytewise", "random"])
async def test_memory_sim_answers_over_every_delivery_mode(delivery: str) -> None:
    async with MemorySim.start([FakeLA(1), FakeLA(2)], delivery=delivery) as sim:  # type: ignore[arg-type]
        assert sim.bus.baud == 921600
        assert await _exchange(sim, la_request(2), 8) == la_reply(2)
        assert sim.bus.stats.requests == 1
        assert [len(m.heard) for m in sim.models if isinstance(m, FakeLA)] == [1, 1]


class ManualTimer:
    """A clock the test moves by hand: deterministic, no waiting."""

    class Handle:
        def __init__(self) -> None:
            self.cancelled = False

        def cancel(self) -> None:
            self.cancelled = True

    def __init__(self) -> None:
        self.t = 0.0
        self.calls: list[tuple[float, ManualTimer.Handle, Callable[[], None]]] = []

    def now(self) -> float:
        return self.t

    def call_at(self, deadline: float, callback: Callable[[], None]) -> ManualTimer.Handle:
        handle = ManualTimer.Handle()
        self.calls.append((deadline, handle, callback))
        return handle

    def advance(self, t: float) -> None:
        self.t = t
        while True:
            due = [c for c in self.calls if c[0] <= t and not c[1].cancelled]
            if not due:
                return
            self.calls.remove(due[0])
            due[0][2]()


async def test_memory_sim_disconnect_fault_unplugs_and_plugs_the_peer() -> None:
    timer = ManualTimer()
    faults = FaultConfig(disconnect_after_s=1.0, reconnect_after_s=0.5, disconnect_count=1)
    async with MemorySim.start([FakeLA(1)], faults=faults, timer=timer) as sim:
        lost = asyncio.get_running_loop().create_future()
        await sim.transport.open(lambda d: None, lost.set_result)
        timer.advance(1.0)
        assert not sim.peer.connected
        assert isinstance(await asyncio.wait_for(lost, 5.0), ConnectionError)
        timer.advance(1.5)
        assert sim.peer.connected
        assert sim.bus.stats.faults_injected["disconnect"] == 1
        got: list[bytes] = []
        await sim.transport.open(got.append, lambda exc: None)
        sim.transport.write(REQ1)
        await asyncio.sleep(0)  # let call_soon hand the bytes to the simulator
        timer.advance(2.0)
        await asyncio.sleep(0)  # and the reply to the host
        assert b"".join(got) == ACK1
        await sim.transport.close()


async def test_memory_sim_uses_a_given_timer() -> None:
    loop = asyncio.get_running_loop()
    calls: list[float] = []

    class Timer:
        def now(self) -> float:
            return loop.time()

        def call_at(self, deadline: float, callback: object) -> asyncio.TimerHandle:
            calls.append(deadline)
            return loop.call_at(deadline, callback)  # type: ignore[arg-type]

    class SlowLA(FakeLA):  # a reply due well after the request: it waits for a timer
        def turnaround(self, rng: random.Random) -> float:
            return 0.05

    async with MemorySim.start([SlowLA(1)], timer=Timer()) as sim:
        assert await _exchange(sim, REQ1, 8) == ACK1
    assert calls, "the simulator never scheduled through the given timer"


# -- the real device models ------------------------------------------------------------

STEPPER_BYTE = BITS_PER_BYTE / 9600


def test_real_la_model_answers_a_status_query_within_its_turnaround_range() -> None:
    from motorbus.sim.la import LAModel

    log: list[dict[str, object]] = []
    bus = SimBus([LAModel(id=i) for i in (1, 2, 3)], baud=BAUD, log=log.append)
    bus.receive(la_request(2), 0.0)
    (reply,) = bus.due_output(1.0)
    assert reply[:4] == bytes.fromhex("AA 55 11 02") and len(reply) == 22
    due = log[-1]["t"]
    assert isinstance(due, float)
    earliest = 8 * BYTE + 120e-6 + 22 * BYTE  # doc 002 C.6: 120 us typical, 800 us max
    assert earliest - 1e-12 <= due <= earliest + (800e-6 - 120e-6) + 1e-12


def test_real_quad_stepper_led_ack_then_done_reply_share_the_line() -> None:
    from motorbus.sim.quad_stepper import QuadStepperModel

    log: list[dict[str, object]] = []
    model = QuadStepperModel(turnaround_s=1e-3, led_delay_s=5e-3)
    bus = SimBus([model], baud=9600, log=log.append)
    bus.receive(bytes.fromhex("FF AA 00 0C 01 01 00 00 B7"), 0.0)  # LED1 on
    ack_due = 9 * STEPPER_BYTE + 1e-3 + 6 * STEPPER_BYTE
    assert bus.next_wakeup() == pytest.approx(9 * STEPPER_BYTE + 5e-3)  # the model's event
    assert bus.due_output(1.0) == [
        bytes.fromhex("FF AA 00 0C 01 00"),
        bytes.fromhex("FF AA 00 0C 01 01"),
    ]
    tx = [r["t"] for r in log if r["dir"] == "tx"]
    # The done reply became due at 5 ms but waits for the ack to leave the line.
    assert tx == pytest.approx([ack_due, ack_due + 6 * STEPPER_BYTE])
    assert bus.stats.unsolicited == 1


def test_real_project_stepper_sends_ee_dd_after_the_start_ack() -> None:
    from motorbus.sim.project_stepper import ProjectStepperModel

    bus = SimBus([ProjectStepperModel()], baud=9600)
    bus.receive(bytes.fromhex("FF AA 6E 01 01 00 00 00 00 00 19"), 0.0)
    bus.receive(bytes.fromhex("FF AA 4E 01 00 00 00 00 00 00 F8"), 0.1)
    assert bus.due_output(10.0) == [
        bytes.fromhex("FF AA 6E 01 00 00"),
        bytes.fromhex("FF AA 4E 01 00 00"),
        bytes.fromhex("EE DD"),
    ]


async def test_memory_sim_with_fifteen_real_actuators_over_random_splits() -> None:
    from motorbus.sim.la import LAModel

    models = [LAModel(id=i) for i in range(1, 16)]
    async with MemorySim.start(models, delivery="random", seed=3) as sim:
        for dev in (1, 8, 15):
            reply = await _exchange(sim, la_request(dev), 22)
            assert reply[:4] == bytes([0xAA, 0x55, 0x11, dev])
        assert sim.bus.stats.requests == 3
