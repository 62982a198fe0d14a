"""``scan()``: adaptive budgets, the second pass, late replies, exact found sets.

Against simulated actuators on the in-memory link with the high-resolution timer, so
reply timing follows the emulated wire.  Tests assert which IDs are found and in
which pass, never how long a scan took.
"""

from __future__ import annotations

import pytest

from motorbus.devices import la_scan as device
from motorbus.devices.la import ScanReport, scan
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import wire_time
from motorbus.sim.faults import FaultConfig
from motorbus.sim.la import TURNAROUND_MAX_S, LAModel
from tests.helpers import sim_bus

#: A model that always takes the manual's slowest turnaround.
SLOW = {"turnaround_typical": TURNAROUND_MAX_S, "turnaround_max": TURNAROUND_MAX_S}


def floor_at(baud: int) -> float:
    query = la.Control(1, la.ControlAction.QUERY_STATUS)
    return (
        wire_time(len(query.encode()), baud)
        + wire_time(la.STATUS_FRAME_SIZE, baud)
        + 800e-6
        + device.SCAN_HOST_ALLOWANCE_S
    )


async def test_fast_scan_finds_exactly_the_present_ids() -> None:
    models = [LAModel(3), LAModel(100, **SLOW), LAModel(254, silent_replies=1)]
    async with sim_bus(models) as (bus, _):
        report = ScanReport()
        seen: list[tuple[int, bool]] = []
        found = await scan(bus, progress=lambda i, n, hit: seen.append((i, hit)), report=report)
    assert found == [3, 100, 254]
    assert report.found == found and report.late == []
    # The floor: wire time of query and reply, the 800 us turnaround, the allowance.
    assert report.floor_s == pytest.approx(floor_at(921600))
    first, second = report.passes
    assert first.budget_s == pytest.approx(report.floor_s)  # nothing measured before
    assert second.budget_s > first.budget_s
    assert first.tried == list(range(1, 255))
    assert 254 not in first.found  # silent on its first query...
    assert 254 in second.found  # ... found by the second pass
    assert set(second.tried) == set(range(1, 255)) - set(first.found)
    # progress: once per ID, when its outcome is final.
    assert sorted(i for i, _ in seen) == list(range(1, 255))
    assert sorted(i for i, hit in seen if hit) == [3, 100, 254]


async def test_the_floor_leaves_room_for_the_slowest_turnaround() -> None:
    async with sim_bus([LAModel(7, **SLOW)]) as (bus, _):
        report = ScanReport()
        assert await scan(bus, [6, 7, 8], report=report) == [7]
    wire = wire_time(len(la.Control(7, la.ControlAction.QUERY_STATUS).encode()), 921600)
    wire += wire_time(la.STATUS_FRAME_SIZE, 921600)
    assert report.passes[0].budget_s >= wire + TURNAROUND_MAX_S + 100e-6
    # Found in the first pass, or (a loaded host) from its late answer in the second.
    assert 7 in report.passes[0].found + report.passes[0].late


