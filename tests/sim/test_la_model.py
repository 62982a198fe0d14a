"""Tests of the simulated Inspire LA actuator (motorbus.sim.la)."""

from __future__ import annotations

import random
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import parse_hex
from motorbus.protocol.la import (
    BROADCAST_ID,
    STATUS_FRAME_SIZE,
    Broadcast,
    BroadcastMode,
    Control,
    ControlAction,
    ErrorFlags,
    Follow,
    MoveTo,
    ReadRegister,
    Register,
    Status,
    WriteAck,
    WriteRegister,
    WriteTable,
    decode_reply,
    decode_request,
    split_broadcast,
)
from motorbus.sim.la import AUTO_CLEAR_S, CONSECUTIVE_WINDOW_S, LAModel, PowerState
from tests.vectors import vectors_of


def _request_vectors() -> list[dict[str, Any]]:
    return [v for v in vectors_of("inspire_la_55aa") if v["decoded"]["header"] == "55 AA"]


REQUEST_VECTORS = _request_vectors()

W = ControlAction.WORK


def _status(frames: list[bytes]) -> Status:
    assert len(frames) == 1
    status = decode_reply(frames[0])
    assert isinstance(status, Status)
    return status


def _query(model: LAModel, now: float) -> Status:
    return _status(model.handle(Control(model.id, ControlAction.QUERY_STATUS).encode(), now))


# --- document vectors ----------------------------------------------------------------------


@pytest.mark.parametrize("vector", REQUEST_VECTORS, ids=lambda v: str(v["description"])[:40])
def test_model_answers_document_requests(vector: dict[str, Any]) -> None:
    request = parse_hex(vector.get("request_hex_corrected", vector["request_hex"]))
    cmd = decode_request(request)
    ident = vector["decoded"]["id"]
    model = LAModel(ident if ident != BROADCAST_ID else 1)
    model.set_register(Register.OVER_TEMPERATURE_LIMIT, 600)
    replies = model.handle(request, 0.0)
    if vector.get("expected_reply_hex"):
        assert replies == [parse_hex(vector["expected_reply_hex"])]
    elif not cmd.expects_reply:
        assert replies == []
    else:
        assert len(replies) == 1
        assert len(replies[0]) == STATUS_FRAME_SIZE
        assert cmd.matches_reply(replies[0])


def test_document_read_exact_reply() -> None:
    model = LAModel(1)
    model.set_register(Register.OVER_TEMPERATURE_LIMIT, 600)
    reply = model.handle(parse_hex("55 AA 03 01 01 62 02 69"), 0.0)
    assert reply == [parse_hex("AA 55 04 01 01 62 58 02 C2")]


def test_bad_checksum_is_ignored() -> None:
    model = LAModel(3)
    assert model.handle(parse_hex("55 AA 04 03 19 37 E8 03 28"), 0.0) == []
    assert model.ignored == 1
    assert model.received == []


# --- reply options ------------------------------------------------------------------------------


def test_write_reply_ack_and_status_echo() -> None:
    ack_model = LAModel(1, write_reply="ack")
    cmd = WriteRegister(1, Register.OVER_CURRENT_LIMIT, 1000)
    (reply,) = ack_model.handle(cmd.encode(), 0.0)
    assert reply == parse_hex("AA 55 03 01 02 20 00 26")
    assert cmd.decode_reply(reply) == WriteAck(1, 0x20, 0)
    assert ack_model.register(Register.OVER_CURRENT_LIMIT) == 1000

    echo_model = LAModel(1, status_cmd_echo="request")
    assert _status(echo_model.handle(MoveTo(1, 10).encode(), 0.0)).cmd_echo == 0x21
    assert _status(echo_model.handle(Follow(1, 10).encode(), 0.0)).cmd_echo == 0x20
    assert _status(echo_model.handle(cmd.encode(), 0.0)).cmd_echo == 0x02
    assert _status(LAModel(1).handle(MoveTo(1, 10).encode(), 0.0)).cmd_echo == 0x04


