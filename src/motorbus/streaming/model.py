"""The vocabulary of streams: limits, safe actions, gap policies, statistics, options.

Pure (no asyncio, no clock): values and the checks that refuse bad ones when a stream
is started, before anything is sent.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from motorbus.bus.stats import LatencyHistogram
from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import check_flag, check_int
from motorbus.validation import check_number

__all__ = [
    "DEFAULT_MAX_SPEED",
    "GAP_TICKS",
    "LATE_AFTER_S",
    "MAX_SPEED_LIMIT",
    "PERIOD_MAX_S",
    "PERIOD_MIN_S",
    "FollowOptions",
    "GapPolicy",
    "SafeAction",
    "StreamStats",
    "broadcast_builder",
    "broadcast_parts",
    "check_follow_options",
    "hold_flag",
    "while_sending",
]

#: Follow-mode targets must come at a fixed interval of 10..50 ms (LA manual 3.5.3).
PERIOD_MIN_S = 0.010
#: The longest stream period, seconds (50 ms: LA manual 3.5.3).
PERIOD_MAX_S = 0.050
#: A tick sent later than this after its deadline counts as late (it is still sent).
LATE_AFTER_S = 1e-3
#: A stream this many ticks behind (or more) has had a gap: its actuators are no longer
#: where its trajectory is (``on_gap``).  Fewer are skipped and counted, nothing more.
GAP_TICKS = 3
#: Default ``max_speed`` (position units per second) of the ramp after a gap: the full
#: 0..2000 stroke in 4 s.
DEFAULT_MAX_SPEED = 500.0
#: Largest ``max_speed``: the full stroke in 0.1 s, beyond what an LA can do.
MAX_SPEED_LIMIT = 20_000.0


class SafeAction(enum.Enum):
    """What a stream does to its actuators when it ends (unless ended with ``hold``)."""

    HOLD = "hold"  # nothing: each actuator holds its last target
    PAUSE = "pause"  # CMD_MC pause: power stage off, the next target resumes
    ESTOP = "estop"  # CMD_MC e-stop: power stage off, "work" needed to move again


class GapPolicy(enum.Enum):
    """What a stream does after a gap (the bus was lost, or the stream fell behind)."""

    RAMP = "ramp"  # read each position, ramp from there to the trajectory at max_speed
    STOP = "stop"  # apply the safe action and end the stream with an error


@dataclass(slots=True)
class StreamStats:
    """Timing and counts of one stream, since it started.

    Every count is a number of ticks, frames or polls, as its name says; durations are
    in seconds.  A tick is late when its first frame went out more than
    ``LATE_AFTER_S`` (1 ms) after its deadline, ``origin + k * period``.  "Went out" is
    when the bus issued the write (the clock read just before ``write``), the moment a
    trace of the write(2) calls shows: not when this thread ran on after it, which on
    a busy process (a server's Zenoh threads wanting the GIL) can be later.
    """

    ticks: int = 0
    """Ticks served: targets sent (a tick skipped or ended is not counted)."""
    late: int = 0
    """Ticks whose first frame went out more than 1 ms (``LATE_AFTER_S``) after their
    deadline; a late tick is still sent, and counted in ``ticks`` too."""
    skipped: int = 0
    """Ticks not sent: the stream was a whole period or more behind (a stalled host),
    the port was gone, or the tick went to reading positions after a gap."""
    #: Ticks whose first frame could not be written at the deadline itself (a reply
    #: was still owed, or the 1 ms spacing from the previous write): sent that much later.
    slipped: int = 0
    frames: int = 0
    """Frames written for this stream: each shared broadcast counts once, each feedback
    frame once."""
    feedback_timeouts: int = 0
    """Feedback round trips (``feedback=True``) that got no good reply: no reply in time,
    or another error on the bus (each one counted)."""
    polls: int = 0
    """Status polls answered (``poll_status=True``): one reply each."""
    #: Polls that could not get a slot before the next tick (dropped unsent), and ticks
    #: whose free slots held no poll at all.
    polls_skipped: int = 0
    poll_timeouts: int = 0
    """Status polls (``poll_status=True``) sent that got no good reply: counted, never
    raised; the next poll of that actuator comes round again."""
    gaps: int = 0
    """Gaps handled (``StreamGap`` events): the bus came back after an outage, or the
    stream fell ``GAP_TICKS`` (3) or more ticks behind."""
    #: Lateness of each tick's first frame against its absolute deadline, in seconds
    #: (``as_dict()`` gives p50/p99/max in microseconds).  Over 1 ms counts as ``late``.
    jitter: LatencyHistogram = field(default_factory=LatencyHistogram)

    def summary(self) -> str:
        """One line of text: ticks, late, skipped, slipped, polls, gaps and tick jitter.

        ``as_dict()`` has the same figures as a JSON-ready dict.
        """
        d = self.as_dict()
        return (
            f"{d['ticks']} ticks ({d['frames']} frames), {d['late']} late, "
            f"{d['skipped']} skipped, {d['slipped']} slipped; polls {d['polls']} "
            f"({d['polls_skipped']} skipped, {d['poll_timeouts']} poll timeouts), "
            f"{d['feedback_timeouts']} feedback timeouts; "
            f"{d['gaps']} gaps; jitter p50 {d['jitter_p50_us']:.0f} / p99 "
            f"{d['jitter_p99_us']:.0f} / max {d['jitter_max_us']:.0f} us"
        )

    def as_dict(self) -> dict[str, float]:
        """Counts plus jitter p50/p99/max in microseconds, as a dict (JSON-ready)."""
        j = self.jitter.summary()
        return {
            "ticks": self.ticks,
            "late": self.late,
            "skipped": self.skipped,
            "slipped": self.slipped,
            "frames": self.frames,
            "feedback_timeouts": self.feedback_timeouts,
            "polls": self.polls,
            "polls_skipped": self.polls_skipped,
            "poll_timeouts": self.poll_timeouts,
            "gaps": self.gaps,
            "jitter_p50_us": j["p50_us"],
            "jitter_p99_us": j["p99_us"],
            "jitter_max_us": j["max_us"],
        }


@dataclass(frozen=True, slots=True)
class FollowOptions:
    """``Streamer.follow``'s options, checked (see there)."""

    period: float
    feedback: bool
    poll_status: bool
    safe_action: SafeAction
    on_gap: GapPolicy
    max_speed: float
    max_missed: int | None = None


#: The most status replies in a row ``max_missed`` may let an actuator miss.
MAX_MISSED_LIMIT = 1000


def check_follow_options(
    *,
    period: object,
    feedback: object,
    poll_status: object,
    safe_action: object,
    on_gap: object,
    max_speed: object,
    max_missed: object = None,
) -> FollowOptions:
    """Check ``Streamer.follow``'s options; ``LocalProtocolError`` names a bad one."""
    # 10..50 ms (LA manual 3.5.3); the slack admits a float32 0.01 (0.00999999978).
    checked_period = check_number("period", period, PERIOD_MIN_S, PERIOD_MAX_S, "s", slack=1e-9)
    try:
        action = SafeAction(safe_action)
    except ValueError:
        raise LocalProtocolError(
            f"safe_action={safe_action!r} is not allowed: choose hold, pause or estop",
            field="safe_action",
            value=safe_action,
        ) from None
    try:
        policy = GapPolicy(on_gap)
    except ValueError:
        raise LocalProtocolError(
            f"on_gap={on_gap!r} is not allowed: choose ramp or stop",
            field="on_gap",
            value=on_gap,
        ) from None
    return FollowOptions(
        period=float(checked_period),
        feedback=check_flag("feedback", feedback),
        poll_status=check_flag("poll_status", poll_status),
        safe_action=action,
        on_gap=policy,
        max_speed=check_number("max_speed", max_speed, 1.0, MAX_SPEED_LIMIT, "units/s"),
        max_missed=None
        if max_missed is None
        else check_int("max_missed", max_missed, 1, MAX_MISSED_LIMIT),
    )


def hold_flag(hold: object, safe: object) -> bool:
    """``hold`` from ``stop``/``close``'s ``hold`` and older ``safe`` arguments
    (``safe=False`` is the older spelling of ``hold=True``)."""
    held = check_flag("hold", hold)
    if safe is None:
        return held
    if check_flag("safe", safe) and held:
        raise LocalProtocolError(
            "hold=True and safe=True contradict each other: hold sends no safe action",
            field="hold",
            value=hold,
        )
    return held or not safe


class Sending(Protocol):
    """A stream, as far as building its frames goes."""

    @property
    def sending(self) -> bool: ...


def while_sending(stream: Sending, cmd: la.Follow) -> Callable[[], la.Follow | None]:
    """A ``refresh`` for one feedback frame: drop it if its stream no longer sends."""
    return lambda: cmd if stream.sending else None


def broadcast_builder(
    parts: Sequence[tuple[Sending, tuple[tuple[int, int], ...]]],
) -> Callable[[], la.Broadcast | None]:
    """A ``refresh`` that builds one 0xF3 frame from the parts still sending: each part a
    stream and its ``(id, position)`` pairs in this frame (15 in all at most).

    The frame is built once, here, when the tick is prepared; while every stream of the
    frame still sends, the refresh returns that same frame (the bus then writes the
    bytes it encoded ahead), and the call is only the check.  A frame is built again
    only when some of its streams stopped.
    """
    # (One stream's part, the common case, is the frame's entries as they are; list
    # comprehensions, no generators: one call each, not one an entry.)
    pairs = parts[0][1] if len(parts) == 1 else tuple([p for _, ps in parts for p in ps])
    frame = la.Broadcast.prevalidated(la.BroadcastMode.FOLLOW, pairs)

    def build() -> la.Broadcast | None:
        for s, _ in parts:
            if not s.sending:
                break
        else:
            return frame
        left = tuple([p for s, ps in parts if s.sending for p in ps])
        if not left:
            return None
        return la.Broadcast.prevalidated(la.BroadcastMode.FOLLOW, left)

    return build


def broadcast_parts(
    targets: Sequence[tuple[Sending, Mapping[int, int]]], size: int = la.MAX_BROADCAST_ENTRIES
) -> list[list[tuple[Sending, tuple[tuple[int, int], ...]]]]:
    """The frames of one tick: the streams' targets in order, ``size`` entries a frame
    (at most the manual's 15; a stream's entries may span two), as
    ``broadcast_builder``'s parts."""
    if not 1 <= size <= la.MAX_BROADCAST_ENTRIES:
        raise ValueError(
            f"size={size!r} is out of range: allowed 1..{la.MAX_BROADCAST_ENTRIES} entries a frame"
        )
    frames: list[list[tuple[Sending, tuple[tuple[int, int], ...]]]] = []
    current: list[tuple[Sending, tuple[tuple[int, int], ...]]] = []
    room = size
    for s, mapping in targets:
        pairs = tuple(mapping.items())
        while pairs:
            part, pairs = pairs[:room], pairs[room:]
            current.append((s, part))
            room -= len(part)
            if not room:
                frames.append(current)
                current, room = [], size
    if current:
        frames.append(current)
    return frames
