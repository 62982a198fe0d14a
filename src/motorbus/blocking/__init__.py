"""motorbus without ``await``: the same buses, devices and streams, for scripts,
notebooks and control loops written as plain loops.

::

    import motorbus
    import motorbus.blocking as mb

    with mb.Bus(motorbus.open_transport("/dev/ttyUSB0", baudrate=921600),
                families=[motorbus.Family.LA]) as bus:
        actuator = mb.InspireLA(bus, 1, stroke_mm=30)
        actuator.enable()
        actuator.move_to(1500, wait=True)

Every object here is a thin view of its asyncio counterpart, which runs on one
background event loop thread of the process (``asyncio.run_coroutine_threadsafe``):
the spacing, deadlines, retries, leases and safe ends are the asyncio bus's own,
unchanged.  It works where an event loop already runs in the calling thread (Jupyter).
Closing a bus (``close()``, the end of its ``with`` block however it is left, or the
interpreter's exit) runs the same safe ends as the asyncio ``async with Bus`` exit; a
Ctrl-C while a call waits cancels the call, closes every open bus safely and is raised
again.

A served bus (``motorbus serve``) is one line away: ``with mb.connect(ENDPOINT).bus()
as bus:`` in place of ``with mb.Bus(...) as bus:``, and the rest of the program stays
(the ``serve`` extra).  See docs/blocking.md.
"""

from __future__ import annotations

from motorbus.blocking._bus import Bus, BusManager, BusView, Lease, read_statuses
from motorbus.blocking._devices import InspireLA, ProjectStepper, QuadStepper
from motorbus.blocking._events import EventHub, Subscription
from motorbus.blocking._served import FrameFeed, ServedBus, ServedSite, connect
from motorbus.blocking._streams import Setpoint, Stream, Streamer

__all__ = [
    "Bus",
    "BusManager",
    "BusView",
    "EventHub",
    "FrameFeed",
    "InspireLA",
    "Lease",
    "ProjectStepper",
    "QuadStepper",
    "ServedBus",
    "ServedSite",
    "Setpoint",
    "Stream",
    "Streamer",
    "Subscription",
    "connect",
    "read_statuses",
]
