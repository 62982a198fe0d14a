"""numpy scalars and arrays are numbers and sequences of numbers everywhere.

IDs, positions and other integer fields accept numpy integers (anything with
``__index__`` that is not a bool) and store plain ints; durations accept numpy floats;
stream targets accept numpy scalars, 1-D arrays (one row a tick) and 2-D arrays (rows =
ticks, columns = actuators).  numpy bools stay refused like bools, NaN stays refused.
"""

from __future__ import annotations

import asyncio
import dataclasses
import enum
import re
from typing import Any

import numpy as np
import pytest

from motorbus.bus.bus import Bus
from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager
from motorbus.protocol import la
from motorbus.protocol.base import check_choice, check_flag, check_int, check_timeout
from motorbus.sim.la import LAModel
from motorbus.streams import Streamer
from motorbus.transport.memory import memory_pair
from tests.fakeclock import rig as fake_rig
from tests.helpers import sim_bus
from tests.test_bad_input import COMMANDS

NP_INTS = (np.int8, np.int16, np.int32, np.int64, np.uint8, np.uint16, np.uint32, np.uint64)


@pytest.mark.parametrize("kind", NP_INTS, ids=[k.__name__ for k in NP_INTS])
def test_check_int_accepts_numpy_integers_and_returns_plain_ints(kind: Any) -> None:
    got = check_int("id", kind(7), 1, 254)
    assert got == 7 and type(got) is int
    assert check_int("id", np.array(7, dtype=kind), 1, 254) == 7  # a 0-d array
    with pytest.raises(LocalProtocolError, match=r"id=0 is out of range: allowed 1\.\.254"):
        check_int("id", kind(0), 1, 254)
    got = check_choice("mode", kind(0x73), [0x72, 0x73])
    assert got == 0x73 and type(got) is int


class _Index:
    """Not numpy: any object with ``__index__`` is an integer."""

    def __init__(self, value: int) -> None:
        self.value = value

    def __index__(self) -> int:
        return self.value


def test_any_index_object_is_an_integer() -> None:
    got = check_int("id", _Index(9), 1, 254)
    assert got == 9 and type(got) is int
    cmd = la.MoveTo(_Index(3), _Index(1500))  # type: ignore[arg-type]
    assert (cmd.id, cmd.position) == (3, 1500)
    assert cmd.encode() == la.MoveTo(3, 1500).encode()


@pytest.mark.parametrize(
    "bad",
    [np.True_, np.False_, np.float64(2.0), np.float32(2.0), np.array([1, 2]), np.array(2.0)],
    ids=repr,
)
def test_check_int_refuses_numpy_bools_floats_and_arrays(bad: Any) -> None:
    with pytest.raises(LocalProtocolError, match=r"id must be an integer in 1\.\.254"):
        check_int("id", bad, 1, 254)


def test_durations_and_flags_accept_numpy_scalars() -> None:
    for value in (np.float32(0.5), np.float64(0.5), np.int64(1), np.float16(0.5)):
        got = check_timeout("timeout", value, 10)
        assert type(got) is float and got == float(value)
    for bad in (np.float64("nan"), np.float32("inf"), np.float64(-1), np.True_):
        with pytest.raises(LocalProtocolError, match="timeout"):
            check_timeout("timeout", bad, 10)
    assert check_flag("reply", np.True_) is True
    assert check_flag("reply", np.False_) is False
    for bad in (np.int64(1), np.float64(1.0)):
        with pytest.raises(LocalProtocolError, match="reply must be True or False"):
            check_flag("reply", bad)


def _numpy_version(valid: dict[str, Any]) -> dict[str, Any]:
    return {
        k: np.int64(v) if type(v) is int and not isinstance(v, enum.Enum) else v
        for k, v in valid.items()
    }


@pytest.mark.parametrize(
    "cls", list(COMMANDS), ids=[f"{c.__module__[18:]}.{c.__name__}" for c in COMMANDS]
)
def test_every_command_takes_numpy_integers_and_encodes_the_same_bytes(cls: Any) -> None:
    valid = COMMANDS[cls][0]
    plain = cls(**valid)
    numpy_cmd = cls(**_numpy_version(valid))
    assert numpy_cmd.encode() == plain.encode()
    for f in dataclasses.fields(numpy_cmd):
        value = getattr(numpy_cmd, f.name)
        assert not isinstance(value, np.generic), f"{cls.__name__}.{f.name} kept {value!r}"
    assert repr(numpy_cmd) == repr(plain)


def test_broadcast_entries_from_a_numpy_array() -> None:
    entries = np.array([[1, 500], [2, 1500]])
    cmd = la.Broadcast(la.BroadcastMode.FOLLOW, entries)  # type: ignore[arg-type]
    assert cmd.encode() == la.Broadcast(la.BroadcastMode.FOLLOW, ((1, 500), (2, 1500))).encode()
    assert all(type(x) is int for pair in cmd.entries for x in pair)


