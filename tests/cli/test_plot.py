"""The terminal plot of ``motorbus monitor --plot``: statuses in, text out."""

from __future__ import annotations

import os

import pytest

from motorbus.cli.plot import render
from motorbus.protocol import la
from motorbus.sim.process import SimProcess
from tests.helpers import CLI_TIMEOUT_S, cli
from tests.zygote import run_motorbus


def status(position: int, target: int, force: int) -> la.Status:
    return la.Status(1, target=target, position=position, force=force)


def test_position_target_and_force_against_time() -> None:
    samples = [
        (0.0, {1: status(0, 100, 0), 2: "timeout"}),
        (1.0, {1: status(50, 100, 0), 2: "timeout"}),
        (2.0, {1: status(100, 100, 20)}),
    ]
    # Columns: t * 9 / 2 rounded: 0, 4, 9; a status holds until the next refresh.
    assert render(samples, [1, 2], width=10, height=3, force_height=2) == [
        "la:1  position *  target -  (# both)  force *",
        "    100|---------#",
        "       |    *****",
        "      0|****",
        "       +----------",
        "    20g|         *",
        "     0g|*********",
        "       +----------",
        "        0.0 s2.0 s",
        "la:2  position *  target -  (# both)  force *",
        "  no status yet (timeout)",
        "x: no status that refresh (timeout)",
    ]


def test_a_timeout_marks_its_column_and_a_still_actuator_draws_a_flat_line() -> None:
    samples = [(k * 0.1, {3: status(800, 800, 0) if k != 5 else "timeout"}) for k in range(10)]
    lines = render(samples, [3], width=10, height=5, force_height=2)
    chart = [line.split("|", 1)[1] if "|" in line else "" for line in lines[1:6]]
    assert sum(row.count("#") for row in chart) == 9  # position on target, every column but one
    assert len({row.count("#") for row in chart if row.count("#")}) == 1  # all on one row
    assert chart[-1][5] == "x"
    assert lines[-1] == "x: no status that refresh (timeout)"
    assert render([], [3]) == ["(no samples yet)"]


def test_monitor_refuses_a_window_without_a_display_and_plot_with_json() -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    base = ["monitor", "--port", "/nonexistent", "--ids", "1"]
    r = run_motorbus([*base, "--plot", "window"], env, CLI_TIMEOUT_S)
    assert r.returncode == 2
    assert r.stderr.startswith("motorbus monitor: --plot window needs a display")
    r = run_motorbus([*base, "--plot", "--json"], env, CLI_TIMEOUT_S)
    assert r.returncode == 2
    assert r.stderr == "motorbus monitor: --plot and --json do not go together: choose one\n"


def test_monitor_plot_draws_each_id_from_a_simulator() -> None:
    with SimProcess(["la:1-2"], baud=921600) as sim:
        r = cli("monitor", "--port", sim.path, "--ids", "1,2", "--count", "3", "--plot")
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    # Not a terminal: each refresh prints a whole plot, one block per actuator.
    heads = [line for line in lines if line.startswith("la:")]
    assert [h.split()[0] for h in heads] == ["la:1", "la:2"] * 3
    assert any("#" in line for line in lines)  # the simulated actuators sit on target


def test_window_plot_puts_each_series_on_its_line() -> None:
    """The window's drawing, on the non-interactive backend (no display needed)."""
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from motorbus.cli.plot import WindowPlot

    window = WindowPlot([1])
    try:
        window.update(
            [(0.0, {1: status(10, 100, 5)}), (0.5, {1: "timeout"}), (1.0, {1: status(60, 100, 7)})]
        )
        ax_pos, ax_force = window.ax_pos, window.ax_force
        series = {line.get_label(): list(line.get_ydata()) for line in ax_pos.get_lines()}
        assert series == {"position 1": [10, 60], "target 1": [100, 100]}
        assert [list(line.get_ydata()) for line in ax_force.get_lines()] == [[5, 7]]
        assert list(ax_pos.get_lines()[0].get_xdata()) == [0.0, 1.0]
        assert window.open
    finally:
        plt.close(window.fig)
    assert not window.open
