"""What can be checked on Linux of motorbus on other platforms (docs/windows-macos.md)."""

from __future__ import annotations

import subprocess
import sys

#: Import the library as Windows would see it: no SIGHUP, no ``resource`` module, and
#: ``sys.platform`` "win32" (the standard library and the dependencies are imported first:
#: they pick their own Windows modules, which Linux does not have).
AS_ON_WINDOWS = """
import asyncio, signal, sys
import anyio, serial, serial_asyncio_fast
sys.platform = "win32"
del signal.SIGHUP
sys.modules["resource"] = None
import motorbus, motorbus.runtime.shutdown as shutdown, motorbus.runtime.realtime
from motorbus import Bus, BusManager, InspireLA, Streamer, run
print([s.name for s in shutdown.STOP_SIGNALS])
"""


def test_the_library_imports_without_sighup_and_without_resource() -> None:
    r = subprocess.run(
        [sys.executable, "-c", AS_ON_WINDOWS], capture_output=True, text=True, timeout=60
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip() == "['SIGINT', 'SIGTERM']"
