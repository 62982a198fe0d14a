"""One ID-list grammar for the bus files, the simulator specs and the CLI."""

from __future__ import annotations

import pytest

from motorbus.cli.ids import parse_ids
from motorbus.errors import LocalProtocolError
from motorbus.manager import parse_devices
from motorbus.protocol.ids import IdListError, parse_id_list
from motorbus.sim.spec import parse_device_spec


def test_grammar() -> None:
    assert parse_id_list("3") == [3]
    assert parse_id_list("1-3,7") == [1, 2, 3, 7]
    assert parse_id_list(" 1 - 3 , 7 ") == [1, 2, 3, 7]
    assert parse_id_list("7,1") == [7, 1]
    assert parse_id_list("0x10-0X11,010") == [16, 17, 10]


@pytest.mark.parametrize(
    ("text", "problem", "reason"),
    [
        ("5-3", "reversed", "reversed range 5-3: write 3-5"),
        ("5-3,7", "reversed", "reversed range 5-3: write 3-5"),
        ("1-3,2", "duplicate", "lists ID 2 twice"),
        ("5,3,5,3", "duplicate", "lists ID 3 twice"),
        ("1,x", "syntax", "'x' is not an ID or a range like 1-15"),
        ("0x5g", "syntax", "'0x5g' is not an ID or a range like 1-15"),
        ("1,,2", "syntax", "'' is not an ID or a range like 1-15"),
        ("250-300", "range", "id=300 is out of range: allowed 1..254"),
    ],
)
def test_refusals(text: str, problem: str, reason: str) -> None:
    with pytest.raises(IdListError) as info:
        parse_id_list(text)
    assert (info.value.problem, info.value.reason) == (problem, reason)
    assert isinstance(info.value, LocalProtocolError)


@pytest.mark.parametrize("text", ["5-3", "5-3,7", "1-3,2", "1,1", "1,x", "250-300", "0", "255"])
def test_manager_simulator_and_cli_refuse_the_same_lists_with_the_same_reason(
    text: str,
) -> None:
    with pytest.raises(IdListError) as info:
        parse_id_list(text)
    reason = info.value.reason.replace("id=", "")  # each names the ID field its own way
    for parse in (
        lambda: parse_devices([f"la:{text}"]),
        lambda: parse_device_spec(f"la:{text}"),
        lambda: parse_ids(text),
    ):
        with pytest.raises(LocalProtocolError) as err:
            parse()
        assert reason in str(err.value)


def test_manager_and_simulator_accept_the_same_lists() -> None:
    for text in ("1-3,7", "4", " 1 - 3 , 7", "0x10"):
        (spec,) = parse_devices([f"la:{text}"])
        models = parse_device_spec(f"la:{text}")
        assert list(spec.ids) == [m.id for m in models] == parse_id_list(text)  # type: ignore[attr-defined]