@pytest.mark.parametrize(("option", "reply_id"), [("old", 3), ("new", 2)])
def test_id_change(option: str, reply_id: int) -> None:
    model = LAModel(3, id_change_reply=option)
    cmd = WriteRegister(3, Register.ID, 2)
    (reply,) = model.handle(cmd.encode(), 0.0)
    assert _status([reply]).id == reply_id
    assert cmd.matches_reply(reply)
    assert model.id == 2
    assert model.handle(Control(3, ControlAction.QUERY_STATUS).encode(), 0.1) == []
    assert _query(model, 0.2).id == 2
    model.power_cycle(1.0)  # not saved: the old ID comes back
    assert model.id == 3


def test_save_and_power_cycle() -> None:
    model = LAModel(3, baud_code=3)
    model.handle(WriteRegister(3, Register.ID, 7).encode(), 0.0)
    model.handle(WriteRegister(7, Register.BAUD, 2).encode(), 0.1)
    model.handle(WriteRegister(7, Register.OVER_CURRENT_LIMIT, 800).encode(), 0.2)
    assert model.baud == 921600  # a baud change needs save + power cycle
    model.handle(Control(7, ControlAction.SAVE).encode(), 0.3)
    assert model.baud == 921600
    model.handle(WriteRegister(7, Register.OVER_CURRENT_LIMIT, 900).encode(), 0.4)  # not saved
    model.power_cycle(1.0)
    assert model.id == 7
    assert model.baud == 115200
    assert model.register(Register.OVER_CURRENT_LIMIT) == 800
    assert model.power_state is PowerState.WORKING


def test_read_only_registers_ignore_writes() -> None:
    model = LAModel(1, position=100.0)
    model.handle(WriteTable(1, 26, b"\x00\x00").encode(), 0.0)
    assert model.register(Register.POSITION) == 100
    reply = model.handle(ReadRegister(1, Register.POSITION).encode(), 0.1)
    assert ReadRegister(1, Register.POSITION).decode_reply(reply[0]) == 100


def test_force_zero() -> None:
    model = LAModel(1)
    model.load_g = 250
    assert _query(model, 0.0).force == 250
    model.handle(WriteRegister(1, Register.FORCE_ZERO, 1).encode(), 0.1)
    assert _query(model, 0.2).force == 0
    assert model.register(Register.FORCE_ZERO) == 0
    assert _query(LAModel(1, force_sensor=False), 0.0).force == 0


# --- motion -----------------------------------------------------------------------------------


def test_positioning_reaches_target_in_plausible_time() -> None:
    model = LAModel(1)
    status = _status(model.handle(MoveTo(1, 2000).encode(), 0.0))
    assert status.target == 2000 and status.position == 0
    mid = _query(model, 0.5)
    assert 500 < mid.position < 1500
    assert mid.current > _query(LAModel(1), 0.0).current  # more current while moving
    assert _query(model, 1.5).position == 2000
    assert model.received == [(0.0, 0x21, 2000)]


def test_write_target_moves() -> None:
    model = LAModel(1)
    model.handle(parse_hex("55 AA 04 01 02 37 14 05 57"), 0.0)
    assert _query(model, 2.0).position == 1300
    assert model.received == [(0.0, 0x02, 1300)]


def test_follow_is_rate_limited() -> None:
    model = LAModel(1, stroke_speed=1000.0)
    for k in range(10):  # 20 ms stream, ramp of 10 units per frame
        model.handle(Follow(1, 10 * (k + 1), reply=False).encode(), 0.02 * k)
    assert model.position <= 100
    assert _query(model, 0.2).position == 100
    model.handle(Follow(1, 2000, reply=False).encode(), 0.2)
    assert _query(model, 0.3).position == pytest.approx(200, abs=1)  # 1000 units/s


