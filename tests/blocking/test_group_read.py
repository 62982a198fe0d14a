"""Group reads: ``read_statuses`` queries many LA actuators in one call, pipelined.

Against a simulator process (blocking form): 15 actuators at 15 positions come back
right, from exactly one status query each, written in the order asked, each answered
before the next went out.  Over the in-memory link (asyncio form): what a silent
actuator gives, after the bus's retries, with ``on_error="raise"`` and ``"return"``;
and bad input is refused before anything is sent.
"""

from __future__ import annotations

from pathlib import Path

import pytest

import motorbus
import motorbus.blocking as mb
from motorbus.devices.group import read_statuses
from motorbus.protocol import la
from motorbus.sim.la import LAModel
from motorbus.sim.process import SimProcess
from tests.blocking.frames import BAUD, HOST_MARGIN_S, query
from tests.helpers import PACINGS, sim_bus

IDS = list(range(1, 16))


def position_of(ident: int) -> int:
    return 100 * ident + 7


def test_fifteen_statuses_in_one_pipelined_round(tmp_path: Path) -> None:
    specs = [f"la:{i},position={position_of(i)}" for i in IDS]
    with SimProcess(specs, baud=BAUD, log_file=tmp_path / "sim.jsonl") as sim:
        transport = motorbus.open_transport(sim.path, baudrate=BAUD)
        with mb.Bus(transport, families=[motorbus.Family.LA], host_margin=HOST_MARGIN_S) as bus:
            statuses = mb.read_statuses(bus, IDS)
            again = bus.read_statuses(reversed(IDS))
            records = sim.log_records()
    assert list(statuses) == IDS
    assert {i: s.position for i, s in statuses.items()} == {i: position_of(i) for i in IDS}
    assert all(s.id == i for i, s in statuses.items())
    assert list(again) == IDS[::-1]
    frames = [(r["direction"], bytes.fromhex(str(r["hex"]))) for r in records]
    # Exactly one query per actuator, in the order asked, and the bus's half-duplex
    # rule kept: each query's reply came before the next query went out.
    expected: list[tuple[str, int]] = []
    for ident in IDS + IDS[::-1]:
        expected += [("request", ident), ("reply", ident)]
    assert [(d, f[3]) for d, f in frames] == expected
    requests = [f for d, f in frames if d == "request"]
    assert requests == [query(i) for i in IDS + IDS[::-1]]
    assert all(len(f) == 22 for d, f in frames if d == "reply")  # full status frames


@pytest.mark.parametrize("pacing", PACINGS)
async def test_a_silent_actuator_is_named_after_the_bus_retries(pacing: str) -> None:
    models = [LAModel(i) for i in (1, 2, 3)]
    models[1] = LAModel(2, silent_replies=1_000)  # la:2 hears and never answers
    async with sim_bus(models, pacing=pacing, retries=1) as (bus, _):  # type: ignore[arg-type]
        with pytest.raises(motorbus.GroupReadError) as raised:
            await read_statuses(bus, [1, 2, 3])
        err = raised.value
        assert list(err.statuses) == [1, 3]
        assert list(err.failures) == [2]
        assert isinstance(err.failures[2], motorbus.ReplyTimeoutError)
        assert "IDs 2" in str(err) and "1 of 3" in str(err)
        # The bus retried la:2's query once before giving up on it.
        assert models[1].silenced == 2  # it heard the query and the bus's one retry

        mixed = await read_statuses(bus, [3, 2, 1], on_error="return")
        assert list(mixed) == [3, 2, 1]
        assert isinstance(mixed[2], motorbus.ReplyTimeoutError)
        assert isinstance(mixed[1], la.Status) and isinstance(mixed[3], la.Status)


@pytest.mark.parametrize("pacing", PACINGS)
async def test_a_reply_lost_once_is_retried_and_the_program_sees_only_the_status(
    pacing: str,
) -> None:
    models = [LAModel(1), LAModel(2, silent_replies=1), LAModel(3)]  # la:2 misses one reply
    async with sim_bus(models, pacing=pacing, retries=1) as (bus, _):  # type: ignore[arg-type]
        statuses = await read_statuses(bus, [1, 2, 3])
        assert list(statuses) == [1, 2, 3]
        assert models[1].silenced == 1  # its first query went unanswered...
        assert bus.stats.retries == 1  # ...and the bus asked again, once
        assert bus.stats.timeouts >= 1


@pytest.mark.parametrize(
    ("ids", "field"),
    [([], "ids"), ([0], "ids"), ([255], "ids"), ([1, 2, 1], "ids"), ("1-3", "ids"), (7, "ids")],
)
async def test_bad_id_lists_are_refused_and_nothing_is_sent(ids: object, field: str) -> None:
    model = LAModel(1)
    async with sim_bus([model]) as (bus, _):
        with pytest.raises(motorbus.LocalProtocolError) as err:
            await read_statuses(bus, ids)  # type: ignore[arg-type]
        assert err.value.field == field
        with pytest.raises(motorbus.LocalProtocolError) as bad_choice:
            await read_statuses(bus, [1], on_error="skip")  # type: ignore[call-overload]
        assert bad_choice.value.field == "on_error"
        assert bus.stats.requests == 0
