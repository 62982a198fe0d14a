"""Fault injection: parsing, each kind visible in the bytes and stats, reproducibility."""

from __future__ import annotations

import random

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Family, sum8
from motorbus.sim.bus import LinkEvent, SimBus
from motorbus.sim.faults import FaultConfig, FaultInjector
from motorbus.sim.model import DeviceModel

BAUD = 921600


def la_request(dev: int) -> bytes:
    body = bytes([0x03, dev, 0x04, 0x00, 0x22])
    return b"\x55\xaa" + body + bytes([sum8(body)])


REQ = la_request(1)
REPLY = bytes.fromhex("AA 55 11 01 04 00 22 EB 03 DE 03 14 64 00 F4 00 01 08 07 0A 07 94")


class Echo(DeviceModel):
    """Answers every request to ID 1 with the documented 22-byte status frame."""

    family = Family.LA

    def handle(self, request: bytes, now: float) -> list[bytes]:
        return [REPLY] if request[3] == 1 else []

    def turnaround(self, rng: random.Random) -> float:
        return 100e-6


Log = list[dict[str, object]]


def run(
    faults: FaultConfig, *, requests: int = 1, seed: int = 0, period: float = 0.01
) -> tuple[list[bytes], SimBus, Log]:
    """Send ``requests`` status queries ``period`` apart; return (output chunks, bus, log)."""
    log: Log = []
    bus = SimBus([Echo()], baud=BAUD, faults=faults, seed=seed, log=log.append)
    out: list[bytes] = []
    for k in range(requests):
        t = k * period
        out += bus.due_output(t)
        bus.receive(REQ, t)
    out += bus.due_output(requests * period + 1.0)
    return out, bus, log


# -- parsing ------------------------------------------------------------------------

PARSE_TABLE = [
    ("", FaultConfig()),
    ("drop=0.01", FaultConfig(drop_byte_rate=0.01)),
    ("flip=0.001", FaultConfig(bit_flip_rate=0.001)),
    ("garbage=0.02", FaultConfig(garbage_rate=0.02)),
    ("late=0.01", FaultConfig(late_reply_rate=0.01)),
    ("late=0.01:0.05", FaultConfig(late_reply_rate=0.01, late_reply_delay_s=0.05)),
    ("dup=0.01", FaultConfig(duplicate_reply_rate=0.01)),
    ("duplicate=0.5", FaultConfig(duplicate_reply_rate=0.5)),
    ("silent", FaultConfig(silent=True)),
    ("silent=2:3,silent=10:11", FaultConfig(silent_windows=((2.0, 3.0), (10.0, 11.0)))),
    ("disconnect=5", FaultConfig(disconnect_after_s=5.0)),
    ("disconnect=5:1", FaultConfig(disconnect_after_s=5.0, reconnect_after_s=1.0)),
    (
        "disconnect=5:1:2",
        FaultConfig(disconnect_after_s=5.0, reconnect_after_s=1.0, disconnect_count=2),
    ),
    (
        "drop=0.01,flip=0.001,garbage=0.02,late=0.01:0.05,dup=0.01,silent,disconnect=5:1",
        FaultConfig(
            drop_byte_rate=0.01,
            bit_flip_rate=0.001,
            garbage_rate=0.02,
            late_reply_rate=0.01,
            late_reply_delay_s=0.05,
            duplicate_reply_rate=0.01,
            silent=True,
            disconnect_after_s=5.0,
            reconnect_after_s=1.0,
        ),
    ),
]


@pytest.mark.parametrize(("spec", "expected"), PARSE_TABLE)
def test_parse(spec: str, expected: FaultConfig) -> None:
    assert FaultConfig.parse(spec) == expected


@pytest.mark.parametrize(
    ("spec", "named"),
    [
        ("drop=2", "drop_byte_rate"),
        ("flip=-0.1", "bit_flip_rate"),
        ("drop=abc", "drop=abc"),
        ("bogus=1", "bogus=1"),
        ("late=0.1:0.2:0.3", "late=0.1:0.2:0.3"),
        ("silent=3:2", "silent_windows"),
        ("disconnect=0", "disconnect_after_s"),
        ("disconnect=5:1:0", "disconnect_count"),
    ],
)
def test_parse_refuses_bad_specs_naming_the_item(spec: str, named: str) -> None:
    with pytest.raises(LocalProtocolError, match=named.replace(".", r"\.")):
        FaultConfig.parse(spec)


