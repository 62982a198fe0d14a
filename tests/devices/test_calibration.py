"""``Calibration``: units, direction, offset and soft limits; streams within the limits."""

from __future__ import annotations

import asyncio

import pytest

from motorbus.bus.bus import Bus
from motorbus.devices.calibration import Calibration
from motorbus.devices.la import InspireLA
from motorbus.errors import LocalProtocolError, StreamEnded
from motorbus.manager import BusManager
from motorbus.sim.la import LAModel, PowerState
from motorbus.sim.memory import MemorySim
from motorbus.transport.memory import memory_pair
from motorbus.validation import CheckedRows
from tests.helpers import eventually


def test_the_default_is_raw_over_the_whole_stroke() -> None:
    cal = Calibration()
    assert (cal.to_raw(0), cal.to_raw(2000), cal.to_raw(1234.4)) == (0, 2000, 1234)
    assert cal.from_raw(700) == 700.0 and cal.limits_in() == (0.0, 2000.0)
    with pytest.raises(LocalProtocolError, match=r"la: position=2001 is out of range"):
        cal.to_raw(2001)


@pytest.mark.parametrize(
    ("cal", "unit", "pairs"),
    [
        # mm from the retracted end, 30 mm over 0..2000.
        (Calibration(stroke_mm=30), "mm", [(0.0, 0), (15.0, 1000), (30.0, 2000)]),
        # reversed: measured from the extended end.
        (Calibration(stroke_mm=30, direction="reversed"), "mm", [(0.0, 2000), (30.0, 0)]),
        # an offset: the retracted end reads 5 mm.
        (Calibration(stroke_mm=30, offset_mm=5), "mm", [(5.0, 0), (20.0, 1000)]),
        # percent of the calibrated range, either way round.
        (Calibration(limits=(200, 1800)), "percent", [(0.0, 200), (50.0, 1000), (100.0, 1800)]),
        (
            Calibration(limits=(200, 1800), direction="reversed"),
            "percent",
            [(0.0, 1800), (25.0, 1400), (100.0, 200)],
        ),
    ],
)
def test_units_convert_both_ways(
    cal: Calibration, unit: str, pairs: list[tuple[float, int]]
) -> None:
    for value, raw in pairs:
        assert cal.to_raw(value, unit) == raw
        assert cal.from_raw(raw, unit) == pytest.approx(value)


def test_limits_are_named_in_the_unit_asked() -> None:
    cal = Calibration(stroke_mm=30, limits=(100, 1900), direction="reversed", offset_mm=2)
    assert cal.limits_in("mm") == pytest.approx((3.5, 30.5))
    with pytest.raises(LocalProtocolError) as info:
        cal.to_raw(31, "mm", device="gripper")
    assert str(info.value) == (
        "gripper: mm=31 is out of range: allowed 3.5..30.5 mm (its soft limits, raw "
        "100..1900); nothing sent"
    )
    assert (info.value.field, info.value.value) == ("mm", 31)


def test_the_existing_millimetre_api_follows_the_calibration() -> None:
    bus = Bus(memory_pair()[0])  # not opened: conversions send nothing
    a = InspireLA(bus, 3, stroke_mm=30)
    assert (a.from_mm(15), a.to_mm(2000), a.unit, a.name) == (1000, 30.0, "raw", "la:3")
    b = InspireLA(bus, 3, calibration=Calibration(stroke_mm=20), stroke_mm=40)
    assert b.stroke_mm == 40.0  # stroke_mm replaces the calibration's
    with pytest.raises(LocalProtocolError, match="name='3x' is not allowed"):
        InspireLA(bus, 3, name="3x")
    with pytest.raises(LocalProtocolError, match=r"bus must be a motorbus Bus .* got None"):
        InspireLA(None, 3)  # type: ignore[arg-type]  # it failed at its first call


async def test_a_stream_of_named_devices_refuses_targets_outside_the_limits() -> None:
    models = [LAModel(1), LAModel(2)]
    async with MemorySim.start(models) as sim:
        mgr = BusManager.from_dict(
            {
                "bus": [
                    {
                        "name": "arm",
                        "url": "memory://arm",
                        "baud": 921600,
                        "host_margin_ms": 50,
                        "la": {
                            "gripper": {
                                "id": 1,
                                "stroke_mm": 30,
                                "limits": [100, 1900],
                                "unit": "mm",
                            },
                            "wrist": {"id": 2, "limits": [500, 1500], "unit": "percent"},
                        },
                    }
                ]
            }
        )
        spec = mgr.specs.pop("arm")
        mgr.add_spec(spec, sim.transport)
        async with mgr:
            before = sim.bus.stats.requests
            # A sequence is converted whole: one bad target refuses the stream, unsent.
            with pytest.raises(LocalProtocolError, match=r"wrist: percent=120 is out of range"):
                mgr.follow(["gripper", "wrist"], [[10.0, 50], [11.0, 120]], period=0.02)
            with pytest.raises(LocalProtocolError, match=r"gripper: mm=0.5 is out of range"):
                mgr.follow("gripper", [0.5])
            with pytest.raises(LocalProtocolError, match=r"targets name 'elbow'"):
                mgr.follow(["gripper"], [{"elbow": 3}])
            # The manager's streamer checks them too, in its raw units.
            streamer = mgr.streamer("arm")
            with pytest.raises(LocalProtocolError, match=r"gripper: position=1950 is out of"):
                streamer.follow(mgr.device("gripper"), [1500, 1950])
            with pytest.raises(LocalProtocolError, match=r"gripper: position=50 is out of"):
                streamer.follow([mgr.la("arm", 1), mgr.la("arm", 2)], [[50, 600]])
            assert sim.bus.stats.requests == before  # the simulator received nothing
            # Within the limits, by name, in each device's unit.
            # 20 rows: a loaded machine may start the stream a tick or two late (the
            # stream skips the rows of missed ticks), and some row must still be sent.
            stream = mgr.follow(["gripper", "wrist"], [{"gripper": 15.0, "wrist": 0}] * 20)
            # Converted and checked once, by the manager: the stream takes the rows as
            # they are, not a second check of each (6 us a row here).
            assert type(stream.source.sequence) is CheckedRows
            await stream.wait()
            assert {t for _, _, t in models[0].received} == {1000}
            assert {t for _, _, t in models[1].received} == {500}
            # A live source: the first target outside the limits ends the stream, unsent,
            # and the stream's safe action pauses the actuator.
            sent = len(models[0].received)

            def source(t: float, statuses: object) -> float:
                return 15.0 if t < 0.05 else 29.0

            live = mgr.follow("gripper", source, safe_action="pause")
            with pytest.raises(StreamEnded, match=r"gripper: mm=29.0 is out of range"):
                await asyncio.wait_for(live.wait(), 10)
            targets = [t for _, _, t in models[0].received[sent:]]
            assert targets and set(targets) == {1000}
            await eventually(lambda: models[0].power_state is PowerState.PAUSED, "paused")
