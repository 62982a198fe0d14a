"""Bus files: every key typed and range-checked when loaded; ``open`` raises a real error.

The tables below hold, per key of a ``[[bus]]`` table, values that must be refused:
wrong types (no coercion of text or floats into bools or ints, bools are not numbers)
and values out of range.  Each is tried through ``BusManager.from_dict``, through
``add_bus`` and through a real TOML file; the error must be one line naming the file
(for a file), the bus, the key, the value and what is allowed.
"""

from __future__ import annotations

import asyncio
import math
import re
from pathlib import Path
from typing import Any

import pytest

from motorbus.bus.bus import BusState
from motorbus.bus.timer import default_timer
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager, BusSpec, DeviceSpec, parse_devices
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim
from motorbus.transport.memory import memory_pair

NAN = float("nan")
INF = float("inf")
VALID: dict[str, Any] = {"name": "arm", "url": "/dev/ttyUSB0", "baud": 921600}

#: key -> values that must be refused, each with the text the message must show (None:
#: the value's repr).
BAD: dict[str, list[tuple[Any, str | None]]] = {
    "name": [("", None), (5, None), (True, None), (["arm"], None)],
    "url": [
        ("", None),
        (5, None),
        (False, None),
        ([], None),
        ("/dev/tty\x00USB0", None),
        ("/dev/ttyUSB0\n", None),
    ],
    "baud": [
        (0, None),
        (1, None),
        (7, None),
        (299, None),
        (4_000_001, None),
        (10**12, None),
        (-9600, None),
        ("921600", None),
        (921600.0, None),
        (1.5, None),
        (True, None),
        (NAN, None),
    ],
    "backend": [("turbo", None), ("", None), ("FAST", None), (1, None), (True, None)],
    "rs485": [("false", None), ("true", None), (0, None), (1, None), ("no", None)],
    "remove_echo": [("no", None), ("yes", None), (1, None), (0.0, None)],
    "low_latency": [("off", None), ("false", None), (0, None), (1, None)],
    "share": [("yes", None), ("true", None), (1, None), (0, None)],
    "guard": [("on", None), ("false", None), (1, None), (1.0, None)],
    "la_stroke_mm": [(0, None), (0.5, None), (1001, None), ("30", None), (True, None), (NAN, None)],
    "min_spacing_ms": [
        (True, None),
        ("1", None),
        ("abc", None),
        (NAN, None),
        (INF, None),
        (-INF, None),
        (-0.1, None),
        (100.5, None),
        (5000, None),
    ],
    "host_margin_ms": [
        (True, None),
        ("2", None),
        (NAN, None),
        (INF, None),
        (-1, None),
        (10_001, None),
    ],
    "retries": [
        (2.7, None),
        (3.0, None),
        ("3", None),
        (True, None),
        (-1, None),
        (11, None),
        (NAN, None),
    ],
    "la_safe_action": [("explode", None), ("PAUSE", None), ("", None), (1, None), (True, None)],
    "process": [
        ("", None),
        ("my arm", None),
        ("arms!", None),
        ("\u00e4rm", None),
        ("x" * 33, None),
        (5, None),
        (True, None),
        (["arms"], None),
    ],
    "devices": [
        ("la:1", None),
        (5, None),
        ([1], "1"),
        ([["la:1"]], "['la:1']"),
        (["la:0"], "id=0"),
        (["la:255"], "id=255"),
        (["la:1-300"], "id=300"),
        (["la:5-3"], "'5-3' is a reversed range"),
        (["la:5-3,7"], "'5-3' is a reversed range"),
        (["la:x"], "'x'"),
        (["la:"], "no IDs"),
        (["la"], "no IDs"),
        (["printer"], "'printer'"),
        (["project-stepper:motor=999"], "motor=999"),
        (["project-stepper:motor=0"], "motor=0"),
        (["project-stepper:motor=0x1E"], "motor=0x1E"),
        (["project-stepper:speed=3"], "motor=N"),
        (["quad-stepper:motor=1"], "no options"),
        (["la:1-2", "la:2"], "la ids [2] are listed twice"),
        (["quad-stepper", "quad-stepper"], "quad_stepper is listed twice"),
        (["project-stepper", "project-stepper:motor=4"], "project_stepper is listed twice"),
    ],
    # Named devices' own keys (limits, unit...) are refused in tests/busfile/test_named.py.
    "la": [(5, None), ("gripper", None), ([1], None), (True, None)],
    "calibration": [("", None), (5, None), (True, None), ("arm\x00.cal.toml", None)],
}