def test_link_schedule_alternates_up_and_down() -> None:
    cfg = FaultConfig(disconnect_after_s=5.0, reconnect_after_s=1.0, disconnect_count=3)
    assert list(cfg.link_schedule()) == [(5.0, 6.0), (11.0, 12.0), (17.0, 18.0)]
    assert list(FaultConfig().link_schedule()) == []


# -- each kind, visible in bytes and stats ---------------------------------------------


def test_no_faults_means_exact_replies() -> None:
    out, bus, log = run(FaultConfig(), requests=3)
    assert out == [REPLY] * 3
    assert all(v == 0 for v in bus.stats.faults_injected.values())
    assert [r["fault"] for r in log if r["dir"] == "tx"] == [None] * 3


def test_drop_every_byte() -> None:
    out, bus, _ = run(FaultConfig(drop_byte_rate=1.0))
    assert out == []
    assert bus.stats.faults_injected["drop"] == len(REPLY)


def test_drop_some_bytes_leaves_a_subsequence() -> None:
    out, bus, log = run(FaultConfig(drop_byte_rate=0.3), seed=3)
    data = b"".join(out)
    dropped = bus.stats.faults_injected["drop"]
    assert dropped > 0 and len(data) == len(REPLY) - dropped
    it = iter(REPLY)
    assert all(b in it for b in data)  # data is REPLY with some bytes removed
    assert log[-1]["fault"] == "drop"


def test_flip_every_byte_changes_exactly_one_bit_of_each() -> None:
    out, bus, log = run(FaultConfig(bit_flip_rate=1.0))
    (data,) = out
    assert len(data) == len(REPLY)
    assert [bin(a ^ b).count("1") for a, b in zip(data, REPLY, strict=True)] == [1] * len(REPLY)
    assert bus.stats.faults_injected["flip"] == len(REPLY)
    assert log[-1]["fault"] == "flip"


def test_garbage_inserts_one_to_eight_bytes_before_or_inside_the_reply() -> None:
    out, bus, log = run(FaultConfig(garbage_rate=1.0), requests=20)
    assert bus.stats.faults_injected["garbage"] == 20
    positions = set()
    for data in out:
        extra = len(data) - len(REPLY)
        assert 1 <= extra <= 8
        cuts = [i for i in range(len(REPLY) + 1) if data[:i] + data[i + extra :] == REPLY]
        assert cuts, data.hex(" ")
        positions.add(cuts[0])
    assert len(positions) > 1  # not always at the same place
    assert {r["fault"] for r in log if r["dir"] == "tx"} == {"garbage"}


def test_late_reply_is_delivered_exactly_the_delay_later() -> None:
    on_time = run(FaultConfig())[2][-1]["t"]
    out, bus, log = run(FaultConfig(late_reply_rate=1.0, late_reply_delay_s=0.05))
    assert out == [REPLY]
    assert log[-1]["t"] == pytest.approx(on_time + 0.05, abs=1e-12)  # type: ignore[operator]
    assert log[-1]["fault"] == "late"
    assert bus.stats.faults_injected["late"] == 1


def test_late_reply_is_not_out_before_its_time() -> None:
    bus = SimBus([Echo()], baud=BAUD, faults=FaultConfig(late_reply_rate=1.0, late_reply_delay_s=1))
    bus.receive(REQ, 0.0)
    assert bus.due_output(0.5) == []
    assert bus.due_output(1.5) == [REPLY]


def test_duplicate_reply_is_sent_twice_back_to_back() -> None:
    out, bus, log = run(FaultConfig(duplicate_reply_rate=1.0))
    assert out == [REPLY, REPLY]
    tx = [r for r in log if r["dir"] == "tx"]
    assert tx[1]["t"] - tx[0]["t"] == pytest.approx(len(REPLY) * 10 / BAUD)  # type: ignore[operator]
    assert bus.stats.faults_injected["duplicate"] == 1


