"""The parts of follow-mode streams that are not the tick loop.

Pure (no asyncio, no clock, no I/O; ``tests/test_layering.py`` checks it):

* :mod:`motorbus.streaming.targets`: turning what a target source yields into
  ``{id: position}`` for a stream's actuators, and the ramp after a gap;
* :mod:`motorbus.streaming.budget`: the time budget one bus's streams share (the
  ``StreamBudget`` of each bus, ``stream_budget(bus)``), on ``bus.occupancy``;
* :mod:`motorbus.streaming.model`: limits, safe actions, gap policies, statistics and
  the checks of ``Streamer.follow``'s options;
* :mod:`motorbus.streaming.tick`: planning a tick (which streams, which targets, what
  is left to await) and counting it once sent.

And :mod:`motorbus.streaming.stream`, the ``Stream`` handle a program keeps (stop,
wait, pause, gaps), what ending one means, and a tick's round trips (feedback frames,
status polls).  ``motorbus.streams`` is the ``Streamer``: one per bus, whose task
and timer callbacks serve every stream on absolute deadlines.
"""

from __future__ import annotations