CASES = [
    pytest.param(key, value, shown, id=f"{key}={value!r}")
    for key, values in BAD.items()
    for value, shown in values
]


def test_every_bus_key_has_bad_values_in_the_table() -> None:
    # A key added to the bus file without refusal cases fails here.
    assert set(BAD) == set(BusSpec.__dataclass_fields__)


def _check_message(err: LocalProtocolError, key: str, value: Any, shown: str | None) -> str:
    text = str(err)
    assert "\n" not in text, text
    assert err.field == key, (err.field, text)
    assert key in text, text
    assert (shown if shown is not None else repr(value)) in text, text
    assert re.search(r"allowed|choose|must be|forms:|once per bus|at most one", text), text
    return text


@pytest.mark.parametrize(("key", "value", "shown"), CASES)
def test_from_dict_refuses(key: str, value: Any, shown: str | None) -> None:
    table = {**VALID, key: value}
    with pytest.raises(LocalProtocolError) as info:
        BusManager.from_dict({"bus": [{"url": "/dev/ttyUSB1", "baud": 9600}, table]})
    text = _check_message(info.value, key, value, shown)
    # The bus is named by its name when it has a usable one, and always by its index.
    assert "#2" in text, text
    if key != "name":
        assert "bus 'arm' (#2)" in text, text


@pytest.mark.parametrize(("key", "value", "shown"), CASES)
def test_add_bus_refuses_and_adds_nothing(key: str, value: Any, shown: str | None) -> None:
    mgr = BusManager()
    table = {**VALID, key: value}
    name, url, baud = table.pop("name"), table.pop("url"), table.pop("baud")
    with pytest.raises(LocalProtocolError) as info:
        mgr.add_bus(name, url, baud=baud, **table)
    _check_message(info.value, key, value, shown)
    assert mgr.specs == {} and mgr.buses == {}


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        text = value.replace("\\", "\\\\").replace('"', '\\"')
        return '"' + re.sub(r"[\x00-\x1f]", lambda m: f"\\u{ord(m.group()):04x}", text) + '"'
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(value)


@pytest.mark.parametrize(("key", "value", "shown"), CASES)
def test_toml_file_refuses_naming_the_file(
    tmp_path: Path, key: str, value: Any, shown: str | None
) -> None:
    table = {**VALID, key: value}
    path = tmp_path / "buses.toml"
    path.write_text(
        "[[bus]]\n" + "".join(f"{k} = {_toml(v)}\n" for k, v in table.items()), encoding="utf-8"
    )
    with pytest.raises(LocalProtocolError) as info:
        BusManager.from_toml(path)
    text = _check_message(info.value, key, value, shown)
    assert text.startswith(f"{path}: bus "), text
    assert "#1" in text, text


def test_the_brief_examples_are_refused_with_their_key_and_bus() -> None:
    # What used to load: a stop command that could not be built at exit, "false" as
    # True, 2.7 as 2, "3" as 3, true as 1.0, 5000 ms; and "abc"/nan as bare ValueErrors.
    for key, value in [
        ("devices", ["project-stepper:motor=999"]),
        ("rs485", "false"),
        ("remove_echo", "no"),
        ("retries", 2.7),
        ("retries", "3"),
        ("min_spacing_ms", True),
        ("min_spacing_ms", 5000),
        ("min_spacing_ms", "abc"),
        ("min_spacing_ms", NAN),
    ]:
        with pytest.raises(LocalProtocolError, match=rf"^bus 'arm' \(#1\): .*{key}"):
            BusManager.from_dict({"bus": [{**VALID, key: value}]})


