"""Process groups of a bus file: ``process = NAME`` in a ``[[bus]]`` table says which
program serves the bus, and a ``[process.NAME]`` table says on which CPUs it runs.

Every group table is checked when the file loads, like the bus tables: a bad value is one
line naming the file, the group's table, the key, the value and what is allowed; choosing
a group the file does not have names the groups it has.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

from motorbus import ProcessGroup, load_bus_file
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager

#: This machine's highest CPU number (the allowed range is 0..TOP).
TOP = (os.cpu_count() or 1) - 1

HEAD = """
[[bus]]
name = "left"
url = "/dev/ttyUSB0"
baud = 921600
process = "arms"

[[bus]]
name = "spare"
url = "/dev/ttyUSB1"
baud = 921600

[[bus]]
name = "right"
url = "/dev/ttyUSB2"
baud = 921600
process = "arms"

[[bus]]
name = "hip"
url = "socket://10.0.0.5:7012"
baud = 921600
process = "legs"
"""


def _file(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "buses.toml"
    path.write_text(HEAD + body, encoding="utf-8")
    return path


def test_groups_are_the_ones_the_buses_name_with_their_tables(tmp_path: Path) -> None:
    bus_file = load_bus_file(_file(tmp_path, f"\n[process.legs]\ncpus = [{TOP}, 0]\n"))
    assert bus_file.groups == {
        "arms": ProcessGroup("arms", ("left", "right"), None),
        "legs": ProcessGroup("legs", ("hip",), frozenset({0, TOP})),
    }
    assert [s.name for s in bus_file.specs_of("arms")] == ["left", "right"]
    assert [s.name for s in bus_file.specs_of("legs")] == ["hip"]
    assert [s.name for s in bus_file.specs_of(None)] == ["left", "spare", "right", "hip"]
    assert bus_file.spec("spare").process is None


def test_a_file_without_groups_loads_as_before(tmp_path: Path) -> None:
    path = tmp_path / "buses.toml"
    path.write_text('[[bus]]\nurl = "/dev/ttyUSB0"\nbaud = 9600\n', encoding="utf-8")
    bus_file = load_bus_file(path)
    assert bus_file.groups == {} and len(bus_file.specs_of(None)) == 1


@pytest.mark.parametrize(
    "cpus", [[0], [TOP], list(range(TOP + 1)), list(range(TOP, -1, -1))], ids=str
)
def test_every_cpu_of_this_machine_is_accepted(tmp_path: Path, cpus: list[int]) -> None:
    path = _file(tmp_path, f"\n[process.arms]\ncpus = {cpus}\n")
    assert load_bus_file(path).groups["arms"].cpus == frozenset(cpus)


#: (the ``[process.arms]`` table's body, what the message must say after "<file>: ")
BAD_TABLES: dict[str, tuple[str, str]] = {
    "cpu-past-the-last": (
        f"cpus = [0, {TOP + 1}]",
        f"[process.arms]: cpus: CPU {TOP + 1} is out of range: allowed 0..{TOP}",
    ),
    "negative-cpu": (
        "cpus = [-1]",
        f"[process.arms]: cpus: CPU -1 is out of range: allowed 0..{TOP}",
    ),
    "bool-cpu": ("cpus = [true]", f"CPU True is out of range: allowed 0..{TOP}"),
    "float-cpu": ("cpus = [1.0]", f"CPU 1.0 is out of range: allowed 0..{TOP}"),
    "text-cpu": ('cpus = ["0"]', f"CPU '0' is out of range: allowed 0..{TOP}"),
    "empty": ("cpus = []", "[process.arms]: cpus is empty: give at least one CPU"),
    "not-a-list": (
        "cpus = 2",
        "[process.arms]: cpus must be a list of CPU numbers such as [2, 3], got 2 (int)",
    ),
    "text": ('cpus = "0-1"', "cpus must be a list of CPU numbers such as [2, 3], got '0-1'"),
    "twice": ("cpus = [0, 0]", "cpus=[0, 0] lists CPU 0 twice: each CPU must be listed once"),
    "unknown-key": (
        "realtime = true",
        "[process.arms]: unknown keys ['realtime']; allowed: ['cpus']",
    ),
}


@pytest.mark.parametrize(("body", "fragment"), BAD_TABLES.values(), ids=BAD_TABLES)
def test_a_bad_group_table_is_refused_naming_file_group_key_and_range(
    tmp_path: Path, body: str, fragment: str
) -> None:
    path = _file(tmp_path, f"\n[process.arms]\n{body}\n")
    with pytest.raises(LocalProtocolError) as info:
        BusManager.from_toml(path)
    text = str(info.value)
    assert "\n" not in text
    assert text.startswith(f"{path}: [process.arms]: "), text
    assert fragment in text, text
    key = "cpus" if "cpus" in body else "process"
    assert info.value.field == key


@pytest.mark.parametrize(
    ("body", "fragment"),
    [
        (
            "[process.arm]\ncpus = [0]",  # a typo of "arms"
            "[process.arm]: no [[bus]] has process = 'arm': a group must serve a bus "
            "(the groups the buses name: arms, legs)",
        ),
        (
            '[process."my arms"]\ncpus = [0]',
            "[process.my arms]: process='my arms' is not allowed: a process group name must "
            "be 1..32 ASCII letters, digits, '-' or '_'",
        ),
        ("[process]\narms = 3", "[process.arms]: must be a table of keys (cpus = [...]), got 3"),
    ],
    ids=["typo", "bad-name", "not-a-table"],
)
def test_a_group_table_of_no_group_is_refused(tmp_path: Path, body: str, fragment: str) -> None:
    path = _file(tmp_path, "\n" + body + "\n")
    with pytest.raises(LocalProtocolError) as info:
        load_bus_file(path)
    assert str(info.value) == f"{path}: {fragment}"


def test_process_at_the_top_level_is_refused_with_where_it_goes(tmp_path: Path) -> None:
    path = tmp_path / "buses.toml"
    path.write_text('process = "arms"\n' + HEAD, encoding="utf-8")
    with pytest.raises(LocalProtocolError) as info:
        load_bus_file(path)
    assert str(info.value).startswith(
        f"{path}: process='arms' is not allowed at the top level: a group's settings are "
        "a [process.NAME] table"
    )


@pytest.mark.parametrize(
    ("process", "fragment"),
    [
        ("hands", "process='hands' is not a process group of this file: choose one of arms, legs"),
        ("", "process='' is not allowed: a process group name must be 1..32"),
        (5, "process=5 is not allowed"),
    ],
)
def test_choosing_a_group_the_file_has_not_names_the_groups_it_has(
    tmp_path: Path, process: Any, fragment: str
) -> None:
    path = _file(tmp_path, "")
    with pytest.raises(LocalProtocolError) as info:
        BusManager.from_toml(path, process=process)
    assert str(info.value).startswith(f"{path}: {fragment}"), str(info.value)
    assert info.value.field == "process"


def test_choosing_a_group_in_a_file_without_groups_says_it_has_none(tmp_path: Path) -> None:
    path = tmp_path / "buses.toml"
    path.write_text('[[bus]]\nurl = "/dev/ttyUSB0"\nbaud = 9600\n', encoding="utf-8")
    with pytest.raises(LocalProtocolError) as info:
        BusManager.from_toml(path, process="arms")
    assert str(info.value) == (
        f"{path}: process='arms' is not a process group of this file: the file has none "
        "(no [[bus]] sets process)"
    )


def test_from_toml_and_from_dict_take_exactly_the_groups_buses(tmp_path: Path) -> None:
    path = _file(tmp_path, "\n[process.arms]\ncpus = [0]\n")
    arms = BusManager.from_toml(path, process="arms")
    assert list(arms.specs) == ["left", "right"]  # not "spare", which has no group
    assert arms.process == ProcessGroup("arms", ("left", "right"), frozenset({0}))
    legs = BusManager.from_toml(path, process="legs")
    assert list(legs.specs) == ["hip"] and legs.process is not None
    assert legs.process.cpus is None
    everything = BusManager.from_toml(path)
    assert list(everything.specs) == ["left", "spare", "right", "hip"]
    assert everything.process is None
    data = {
        "bus": [
            {"name": "a", "url": "/dev/ttyUSB0", "baud": 9600, "process": "g"},
            {"name": "b", "url": "/dev/ttyUSB1", "baud": 9600},
        ],
        "process": {"g": {"cpus": [TOP]}},
    }
    mgr = BusManager.from_dict(data, process="g")
    assert list(mgr.specs) == ["a"] and mgr.process == ProcessGroup("g", ("a",), frozenset({TOP}))
    with pytest.raises(LocalProtocolError, match="process='h' is not a process group"):
        BusManager.from_dict(data, process="h")


def test_a_group_built_in_code_is_checked_too() -> None:
    with pytest.raises(LocalProtocolError, match="process='a b' is not allowed"):
        ProcessGroup("a b", ("x",))
    with pytest.raises(LocalProtocolError, match=f"CPU {TOP + 1} is out of range"):
        ProcessGroup("a", ("x",), frozenset({TOP + 1}))
