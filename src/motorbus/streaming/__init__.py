"""The pure parts of follow-mode streams: no asyncio, no clock, no I/O.

* :mod:`motorbus.streaming.targets`: turning what a target source yields into
  ``{id: position}`` for a stream's actuators, and the ramp after a gap;
* :mod:`motorbus.streaming.budget`: the time budget one bus's streams share (the
  ``StreamBudget`` object each bus holds as ``bus.stream_budget``).

``motorbus.streams`` is the asyncio shell around them (the tick loop, polls, safe
actions).
"""

from __future__ import annotations