@pytest.mark.parametrize(
    ("key", "value", "stored"),
    [
        ("baud", 300, 300),
        ("baud", 4_000_000, 4_000_000),
        ("min_spacing_ms", 0, 0.0),
        ("min_spacing_ms", 100, 100.0),
        ("min_spacing_ms", 0.5, 0.5),
        ("host_margin_ms", 0, 0.0),
        ("host_margin_ms", 10_000, 10_000.0),
        ("retries", 0, 0),
        ("retries", 10, 10),
        ("rs485", True, True),
        ("remove_echo", True, True),
        ("low_latency", False, False),
        ("share", True, True),
        ("guard", True, True),
        ("backend", "pyserial-asyncio", "pyserial-asyncio"),
        ("la_safe_action", "hold", "hold"),
        ("la_stroke_mm", 1, 1.0),
        ("la_stroke_mm", 30, 30.0),
        ("la_stroke_mm", 1000, 1000.0),
        ("process", "a", "a"),
        ("process", "Arms_2-" + "x" * 25, "Arms_2-" + "x" * 25),
    ],
)
def test_boundary_values_are_accepted(key: str, value: Any, stored: Any) -> None:
    spec = BusManager.from_dict({"bus": [{**VALID, key: value}]}).specs["arm"]
    got = getattr(spec, key)
    assert got == stored and type(got) is type(stored)


def test_a_valid_file_loads_every_key(tmp_path: Path) -> None:
    path = tmp_path / "buses.toml"
    path.write_text(
        """
[[bus]]
name = "arm"
url = "/dev/ttyUSB0"
baud = 921600
backend = "fast"
rs485 = true
remove_echo = true
low_latency = false
min_spacing_ms = 2
host_margin_ms = 3.5
retries = 2
share = true
guard = true
la_safe_action = "estop"
devices = ["la: 1 - 3 , 7"]

[[bus]]
url = "socket://127.0.0.1:7012"
baud = 9600
devices = ["quad-stepper", "project-stepper:motor=0x05"]
""",
        encoding="utf-8",
    )
    mgr = BusManager.from_toml(path)
    arm, other = mgr.specs["arm"], mgr.specs["bus1"]
    assert (arm.rs485, arm.remove_echo, arm.low_latency) == (True, True, False)
    assert (arm.min_spacing_ms, arm.host_margin_ms, arm.retries) == (2.0, 3.5, 2)
    assert (arm.share, arm.guard) == (True, True)
    assert arm.devices == [DeviceSpec("la", (1, 2, 3, 7))]
    assert other.host_margin_ms == 20.0  # a network bus gets the remote default
    assert (other.share, other.guard) == (False, False)
    assert other.devices == [DeviceSpec("quad_stepper"), DeviceSpec("project_stepper", motor=5)]


@pytest.mark.parametrize(
    ("data", "fragment"),
    [
        ({}, "at least one"),
        ({"bus": []}, "at least one"),
        ({"bus": {"url": "x", "baud": 9600}}, "[[bus]] table (it has [bus]: write [[bus]]"),
        ({"bus": ["x"]}, "bus #1 must be a table"),
        ({"bus": [VALID], "buss": [VALID]}, "unknown top-level keys ['buss']"),
        ({"bus": [{"url": "x"}]}, "'baud' is required"),
        ({"bus": [{"baud": 9600}]}, "'url' is required"),
        ({"bus": [VALID, VALID]}, "bus 'arm' (#2): name='arm' is used twice"),
    ],
)
def test_malformed_files_are_refused(data: dict[str, Any], fragment: str) -> None:
    with pytest.raises(LocalProtocolError) as info:
        BusManager.from_dict(data)
    assert fragment in str(info.value)


def test_unknown_keys_are_refused_with_the_allowed_list() -> None:
    with pytest.raises(LocalProtocolError) as info:
        BusManager.from_dict({"bus": [{**VALID, "speed": 3, "baudrate": 9600}]})
    text = str(info.value)
    assert "bus 'arm' (#1): unknown keys ['baudrate', 'speed']" in text
    assert "allowed: " in text and "'min_spacing_ms'" in text and "'la_safe_action'" in text


def test_invalid_toml_and_missing_files(tmp_path: Path) -> None:
    path = tmp_path / "broken.toml"
    path.write_text("[[bus]\nurl = 1\n", encoding="utf-8")
    with pytest.raises(LocalProtocolError, match=re.escape(f"{path}: not valid TOML")):
        BusManager.from_toml(path)
    with pytest.raises(FileNotFoundError):
        BusManager.from_toml(tmp_path / "missing.toml")


