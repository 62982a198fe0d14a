"""What the simulator received, for the blocking tests: frames in arrival order."""

from __future__ import annotations

from motorbus.protocol import la
from motorbus.sim.process import SimProcess
from tests.helpers import LOADED_HOST_MARGIN_MS

#: The simulated bus of these tests: the LA's fastest documented rate.
BAUD = 921600
#: The reply allowance of these tests' buses: the simulator is another process, which a
#: loaded machine (CI: six workers on two CPUs) can hold for tens of ms; these tests
#: judge frames and safe ends, not timing, and none waits for a timeout over a pty.
HOST_MARGIN_S = LOADED_HOST_MARGIN_MS / 1e3


def received(sim: SimProcess) -> list[bytes]:
    """Every frame the simulator received so far, in arrival order."""
    return [bytes.fromhex(str(r["hex"])) for r in sim.log_records() if r["direction"] == "request"]


def replies(sim: SimProcess) -> list[bytes]:
    """Every frame the simulator sent so far, in order."""
    return [bytes.fromhex(str(r["hex"])) for r in sim.log_records() if r["direction"] == "reply"]


def control(ident: int, action: la.ControlAction) -> bytes:
    return la.Control(ident, action).encode()


def query(ident: int) -> bytes:
    return control(ident, la.ControlAction.QUERY_STATUS)


def pause(ident: int) -> bytes:
    return control(ident, la.ControlAction.PAUSE)


def is_broadcast_follow(frame: bytes) -> bool:
    """``55 AA LEN FF F3 ...``: a broadcast of follow targets."""
    return len(frame) > 4 and frame[3] == la.BROADCAST_ID and frame[4] == la.CMD_BROADCAST_FOLLOW


def broadcast_targets(frame: bytes) -> dict[int, int]:
    """The ``{id: position}`` entries of a broadcast follow frame."""
    body = frame[5:-1]
    size = la.BROADCAST_ENTRY_SIZE
    return {
        body[i]: int.from_bytes(body[i + 1 : i + size], "little") for i in range(0, len(body), size)
    }


def assert_paused_after(frames: list[bytes], last_motion: int, ids: list[int]) -> None:
    """Each of ``ids`` got a pause after frame ``last_motion`` (the last motion sent)."""
    later = frames[last_motion + 1 :]
    for ident in ids:
        assert pause(ident) in later, f"no pause for la:{ident} after its last motion"
