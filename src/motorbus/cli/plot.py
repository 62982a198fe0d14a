"""Plots of LA status against time for ``motorbus monitor --plot``.

:func:`render` is pure - statuses in, text out - and draws with plain characters, so a
terminal plot needs no dependency.  :class:`WindowPlot` draws the same in a matplotlib
window (``--plot window``) when matplotlib and a display are there.

Each actuator gets two charts over the same time axis (oldest sample at the left,
newest at the right):

* position ``*`` and target ``-`` (``#`` where they share a cell), scaled to the range
  the samples cover; a column whose query timed out shows ``x`` on the bottom row;
* force in grams ``*``, scaled likewise.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

from motorbus.cli.main import UsageError
from motorbus.protocol import la

__all__ = ["LABEL_WIDTH", "MIN_WIDTH", "Sample", "WindowPlot", "check_window", "render"]

#: One refresh: its time (s since the monitor started) and each ID's status, or a
#: short text such as ``"timeout"`` where there was none.
Sample = tuple[float, Mapping[int, la.Status | str]]

#: Narrowest plot area in columns; narrower terminals still get this many.
MIN_WIDTH = 10
#: Width of the value labels left of each chart.
LABEL_WIDTH = _LABEL = 7
#: Smallest span of a chart's value axis, so a still actuator draws a flat line
#: in the middle rather than noise stretched over the whole height.
_MIN_SPAN = {"position": 10, "force": 10}


def _column(t: float, t0: float, t1: float, width: int) -> int:
    if t1 <= t0:
        return width - 1
    return round((t - t0) / (t1 - t0) * (width - 1))


def _scale(values: Sequence[int], min_span: int) -> tuple[float, float]:
    lo, hi = float(min(values)), float(max(values))
    if hi - lo < min_span:
        mid = (hi + lo) / 2
        lo, hi = mid - min_span / 2, mid + min_span / 2
        if lo < 0 <= min(values):  # a force of 0 need not make the axis go negative
            lo, hi = 0.0, float(min_span)
    return lo, hi


def _row(value: float, lo: float, hi: float, height: int) -> int:
    """Row of ``value``, 0 at the bottom."""
    return round((value - lo) / (hi - lo) * (height - 1))


def _chart(grid: list[list[str]], lo: float, hi: float, unit: str = "") -> list[str]:
    """Label the rows of ``grid`` (top row first) with the values they stand for."""
    height = len(grid)
    lines = []
    for k, row in enumerate(grid):
        level = height - 1 - k
        if level in (0, height - 1) or (height > 4 and level == (height - 1) // 2):
            value = lo + (hi - lo) * level / (height - 1)
            label = f"{value:.0f}{unit}".rjust(_LABEL)
        else:
            label = " " * _LABEL
        lines.append(f"{label}|{''.join(row)}".rstrip())
    return lines


def render(
    samples: Sequence[Sample],
    ids: Sequence[int],
    *,
    width: int = 60,
    height: int = 8,
    force_height: int = 4,
) -> list[str]:
    """Draw position, target and force of each ID against time; return the lines.

    Args:
        samples: refreshes in time order (the caller keeps as many as it wants shown).
        ids: the actuators to draw, in this order.
        width: columns of the plot area (at least ``MIN_WIDTH``).
        height: rows of the position chart (at least 2).
        force_height: rows of the force chart (at least 2).
    """
    width = max(MIN_WIDTH, width)
    height = max(2, height)
    force_height = max(2, force_height)
    if not samples:
        return ["(no samples yet)"]
    t0, t1 = samples[0][0], samples[-1][0]
    axis = " " * _LABEL + "+" + "-" * width
    first = f"{t0:.1f} s"
    span = " " * (_LABEL + 1) + first + f"{t1:.1f} s".rjust(width - len(first))
    lines: list[str] = []
    for ident in ids:
        # Every column from one refresh to the next shows the earlier one (a status
        # holds until the next is read); a refresh without a status marks its column.
        events = [
            (_column(t, t0, t1, width), s)
            for t, statuses in samples
            if (s := statuses.get(ident)) is not None
        ]
        points: list[tuple[int, la.Status]] = []
        missing: list[tuple[int, str]] = []
        for k, (col, s) in enumerate(events):
            if isinstance(s, str):
                missing.append((col, s))
                continue
            end = events[k + 1][0] if k + 1 < len(events) else col + 1
            points += [(c, s) for c in range(col, max(end, col + 1))]
        lines.append(f"la:{ident}  position *  target -  (# both)  force *")
        if not points:
            lines.append(f"  no status yet ({missing[-1][1] if missing else 'not polled'})")
            continue
        lo, hi = _scale(
            [s.position for _, s in points] + [s.target for _, s in points], _MIN_SPAN["position"]
        )
        grid = [[" "] * width for _ in range(height)]
        for col, s in points:
            tr = _row(s.target, lo, hi, height)
            pr = _row(s.position, lo, hi, height)
            grid[height - 1 - tr][col] = "-"
            grid[height - 1 - pr][col] = "#" if pr == tr else "*"
        for col, _ in missing:
            grid[height - 1][col] = "x"
        lines += _chart(grid, lo, hi)
        lines.append(axis)
        flo, fhi = _scale([s.force for _, s in points], _MIN_SPAN["force"])
        fgrid = [[" "] * width for _ in range(force_height)]
        for col, s in points:
            fgrid[force_height - 1 - _row(s.force, flo, fhi, force_height)][col] = "*"
        lines += _chart(fgrid, flo, fhi, "g")
        lines.append(axis)
        lines.append(span)
    if any(isinstance(s, str) for _, st in samples for s in st.values()):
        lines.append("x: no status that refresh (timeout)")
    return lines


def check_window() -> None:
    """Refuse ``--plot window`` where it cannot work, before anything is opened.

    Raises:
        UsageError: no display, or matplotlib (or its window backend) is missing.
    """
    if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise UsageError(
            "--plot window needs a display (DISPLAY and WAYLAND_DISPLAY are unset); "
            "use --plot terminal"
        )
    try:
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise UsageError(
            f"--plot window needs matplotlib (pip install 'motorbus[plot]'): {err}"
        ) from err
    backend = str(plt.get_backend()).lower()
    if backend in ("agg", "pdf", "svg", "ps", "cairo", "template"):
        raise UsageError(
            f"--plot window: matplotlib has no window backend here (it chose {backend}); "
            "use --plot terminal"
        )


class WindowPlot:
    """A matplotlib window with position, target and force of each ID, redrawn live."""

    def __init__(self, ids: Sequence[int]) -> None:
        import matplotlib.pyplot as plt

        self._plt = plt
        self.ids = list(ids)
        plt.ion()
        self.fig, (self.ax_pos, self.ax_force) = plt.subplots(2, 1, sharex=True, figsize=(9, 6))
        self._lines: dict[tuple[int, str], Any] = {}
        for ident in self.ids:
            (pos,) = self.ax_pos.plot([], [], "-", label=f"position {ident}")
            (tgt,) = self.ax_pos.plot(
                [], [], "--", color=pos.get_color(), linewidth=1, label=f"target {ident}"
            )
            (force,) = self.ax_force.plot([], [], "-", color=pos.get_color(), label=f"{ident}")
            self._lines[ident, "position"] = pos
            self._lines[ident, "target"] = tgt
            self._lines[ident, "force"] = force
        self.ax_pos.set_ylabel("position (0..2000)")
        self.ax_pos.legend(ncol=2, fontsize="small")
        self.ax_force.set_ylabel("force (g)")
        self.ax_force.set_xlabel("time (s)")
        self.fig.tight_layout()

    def update(self, samples: Sequence[Sample]) -> None:
        """Redraw with ``samples`` and let the window handle its events."""
        for ident in self.ids:
            pts = [(t, s) for t, st in samples if isinstance(s := st.get(ident), la.Status)]
            ts = [t for t, _ in pts]
            self._lines[ident, "position"].set_data(ts, [s.position for _, s in pts])
            self._lines[ident, "target"].set_data(ts, [s.target for _, s in pts])
            self._lines[ident, "force"].set_data(ts, [s.force for _, s in pts])
        for ax in (self.ax_pos, self.ax_force):
            ax.relim()
            ax.autoscale_view()
        self.fig.canvas.draw_idle()
        self._plt.pause(0.001)

    @property
    def open(self) -> bool:
        """False once the user closed the window."""
        return bool(self._plt.fignum_exists(self.fig.number))