def test_bus_and_device_specs_built_in_code_are_checked_too() -> None:
    with pytest.raises(LocalProtocolError, match=r"^bus 'a': baud=7 is out of range"):
        BusSpec(name="a", url="x", baud=7)
    with pytest.raises(LocalProtocolError, match=r"^bus 'a': rs485 must be True or False"):
        BusSpec(name="a", url="x", baud=9600, rs485="false")  # type: ignore[arg-type]
    with pytest.raises(LocalProtocolError, match="motor=999"):
        DeviceSpec("project_stepper", motor=999)
    with pytest.raises(LocalProtocolError, match="id=0"):
        DeviceSpec("la", (0,))
    with pytest.raises(LocalProtocolError, match="kind='servo'"):
        DeviceSpec("servo")
    with pytest.raises(LocalProtocolError, match="listed twice"):
        BusSpec(name="a", url="x", baud=9600, devices=[DeviceSpec("la", (1,))] * 2)
    assert parse_devices(["la:3-5"]) == [DeviceSpec("la", (3, 4, 5))]


# -- open() --------------------------------------------------------------------------------

MISSING = "/dev/motorbus-no-such-port-{}"


async def test_open_raises_the_missing_port_as_oserror_and_closes_the_others() -> None:
    async with MemorySim.start([LAModel(1)], timer=default_timer()) as sim:
        mgr = BusManager()
        mgr.add_bus("ok", "memory://ok", baud=921600, devices=["la:1"], transport=sim.transport)
        mgr.add_bus("gone", MISSING.format(1), baud=921600, devices=["la:1"])
        mgr.add_bus("gone2", MISSING.format(2), baud=9600)
        with pytest.raises(OSError) as info:  # not an ExceptionGroup
            async with mgr:
                pytest.fail("opened with a missing port")
        err = info.value
        assert not isinstance(err, BaseExceptionGroup)
        assert MISSING.format(1) in str(err)  # the first failing bus in file order
        notes = getattr(err, "__notes__", [])
        assert f"while opening bus 'gone' ({MISSING.format(1)})" in notes
        assert any("bus 'gone2'" in n and MISSING.format(2) in n for n in notes), notes
        assert set(mgr.open_errors) == {"gone", "gone2"}
        assert mgr.buses["ok"].state is BusState.CLOSED
        assert not sim.transport.is_open


class _Broken(Exception):
    pass


async def test_open_prefers_a_real_error_to_an_unexpected_one() -> None:
    host, _peer = memory_pair()

    async def explode(*_args: object) -> None:
        raise _Broken("not an I/O error")

    host.open = explode  # type: ignore[method-assign]
    mgr = BusManager()
    mgr.add_bus("first", "memory://first", baud=921600, transport=host)
    mgr.add_bus("second", MISSING.format(3), baud=921600)
    with pytest.raises(OSError) as info:
        await mgr.open()
    notes = getattr(info.value, "__notes__", [])
    assert any("bus 'first'" in n and "_Broken: not an I/O error" in n for n in notes), notes
    assert isinstance(mgr.open_errors["first"], _Broken)


async def test_open_raises_an_unexpected_error_when_it_is_the_only_one() -> None:
    host, _peer = memory_pair()

    async def explode(*_args: object) -> None:
        raise _Broken("boom")

    host.open = explode  # type: ignore[method-assign]
    mgr = BusManager()
    mgr.add_bus("only", "memory://only", baud=921600, transport=host)
    with pytest.raises(_Broken, match="boom"):
        await mgr.open()


async def test_an_open_cancelled_halfway_closes_the_buses_already_open() -> None:
    host, _peer = memory_pair()
    hanging = asyncio.Event()

    async def hang(*_args: object) -> None:
        hanging.set()
        await asyncio.Event().wait()  # a port that never finishes opening

    host.open = hang  # type: ignore[method-assign]
    async with MemorySim.start([LAModel(1)], timer=default_timer()) as sim:
        mgr = BusManager()
        mgr.add_bus("ok", "memory://ok", baud=921600, devices=["la:1"], transport=sim.transport)
        mgr.add_bus("hangs", "memory://hangs", baud=921600, transport=host)
        task = asyncio.create_task(mgr.open())
        await asyncio.wait_for(hanging.wait(), 5)
        await mgr.buses["ok"].wait_state(BusState.OPEN, timeout=5)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        assert mgr.buses["ok"].state is BusState.CLOSED
        assert not sim.transport.is_open
