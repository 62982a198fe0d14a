"""``benchmarks/bench_serve_scale.py --quick`` runs and writes the JSON its table and
docs/serve.md rely on (no timing is asserted: figures belong to the benchmark)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_serve_scale.py"


def bench(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=180
    )


def test_quick_run_measures_both_sides_and_the_deadman(tmp_path: Path) -> None:
    out = tmp_path / "scale.json"
    done = bench("--quick", "--out", str(out))
    assert done.returncode == 0, done.stderr
    report = json.loads(out.read_text(encoding="utf-8"))
    assert report["bus_tick"].startswith("one 10 ms period of one bus")
    (size,) = report["sizes"]
    assert (size["buses"], size["clients"]) == (4, 2)
    for side in ("embedded", "served"):
        row = size[side]
        assert row["bus_ticks_due"] == 400
        assert 0 < row["bus_ticks"] <= row["bus_ticks_due"]
        assert row["bus_ticks"] + row["skipped_ticks"] <= row["bus_ticks_due"]
        assert row["rtt_ms"]["n"] == row["bus_ticks"]
        assert 0 < row["rtt_ms"]["p50"] <= row["rtt_ms"]["p99"]
        assert row["owner_cpu_us_per_bus_tick"] > 0
    # The served side counts its clients' CPU; embedded has none.
    assert set(size["served"]["cpu_s"]) == {"owner", "sim", "client0", "client1"}
    assert set(size["embedded"]["cpu_s"]) == {"owner", "sim"}
    # The killed client's two buses were paused at their simulators, no other bus.
    deadman = size["deadman"]
    assert deadman["buses_of_the_victim"] == 2 and len(deadman["kills"]) == 1
    kill = deadman["kills"][0]
    assert 0 < kill["first_ms"] <= kill["last_ms"]
    assert deadman["other_buses_stopped"] == 0
    assert "ticks done" in done.stdout
    assert "deadman" in done.stdout


@pytest.mark.parametrize(
    ("args", "named"),
    [
        (["--buses", "8,12", "--per-client", "8"], "--buses='8,12'"),
        (["--buses", "eight"], "--buses='eight'"),
        (["--kills", "0"], "--kills=0"),
        (["--seconds", "0.1"], "--seconds=0.1"),
    ],
)
def test_bad_arguments_are_refused_naming_them(args: list[str], named: str) -> None:
    done = bench(*args)
    assert done.returncode == 2 and named in done.stderr
