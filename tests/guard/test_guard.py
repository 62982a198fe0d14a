"""The guard process (issue 19 case 3): a killed program's devices get their safe action."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from motorbus.errors import GuardError, LocalProtocolError
from motorbus.protocol import la
from motorbus.runtime import guard as guard_process
from motorbus.runtime.guard import (
    GuardDevice,
    GuardPort,
    GuardState,
    port_message,
    send_safe_frames,
)
from motorbus.sim.process import SimProcess

ROOT = Path(__file__).resolve().parents[2]
VICTIM = ROOT / "benchmarks" / "guard_victim.py"
START_TIMEOUT_S = 60.0
IDS = (1, 2, 3)
PAUSES = [la.Control(i, la.ControlAction.PAUSE).encode().hex(" ").upper() for i in IDS]


def is_motion(hex_: str) -> bool:
    """An LA follow-mode target broadcast (0xF3) or single-ID position command."""
    return hex_.startswith("55 AA") and hex_.split()[4] in ("F3", "F2", "21")


# -- the pure part --------------------------------------------------------------------------


def test_state_follows_port_and_closed_messages() -> None:
    state = GuardState()
    port = GuardPort("/dev/ttyX", 921600, {"rs485": False}, (GuardDevice("la:1", "s", (b"\x01",)),))
    state.apply(port_message("a", port))
    state.apply(port_message("b", GuardPort("/dev/ttyY", 9600)))  # nothing leased
    assert state.plan() == [port]
    state.apply({"op": "closed", "bus": "a"})
    assert state.plan() == []
    assert not state.clean_exit
    state.apply({"op": "clean_exit"})
    assert state.clean_exit


def port_msg(**changes: Any) -> dict[str, Any]:
    message = {"op": "port", "bus": "a", "url": "/x", "baud": 9600, "options": {}, "devices": []}
    return {**message, **changes}


@pytest.mark.parametrize(
    ("message", "field"),
    [
        ({"op": "explode"}, "op"),
        (port_msg(url=""), "url"),
        (port_msg(url="/x\0"), "url"),
        (port_msg(baud=True), "baud"),
        (port_msg(baud=0), "baud"),
        (port_msg(devices=[{"key": "k", "owner": "o", "safe": ["zz"]}]), "safe"),
        (port_msg(options={"quiet_s": "1"}), "quiet_s"),
        (port_msg(options={"quiet_s": 5.0}), "quiet_s"),
    ],
)
def test_bad_messages_are_refused_naming_the_field(message: dict[str, Any], field: str) -> None:
    state = GuardState()
    with pytest.raises(LocalProtocolError) as info:
        state.apply(message)
    assert info.value.field == field
    assert state.ports == {}


class FakePort:
    def __init__(self) -> None:
        self.calls: list[tuple[str, bytes]] = []

    def write(self, data: bytes) -> None:
        self.calls.append(("write", data))

    def flush(self) -> None:
        self.calls.append(("flush", b""))

    def close(self) -> None:
        self.calls.append(("close", b""))


def test_safe_frames_go_out_device_by_device_each_drained_before_the_next() -> None:
    fake = FakePort()
    port = GuardPort(
        "/dev/ttyX",
        9600,
        {},
        (GuardDevice("p", "o", (b"\x05\x0e", b"\x03\x0d")), GuardDevice("q", "o", (b"\x07",))),
    )
    result = send_safe_frames(port, spacing=0, opener=lambda p: fake)
    assert fake.calls == [
        ("write", b"\x05\x0e"), ("flush", b""),
        ("write", b"\x03\x0d"), ("flush", b""),
        ("write", b"\x07"), ("flush", b""),
        ("close", b""),
    ]  # fmt: skip
    assert (result.frames, result.devices, result.error) == (3, 2, None)


class TalkingPort(FakePort):
    """A fake port on a fake clock: each write is answered ``reply_after`` later (6
    bytes); ``pending`` comes whatever the guard writes (an answer to the program)."""

    def __init__(self, pending: list[tuple[float, bytes]], reply_after: float) -> None:
        super().__init__()
        self.now = 0.0
        self.pending = pending
        self.reply_after = reply_after
        self.writes: list[tuple[bytes, float]] = []  # (frame, ms)

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds

    def read(self, size: int) -> bytes:
        due = [b for t, b in self.pending if t <= self.now]
        self.pending = [(t, b) for t, b in self.pending if t > self.now]
        return b"".join(due)

    def write(self, data: bytes) -> None:
        super().write(data)
        self.writes.append((data, self.now * 1e3))
        self.pending.append((self.now + self.reply_after, b"\xff\xaa\x5e\x00\x00\x00"))


def test_each_safe_frame_waits_for_a_quiet_line_on_a_half_duplex_bus() -> None:
    """A device answering the program's last request, or the guard's previous frame,
    does not hear a frame written meanwhile: the guard waits until the line is quiet."""
    fake = TalkingPort([(0.010, b"\xff\xaa\x03\x08\x00\x02")], reply_after=0.007)
    frames = (b"\x01" * 11, b"\x02" * 11)
    port = GuardPort("/dev/ttyX", 9600, {"quiet_s": 0.040}, (GuardDevice("p", "o", frames),))
    result = send_safe_frames(
        port, spacing=0.001, opener=lambda p: fake, clock=fake.clock, sleep=fake.sleep
    )
    assert result.error is None and result.frames == 2
    writes = fake.writes
    own = 11 * 10 / 9600 * 1e3  # 11.5 ms on the wire
    gap = guard_process.GAP_AFTER_REPLY_S * 1e3 + own
    # The program's reply came at 10 ms: then a gap; the guard's reply at +7 ms: a gap.
    assert writes[0][0] == frames[0] and 10 + gap <= writes[0][1] < 10 + gap + 0.5
    assert writes[1][0] == frames[1]
    assert writes[0][1] + 7 + gap <= writes[1][1] < writes[0][1] + 7 + gap + 0.5


def test_a_network_port_closes_only_after_the_last_frames_answer() -> None:
    """Behind ser2net the frame can still be on its way when the guard is done: a close
    within the device's turnaround overtook it on a loaded machine (the last pause never
    reached the device).  The guard waits to hear the answer, however late."""

    class ClosingPort(TalkingPort):
        closed_at: float | None = None

        def close(self) -> None:
            super().close()
            self.closed_at = self.now

    fake = ClosingPort([], reply_after=0.200)  # a loaded ser2net: 200 ms, not 40
    port = GuardPort(
        "socket://127.0.0.1:9", 9600, {"quiet_s": 0.040}, (GuardDevice("p", "o", (b"\x01",)),)
    )
    result = send_safe_frames(port, opener=lambda p: fake, clock=fake.clock, sleep=fake.sleep)
    assert result.error is None and result.frames == 1
    ((_, at),) = fake.writes
    assert fake.closed_at is not None and fake.closed_at * 1e3 >= at + 200
    # A local port still closes after its quiet time (tcdrain put the frame on the line).
    local = ClosingPort([], reply_after=0.200)
    port = GuardPort("/dev/ttyX", 9600, {"quiet_s": 0.040}, (GuardDevice("p", "o", (b"\x01",)),))
    send_safe_frames(port, opener=lambda p: local, clock=local.clock, sleep=local.sleep)
    ((_, at),) = local.writes
    assert local.closed_at is not None and local.closed_at * 1e3 < at + 200


def test_a_silent_line_is_quiet_after_the_turnaround_time() -> None:
    fake = TalkingPort([], reply_after=1.0)  # nothing answers in time
    port = GuardPort("/dev/ttyX", 9600, {"quiet_s": 0.040}, (GuardDevice("p", "o", (b"\x01",)),))
    send_safe_frames(port, opener=lambda p: fake, clock=fake.clock, sleep=fake.sleep)
    ((frame, at),) = fake.writes
    assert frame == b"\x01" and 40 + 10 / 9.6 <= at < 40 + 10 / 9.6 + 0.5  # quiet + own


def test_a_port_that_does_not_open_is_reported() -> None:
    port = GuardPort("/dev/motorbus-no-such-port", 9600, {}, (GuardDevice("p", "o", (b"\x01",)),))
    result = send_safe_frames(port)
    assert result.frames == 0
    assert result.error is not None and "cannot open /dev/motorbus-no-such-port" in result.error


def test_no_pidfd_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delattr(os, "pidfd_open")
    with pytest.raises(GuardError, match=r"needs Linux pidfds \(os.pidfd_open\)"):
        guard_process.Guard.start()


# -- over ptys: kill the program --------------------------------------------------------------


@pytest.fixture
def la_sims(tmp_path: Path) -> Iterator[list[SimProcess]]:
    sims = [
        SimProcess(["la:1-3"], baud=921600, log_file=tmp_path / f"bus{n}.jsonl").start()
        for n in range(2)
    ]
    try:
        yield sims
    finally:
        for sim in sims:
            sim.stop()


def requests(sim: SimProcess) -> list[str]:
    return [r["hex"] for r in sim.log_records() if r["direction"] == "request"]


def unheard(sim: SimProcess) -> list[str]:
    """Requests the simulated devices missed: they came while a device was answering
    (half duplex), so nothing acted on them."""
    return [
        r["hex"]
        for r in sim.log_records()
        if r["direction"] == "request" and r.get("fault") == "half_duplex"
    ]


def kill_while_streaming(sims: list[SimProcess], *extra: str) -> str:
    """Start the victim on ``sims``, SIGKILL it mid-stream; return its stderr."""
    ports = [a for sim in sims for a in ("--port", sim.path)]
    proc = subprocess.Popen(
        [sys.executable, str(VICTIM), *ports, "--ids", "1-3", *extra],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()  # "streaming" once every bus sends targets
        assert line == "streaming\n", proc.communicate(timeout=START_TIMEOUT_S)
        time.sleep(0.2)  # let the stream run; any moment would do
        children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
        for child in children:  # the guard, if any: what is meant for the program
            for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # must not end it
                os.kill(int(child), sig)
        assert len(children) == ("--guard" in extra)
        proc.send_signal(signal.SIGKILL)
        _, err = proc.communicate(timeout=START_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    return err


def wait_for_frames(sims: list[SimProcess], wanted: set[str]) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while not all(wanted <= set(requests(sim)) for sim in sims):
        assert time.monotonic() < deadline, [requests(sim)[-5:] for sim in sims]
        time.sleep(0.02)  # polling the simulators' logs


def test_sigkill_with_the_guard_pauses_every_device_after_the_last_motion(
    la_sims: list[SimProcess],
) -> None:
    err = kill_while_streaming(la_sims, "--guard")
    wait_for_frames(la_sims, set(PAUSES))
    for sim in la_sims:
        sent = requests(sim)
        last_motion = max(n for n, h in enumerate(sent) if is_motion(h))
        assert sorted(sent[last_motion + 1 :]) == sorted(PAUSES), sent[-6:]
        assert "motorbus guard: program " in err and f"on {sim.path} (3 frames" in err
        assert not set(PAUSES) & set(unheard(sim))  # each came once the line was quiet


def test_sigkill_without_the_guard_leaves_motion_as_the_last_frame(
    la_sims: list[SimProcess],
) -> None:
    """The limit the guard exists for: nothing runs in a killed program."""
    kill_while_streaming(la_sims)
    time.sleep(0.5)  # nothing is coming; give a wrong sender time to show
    for sim in la_sims:
        sent = requests(sim)
        assert is_motion(sent[-1]), sent[-3:]
        assert not set(PAUSES) & set(sent)


def test_a_clean_end_lets_the_guard_go_without_sending_anything(tmp_path: Path) -> None:
    code = (
        "import motorbus, motorbus.runtime.guard as g\n"
        "async def main():\n"
        "    guard = g.active_guard()\n"
        "    print(guard.proc.pid, flush=True)\n"
        "    guard.set_port('b', g.GuardPort('/dev/motorbus-nowhere', 9600))\n"
        "motorbus.run(main(), guard=True)\n"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=START_TIMEOUT_S
    )
    assert r.returncode == 0, r.stderr
    guard_pid = int(r.stdout.split()[0])
    with pytest.raises(ProcessLookupError):
        os.kill(guard_pid, 0)  # exited (and reaped) before the program did
    assert "motorbus guard" not in r.stderr


def test_cli_guard_option_starts_the_guard_and_lets_it_go_at_a_clean_end(
    la_sims: list[SimProcess],
) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MOTORBUS_")}
    env["XDG_CONFIG_HOME"] = "/nonexistent/motorbus-test-config"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "motorbus",
            "la",
            "move",
            "1",
            "500",
            "--guard",
            "--port",
            la_sims[0].path,
        ],
        capture_output=True,
        text=True,
        timeout=START_TIMEOUT_S,
        env=env,
    )
    assert r.returncode == 0, r.stderr
    assert "motorbus guard" not in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "motorbus", "la", "status", "1", "--guard"],
        capture_output=True,
        text=True,
        timeout=START_TIMEOUT_S,
        env=env,
    )
    assert r.returncode == 2 and "unrecognized arguments: --guard" in r.stderr  # moves nothing


# -- the CLI under --guard, killed ------------------------------------------------------------


def cli_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MOTORBUS_")}
    env["XDG_CONFIG_HOME"] = "/nonexistent/motorbus-test-config"
    return env


def kill_cli_once(sim: SimProcess, args: list[str], prefix: str) -> str:
    """Run ``motorbus ARGS``; SIGKILL it soon after ``sim`` got a ``prefix`` frame; return
    its stderr (the guard's report lands there)."""
    before = len(requests(sim))
    proc = subprocess.Popen(
        [sys.executable, "-m", "motorbus", *args, "--port", sim.path],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=cli_env(),
    )
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while not any(h.startswith(prefix) for h in requests(sim)[before:]):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, f"no {prefix} frame was sent"
            time.sleep(0.02)  # polling the simulator's log
        time.sleep(0.1)
        proc.send_signal(signal.SIGKILL)
        _, err = proc.communicate(timeout=START_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    return err


@pytest.fixture
def project_sim(tmp_path: Path) -> Iterator[SimProcess]:
    """A project stepper whose project 1 repeats forever (a run never ends by itself)."""
    with SimProcess(["project-stepper"], baud=9600, log_file=tmp_path / "p.jsonl") as sim:
        text = (ROOT / "examples" / "project.toml").read_text(encoding="utf-8")
        forever = tmp_path / "forever.toml"
        forever.write_text(text.replace("repeat = 0", 'repeat = "forever"'), encoding="utf-8")
        upload = ["project", "upload", str(forever), "--no-save", "--port", sim.path]
        r = subprocess.run(
            [sys.executable, "-m", "motorbus", *upload],
            capture_output=True,
            text=True,
            timeout=START_TIMEOUT_S,
            env=cli_env(),
        )
        assert r.returncode == 0, r.stderr
        yield sim


START_PROJECT_1 = "FF AA 4E 01"
STOP_PROJECT = "FF AA 5E 00 00 00 00 00 00 00 07"
MANUAL_STOP_3 = "FF AA 03 0D 00 00 00 00 00 00 B9"


def test_sigkill_of_project_run_with_guard_stops_the_project(project_sim: SimProcess) -> None:
    kill_cli_once(project_sim, ["project", "run", "1", "--timeout", "60", "--guard"], "FF AA 4E")
    wait_for_frames([project_sim], {STOP_PROJECT})
    sent = requests(project_sim)
    last_run = max(n for n, h in enumerate(sent) if h.startswith(START_PROJECT_1))
    assert sent[last_run + 1 :] == [STOP_PROJECT, MANUAL_STOP_3]
    # The manual stop waited for the reply to the stop project: the device heard both.
    wait_for_frames([project_sim], {MANUAL_STOP_3})
    assert not {STOP_PROJECT, MANUAL_STOP_3} & set(unheard(project_sim))


def test_sigkill_of_project_run_without_guard_leaves_it_running(project_sim: SimProcess) -> None:
    kill_cli_once(project_sim, ["project", "run", "1", "--timeout", "60"], "FF AA 4E")
    time.sleep(0.5)  # nothing is coming
    assert requests(project_sim)[-1].startswith(START_PROJECT_1)


def test_sigkill_of_motorbus_stream_with_guard_pauses_every_actuator(
    la_sims: list[SimProcess], tmp_path: Path
) -> None:
    csv = tmp_path / "slow.csv"
    rows = [f"{n * 0.01:.2f},{500 + n % 100},{600 + n % 100},{700 + n % 100}" for n in range(3000)]
    csv.write_text("t,1,2,3\n" + "\n".join(rows) + "\n", encoding="utf-8")
    sim = la_sims[0]
    kill_cli_once(sim, ["stream", str(csv), "--ramp", "0", "--guard"], "55 AA 0A FF F3")
    wait_for_frames([sim], set(PAUSES))
    # The stream polls statuses between ticks (it checks that they follow): queries.
    sent = [h for h in requests(sim) if h[15:20] != "00 22"]
    last_motion = max(n for n, h in enumerate(sent) if is_motion(h))
    assert sorted(sent[last_motion + 1 :]) == sorted(PAUSES), sent[-6:]


# -- guard = true in a bus file -----------------------------------------------------------------

BUS_FILE_PROGRAM = """
import sys, motorbus
async def main():
    async with motorbus.BusManager.from_toml(sys.argv[1]) as mgr:
        acts = [mgr.la("arm", i) for i in (1, 2, 3)]
        for a in acts:
            await a.enable()
        stream = mgr.streamer("arm").follow(
            acts, lambda t, s: [500 + 10 * t, 600, 700], period=0.01, safe_action="pause"
        )
        print("streaming", flush=True)
        await stream.wait()
motorbus.run(main())
"""


def test_guard_true_in_a_bus_file_guards_a_plain_program(
    la_sims: list[SimProcess], tmp_path: Path
) -> None:
    sim = la_sims[0]
    bus_file = tmp_path / "buses.toml"
    bus_file.write_text(
        f'[[bus]]\nname = "arm"\nurl = "{sim.path}"\nbaud = 921600\nhost_margin_ms = 50\n'
        'devices = ["la:1-3"]\nguard = true\n',
        encoding="utf-8",
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", BUS_FILE_PROGRAM, str(bus_file)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=cli_env(),
    )
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "streaming\n", proc.communicate(timeout=60)
        deadline = time.monotonic() + START_TIMEOUT_S
        while not any(is_motion(h) for h in requests(sim)):
            assert time.monotonic() < deadline
            time.sleep(0.02)  # polling the simulator's log
        proc.send_signal(signal.SIGKILL)
        proc.communicate(timeout=START_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
    wait_for_frames([sim], set(PAUSES))
    sent = requests(sim)
    last_motion = max(n for n, h in enumerate(sent) if is_motion(h))
    assert sorted(sent[last_motion + 1 :]) == sorted(PAUSES), sent[-6:]


def test_a_bus_file_guard_that_is_no_bool_is_refused_by_name(tmp_path: Path) -> None:
    from motorbus.manager import BusManager

    bus_file = tmp_path / "buses.toml"
    bus_file.write_text('[[bus]]\nurl = "/dev/x"\nbaud = 9600\nguard = "yes"\n', encoding="utf-8")
    with pytest.raises(
        LocalProtocolError, match=r"bus #1: guard must be True or False, got 'yes'"
    ) as info:
        BusManager.from_toml(bus_file)
    assert info.value.field == "guard"


def test_sigkill_of_quad_run_with_guard_stops_all_motors(tmp_path: Path) -> None:
    from motorbus.protocol import safety

    stop_all = [c.encode().hex(" ").upper() for c in safety.safe_stop_commands("quad_stepper")]
    assert stop_all == ["FF AA 09 06 00 00 00 00 B8"]  # stop all (B.1)
    with SimProcess(["quad-stepper"], baud=9600, log_file=tmp_path / "q.jsonl") as sim:
        config = ["quad", "config", "3", "--subdivision", "8", "--pulses", "16777215"]
        config += ["--start-hz", "10", "--accel", "0", "--rpm", "1", "--port", sim.path]
        r = subprocess.run(
            [sys.executable, "-m", "motorbus", *config],
            capture_output=True,
            text=True,
            timeout=START_TIMEOUT_S,
            env=cli_env(),
        )
        assert r.returncode == 0, r.stderr
        kill_cli_once(sim, ["quad", "run", "3", "--timeout", "60", "--guard"], "FF AA 03 09")
        wait_for_frames([sim], set(stop_all))
        sent = requests(sim)
        last_run = max(n for n, h in enumerate(sent) if h.startswith("FF AA 03 09"))
        assert sent[last_run + 1 :] == stop_all
