"""``benchmarks/soak.py`` runs for a few seconds and writes the JSON the report relies on."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SOAK = Path(__file__).resolve().parent.parent / "benchmarks" / "soak.py"
KEYS = {
    "duration_s",
    "requests",
    "replies",
    "timeouts",
    "late_replies",
    "garbage_bytes",
    "faults_injected",
    "recoveries",
    "mismatched_replies",
    "memory",
    "memory_growth_kb",
    "fuzz",
    "invariants",
}


def test_soak_runs_and_writes_its_json(tmp_path: Path) -> None:
    out = tmp_path / "soak.json"
    done = subprocess.run(
        [
            sys.executable,
            str(SOAK),
            "--seconds",
            "2",
            "--fault-rate",
            "0.05",
            "--fuzz-examples",
            "100",
            "--sample-every",
            "1",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode in (0, 1), done.stderr
    result = json.loads(out.read_text())
    assert set(result) >= KEYS
    assert set(result["invariants"]) == {"no_mismatch", "memory_flat", "fuzz_clean"}
    # The invariants that do not depend on run length must hold even in 2 s.
    assert result["mismatched_replies"] == 0 and result["invariants"]["no_mismatch"]
    assert result["fuzz"]["examples"] >= 100 and result["fuzz"]["exceptions"] == 0
    assert result["invariants"]["fuzz_clean"]
    # Counters are consistent with each other and the faults really happened.
    assert result["requests"] > 0 and 0 < result["replies"] <= result["requests"]
    assert sum(result["faults_injected"].values()) > 0
    assert result["garbage_bytes"] > 0
    assert result["recoveries"] <= result["disconnects"]
    assert result["memory"] and {"t", "rss_kb", "tracemalloc_kb"} <= set(result["memory"][0])
    assert "summary over" in done.stdout
