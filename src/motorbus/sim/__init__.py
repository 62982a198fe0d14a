"""Simulated devices and the hosts that serve them.

* Device models (pure, time passed in): ``motorbus.sim.la.LAModel``,
  ``motorbus.sim.project_stepper.ProjectStepperModel``,
  ``motorbus.sim.quad_stepper.QuadStepperModel``, all ``DeviceModel``.
* ``SimBus``: the pure core that emulates the wire (timing, half duplex, faults);
  ``pacing="wire"`` (default) emulates wire time and turnarounds at the baud,
  ``pacing="prompt"`` answers the moment a request is complete (a USB-CDC device, a TCP
  bridge).  Every host takes ``pacing=``; ``motorbus sim`` takes ``--pacing``/``--prompt``.
* ``MemorySim``: serves a ``SimBus`` over an in-memory link on the asyncio loop.
* ``PtySim``: serves a ``SimBus`` on a pseudo-terminal from a thread.

Log records of ``SimBus(log=...)`` are dicts, one per frame (the ``--log`` file of
``motorbus sim`` and ``PtySim(log_file=...)`` is a frame log, docs/frame-log.md, into
which ``motorbus.protocol.framelog.from_sim`` translates them):

* ``"t"``: seconds since serving started (when the frame's last byte was on the wire;
  with prompt pacing, when it was complete or produced);
* ``"dir"``: ``"rx"`` (host -> device), ``"tx"`` (device -> host) or ``"link"``;
* ``"hex"``: the bytes, e.g. ``"55 AA 03 01 04 00 22 2A"``;
* ``"family"``: ``"la"``, ``"project_stepper"``, ``"quad_stepper"`` or ``None``;
* ``"fault"``: ``None``, applied kinds such as ``"drop,flip"``, ``"silent"``,
  ``"half_duplex"``, ``"discarded: REASON"`` or ``"disconnect"``.

Names are loaded on first use, so ``import motorbus.sim`` stays cheap.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from motorbus.sim.analysis import tick_timing
    from motorbus.sim.bus import LinkEvent, SimBus, SimStats
    from motorbus.sim.faults import FaultConfig
    from motorbus.sim.memory import MemorySim
    from motorbus.sim.model import DeviceModel
    from motorbus.sim.process import SimProcess
    from motorbus.sim.pty import PtySim
    from motorbus.sim.spec import default_baud, parse_device_spec, parse_device_specs
    from motorbus.sim.timing import wire_time

__all__ = [
    "DeviceModel",
    "FaultConfig",
    "LinkEvent",
    "MemorySim",
    "PtySim",
    "SimBus",
    "SimProcess",
    "SimStats",
    "default_baud",
    "parse_device_spec",
    "parse_device_specs",
    "tick_timing",
    "wire_time",
]

_WHERE = {
    "DeviceModel": "motorbus.sim.model",
    "FaultConfig": "motorbus.sim.faults",
    "LinkEvent": "motorbus.sim.bus",
    "MemorySim": "motorbus.sim.memory",
    "PtySim": "motorbus.sim.pty",
    "SimBus": "motorbus.sim.bus",
    "SimProcess": "motorbus.sim.process",
    "SimStats": "motorbus.sim.bus",
    "default_baud": "motorbus.sim.spec",
    "parse_device_spec": "motorbus.sim.spec",
    "parse_device_specs": "motorbus.sim.spec",
    "tick_timing": "motorbus.sim.analysis",
    "wire_time": "motorbus.sim.timing",
}


def __getattr__(name: str) -> object:
    """Load a public name from its module on first use."""
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module 'motorbus.sim' has no attribute {name!r}")
    return getattr(importlib.import_module(module), name)
