"""The interface every simulated device implements.

A device model is pure: it never sleeps, never reads a clock and never touches a
port.  The host (``motorbus.sim.host``) owns time and the wire: it passes each
complete request it receives (a checksum-valid frame of the model's family,
whatever its address) to every model on the bus, applies the device turnaround and
the wire time to what the model answers, and asks the model for unsolicited output
(the project stepper's ``EE DD``, the quad stepper's "done" replies) when
``next_event_time`` comes due.

Times are floats in seconds on the host's clock (simulated or monotonic).
"""

from __future__ import annotations

import abc
import random
from typing import ClassVar

from motorbus.protocol.base import Family

__all__ = ["DeviceModel"]


class DeviceModel(abc.ABC):
    """A simulated device: requests in, reply bytes out, time passed in."""

    #: The protocol family this model speaks; the host routes requests by it.
    family: ClassVar[Family]

    @abc.abstractmethod
    def handle(self, request: bytes, now: float) -> list[bytes]:
        """Process one complete request frame received at ``now``.

        Called for every request of this family on the bus, including those addressed
        to other devices and broadcasts; a model that is not addressed returns ``[]``.
        Returns the frames to send back, in order (usually zero or one).  The host
        sends them after the device turnaround.
        """

    def poll(self, now: float) -> list[bytes]:
        """Advance internal state to ``now``; return unsolicited frames that became due."""
        return []

    def next_event_time(self) -> float | None:
        """The earliest time at which ``poll`` would return something, or ``None``."""
        return None

    def turnaround(self, rng: random.Random) -> float:
        """Seconds between the end of a request and the first reply byte (drawn per reply)."""
        return 100e-6

    def power_cycle(self, now: float) -> None:  # noqa: B027 - optional hook, no-op by default
        """Simulate power off and on: RAM state reloads from simulated flash."""
