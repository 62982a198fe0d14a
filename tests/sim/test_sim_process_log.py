"""``SimProcess.log_records`` reads a frame log that its simulator is still writing.

The simulator writes its log through an 8 KiB buffer, so a record can reach the file
in two writes.  A reader that met the end of the file after the first part skipped it
(a line still being written), then read on and took the rest as a line of its own: a
CI run failed on "frames.jsonl line 63 is not JSON" at byte 8192.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

from motorbus.protocol import framelog
from motorbus.sim.process import SimProcess


def test_a_record_written_in_two_parts_is_read_whole_or_not_at_all(tmp_path: Path) -> None:
    path = tmp_path / "frames.jsonl"
    header = framelog.header("sim", started_utc="2026-01-01T00:00:00Z", families=["la"])
    path.write_text(json.dumps(header) + "\n", encoding="utf-8")
    records = [
        {"t": n / 1000, "direction": "request", "family": "la", "kind": "frame",
         "hex": "55 AA 03 01 04 00 22 2A"}
        for n in range(3000)
    ]  # fmt: skip
    done = threading.Event()

    def write() -> None:  # each record in two writes, the first ending mid-record
        with path.open("a", encoding="utf-8", buffering=1 << 16) as f:
            for record in records:
                line = json.dumps(record) + "\n"
                for part in (line[:7], line[7:]):
                    f.write(part)
                    f.flush()
        done.set()

    sim = SimProcess(["la:1"], log_file=path)  # never started: only its log is read
    writer = threading.Thread(target=write)
    writer.start()
    try:
        seen = 0
        while not done.is_set():
            got = sim.log_records()  # raised on a torn record before
            assert [r["t"] for r in got] == [r["t"] for r in records[: len(got)]]
            seen = len(got)
    finally:
        writer.join()
    assert [r["t"] for r in sim.log_records()] == [r["t"] for r in records]
    assert seen <= len(records)
