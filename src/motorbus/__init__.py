"""motorbus: asyncio buses of serial motion devices.

The supported public API.  The sans-I/O protocol values live in
``motorbus.protocol.la``, ``motorbus.protocol.project_stepper`` and
``motorbus.protocol.quad_stepper`` (and the other ``motorbus.protocol`` modules); the
simulators in ``motorbus.sim``.  The command line (``motorbus.cli``) uses nothing else.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"


def _load_runtime() -> None:
    # Signals, the guard and real-time mode (motorbus.runtime) come with every bus:
    # motorbus.lifecycle calls this the first time the library needs them (the first
    # Bus.open), so a program that never imports the runtime still gets its safety.
    importlib.import_module("motorbus.runtime.hooks")


from motorbus import lifecycle as _lifecycle  # noqa: E402 (after the loader it is given)
from motorbus.protocol.exports import lazy_names  # noqa: E402

_lifecycle.set_loader(_load_runtime)

#: The public names and the module each is loaded from on first use, so that
#: ``import motorbus.protocol`` (sans-I/O) does not pull in asyncio and the serial
#: backends through this package's __init__.  The one list: ``__all__`` is made from it,
#: and tests/test_public_api.py checks that the ``TYPE_CHECKING`` imports below (which
#: type checkers read) name exactly these.
_EXPORTS: dict[str, tuple[str, ...]] = {
    "motorbus.bus.bus": ("DEFAULT_HOST_MARGIN_S", "Bus", "BusState", "PreparedSubmit", "Priority"),
    "motorbus.bus.events": ("BusStateChanged", "FaultChanged", "ProjectFinished", "QuadDone"),
    "motorbus.bus.leases": ("Lease", "LeaseInfo"),
    "motorbus.devices.la": ("InspireLA", "ScanReport", "scan"),
    "motorbus.devices.la_scan": ("SCAN_PASSES_MAX",),
    "motorbus.devices.group": ("read_statuses",),
    "motorbus.devices.calibration": ("Calibration", "NamedActuator", "write_calibration_file"),
    "motorbus.devices.project_stepper": ("ProjectStepper",),
    "motorbus.doctor": ("DoctorConfig", "DoctorReport", "diagnose", "diagnose_served"),
    "motorbus.devices.quad_stepper": ("QuadStepper",),
    "motorbus.errors": (
        "ArrivalTimeoutError",
        "BusClosedError",
        "GroupReadError",
        "GuardError",
        "LeaseConflictError",
        "LocalProtocolError",
        "MotorbusError",
        "NotSentError",
        "PortInUseError",
        "ProjectInvalidError",
        "ProjectStopped",
        "ProjectVerifyError",
        "RemoteProtocolError",
        "ReplyTimeoutError",
        "StreamEnded",
        "WrongLoopError",
    ),
    "motorbus.busfile": ("BusFile", "BusSpec", "default_bus_file", "load_bus_file"),
    "motorbus.manager": ("BusManager", "DeviceStop", "StopReport"),
    "motorbus.runtime.process_groups": ("ProcessGroup",),
    "motorbus.protocol.base": ("Family",),
    "motorbus.runtime.realtime": ("RealtimeReport",),
    "motorbus.serve.client": ("connect",),
    "motorbus.runtime.shutdown": ("install_signal_handlers", "run"),
    "motorbus.streams": ("PERIOD_MAX_S", "PERIOD_MIN_S", "SafeAction", "Stream", "Streamer"),
    "motorbus.transport.base": ("DataCallback", "LostCallback", "Transport", "TransportStats"),
    "motorbus.transport.serial": ("BACKENDS", "DEFAULT_BACKEND", "open_transport"),
    "motorbus.transport.usb": ("SerialPortInfo", "list_serial_ports", "resolve_port"),
}

if TYPE_CHECKING:
    from motorbus.bus.bus import DEFAULT_HOST_MARGIN_S as DEFAULT_HOST_MARGIN_S
    from motorbus.bus.bus import Bus as Bus
    from motorbus.bus.bus import BusState as BusState
    from motorbus.bus.bus import PreparedSubmit as PreparedSubmit
    from motorbus.bus.bus import Priority as Priority
    from motorbus.bus.events import BusStateChanged as BusStateChanged
    from motorbus.bus.events import FaultChanged as FaultChanged
    from motorbus.bus.events import ProjectFinished as ProjectFinished
    from motorbus.bus.events import QuadDone as QuadDone
    from motorbus.bus.leases import Lease as Lease
    from motorbus.bus.leases import LeaseInfo as LeaseInfo
    from motorbus.busfile import BusFile as BusFile
    from motorbus.busfile import BusSpec as BusSpec
    from motorbus.busfile import default_bus_file as default_bus_file
    from motorbus.busfile import load_bus_file as load_bus_file
    from motorbus.devices.calibration import Calibration as Calibration
    from motorbus.devices.calibration import NamedActuator as NamedActuator
    from motorbus.devices.calibration import write_calibration_file as write_calibration_file
    from motorbus.devices.group import read_statuses as read_statuses
    from motorbus.devices.la import InspireLA as InspireLA
    from motorbus.devices.la import ScanReport as ScanReport
    from motorbus.devices.la import scan as scan
    from motorbus.devices.la_scan import SCAN_PASSES_MAX as SCAN_PASSES_MAX
    from motorbus.devices.project_stepper import ProjectStepper as ProjectStepper
    from motorbus.devices.quad_stepper import QuadStepper as QuadStepper
    from motorbus.doctor import DoctorConfig as DoctorConfig
    from motorbus.doctor import DoctorReport as DoctorReport
    from motorbus.doctor import diagnose as diagnose
    from motorbus.doctor import diagnose_served as diagnose_served
    from motorbus.errors import ArrivalTimeoutError as ArrivalTimeoutError
    from motorbus.errors import BusClosedError as BusClosedError
    from motorbus.errors import GroupReadError as GroupReadError
    from motorbus.errors import GuardError as GuardError
    from motorbus.errors import LeaseConflictError as LeaseConflictError
    from motorbus.errors import LocalProtocolError as LocalProtocolError
    from motorbus.errors import MotorbusError as MotorbusError
    from motorbus.errors import NotSentError as NotSentError
    from motorbus.errors import PortInUseError as PortInUseError
    from motorbus.errors import ProjectInvalidError as ProjectInvalidError
    from motorbus.errors import ProjectStopped as ProjectStopped
    from motorbus.errors import ProjectVerifyError as ProjectVerifyError
    from motorbus.errors import RemoteProtocolError as RemoteProtocolError
    from motorbus.errors import ReplyTimeoutError as ReplyTimeoutError
    from motorbus.errors import StreamEnded as StreamEnded
    from motorbus.errors import WrongLoopError as WrongLoopError
    from motorbus.manager import BusManager as BusManager
    from motorbus.manager import DeviceStop as DeviceStop
    from motorbus.manager import StopReport as StopReport
    from motorbus.protocol.base import Family as Family
    from motorbus.runtime.process_groups import ProcessGroup as ProcessGroup
    from motorbus.runtime.realtime import RealtimeReport as RealtimeReport
    from motorbus.runtime.shutdown import install_signal_handlers as install_signal_handlers
    from motorbus.runtime.shutdown import run as run
    from motorbus.serve.client import connect as connect
    from motorbus.streams import PERIOD_MAX_S as PERIOD_MAX_S
    from motorbus.streams import PERIOD_MIN_S as PERIOD_MIN_S
    from motorbus.streams import SafeAction as SafeAction
    from motorbus.streams import Stream as Stream
    from motorbus.streams import Streamer as Streamer
    from motorbus.transport.base import DataCallback as DataCallback
    from motorbus.transport.base import LostCallback as LostCallback
    from motorbus.transport.base import Transport as Transport
    from motorbus.transport.base import TransportStats as TransportStats
    from motorbus.transport.serial import BACKENDS as BACKENDS
    from motorbus.transport.serial import DEFAULT_BACKEND as DEFAULT_BACKEND
    from motorbus.transport.serial import open_transport as open_transport
    from motorbus.transport.usb import SerialPortInfo as SerialPortInfo
    from motorbus.transport.usb import list_serial_ports as list_serial_ports
    from motorbus.transport.usb import resolve_port as resolve_port

if not TYPE_CHECKING:  # (type checkers read the imports above: a misspelt name is caught)
    __all__, __getattr__, __dir__ = lazy_names(__name__, _EXPORTS, also=["__version__"])
