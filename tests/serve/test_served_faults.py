"""Malformed payloads and unknown keys get a clear error and send nothing; the served
steppers run to their end (``EE DD``, the quad's done); the command needs its extra."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

import zenoh

import motorbus
from motorbus import InspireLA, ProjectStepper, QuadStepper, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol import project_stepper as ps
from motorbus.protocol import quad_stepper as q
from motorbus.serve import keys as k
from motorbus.sim import SimProcess
from tests.serve.conftest import Child, free_endpoint, serve
from tests.waiting import eventually

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


async def test_a_served_run_that_times_out_or_is_cancelled_is_stopped(tmp_path: Path) -> None:
    # The stop of an abandoned run goes through the served bus's sender of safe actions
    # as through a local bus's lease keeper (before: an AttributeError on a served bus,
    # and the motor or project ran on).
    endpoint = free_endpoint()
    log = tmp_path / "sim.jsonl"
    with SimProcess(["project-stepper", "quad-stepper"], baud=9600, log_file=log) as sim:

        def requests() -> list[bytes]:
            records = sim.log_records()
            return [bytes.fromhex(r["hex"]) for r in records if r["direction"] == "request"]

        server = serve(sim.path, 9600, "project-stepper,quad-stepper", endpoint)
        try:
            async with motorbus.connect(endpoint) as site:
                bus = site.bus()
                quad = QuadStepper(bus)
                # A move of hours: 16777215 pulses at 1 RPM.
                await quad.configure(
                    1, subdivision=8, step_angle_x100=180, pulses=16_777_215, start_hz=10,
                    accel_hz=0, speed_rpm=1,
                )  # fmt: skip
                with pytest.raises(ReplyTimeoutError) as info:
                    await quad.run(1, timeout=0.5)
                assert str(info.value).endswith("stopped it (stop 0x06 to motor 1 sent)")
                assert q.Stop(1).encode() in requests()

                stepper = ProjectStepper(bus)
                step = ps.StepSpec(run_distance=1, start_hz=1000, speed_rpm=600, delay_ms=20)
                looping = ps.Project(
                    number=1, subdivision=8, step_angle_x100=180, distance_per_rev=1,
                    steps=(step, step), repeat_count=255,
                )  # fmt: skip
                await stepper.upload(looping, verify=False, save=False)
                start = ps.StartProject(1).encode()
                run = asyncio.create_task(stepper.run_project(1, timeout=60))
                await eventually(lambda: start in requests(), "the run started")
                run.cancel()
                with pytest.raises(asyncio.CancelledError):
                    await run
                stop = ps.StopProject().encode()
                sent = requests()
                assert stop in sent[sent.index(start) :]
        finally:
            server.finish()


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