def test_no_reply_commands_and_broadcast_id_are_silent() -> None:
    model = LAModel(1)
    assert model.handle(MoveTo(1, 5, reply=False).encode(), 0.0) == []
    assert model.handle(Follow(1, 6, reply=False).encode(), 0.1) == []
    assert model.handle(MoveTo(BROADCAST_ID, 7).encode(), 0.2) == []
    assert model.handle(Control(BROADCAST_ID, ControlAction.QUERY_STATUS).encode(), 0.3) == []
    assert (
        model.handle(WriteRegister(BROADCAST_ID, Register.OVER_CURRENT_LIMIT, 700).encode(), 0.4)
        == []
    )
    assert model.register(Register.OVER_CURRENT_LIMIT) == 700
    assert [r[1:] for r in model.received] == [(0x03, 5), (0x19, 6), (0x21, 7)]
    assert model.handle(MoveTo(2, 9).encode(), 0.5) == []  # another actuator's frame
    assert len(model.received) == 3


def test_broadcast_applies_own_entry() -> None:
    models = [LAModel(i) for i in range(1, 21)]
    frames = split_broadcast(BroadcastMode.POSITION, {i: 100 * i for i in range(1, 21)})
    for frame in frames:
        for model in models:
            assert model.handle(frame.encode(), 0.0) == []
    for model in models:
        assert model.received == [(0.0, 0xF2, 100 * model.id)]
        assert _query(model, 3.0).position == 100 * model.id
    follow = Broadcast(BroadcastMode.FOLLOW, ((3, 500),))
    assert models[2].handle(follow.encode(), 3.0) == []
    assert models[2].received[-1] == (3.0, 0xF3, 500)


# --- work / e-stop / pause (manual 3.5.4) ------------------------------------------------------


def test_estop_ignores_positions_until_work() -> None:
    model = LAModel(1)
    model.handle(MoveTo(1, 2000).encode(), 0.0)
    stopped = _status(model.handle(Control(1, ControlAction.ESTOP).encode(), 0.3))
    assert model.power_state is PowerState.ESTOPPED
    assert _query(model, 1.5).position == stopped.position < 2000
    status = _status(model.handle(MoveTo(1, 100).encode(), 1.6))
    assert status.target == 2000  # target not adopted
    assert _query(model, 3.0).position == stopped.position
    model.handle(Control(1, W).encode(), 3.1)
    assert _query(model, 5.0).position == stopped.position  # WORK alone does not move
    model.handle(MoveTo(1, 100).encode(), 5.1)
    assert _query(model, 7.0).position == 100
    assert [r[2] for r in model.received] == [2000, 100, 100]


def test_pause_then_position_resumes() -> None:
    model = LAModel(1)
    model.handle(MoveTo(1, 2000).encode(), 0.0)
    paused = _status(model.handle(Control(1, ControlAction.PAUSE).encode(), 0.3))
    assert model.power_state is PowerState.PAUSED
    assert _query(model, 1.0).position == paused.position
    model.handle(MoveTo(1, 2000).encode(), 1.0)
    resumed: PowerState = model.power_state
    assert resumed is PowerState.WORKING
    assert _query(model, 3.0).position == 2000


# --- faults (manual 3.8) -------------------------------------------------------------------------


def test_stall_stops_and_auto_clears() -> None:
    model = LAModel(1)
    model.handle(MoveTo(1, 2000).encode(), 0.0)
    model.trigger_fault("stall", 0.3)
    at_fault = _query(model, 0.3)
    assert at_fault.errors == ErrorFlags.STALL and at_fault.fault
    model.handle(MoveTo(1, 0).encode(), 1.0)  # not obeyed while faulted
    assert _query(model, 2.0).position == at_fault.position
    assert _query(model, 0.3 + AUTO_CLEAR_S - 0.01).errors == ErrorFlags.STALL
    assert not _query(model, 0.3 + AUTO_CLEAR_S).fault
    model.handle(MoveTo(1, 0).encode(), 6.0)
    assert _query(model, 8.0).position == 0


