"""Named, calibrated devices in the bus file: ``[bus.la.NAME]`` and calibration files.

A bus file whose calibration cannot be right is refused when it loads, with one line
naming the file, the device, the key, the value and what is allowed; a calibration
file written by ``write_calibration_file`` is read back by the next load (a restart).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from motorbus.devices.calibration import Calibration, write_calibration_file
from motorbus.errors import LocalProtocolError
from motorbus.manager import BusManager
from motorbus.sim.la import LAModel
from motorbus.sim.memory import MemorySim

ARM = """
[[bus]]
name = "arm"
url = "/dev/ttyUSB0"
baud = 921600
devices = ["la:1"]
{extra}

[bus.la.gripper]
id = 1
stroke_mm = 30
limits = [100, 1900]
unit = "mm"

[bus.la.left_knee]
id = 2
{knee}
"""


def _write(tmp_path: Path, extra: str = "", knee: str = "") -> Path:
    path = tmp_path / "arm.toml"
    path.write_text(ARM.format(extra=extra, knee=knee), encoding="utf-8")
    return path


def test_named_devices_load_with_their_calibration(tmp_path: Path) -> None:
    mgr = BusManager.from_toml(_write(tmp_path, knee='direction = "reversed"'))
    spec = mgr.specs["arm"]
    gripper, knee = spec.la
    assert (gripper.name, gripper.id) == ("gripper", 1)
    assert gripper.calibration == Calibration(stroke_mm=30, limits=(100, 1900), unit="mm")
    assert knee.calibration == Calibration(direction="reversed")
    # A named ID the devices list leaves out is added: the safe stop reaches it.
    assert sorted(i for d in spec.devices for i in d.ids) == [1, 2]


def test_the_bus_stroke_is_each_named_devices_default(tmp_path: Path) -> None:
    path = _write(tmp_path, extra="la_stroke_mm = 50")
    gripper, knee = BusManager.from_toml(path).specs["arm"].la
    assert gripper.calibration.stroke_mm == 30.0 and knee.calibration.stroke_mm == 50.0


# -- refused at load: file, device, key, value, what is allowed ------------------------------

BAD_DEVICE_KEYS = [
    ("limits = [0, 2100]", "limits=[0, 2100]", "0 <= low < high <= 2000"),
    ("limits = [-1, 100]", "limits=[-1, 100]", "0 <= low < high <= 2000"),
    ("limits = [500, 500]", "limits=[500, 500]", "low < high"),
    ("limits = [1900, 100]", "limits=[1900, 100]", "low < high"),
    ("limits = [1.5, 100]", "limits=[1.5, 100]", "two integer raw positions"),
    ("limits = 100", "limits=100", "two integer raw positions"),
    ('unit = "inch"', "unit='inch'", "raw | mm | percent"),
    ('unit = "mm"', "unit='mm' needs stroke_mm", "1..1000"),
    ("offset_mm = 3.0", "offset_mm=3.0 needs stroke_mm", "1..1000"),
    ('direction = "up"', "direction='up'", "normal | reversed"),
    ("stroke_mm = 0", "stroke_mm=0", "allowed 1..1000 mm"),
    ("stroke_mm = nan", "stroke_mm=nan", "allowed 1..1000 mm"),
    ("stroke_mm = 30\noffset_mm = 5000", "offset_mm=5000", "allowed -1000..1000 mm"),
    ("limit = [0, 10]", "unknown keys ['limit']", "allowed: ['stroke_mm', 'limits'"),
    ("id = 0", "id=0", "1..254"),
]


@pytest.mark.parametrize(("knee", "shown", "allowed"), BAD_DEVICE_KEYS)
def test_a_bad_key_of_a_named_device_is_refused_naming_it(
    tmp_path: Path, knee: str, shown: str, allowed: str
) -> None:
    path = _write(tmp_path, knee=knee.replace("id = 0", ""))
    if knee == "id = 0":
        path.write_text(path.read_text().replace("id = 2", "id = 0"))
    with pytest.raises(LocalProtocolError) as info:
        BusManager.from_toml(path)
    text = str(info.value)
    assert text.startswith(f"{path}: bus 'arm' (#1): la.left_knee: "), text
    assert shown in text and allowed in text and "\n" not in text, text


@pytest.mark.parametrize(
    ("change", "shown"),
    [
        (("id = 2", "id = 1"), "la.left_knee: id=1 is the ID of la.gripper too: each ID once"),
        (("[bus.la.left_knee]", "[bus.la.1knee]"), "name='1knee' is not allowed"),
        (("[bus.la.left_knee]\nid = 2", "[bus.la.left_knee]"), "a table with id = 1..254"),
    ],
)
def test_ids_and_names_are_checked(tmp_path: Path, change: tuple[str, str], shown: str) -> None:
    path = _write(tmp_path)
    path.write_text(path.read_text().replace(*change))
    with pytest.raises(LocalProtocolError, match=shown.replace(".", r"\.")) as info:
        BusManager.from_toml(path)
    assert str(info.value).startswith(f"{path}: bus 'arm'")


def test_a_name_on_two_buses_is_refused(tmp_path: Path) -> None:
    path = _write(tmp_path)
    other = (
        '\n[[bus]]\nname = "leg"\nurl = "/dev/ttyUSB1"\nbaud = 921600\n[bus.la.gripper]\nid = 4\n'
    )
    path.write_text(path.read_text() + other)
    with pytest.raises(LocalProtocolError) as info:
        BusManager.from_toml(path)
    assert str(info.value) == (
        f"{path}: bus 'leg': la.gripper is a device of bus 'arm' too: each name once per file"
    )


# -- calibration files ---------------------------------------------------------------------------


def test_a_calibration_file_overrides_the_bus_file_and_survives_a_restart(tmp_path: Path) -> None:
    path = _write(tmp_path, extra='calibration = "arm.cal.toml"')
    cal_path = tmp_path / "arm.cal.toml"
    measured = Calibration(stroke_mm=30, limits=(212, 1788), unit="percent")
    write_calibration_file(cal_path, "gripper", measured)
    write_calibration_file(cal_path, "left_knee", Calibration(limits=(5, 1995)))
    # A restart: a new manager reads the bus file and its calibration file again.
    mgr = BusManager.from_toml(path)
    gripper, knee = mgr.specs["arm"].la
    assert gripper.calibration == measured and knee.calibration.limits == (5, 1995)
    assert mgr.specs["arm"].calibration == str(cal_path)
    # Writing one device keeps the others' entries.
    write_calibration_file(cal_path, "gripper", Calibration(stroke_mm=30, limits=(0, 2000)))
    gripper, knee = BusManager.from_toml(path).specs["arm"].la
    assert gripper.calibration.limits == (0, 2000) and knee.calibration.limits == (5, 1995)
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


@pytest.mark.parametrize(
    ("text", "shown"),
    [
        ("[gripper]\nlimits = [0, 3000]\n", "arm.cal.toml: [gripper]: limits=[0, 3000]"),
        ('[gripper]\nunit = "feet"\n', "arm.cal.toml: [gripper]: unit='feet' is not allowed"),
        ("[gripper]\nlimits = [7, 7]\n", "[gripper]: limits=[7, 7] is not allowed"),
        ("[gripper]\nspeed = 3\n", "[gripper]: unknown keys ['speed']"),
        ("[wrist]\nlimits = [0, 10]\n", "[wrist] names no device of the buses that use this"),
        ("gripper = 3\n", "gripper=3 is not allowed: each entry is a [NAME] table"),
        ("[gripper\n", "arm.cal.toml: not valid TOML"),
    ],
)
def test_a_bad_calibration_file_is_refused_naming_file_and_key(
    tmp_path: Path, text: str, shown: str
) -> None:
    path = _write(tmp_path, extra='calibration = "arm.cal.toml"')
    (tmp_path / "arm.cal.toml").write_text(text, encoding="utf-8")
    with pytest.raises(LocalProtocolError) as info:
        BusManager.from_toml(path)
    assert str(info.value).startswith(f"{path}: {tmp_path}/"), str(info.value)
    assert shown in str(info.value)


def test_a_missing_calibration_file_is_refused_unless_allowed(tmp_path: Path) -> None:
    path = _write(tmp_path, extra='calibration = "arm.cal.toml"')
    with pytest.raises(LocalProtocolError, match=r"calibration='.*arm\.cal\.toml': no such file"):
        BusManager.from_toml(path)
    from motorbus.busfile import load_bus_file

    assert load_bus_file(path, missing_calibration_ok=True).specs[0].la[0].name == "gripper"


# -- the manager's named devices -----------------------------------------------------------------


async def test_device_by_name_moves_in_its_unit_within_its_limits(tmp_path: Path) -> None:
    models = [LAModel(1), LAModel(2)]
    async with MemorySim.start(models) as sim:
        mgr = BusManager.from_toml(_write(tmp_path, knee='unit = "percent"\nlimits = [0, 1000]'))
        spec = mgr.specs.pop("arm")
        spec.host_margin_ms = 50.0
        mgr.add_spec(spec, sim.transport)
        async with mgr:
            gripper = mgr.device("gripper")
            assert (gripper.name, gripper.id, gripper.unit) == ("gripper", 1, "mm")
            status = await gripper.move_to(12.5)  # mm: 12.5 / 30 * 2000
            assert status is not None and status.target == 833
            await mgr.device("left_knee").move_to(50)  # percent of 0..1000
            assert models[1].target == 500
            # By ID: the same limits, raw units (programs that use IDs are unchanged).
            by_id = mgr.la("arm", 1)
            assert (by_id.name, by_id.unit, by_id.calibration.limits) == (
                "gripper",
                "raw",
                (100, 1900),
            )
            before = sim.bus.stats.requests
            for call, shown in [
                (gripper.move_to(29.0), "gripper: mm=29.0 is out of range: allowed 1.5..28.5 mm"),
                (gripper.move_to(1.0, unit="mm"), "gripper: mm=1.0 is out of range"),
                (gripper.move_to(1950, unit="raw"), "gripper: position=1950 is out of range"),
                (by_id.move_to(50), "gripper: position=50 is out of range: allowed 100..1900"),
                (gripper.follow(101.0, unit="percent"), "gripper: percent=101.0 is out of range"),
                (gripper.move_to(float("nan")), "gripper: mm must be a finite number"),
            ]:
                with pytest.raises(LocalProtocolError) as info:
                    await call
                assert shown in str(info.value) and "nothing sent" in str(info.value)
            assert sim.bus.stats.requests == before  # the simulator received nothing
            with pytest.raises(LocalProtocolError, match=r"no device named 'wrist'.*gripper"):
                mgr.device("wrist")