async def test_the_budget_follows_replies_measured_before_the_scan(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    async with sim_bus([LAModel(1)]) as (bus, _):
        report = ScanReport()
        bus.stats.device("la:1").latency.record(0.004)  # this host answers in 4 ms
        assert await scan(bus, [1, 2], report=report) == [1]
    assert report.passes[0].budget_s == pytest.approx(device.SCAN_MEASURED_FACTOR * 0.004)
    extra = device.SCAN_SECOND_PASS_EXTRA_S
    assert report.passes[1].budget_s >= report.passes[0].budget_s + extra


async def test_the_adaptive_budget_never_exceeds_the_ceiling() -> None:
    async with sim_bus([LAModel(1)]) as (bus, _):
        report = ScanReport()
        bus.stats.device("la:1").latency.record(1.0)  # one absurd outlier
        await scan(bus, [2], report=report)
    assert [p.budget_s for p in report.passes] == [device.SCAN_BUDGET_MAX_S] * 2


async def test_stepper_latencies_do_not_shape_the_la_budget() -> None:
    async with sim_bus([LAModel(1)]) as (bus, _):
        report = ScanReport()
        bus.stats.device("quad_stepper").latency.record(0.040)
        await scan(bus, [1], report=report)
    assert report.passes[0].budget_s == pytest.approx(report.floor_s)


async def test_a_late_answer_is_asked_again_patiently() -> None:
    # Every reply is held back 25 ms: beyond both adaptive budgets, so only the late
    # reply says the actuator is there; the second pass gives it SCAN_LATE_BUDGET_S.
    faults = FaultConfig(late_reply_rate=1.0, late_reply_delay_s=0.025)
    async with sim_bus([LAModel(2)], faults=faults) as (bus, _):
        report = ScanReport()
        seen: list[tuple[int, bool]] = []
        found = await scan(
            bus, range(2, 40), report=report, progress=lambda i, n, hit: seen.append((i, hit))
        )
    assert found == [2], (
        report.as_dict()["passes"],
        bus.stats.as_dict()["devices"]["la:2"],
        bus.stats.late_replies,
        bus.stats.unexpected_frames,
    )
    assert report.passes[0].found == [] and report.passes[0].late == [2], report.as_dict()
    assert report.passes[1].found == [2]
    assert bus.stats.late_replies >= 1
    assert sorted(seen) == [(2, True)] + [(i, False) for i in range(3, 40)]


async def test_a_late_answer_in_the_second_pass_gets_one_patient_query() -> None:
    # la:7 misses its first query, and its second answer comes 25 ms late: it is
    # asked a third time, with SCAN_LATE_BUDGET_S.
    faults = FaultConfig(late_reply_rate=1.0, late_reply_delay_s=0.025)
    async with sim_bus([LAModel(7, silent_replies=1)], faults=faults) as (bus, _):
        report = ScanReport()
        seen: list[int] = []
        assert await scan(
            bus, range(1, 40), report=report, progress=lambda i, n, h: seen.append(i)
        ) == [7]
    assert report.passes[0].late == [] and report.passes[1].found == [7]
    assert report.passes[1].tried.count(7) == 2
    assert sorted(seen) == list(range(1, 40))  # still once per ID


async def test_an_id_that_only_ever_answers_late_is_reported_not_found() -> None:
    faults = FaultConfig(late_reply_rate=1.0, late_reply_delay_s=0.080)
    async with sim_bus([LAModel(2)], faults=faults) as (bus, _):
        report = ScanReport()
        assert await scan(bus, range(2, 101), report=report) == []
        # The last late reply may still be on its way: wait for it before closing.
        while bus.stats.late_replies < 2:
            await bus.timer.sleep_until(bus.timer.now() + 0.01)
    assert report.late == [2]


async def test_one_pass_and_a_fixed_timeout_are_the_old_scan() -> None:
    async with sim_bus([LAModel(1), LAModel(4, silent_replies=1)]) as (bus, _):
        report = ScanReport()
        seen: list[int] = []
        found = await scan(
            bus,
            range(1, 6),
            timeout=0.050,
            passes=1,
            progress=lambda i, n, hit: seen.append(i),
            report=report,
        )
    assert found == [1]  # 4 missed its only query
    assert seen == [1, 2, 3, 4, 5]  # one pass: progress in ID order
    assert [p.budget_s for p in report.passes] == [0.050]


async def test_a_fixed_timeout_holds_for_both_passes() -> None:
    async with sim_bus([LAModel(4, silent_replies=1)]) as (bus, _):
        report = ScanReport()
        assert await scan(bus, [4, 5], timeout=0.004, report=report) == [4]
    assert [p.budget_s for p in report.passes] == [0.004, 0.004]
    assert report.passes[1].found == [4]


async def test_slower_baud_rates_get_a_floor_of_their_wire_time() -> None:
    async with sim_bus([LAModel(1, baud_code=la.BaudCode.B19200)], baud=19200) as (bus, _):
        report = ScanReport()
        assert await scan(bus, [1, 2], report=report) == [1]
    assert report.floor_s == pytest.approx(floor_at(19200))
    assert report.floor_s > 0.015  # 30 bytes at 19200 bit/s alone take 15.6 ms


async def test_bad_scan_arguments_send_nothing() -> None:
    async with sim_bus([LAModel(1)]) as (bus, _):
        for kwargs in ({"passes": 0}, {"passes": 3}, {"timeout": -1}, {"timeout": float("nan")}):
            with pytest.raises(LocalProtocolError):
                await scan(bus, [1], **kwargs)  # type: ignore[arg-type]
        with pytest.raises(LocalProtocolError, match="id"):
            await scan(bus, [1, 255])
        assert bus.stats.requests == 0


async def test_the_report_is_json_ready() -> None:
    async with sim_bus([LAModel(1)]) as (bus, _):
        report = ScanReport()
        await scan(bus, [1, 2], report=report)
    doc = report.as_dict()
    assert doc["found"] == [1] and len(doc["passes"]) == 2  # type: ignore[arg-type]
    assert doc["passes"][0]["tried"] == 2  # type: ignore[index]
    assert set(doc["passes"][0]) == {"budget_ms", "tried", "found", "late", "seconds"}  # type: ignore[index]


def test_the_model_option_silences_only_the_first_replies() -> None:
    model = LAModel(5, silent_replies=2)
    query = la.Control(5, la.ControlAction.QUERY_STATUS).encode()
    assert [len(model.handle(query, 0.0)) for _ in range(3)] == [0, 0, 1]
    assert model.silenced == 2
    assert model.handle(la.Control(6, la.ControlAction.QUERY_STATUS).encode(), 0.0) == []
    with pytest.raises(LocalProtocolError, match="silent_replies"):
        LAModel(5, silent_replies=-1)