def test_third_consecutive_trip_latches_until_clear() -> None:
    model = LAModel(1)
    t = 0.0
    for _ in range(2):
        model.trigger_fault("over_current", t)
        t += AUTO_CLEAR_S
        assert not _query(model, t).fault  # auto-cleared
        t += 1.0  # next trip well within the window
    model.trigger_fault("over_current", t)
    assert _query(model, t + 60.0).errors == ErrorFlags.OVER_CURRENT  # latched
    cleared = _status(model.handle(Control(1, ControlAction.CLEAR_FAULT).encode(), t + 61))
    assert not cleared.fault
    model.trigger_fault("stall", t + 62)  # the chain restarted: auto-clears again
    assert not _query(model, t + 62 + AUTO_CLEAR_S).fault


def test_trips_far_apart_do_not_latch() -> None:
    model = LAModel(1)
    t = 0.0
    for _ in range(4):
        model.trigger_fault("stall", t)
        t += AUTO_CLEAR_S + CONSECUTIVE_WINDOW_S + 1.0
        assert not _query(model, t).fault


def test_over_temperature_not_clearable_and_cools() -> None:
    model = LAModel(1, temperature=25.0, cooling_rate=2.0)
    model.handle(MoveTo(1, 2000).encode(), 0.0)
    model.trigger_fault("over_temperature", 0.2)
    status = _query(model, 0.2)
    assert status.errors == ErrorFlags.OVER_TEMPERATURE
    assert status.temperature > 80  # above the default 80.0 degC limit
    assert not model.moving
    cleared = _status(model.handle(Control(1, ControlAction.CLEAR_FAULT).encode(), 0.3))
    assert cleared.errors == ErrorFlags.OVER_TEMPERATURE
    # 85 degC cooling at 2 degC/s falls below the 60.0 degC recovery after 12.5 s.
    assert _query(model, 12.0).fault
    recovered = _query(model, 13.0)
    assert not recovered.fault and recovered.temperature < 60
    model.handle(MoveTo(1, 0).encode(), 13.0)
    assert _query(model, 15.0).position == 0


def test_motor_abnormal_clears_on_motion_or_command() -> None:
    model = LAModel(1)
    model.trigger_fault("motor_abnormal", 0.0)
    assert _query(model, 0.0).errors == ErrorFlags.MOTOR_ABNORMAL
    assert _query(model, 0.0).current == 0  # full output, zero measured current
    model.handle(Control(1, ControlAction.CLEAR_FAULT).encode(), 0.1)
    assert not _query(model, 0.1).fault
    model.trigger_fault("motor_abnormal", 0.2)
    model.handle(MoveTo(1, 500).encode(), 0.3)  # a notice: motion is still obeyed
    assert not _query(model, 0.5).fault


# --- odds and ends ---------------------------------------------------------------------------


def test_turnaround_draws() -> None:
    model = LAModel(
        1, turnaround_typical=120e-6, turnaround_max=800e-6, slow_turnaround_probability=0.5
    )
    rng = random.Random(4)
    draws = [model.turnaround(rng) for _ in range(200)]
    assert all(120e-6 <= d <= 800e-6 for d in draws)
    assert draws.count(120e-6) > 50
    assert any(d > 120e-6 for d in draws)
    assert LAModel(1, slow_turnaround_probability=0.0).turnaround(rng) == 120e-6


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"id": 0}, "id"),
        ({"write_reply": "short"}, "write_reply"),
        ({"status_cmd_echo": "0x21"}, "status_cmd_echo"),
        ({"id_change_reply": "both"}, "id_change_reply"),
        ({"baud_code": 4}, "baud_code"),
        ({"stroke_speed": 0.0}, "stroke_speed"),
    ],
)
def test_bad_options(kwargs: dict[str, Any], field: str) -> None:
    with pytest.raises(LocalProtocolError, match=field):
        LAModel(**kwargs)
    with pytest.raises(LocalProtocolError, match="kind"):
        LAModel(1).trigger_fault("fire", 0.0)


@settings(max_examples=200)
@given(st.binary(max_size=40), st.floats(0.0, 100.0))
def test_random_bytes_never_crash(raw: bytes, now: float) -> None:
    model = LAModel(1)
    replies = model.handle(raw, now)
    assert replies == [] or all(decode_reply(r) is not None for r in replies)