async def test_device_calls_take_numpy_ids_and_positions() -> None:
    model = LAModel(2)
    async with sim_bus([model]) as (bus, _sim):
        actuator = InspireLA(bus, np.int64(2))  # type: ignore[arg-type]
        assert actuator.id == 2 and type(actuator.id) is int
        status = await actuator.move_to(np.int64(1000))  # type: ignore[arg-type]
        assert status is not None and status.target == 1000
        await actuator.follow(np.uint16(900), reply=False)  # type: ignore[arg-type]
        query = la.Control(2, la.ControlAction.QUERY_STATUS)
        status = await bus.request(query, timeout=np.float32(0.5))  # type: ignore[arg-type]
        assert status.target == 900
        with pytest.raises(LocalProtocolError, match="position"):
            await actuator.move_to(np.float64(1000.0))  # type: ignore[arg-type]
        with pytest.raises(LocalProtocolError, match="id"):
            InspireLA(bus, np.True_)  # type: ignore[arg-type]


async def test_bus_and_streamer_options_take_numpy_scalars() -> None:
    host, _peer = memory_pair()
    bus = Bus(
        host,
        min_spacing=np.float64(0.001),  # type: ignore[arg-type]
        host_margin=np.float32(0.004),  # type: ignore[arg-type]
        retries=np.int64(2),  # type: ignore[arg-type]
        late_guard=np.float32(0.02),  # type: ignore[arg-type]
    )
    for value in (bus.config.min_spacing, bus.config.host_margin, bus.config.late_guard):
        assert type(value) is float
    assert bus.config.retries == 2 and type(bus.config.retries) is int
    streamer = Streamer(bus, phase=np.float64(0.0025))  # type: ignore[arg-type]
    assert streamer.phase == 0.0025 and type(streamer.phase) is float


def test_bus_file_values_from_code_may_be_numpy_scalars() -> None:
    mgr = BusManager()
    mgr.add_bus(
        "arm",
        "/dev/ttyUSB0",
        baud=np.int64(921600),  # type: ignore[arg-type]
        retries=np.int32(3),
        min_spacing_ms=np.float32(1.5),
        rs485=np.True_,
    )
    spec = mgr.specs["arm"]
    assert (spec.baud, spec.retries, spec.min_spacing_ms, spec.rs485) == (921600, 3, 1.5, True)
    assert [type(v) for v in (spec.baud, spec.retries, spec.min_spacing_ms, spec.rs485)] == [
        int,
        int,
        float,
        bool,
    ]
    with pytest.raises(LocalProtocolError, match=r"retries must be an integer"):
        mgr.add_bus("b", "/dev/ttyUSB1", baud=9600, retries=np.float64(3.0))
    with pytest.raises(LocalProtocolError, match=r"min_spacing_ms must be a number"):
        mgr.add_bus("b", "/dev/ttyUSB1", baud=9600, min_spacing_ms=np.True_)


# -- stream targets ---------------------------------------------------------------------------


def _follow_targets(model: LAModel) -> list[int]:
    return [target for _, cmd, target in model.received if cmd == la.CMD_BROADCAST_FOLLOW]


@pytest.mark.parametrize(
    "period", [np.float32(0.01), np.float32(0.02), np.float64(0.02), np.float32(0.05)], ids=repr
)
async def test_follow_takes_a_numpy_period(period: Any) -> None:
    model = LAModel(1)
    async with fake_rig(models=[model]) as r:  # fake time: no tick skipped
        bus = r.bus
        streamer = Streamer(bus)
        stream = streamer.follow(InspireLA(bus, 1), np.array([700, 800]), period=period)
        assert type(stream.period) is float and stream.period == pytest.approx(float(period))
        await asyncio.wait_for(stream.wait(), 5)
        assert _follow_targets(model) == [700, 800]
        await streamer.close()


async def test_a_2d_array_streams_rows_as_ticks_and_columns_as_actuators() -> None:
    # This used to fail at tick 0 with "a single target was given for 3 actuators": a
    # numpy row has __index__, and was taken for one number.
    models = [LAModel(i) for i in (1, 2, 3)]
    rows = np.array([[100.0, 200.4, 300.6], [110.0, 210.0, 310.0], [120.0, 220.0, 320.0]])
    async with fake_rig(models=models) as r:  # fake time: no tick skipped
        bus = r.bus
        streamer = Streamer(bus)
        stream = streamer.follow([InspireLA(bus, i) for i in (1, 2, 3)], rows, period=0.01)
        await asyncio.wait_for(stream.wait(), 5)
        assert stream.error is None and stream.stats.ticks == 3
        for column, model in enumerate(models):
            assert _follow_targets(model) == [round(v) for v in rows[:, column]]
        await streamer.close()


