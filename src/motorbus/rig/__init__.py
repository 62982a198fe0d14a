"""An actuator test rig: step, tracking, latency and repeatability figures.

``analysis`` is the pure core (samples in, figures out), ``plan`` the validated test
plan, ``compare`` the run-to-run judgement (all three pure); ``runner`` runs a plan on
an open bus and ``report`` writes ``results.json``, ``samples.csv`` and ``report.html``.
``docs/rig.md`` defines every figure.  Names load on first use, so importing the
package (the command line does, to build its help) costs nothing until a rig runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from motorbus.protocol.exports import lazy_names

_EXPORTS = {
    "motorbus.rig.compare": (
        "FIGURES",
        "Row",
        "compare_results",
        "parse_tolerances",
        "read_results",
    ),
    "motorbus.rig.plan": ("DEFAULT_FREQUENCIES", "TESTS", "RigPlan", "default_window"),
    "motorbus.rig.report": ("write_report",),
    "motorbus.rig.runner": ("DeviceResult", "Failure", "RigResult", "run_rig"),
    "motorbus.errors": ("RigAborted",),
}

if TYPE_CHECKING:
    from motorbus.errors import RigAborted as RigAborted
    from motorbus.rig.compare import FIGURES as FIGURES
    from motorbus.rig.compare import Row as Row
    from motorbus.rig.compare import compare_results as compare_results
    from motorbus.rig.compare import parse_tolerances as parse_tolerances
    from motorbus.rig.compare import read_results as read_results
    from motorbus.rig.plan import DEFAULT_FREQUENCIES as DEFAULT_FREQUENCIES
    from motorbus.rig.plan import TESTS as TESTS
    from motorbus.rig.plan import RigPlan as RigPlan
    from motorbus.rig.plan import default_window as default_window
    from motorbus.rig.report import write_report as write_report
    from motorbus.rig.runner import DeviceResult as DeviceResult
    from motorbus.rig.runner import Failure as Failure
    from motorbus.rig.runner import RigResult as RigResult
    from motorbus.rig.runner import run_rig as run_rig

if not TYPE_CHECKING:  # (type checkers read the imports above: a misspelt name is caught)
    __all__, __getattr__, __dir__ = lazy_names(__name__, _EXPORTS)
