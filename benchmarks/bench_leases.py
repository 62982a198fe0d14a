"""What the lease rule adds to every motion frame a bus sends (issue 19).

The bus checks and records leases in two places per motion frame: ``submit`` (the
owner check, ``Bus._claim``) and the write (``LeaseTable.moved``); a stop written
afterwards pays what is owed (``LeaseTable.sent``).  This times those table operations
alone, for a single LA target and for 15-actuator F3 broadcasts (a stream tick), next to
the frame's own ``encode()`` for scale.  Pure Python, no bus, no I/O.

    python benchmarks/bench_leases.py [--quick] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import timeit
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

from motorbus.bus.leases import LeaseTable
from motorbus.protocol import la, safety


def pause_for(key: str) -> tuple[object, ...]:
    return safety.safe_stop_commands(key, "pause")


def measure(n: int) -> dict[str, float]:
    table = LeaseTable()
    program = table.implicit(pause_for, "pause")  # type: ignore[arg-type]
    single = la.MoveTo(3, 1500)
    entries = tuple((i, 1000 + i) for i in range(1, 16))
    broadcast = la.Broadcast.prevalidated(la.BroadcastMode.FOLLOW, entries)
    stop = la.Control(3, la.ControlAction.PAUSE)

    def submit_and_write(cmd: la.LACommand[object]) -> None:
        keys = safety.motion_keys(cmd)
        for key in keys:
            table.note(key)
        table.claim(keys, program)
        table.moved(cmd)

    submit_and_write(single)
    submit_and_write(broadcast)  # the first frame creates the entries; time the rest

    def us(fn: object) -> float:
        best = min(timeit.repeat(fn, number=n, repeat=5))  # type: ignore[arg-type]
        return best / n * 1e6

    return {
        "single_target_lease_us": us(lambda: submit_and_write(single)),
        "single_target_encode_us": us(single.encode),
        "broadcast15_lease_us": us(lambda: submit_and_write(broadcast)),
        "broadcast15_encode_us": us(broadcast.encode),
        "stop_sent_us": us(lambda: table.sent(stop)),
        "n": n,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer iterations")
    parser.add_argument("--json", type=Path, default=None, help="write the results here")
    args = parser.parse_args()
    result = measure(2_000 if args.quick else 20_000)
    result["python"] = platform.python_version()  # type: ignore[assignment]
    rows = [
        ("LA target (0x21)", "single_target_lease_us", "single_target_encode_us"),
        ("F3 broadcast, 15 IDs", "broadcast15_lease_us", "broadcast15_encode_us"),
    ]
    print(f"{'frame':<22} {'lease path (us)':>16} {'encode (us)':>12}")
    for label, lease_key, encode_key in rows:
        print(f"{label:<22} {result[lease_key]:>16.2f} {result[encode_key]:>12.2f}")
    print(f"{'a stop paying its debt':<22} {result['stop_sent_us']:>16.2f}")
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
