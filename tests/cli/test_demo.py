"""``motorbus demo``: --json output, the ramp from the read positions, the plot."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys
from pathlib import Path

import pytest

from motorbus.cli import demo
from motorbus.protocol import framelog, la
from motorbus.protocol.base import parse_hex

DEMO_TIMEOUT_S = 120


def test_the_ramp_starts_at_the_read_position_and_joins_the_trajectory() -> None:
    ramp = 2.0
    for i, start in ((0, 0.0), (7, 1800.0)):
        assert demo.ramped(0.0, i, start, ramp) == start
        assert demo.ramped(ramp, i, start, ramp) == demo.trajectory(ramp, i)
        assert demo.ramped(ramp + 1, i, start, ramp) == demo.trajectory(ramp + 1, i)
        # No jump anywhere: 10 ms apart, targets differ by far less than a stroke.
        steps = [demo.ramped(k * 0.01, i, start, ramp) for k in range(300)]
        assert max(abs(b - a) for a, b in itertools.pairwise(steps)) < 25
    assert demo.ramp_s(8.0) == demo.RAMP_S
    assert demo.ramp_s(1.0) == 0.5


def test_the_jitter_histogram_is_log_scale_in_microseconds_with_outliers_marked() -> None:
    pytest.importorskip("matplotlib")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    log = demo.DemoLog(samples=[(k * 0.01, 1, 1000 + k, 990 + k) for k in range(50)])
    # 200 ticks 10 ms apart with 5..104 us of jitter, and two late ones (3 ms, 6 ms).
    arrivals = [k * 0.01 + (5 + k % 100) * 1e-6 for k in range(200)]
    arrivals[50] += 3e-3
    arrivals[150] += 6e-3
    fig = demo.figure(log, arrivals)
    try:
        hist = fig.axes[1]
        assert hist.get_xscale() == "log"
        assert "µs" in hist.get_xlabel() and "us)" not in hist.get_xlabel()
        assert "µs" in hist.get_title()
        labels = hist.get_legend_handles_labels()[1]
        assert "2 outliers beyond p99" in labels
        assert {"p50", "p99"} <= set(labels)
    finally:
        plt.close(fig)


def test_demo_json_writes_one_document_to_stdout(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    r = subprocess.run(
        [sys.executable, "-m", "motorbus", "demo", "--seconds", "1", "--json", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=DEMO_TIMEOUT_S,
    )
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)  # the whole of stdout is one JSON document
    assert summary["project"] == "done" and summary["quad"] == "done"
    assert summary["stream_host"]["ticks"] > 0
    assert json.loads((out / "summary.json").read_text(encoding="utf-8")) == summary
    assert f"summary written to {out / 'summary.json'}" in r.stderr
    assert "simulators: LA bus" in r.stderr and "project stepper" in r.stderr
    # The simulator's log is a frame log, and the stream began at the read positions
    # (the simulated actuators start at 0), not at the trajectory's 400..1600.
    with (out / "la-bus-frames.jsonl").open(encoding="utf-8") as fh:
        log = framelog.read_frame_log(fh)
    assert log.headers[0]["source"] == "sim"
    broadcasts = [
        la.decode_request(parse_hex(r["hex"]))
        for r in log.records
        if r["direction"] == "request" and r["hex"][9:14] == "FF F3"
    ]
    first = broadcasts[0]
    assert isinstance(first, la.Broadcast)
    assert len(first.entries) == demo.N_ACTUATORS
    assert max(position for _, position in first.entries) <= 5
