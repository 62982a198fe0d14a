"""Malformed payloads and unknown keys get a clear error and send nothing; the served
steppers run to their end (``EE DD``, the quad's done); the command needs its extra."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytest.importorskip("zenoh")

import zenoh

import motorbus
from motorbus import InspireLA, ProjectStepper, QuadStepper
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.serve import keys as k
from motorbus.sim import SimProcess
from tests.serve.conftest import Child

ERR = "bad_payload"
STATUS_1 = la.Control(1, la.ControlAction.QUERY_STATUS).encode()


def raw_query(endpoint: str, key: str, payload: bytes) -> dict[str, object]:
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("mode", '"client"')
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    with zenoh.open(config) as session:
        for reply in session.get(key, payload=payload, timeout=10):
            if reply.ok is not None:
                return {"ok": True, **json.loads(reply.ok.payload.to_bytes())}
            return json.loads(reply.err.payload.to_bytes())  # type: ignore[no-any-return]
    raise AssertionError(f"no answer to {key}")


@pytest.mark.parametrize(
    ("payload", "error", "field"),
    [
        (b"\xff not json", "bad_payload", "payload"),
        (b"[1, 2]", "bad_payload", "payload"),
        (b'{"frame": "55aa03010400141c"}', "bad_payload", "client"),
        (b'{"client": "x", "frame": "zz"}', "bad_payload", "frame"),
        (b'{"client": "x", "frame": "55aa03010400141d"}', "bad_payload", "frame"),
        (
            b'{"client": "x", "frame": "55aa03010400141c", "priority": "now"}',
            "bad_payload",
            "priority",
        ),
        (b'{"client": "x", "frame": "55aa03010400141c", "timeout": "1"}', "bad_payload", "timeout"),
        (b'{"client": "x", "frame": "ffaa0000000000000000"}', "bad_payload", "frame"),
        # A misspelt option is refused, not ignored.
        (b'{"client": "x", "frame": "55aa03010400141c", "timeuot": 1}', "bad_payload", "timeuot"),
    ],
)
def test_a_malformed_request_is_refused_naming_the_field_and_nothing_is_sent(
    la_sim: SimProcess, la_server: Child, endpoint: str, payload: bytes, error: str, field: str
) -> None:
    before = len(la_sim.log_records())
    answer = raw_query(endpoint, k.bus_key("bus", "request"), payload)
    assert answer["ok"] is False and answer["error"] == error and answer["field"] == field
    assert len(la_sim.log_records()) == before  # nothing reached the bus
    # The server keeps serving.
    good = raw_query(
        endpoint,
        k.bus_key("bus", "request"),
        k.encode_json(
            {"client": "x", "frame": la.Control(1, la.ControlAction.QUERY_STATUS).encode().hex()}
        ),
    )
    assert good["ok"] is True and isinstance(good["reply"], str)


def test_unknown_lease_operations_and_leases_are_refused(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    key = k.bus_key("bus", "lease")
    answer = raw_query(endpoint, key, k.encode_json({"client": "x", "op": "steal"}))
    assert answer["error"] == "bad_payload" and answer["field"] == "op"
    answer = raw_query(
        endpoint,
        key,
        k.encode_json({"client": "x", "op": "acquire", "keys": ["la:1"], "owner": "x", "bind": 1}),
    )
    assert answer["error"] == "bad_payload" and answer["field"] == "bind"
    leases = raw_query(endpoint, k.bus_key("bus", "leases"), b'{"client": "x", "all": true}')
    assert leases["error"] == "bad_payload" and leases["field"] == "all"
    answer = raw_query(endpoint, key, k.encode_json({"client": "x", "op": "release", "lease": 99}))
    assert answer["error"] == "lease_gone" and "lease 99" in str(answer["message"])
    move = la.MoveTo(1, 300, True).encode().hex()
    answer = raw_query(
        endpoint,
        k.bus_key("bus", "request"),
        k.encode_json({"client": "x", "frame": move, "lease": 7}),
    )
    assert answer["error"] == "lease_gone"
    assert bytes.fromhex(move) not in [bytes.fromhex(r["hex"]) for r in la_sim.log_records()]


async def test_a_served_bus_refuses_another_familys_command_before_sending(
    la_sim: SimProcess, la_server: Child, endpoint: str
) -> None:
    async with motorbus.connect(endpoint) as site:
        with pytest.raises(motorbus.LocalProtocolError, match="carries la"):
            await site.bus().request(ps.StartProject(1))
        with pytest.raises(motorbus.LocalProtocolError, match="serves bus"):
            site.bus("nope")
        assert (await InspireLA(site.bus(), 2).status()).id == 2


async def test_served_project_upload_and_run_to_ee_dd_and_quad_run_to_done(
    stepper_server: str,
) -> None:
    step = ps.StepSpec(run_distance=20, start_hz=2000, speed_rpm=600)
    project = ps.Project(
        number=1, subdivision=1, step_angle_x100=180, distance_per_rev=200, steps=(step,)
    )
    async with motorbus.connect(stepper_server) as site:
        bus = site.bus()
        stepper = ProjectStepper(bus)
        dump = await stepper.upload(project, save=False)
        assert dump is not None and dump.to_project() == project
        await stepper.run_project(1, timeout=10)  # returns on the served EE DD
        quad = QuadStepper(bus)
        await quad.configure(
            2, subdivision=8, step_angle_x100=180, pulses=400, start_hz=50, accel_hz=0,
            speed_rpm=600,
        )  # fmt: skip
        await quad.run(2, timeout=10)  # returns on the served done reply


def test_serve_without_zenoh_names_the_extra_and_exits_2() -> None:
    code = (
        "import sys; sys.modules['zenoh'] = None\n"
        "from motorbus.cli.main import main\n"
        "sys.exit(main(['serve', '--port', '/dev/null', '--baud', '921600']))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert "pip install 'motorbus[serve]'" in out.stderr


def test_connect_without_zenoh_names_the_extra() -> None:
    code = (
        "import sys, asyncio; sys.modules['zenoh'] = None\n"
        "import motorbus\n"
        "async def main():\n"
        "    async with motorbus.connect('tcp/127.0.0.1:1'):\n"
        "        pass\n"
        "try:\n"
        "    asyncio.run(main())\n"
        "except ImportError as err:\n"
        "    print(err)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert "pip install 'motorbus[serve]'" in out.stdout
