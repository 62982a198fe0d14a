"""The records of ``Bus``'s asyncio shell: its jobs, states and observers.

``BusJob`` extends the pure core's ``Job`` (``motorbus.bus.schedule``) with what the
shell keeps beside it: the future of its reply, its timer handles, its ``refresh``.
The core (``motorbus.bus.core``) handles it only as a ``Job``.
"""

from __future__ import annotations

import asyncio
import enum
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from motorbus.bus.schedule import Job
from motorbus.bus.timer import TimerHandle
from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Command

__all__ = ["BusJob", "BusObserver", "BusState", "Refresh"]


class BusObserver(Protocol):
    """What ``Bus.add_observer`` calls (see there)."""

    def on_write(self, cmd: Command[object], at: float) -> None: ...

    def on_reply(
        self, cmd: Command[object], value: Any, written_at: float, replied_at: float
    ) -> None: ...


class BusState(enum.Enum):
    """Where the bus is in its life."""

    CLOSED = "closed"
    OPEN = "open"
    LOST = "lost"  # the port went away; reconnecting if enabled

    @classmethod
    def checked(cls, value: object) -> BusState:
        """``value`` (a ``BusState``, or its value: ``"open"``) as a ``BusState``;
        ``LocalProtocolError`` naming the allowed ones otherwise."""
        try:
            return cls(value)
        except ValueError:
            raise LocalProtocolError(
                f"state={value!r} is not a bus state: choose one of "
                f"{', '.join(s.value for s in cls)} (motorbus.BusState)",
                field="state",
                value=value,
            ) from None


#: Called at the moment a queued frame is written: returns the command to send now
#: (rebuilt from what is still wanted) or None to drop it unsent.
Refresh = Callable[[], "Command[object] | None"]


@dataclass(slots=True, eq=False, kw_only=True)
class BusJob(Job):
    """One request travelling through the bus: the pure core's record (``Job``), and
    beside it what the asyncio shell keeps: its future and its timer handles."""

    future: asyncio.Future[Any]
    #: ``cmd.expects_reply`` and ``cmd.starts_motion``, read once when the job is made
    #: (and again if its refresh changes the frame), not at every step of its way.
    expects: bool = False
    moves: bool = False
    #: The devices its motion moves (``safety.motion_keys``), as its lease claim worked
    #: them out: its write owes their stops without working them out again.  None for
    #: a frame that does not move, or whose refresh changed it since.
    motion_keys: tuple[str, ...] | None = None
    handle: TimerHandle | None = None  # its reply deadline
    refresh: Refresh | None = None
    start_by: float = math.inf
    expiry: TimerHandle | None = None  # its start_by

    def gone(self) -> bool:
        return self.future.done()
