"""Fixtures of the integration tests: a simulator process behind the real ser2net.

``ser2net_server`` starts two ``motorbus sim`` processes (LA IDs 1-3 at 921600 baud),
each on its own pty, and a ser2net 4.x in front of them with an accepter each on
127.0.0.1: raw TCP (``socket://``) and RFC 2217 (``rfc2217://``), configured as
docs/platform.md section 4 recommends; a third accepter serves a device that does not
exist (what a server with its adapter unplugged says).  The tests skip, with the
reason, when ser2net is not installed; ``.ci/run`` installs it.

Each accepter has its own device because ser2net lets one connection at a time hold a
device: while a connection of the other accepter is open, or still closing, a new one is
told "Port's device already in use" and closed.  A fresh-clone CI run failed that way: the
RFC 2217 test's connection was still closing when the next raw test connected.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from motorbus.protocol import la
from motorbus.protocol.base import LA_REQUEST_HEADER
from motorbus.sim.process import SimProcess

#: The simulated bus: three LA actuators at the LA's fastest documented rate.
SIM_DEVICES = ("la:1-3",)
SIM_BAUD = 921600
#: Longest wait for ser2net to accept TCP connections after it starts.
SER2NET_START_TIMEOUT_S = 5.0
#: Pause between two connection attempts while ser2net starts.
SER2NET_RETRY_S = 0.02
#: Longest wait for ser2net to exit after SIGTERM before it is killed.
SER2NET_STOP_TIMEOUT_S = 5.0

#: One connection of the configuration, as docs/remote-buses.md recommends it.
SER2NET_CONNECTION = """\
connection: &{alias}
    accepter: {accepter}
    enable: on
    options:
      chardelay: false
    connector: serialdev,{device},{baud}n81,local
"""


def ser2net_config(baud: int, *connections: tuple[str, str, object]) -> str:
    """ser2net's YAML for ``(alias, accepter, device)`` connections at ``baud``."""
    blocks = [
        SER2NET_CONNECTION.format(alias=alias, accepter=accepter, device=device, baud=baud)
        for alias, accepter, device in connections
    ]
    return "%YAML 1.1\n---\n" + "\n".join(blocks)


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (bind to 0, read, close)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def require_ser2net() -> str:
    """The path of ``ser2net``, or skip the test saying how to get it."""
    path = shutil.which("ser2net")
    if path is None:
        pytest.skip(
            "ser2net is not installed: these tests need the Debian package 'ser2net' "
            "(4.x); .ci/run installs it (apt-get install ser2net)"
        )
    return path


@dataclass(frozen=True, slots=True)
class Ser2netServer:
    """A running ser2net in front of two simulator processes."""

    sim: SimProcess  # behind raw_url
    rfc2217_sim: SimProcess  # behind rfc2217_url
    raw_url: str  # socket://127.0.0.1:PORT
    rfc2217_url: str  # rfc2217://127.0.0.1:PORT
    missing_url: str  # socket://127.0.0.1:PORT of a device that does not exist
    log_file: Path  # ser2net's own stdout and stderr


def _wait_accepting(proc: subprocess.Popen[bytes], ports: list[int], log_file: Path) -> None:
    deadline = time.monotonic() + SER2NET_START_TIMEOUT_S
    waiting = list(ports)
    while waiting:
        if proc.poll() is not None:
            raise RuntimeError(
                f"ser2net exited with status {proc.returncode}: "
                f"{log_file.read_text(errors='replace').strip()}"
            )
        try:
            with socket.create_connection(("127.0.0.1", waiting[0]), timeout=0.5):
                pass
        except OSError:
            if time.monotonic() > deadline:
                raise RuntimeError(
                    f"ser2net did not accept on 127.0.0.1:{waiting[0]} within "
                    f"{SER2NET_START_TIMEOUT_S} s: {log_file.read_text(errors='replace')}"
                ) from None
            time.sleep(SER2NET_RETRY_S)  # polling for readiness, bounded by the deadline
        else:
            waiting.pop(0)