def test_silent_devices_hear_but_do_not_answer() -> None:
    out, bus, log = run(FaultConfig(silent=True), requests=2)
    assert out == []
    assert bus.stats.requests == 2
    assert bus.stats.faults_injected["silent"] == 2
    assert [r["fault"] for r in log if r["dir"] == "tx"] == ["silent", "silent"]


def test_silent_window_only_silences_replies_inside_it() -> None:
    cfg = FaultConfig(silent_windows=((0.015, 0.035),))
    out, bus, _ = run(cfg, requests=5, period=0.01)  # requests at 0, 10, 20, 30, 40 ms
    assert out == [REPLY] * 3
    assert bus.stats.faults_injected["silent"] == 2


def test_disconnect_drops_the_link_loses_bytes_and_comes_back() -> None:
    cfg = FaultConfig(disconnect_after_s=1.0, reconnect_after_s=0.5, disconnect_count=1)
    bus = SimBus([Echo()], baud=BAUD, faults=cfg, epoch=10.0)
    assert bus.next_wakeup() == 11.0
    bus.receive(REQ, 10.9999)  # its reply would be due after the link went down
    assert bus.due_output(11.0) == []
    assert bus.link_events(11.0) == [LinkEvent.DOWN]
    assert not bus.link_up
    assert bus.next_wakeup() == 11.5
    bus.receive(REQ, 11.2)  # nobody is listening
    assert bus.due_output(11.4) == []
    assert bus.link_events(11.5) == [LinkEvent.UP]
    bus.receive(REQ, 12.0)
    assert bus.due_output(13.0) == [REPLY]
    assert bus.stats.faults_injected["disconnect"] == 1
    assert bus.stats.lost_while_down == len(REPLY) + len(REQ)
    assert bus.link_events(100.0) == []


def test_output_due_before_a_disconnect_is_still_delivered() -> None:
    cfg = FaultConfig(disconnect_after_s=1.0, disconnect_count=1)
    bus = SimBus([Echo()], baud=BAUD, faults=cfg)
    bus.receive(REQ, 0.5)
    assert bus.due_output(1.9) == [REPLY]
    assert bus.link_events(1.9) == [LinkEvent.DOWN]
    # A driver that wakes up late learns of both changes, in order.
    bus = SimBus([Echo()], baud=BAUD, faults=cfg)
    assert bus.link_events(5.0) == [LinkEvent.DOWN, LinkEvent.UP]


# -- reproducibility --------------------------------------------------------------------

MIXED = FaultConfig.parse("drop=0.02,flip=0.02,garbage=0.2,late=0.1:0.003,dup=0.1")


def test_same_seed_same_bytes() -> None:
    a = run(MIXED, requests=100, seed=7)
    b = run(MIXED, requests=100, seed=7)
    assert a[0] == b[0]
    assert a[2] == b[2]
    assert a[1].stats == b[1].stats
    kinds = a[1].stats.faults_injected
    assert all(kinds[k] > 0 for k in ("drop", "flip", "garbage", "late", "duplicate"))


def test_another_seed_other_bytes() -> None:
    assert run(MIXED, requests=100, seed=7)[0] != run(MIXED, requests=100, seed=8)[0]


@given(st.binary(min_size=1, max_size=64), st.integers(0, 2**32))
def test_an_inactive_injector_passes_frames_through(frame: bytes, seed: int) -> None:
    fate = FaultInjector(FaultConfig(), random.Random(seed)).apply(frame)
    assert (fate.data, fate.copies, fate.extra_delay_s, fate.kinds) == (frame, 1, 0.0, ())


@given(st.binary(min_size=1, max_size=64), st.integers(0, 2**32))
def test_the_injector_is_a_function_of_its_seed(frame: bytes, seed: int) -> None:
    a = FaultInjector(MIXED, random.Random(seed)).apply(frame)
    b = FaultInjector(MIXED, random.Random(seed)).apply(frame)
    assert a == b
