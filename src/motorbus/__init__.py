"""motorbus: asyncio buses of serial motion devices.

The supported public API.  The sans-I/O protocol values live in
``motorbus.protocol.la``, ``motorbus.protocol.project_stepper`` and
``motorbus.protocol.quad_stepper``; the simulators in ``motorbus.sim``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from motorbus.bus.bus import Bus, BusState, Priority
    from motorbus.bus.events import BusStateChanged, FaultChanged, ProjectFinished, QuadDone
    from motorbus.devices.la import InspireLA, scan
    from motorbus.devices.project_stepper import (
        ProjectStepper,
        ProjectStopped,
        ProjectVerifyError,
    )
    from motorbus.devices.quad_stepper import QuadStepper
    from motorbus.errors import (
        BusClosedError,
        LocalProtocolError,
        MotorbusError,
        NotSentError,
        RemoteProtocolError,
        ReplyTimeoutError,
    )
    from motorbus.manager import BusManager, DeviceStop, StopReport
    from motorbus.protocol.base import Family
    from motorbus.shutdown import install_signal_handlers, run
    from motorbus.streams import SafeAction, Stream, StreamEnded, Streamer
    from motorbus.transport.serial import open_transport

# Loaded on first use, so that ``import motorbus.protocol`` (sans-I/O) does not pull in
# asyncio and the serial backends through this package's __init__.
_LAZY = {
    "Bus": "motorbus.bus.bus",
    "BusState": "motorbus.bus.bus",
    "Priority": "motorbus.bus.bus",
    "BusStateChanged": "motorbus.bus.events",
    "FaultChanged": "motorbus.bus.events",
    "ProjectFinished": "motorbus.bus.events",
    "QuadDone": "motorbus.bus.events",
    "BusManager": "motorbus.manager",
    "DeviceStop": "motorbus.manager",
    "StopReport": "motorbus.manager",
    "NotSentError": "motorbus.errors",
    "install_signal_handlers": "motorbus.shutdown",
    "run": "motorbus.shutdown",
    "StreamEnded": "motorbus.streams",
    "InspireLA": "motorbus.devices.la",
    "scan": "motorbus.devices.la",
    "ProjectStepper": "motorbus.devices.project_stepper",
    "ProjectStopped": "motorbus.devices.project_stepper",
    "ProjectVerifyError": "motorbus.devices.project_stepper",
    "QuadStepper": "motorbus.devices.quad_stepper",
    "RealtimeReport": "motorbus.realtime",
    "BusClosedError": "motorbus.errors",
    "LocalProtocolError": "motorbus.errors",
    "MotorbusError": "motorbus.errors",
    "RemoteProtocolError": "motorbus.errors",
    "ReplyTimeoutError": "motorbus.errors",
    "Family": "motorbus.protocol.base",
    "SafeAction": "motorbus.streams",
    "Stream": "motorbus.streams",
    "Streamer": "motorbus.streams",
    "open_transport": "motorbus.transport.serial",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'motorbus' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


__version__ = "0.1.0"

__all__ = [
    "Bus",
    "BusClosedError",
    "BusManager",
    "BusState",
    "BusStateChanged",
    "DeviceStop",
    "Family",
    "FaultChanged",
    "InspireLA",
    "LocalProtocolError",
    "MotorbusError",
    "NotSentError",
    "Priority",
    "ProjectFinished",
    "ProjectStepper",
    "ProjectStopped",
    "ProjectVerifyError",
    "QuadDone",
    "QuadStepper",
    "RealtimeReport",
    "RemoteProtocolError",
    "ReplyTimeoutError",
    "SafeAction",
    "StopReport",
    "Stream",
    "StreamEnded",
    "Streamer",
    "__version__",
    "install_signal_handlers",
    "open_transport",
    "run",
    "scan",
]