@pytest.fixture(scope="module")
def ser2net_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Ser2netServer]:
    """Two simulators (la:1-3, 921600 baud, frame logs) served by ser2net, one on each of
    two TCP ports."""
    ser2net = require_ser2net()
    workdir = tmp_path_factory.mktemp("ser2net")
    with (
        SimProcess(SIM_DEVICES, baud=SIM_BAUD, log_file=workdir / "sim.jsonl") as sim,
        SimProcess(SIM_DEVICES, baud=SIM_BAUD, log_file=workdir / "rfc2217.jsonl") as sim2,
    ):
        raw_port = free_tcp_port()
        rfc2217_port = free_tcp_port()
        missing_port = free_tcp_port()
        config = workdir / "ser2net.yaml"
        config.write_text(
            ser2net_config(
                SIM_BAUD,
                ("bus0-raw", f"tcp,127.0.0.1,{raw_port}", sim.path),
                ("bus1-rfc2217", f"telnet(rfc2217),tcp,127.0.0.1,{rfc2217_port}", sim2.path),
                ("bus2-missing", f"tcp,127.0.0.1,{missing_port}", workdir / "no-such-device"),
            ),
            encoding="utf-8",
        )
        log_file = workdir / "ser2net.out"
        with log_file.open("wb") as out:
            proc = subprocess.Popen(
                [ser2net, "-n", "-u", "-c", str(config), "-P", str(workdir / "ser2net.pid")],
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        try:
            _wait_accepting(proc, [raw_port, rfc2217_port], log_file)
            yield Ser2netServer(
                sim=sim,
                rfc2217_sim=sim2,
                raw_url=f"socket://127.0.0.1:{raw_port}",
                rfc2217_url=f"rfc2217://127.0.0.1:{rfc2217_port}",
                missing_url=f"socket://127.0.0.1:{missing_port}",
                log_file=log_file,
            )
        finally:
            proc.terminate()
            try:
                proc.wait(SER2NET_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


# -- reading the simulator's frame log ------------------------------------------------


def received_frames(records: list[dict[str, Any]]) -> list[bytes]:
    """The frames the simulator received (``"request"`` records), in arrival order."""
    return [bytes.fromhex(str(r["hex"])) for r in records if r.get("direction") == "request"]


def is_broadcast_follow(frame: bytes) -> bool:
    """True for a ``55 AA LEN FF F3 ...`` broadcast follow frame (LA manual 3.5.3)."""
    return (
        len(frame) > 4
        and frame[:2] == LA_REQUEST_HEADER
        and frame[3] == la.BROADCAST_ID
        and frame[4] == la.CMD_BROADCAST_FOLLOW
    )


def broadcast_targets(frame: bytes) -> dict[int, int]:
    """The ``{id: position}`` entries of a broadcast follow frame (3 bytes each, LE)."""
    body = frame[5:-1]
    size = la.BROADCAST_ENTRY_SIZE
    return {
        body[i]: int.from_bytes(body[i + 1 : i + size], "little") for i in range(0, len(body), size)
    }


# -- running an example program as a child, for the exit-path tests ---------------------

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "safe_stream.py"
IDS = (1, 2, 3)
#: Longest wait for the child to start streaming, and to exit after the signal.
START_TIMEOUT_S = 20.0
EXIT_TIMEOUT_S = 10.0


def default_signals() -> None:
    """A child's ``preexec_fn``: the stop signals the tests send at their defaults.

    A child started from a background job inherits SIGINT ignored (Python then installs
    no KeyboardInterrupt handler), and one started under ``nohup`` SIGHUP ignored (and
    motorbus rightly leaves an ignored signal alone); the tests need each signal's real
    behaviour, however the suite itself was started.
    """
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_DFL)


def start_example(port: str, *extra: str, example: Path | None = None) -> subprocess.Popen[str]:
    """Run the example on ``port`` for IDs 1-3 and wait until it prints "streaming"."""
    # Behaviour, not speed: a generous host margin keeps a loaded machine from turning a
    # slow reply into a timeout (tests/test_examples.py does the same).  The streams
    # here are broadcasts, which await no reply; the enables before them do, and a
    # simulator starved for over 100 ms (seen) failed them with a 50 ms margin.
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "MOTORBUS_HOST_MARGIN_MS": "250"}
    script = example or EXAMPLE
    args = [sys.executable, str(script), "--port", port, "--baud", str(SIM_BAUD), "--ids", "1-3"]
    proc = subprocess.Popen(
        [*args, *extra],
        cwd=EXAMPLE.parent,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=default_signals,
        start_new_session=True,  # our signal goes to the child alone
    )
    assert proc.stdout is not None
    lines = []
    for line in proc.stdout:  # ends at EOF if the child dies before streaming
        lines.append(line)
        if line.strip() == "streaming":
            return proc
    proc.wait(EXIT_TIMEOUT_S)
    err = proc.stderr.read() if proc.stderr else ""
    pytest.fail(f"the example exited ({proc.returncode}) before streaming: {lines} {err}")


def finish(proc: subprocess.Popen[str]) -> tuple[int, str, str]:
    """Wait (bounded) for the child to exit; return its status and the rest of its output."""
    try:
        out, err = proc.communicate(timeout=EXIT_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"the example did not exit within {EXIT_TIMEOUT_S} s: {out} {err}")
    return proc.returncode, out, err


def assert_safe_action_after_last_broadcast(frames: list[bytes], sub: la.ControlAction) -> None:
    """Each actuator's CMD_MC ``sub`` frame arrived after the last 0xF3 broadcast."""
    broadcasts = [i for i, f in enumerate(frames) if is_broadcast_follow(f)]
    assert broadcasts, "the stream sent no broadcast follow frame"
    last_broadcast = broadcasts[-1]
    later = frames[last_broadcast + 1 :]
    for ident in IDS:
        expected = la.Control(ident, sub).encode()
        assert expected[:7] == bytes([0x55, 0xAA, 0x03, ident, 0x04, 0x00, int(sub)])
        assert expected in later, f"no {sub.name} frame for la:{ident} after the last 0xF3"
