"""``motorbus doctor``: why a bus is slow, silent or noisy, and what it can sustain.

    report = await motorbus.diagnose(motorbus.DoctorConfig("/dev/ttyUSB0", 921600))
    print(report.format_text())      # one line per check: green / yellow / red + what to do
    report.exit_code                 # 0 when nothing is red
    report.as_dict()                 # the --json form

``checks``, ``host`` and ``budget`` judge facts (pure); ``system`` reads them from sysfs
and /proc, ``probe`` from the bus (asyncio, read-only); ``report`` prints them.
"""

from __future__ import annotations

from motorbus.doctor.checks import Finding, Level
from motorbus.doctor.probe import DOCTOR_BAUDS, DoctorConfig, diagnose
from motorbus.doctor.report import DoctorReport
from motorbus.doctor.served import diagnose_served

__all__ = [
    "DOCTOR_BAUDS",
    "DoctorConfig",
    "DoctorReport",
    "Finding",
    "Level",
    "diagnose",
    "diagnose_served",
]
