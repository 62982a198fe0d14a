"""An actuator test rig: step, tracking, latency and repeatability figures.

``analysis`` is the pure core (samples in, figures out), ``plan`` the validated test
plan, ``compare`` the run-to-run judgement (both pure); ``runner`` runs a plan on an
open bus and ``report`` writes ``results.json``, ``samples.csv`` and ``report.html``.
``docs/rig.md`` defines every figure.
"""

from __future__ import annotations

from motorbus.rig.compare import FIGURES as FIGURES
from motorbus.rig.compare import Row as Row
from motorbus.rig.compare import compare_results as compare_results
from motorbus.rig.compare import parse_tolerances as parse_tolerances
from motorbus.rig.plan import DEFAULT_FREQUENCIES as DEFAULT_FREQUENCIES
from motorbus.rig.plan import TESTS as TESTS
from motorbus.rig.plan import RigPlan as RigPlan
from motorbus.rig.plan import default_window as default_window
from motorbus.rig.report import write_report as write_report
from motorbus.rig.runner import DeviceResult as DeviceResult
from motorbus.rig.runner import RigResult as RigResult
from motorbus.rig.runner import run_rig as run_rig
from motorbus.rig.sampler import RigAborted as RigAborted

__all__ = [
    "DEFAULT_FREQUENCIES",
    "FIGURES",
    "TESTS",
    "DeviceResult",
    "RigAborted",
    "RigPlan",
    "RigResult",
    "Row",
    "compare_results",
    "default_window",
    "parse_tolerances",
    "run_rig",
    "write_report",
]