@pytest.mark.parametrize(
    "source",
    [
        np.array([500, 600, 700]),  # 1-D ints: one number a tick
        np.array([500.2, 600.0, 699.7]),  # 1-D floats
        np.array([[500], [600], [700]]),  # 2-D, one column
        [np.int64(500), np.float32(600.0), np.array(700)],  # a list of numpy scalars
        [np.array([500]), np.array([600]), np.array([700])],  # a list of rows
        [{np.int64(1): np.float64(500.0)}, {1: np.int16(600)}, {np.uint8(1): 700}],
    ],
    ids=["1d-int", "1d-float", "2d-one-column", "scalars", "rows", "mappings"],
)
async def test_one_actuator_takes_numpy_targets_in_every_shape(source: Any) -> None:
    model = LAModel(1)
    async with fake_rig(models=[model]) as r:  # fake time: no tick skipped
        bus = r.bus
        streamer = Streamer(bus)
        stream = streamer.follow(InspireLA(bus, 1), source, period=0.01)
        await asyncio.wait_for(stream.wait(), 5)
        assert _follow_targets(model) == [500, 600, 700]
        await streamer.close()


async def test_a_callable_may_return_numpy_rows() -> None:
    models = [LAModel(i) for i in (1, 2)]

    def source(t: float, _statuses: Any) -> Any:
        return None if t > 0.015 else np.array([1000, 1100]) + round(t * 1000)

    async with sim_bus(models) as (bus, _sim):
        streamer = Streamer(bus)
        stream = streamer.follow([InspireLA(bus, 1), InspireLA(bus, 2)], source, period=0.01)
        await asyncio.wait_for(stream.wait(), 5)
        assert _follow_targets(models[0]) == [1000, 1010]
        assert _follow_targets(models[1]) == [1100, 1110]
        await streamer.close()


@pytest.mark.parametrize(
    ("rows", "match"),
    [
        (np.array([[100.0, np.nan]]), r"targets\[2\]=nan is out of range"),
        (np.array([[100, 3000]]), r"targets\[2\]=3000 is out of range: allowed 0..2000"),
        (np.array([[True, False]]), r"targets\[1\] must be a number"),
        ([[np.True_, np.int64(5)]], r"targets\[1\] must be a number"),
        (np.array([[100, 200, 300]]), "targets has 3 values for 2 actuators"),
        (np.array([np.nan]), "out of range"),
    ],
    ids=["nan", "out-of-range", "bool-array", "numpy-bool", "too-many-columns", "1d-nan"],
)
async def test_bad_numpy_targets_are_refused_at_follow(rows: Any, match: str) -> None:
    models = [LAModel(1), LAModel(2)]
    async with sim_bus(models) as (bus, _sim):
        streamer = Streamer(bus)
        one = isinstance(rows, np.ndarray) and rows.ndim == 1
        group = InspireLA(bus, 1) if one else [InspireLA(bus, 1), InspireLA(bus, 2)]
        with pytest.raises(LocalProtocolError) as info:
            streamer.follow(group, rows, period=0.01)
        assert re.search(match, str(info.value)), str(info.value)
        assert str(info.value).startswith("targets row 0 (of 1): ")
        assert streamer.streams == []
        assert all(m.received == [] for m in models)
        await streamer.close()


@pytest.mark.parametrize("bad", [np.nan, np.inf, 2001.0, -0.6], ids=repr)
async def test_the_one_bad_value_of_a_long_array_is_named_by_its_row(bad: float) -> None:
    models = [LAModel(1), LAModel(2)]
    async with sim_bus(models) as (bus, _sim):
        streamer = Streamer(bus)
        rows = np.full((20_000, 2), 1000.0)
        rows[16_543, 1] = bad
        with pytest.raises(LocalProtocolError, match=r"^targets row 16543 \(of 20000\): ") as info:
            streamer.follow([InspireLA(bus, 1), InspireLA(bus, 2)], rows, period=0.01)
        assert "targets[2]" in str(info.value) and "0..2000" in str(info.value)
        assert info.value.field == "targets[2]"
        assert all(m.received == [] for m in models)
        await streamer.close()


async def test_a_good_numpy_array_is_checked_in_c_and_streams() -> None:
    models = [LAModel(1), LAModel(2)]
    async with sim_bus(models) as (bus, _sim):
        streamer = Streamer(bus)
        rows = np.array([[1000.4, 2000], [0, 999.6]])
        stream = streamer.follow([InspireLA(bus, 1), InspireLA(bus, 2)], rows, period=0.01)
        await asyncio.wait_for(stream.wait(), 5)
        sent = _follow_targets(models[0]) + _follow_targets(models[1])
        assert set(sent) <= {1000, 0, 2000}  # a late first tick may skip to the last row
        assert _follow_targets(models[0])[-1] == 0 and _follow_targets(models[1])[-1] == 1000
        await streamer.close()
