"""Frames per second through the stream reassembler, against pymodbus's RTU framer.

The stream is LA 22-byte status frames (doc 002 section 3.5.4) fed in 4 KiB chunks, as a
serial read loop would deliver them.  Four measurements, each with 0 % and 1 % garbage
(random bytes inserted between frames, 1 % of all bytes, seeded):

* framing: ``Reassembler(families=[Family.LA]).feed`` alone;
* decoded: framing plus ``la.decode_status`` on every frame (a typed ``la.Status``);

and, as the baseline measured in the same run, pymodbus's ``FramerRTU.handleFrame`` with
its client ``DecodePDU`` on 21-byte RTU frames (a Read Holding Registers response of 8
registers, the closest Modbus frame to an LA status).  ``handleFrame`` consumes its whole
buffer and returns at most one PDU (RTU is one frame per read), so it gets one call per
frame, not per chunk.  Every figure is the best of ``--repeats`` runs of ``--seconds``.

Then the resynchronisation table: time per byte of each kind of junk against random junk
of the same set-up and read size, measured in the same run, for three reassembler set-ups
(an LA bus, ``motorbus decode`` with every family and both directions, a simulator reading
requests of every family), fed in 4 KiB reads and in 64-byte reads (what a pty read
delivers at speed).  The kinds: random bytes; ``AA 55``, ``55 AA`` and ``FF AA`` repeated;
"dense" junk (90 % the two header bytes in random order, 10 % random); all ``FF``; an
``EE DD`` flood; the set-up's own frames with a wrong checksum; its frames each missing
its last byte (near-frames); and headers built to pass every rule but the checksum (LA
read-reply headers claiming 260 bytes every 5 bytes, stepper requests every 4).  The goal
is bounded work per byte: every kind within 5x of random junk.  A second table counts the
work instead of timing it (function calls per byte, cProfile's count): it does not depend
on the load of a shared machine.

Usage: ``python benchmarks/bench_reassembler.py [--seconds 2] [--quick] [--profile] [--junk-only]``;
``--best-of REPORT...`` prints the least time of each cell over several ``--junk-only``
reports (sittings), relative to random junk.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import random
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from harness import write_report
from motorbus.protocol import la
from motorbus.protocol.base import Direction, Family, sum8
from motorbus.protocol.reassembler import Frame, Reassembler

DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "reassembler.json"
#: A typical serial read: what one ``feed`` call gets.
CHUNK_SIZE = 4096
#: Frames in the synthetic stream (about 440 kB of LA status frames).
STREAM_FRAMES = 20_000
#: Share of stream bytes that are garbage in the "1 %" runs.
GARBAGE_SHARE = 0.01
SEED = 20_240_601
#: Registers in the Modbus response: 1 + 1 + 1 + 2 * 8 + 2 = 21 bytes, like an LA status.
MODBUS_REGISTERS = 8

GOAL_FRAMES_PER_S = 1_000_000
GOAL_DECODED_PER_S = 400_000
GOAL_RATIO_VS_PYMODBUS = 5.0
#: Every kind of junk must cost within this factor of random junk per byte.
GOAL_JUNK_RATIO = 5.0
#: Bytes of each kind of junk per measured pass.
JUNK_BYTES = 100_000
#: Passes per kind at least (each pass is short; the best of a few is what the code costs).
JUNK_MIN_REPEATS = 7
#: Read sizes for the junk table: a bulk read, and a small pty read.
JUNK_CHUNKS = (4096, 64)
#: Reassembler set-ups: (name, direction, families).
JUNK_SETUPS: tuple[tuple[str, Direction | None, tuple[Family, ...]], ...] = (
    ("la-bus", Direction.REPLY, (Family.LA,)),
    ("decode", None, tuple(Family)),
    ("simulator", Direction.REQUEST, tuple(Family)),
)
JUNK_KINDS = (
    "normal",
    "random",
    "aa55-repeat",
    "55aa-repeat",
    "ffaa-repeat",
    "aa55-dense",
    "ffaa-dense",
    "all-ff",
    "eedd-flood",
    "bad-checksum",
    "near-frames",
    "plausible-headers",
)
#: Bytes per kind and read sizes for the calls-per-byte table (a byte at a time is slow
#: under the profiling hook, hence the small size).
WORK_BYTES = 4000
WORK_CHUNKS = (4096, 64)


# -- streams ---------------------------------------------------------------------------------


def status_frames(count: int, rng: random.Random) -> list[bytes]:
    """``count`` valid status frames with varied fields (so no two checksums agree)."""
    return [
        la.encode_status(
            rng.randint(1, 254),
            target=rng.randint(0, 2000),
            position=rng.randint(-20, 2020),
            temperature=rng.randint(15, 70),
            current=rng.randint(0, 1500),
            force=rng.randint(-2000, 2000),
            errors=rng.choice((0, 0, 0, 1, 4)),
            internal1=rng.randint(0, 0xFFFF),
            internal2=rng.randint(0, 0xFFFF),
        )
        for _ in range(count)
    ]


def with_garbage(frames: list[bytes], share: float, rng: random.Random) -> bytes:
    """Join ``frames`` with random bytes inserted between them, ``share`` of all bytes."""
    if share <= 0:
        return b"".join(frames)
    frame_bytes = sum(len(f) for f in frames)
    garbage = round(frame_bytes * share / (1 - share))
    gaps = [0] * (len(frames) + 1)
    for gap in rng.choices(range(len(gaps)), k=garbage):
        gaps[gap] += 1
    out = bytearray()
    for gap, frame in zip(gaps, [*frames, b""], strict=True):
        out += rng.randbytes(gap)
        out += frame
    return bytes(out)


def chunks_of(stream: bytes) -> list[bytes]:
    """The stream cut into ``CHUNK_SIZE`` reads."""
    return [stream[i : i + CHUNK_SIZE] for i in range(0, len(stream), CHUNK_SIZE)]


# -- the measured loops: each processes the whole stream once and returns frames done ----------


def framing_pass(chunks: list[bytes]) -> int:
    """Frame the stream; return the frames found."""
    r = Reassembler(families=[Family.LA])
    feed = r.feed
    for chunk in chunks:
        feed(chunk)
    r.end_of_stream()
    return r.stats.frames


def decoding_pass(chunks: list[bytes]) -> int:
    """Frame the stream and decode every frame to an ``la.Status``; return the count."""
    r = Reassembler(families=[Family.LA])
    feed = r.feed
    decode = la.decode_status
    count = 0
    for chunk in chunks:
        for item in feed(chunk):
            if type(item) is Frame:
                # The reassembler has verified header, Len and checksum: not again.
                decode(item.raw, checked=True)
                count += 1
    return count


def pymodbus_setup(count: int, rng: random.Random) -> tuple[Callable[[], int], str]:
    """A pass over ``count`` RTU frames through pymodbus, and its version."""
    import pymodbus
    from pymodbus.framer import FramerRTU
    from pymodbus.pdu import DecodePDU
    from pymodbus.pdu.register_message import ReadHoldingRegistersResponse

    framer = FramerRTU(DecodePDU(is_server=False))
    frames = [
        framer.buildFrame(
            ReadHoldingRegistersResponse(
                dev_id=rng.randint(1, 247),
                registers=[rng.randint(0, 0xFFFF) for _ in range(MODBUS_REGISTERS)],
            )
        )
        for _ in range(count)
    ]
    assert {len(f) for f in frames} == {21}

    def run() -> int:
        handle = framer.handleFrame
        done = 0
        for f in frames:
            _, pdu = handle(f, 0, 0)
            if pdu is not None:
                done += 1
        return done

    return run, pymodbus.__version__


def best_rate(one_pass: Callable[[], int], seconds: float, repeats: int) -> tuple[float, int]:
    """Best frames/s over ``repeats`` runs of whole passes lasting at least ``seconds``.

    Returns the rate and the frames one pass handles (so callers can check the count).
    """
    best = 0.0
    per_pass = one_pass()  # warm-up, and the count to check
    for _ in range(repeats):
        frames = 0
        start = time.perf_counter()
        elapsed = 0.0
        while elapsed < seconds:
            frames += one_pass()
            elapsed = time.perf_counter() - start
        best = max(best, frames / elapsed)
    return best, per_pass


# -- junk: time per byte -------------------------------------------------------------------------


def dense_junk(size: int, pair: tuple[int, int], rng: random.Random) -> bytes:
    """``size`` bytes, 90 % drawn from ``pair`` (in random order), 10 % random."""
    return bytes(
        rng.choice(pair) if rng.random() < 0.9 else rng.randrange(256) for _ in range(size)
    )


def project_requests(size: int, rng: random.Random) -> bytes:
    """About ``size`` bytes of valid 11-byte project stepper requests: motor commands
    (01..0F, to motor bytes 1..4) with random parameter bytes and a step (0..10)."""
    return b"".join(project_request_list(size, rng))


def project_request_list(size: int, rng: random.Random) -> list[bytes]:
    """The requests of ``project_requests``, one by one."""
    out: list[bytes] = []
    total = 0
    while total < size:
        motor, cmd, step = rng.randint(1, 4), rng.randint(1, 0x0F), rng.randint(0, 10)
        body = bytes((0xFF, 0xAA, motor, cmd, *rng.randbytes(5), step))
        out.append(body + bytes((sum8(body),)))
        total += PROJECT_REQUEST_BYTES
    return out


PROJECT_REQUEST_BYTES = 11


def repeated(pattern: bytes, size: int) -> bytes:
    """``pattern`` over and over, ``size`` bytes."""
    return (pattern * (size // len(pattern) + 1))[:size]


def bad_checksums(frames: list[bytes]) -> bytes:
    """``frames`` joined, each with its checksum byte one off: headers, lengths and
    command bytes right, so every one passes to a verdict."""
    return b"".join(f[:-1] + bytes(((f[-1] + 1) & 0xFF,)) for f in frames)


def near_frames(frames: list[bytes]) -> bytes:
    """``frames`` joined, each without its last byte: a header whose claimed length runs
    into the next frame."""
    return b"".join(f[:-1] for f in frames)


def junk_streams(size: int, rng: random.Random) -> dict[str, dict[str, bytes]]:
    """Per set-up, the stream of each kind (frame-like kinds depend on the set-up)."""
    common = {
        "random": rng.randbytes(size),
        "aa55-repeat": repeated(b"\xaa\x55", size),
        "55aa-repeat": repeated(b"\x55\xaa", size),
        "ffaa-repeat": repeated(b"\xff\xaa", size),
        "aa55-dense": dense_junk(size, (0xAA, 0x55), rng),
        "ffaa-dense": dense_junk(size, (0xFF, 0xAA), rng),
        "all-ff": b"\xff" * size,
        "eedd-flood": repeated(b"\xee\xdd", size),
    }
    statuses = status_frames(size // la.STATUS_FRAME_SIZE, rng)
    requests = project_request_list(size, rng)
    streams: dict[str, dict[str, bytes]] = {}
    for name, direction, _ in JUNK_SETUPS:
        frames = requests if direction is Direction.REQUEST else statuses
        streams[name] = {
            "normal": b"".join(frames),
            **common,
            "bad-checksum": bad_checksums(frames),
            "near-frames": near_frames(frames),
            "plausible-headers": repeated(ADVERSARIAL[name], size),
        }
    return streams


#: Per set-up, headers built to pass every rule but the checksum: LA reply headers
#: every 5 bytes claiming 260-byte read replies (CMD 01 allows any Len), or stepper
#: request headers every 4 bytes (byte 3 at most 0x0F, byte 2 a quad address).
ADVERSARIAL = {
    "la-bus": b"\xaa\x55\xff\x01\x01",
    "decode": b"\xaa\x55\xff\x01\x01",
    "simulator": b"\xff\xaa\x00\x01",
}


def junk_pass(
    data: bytes, chunk: int, direction: Direction | None, families: tuple[Family, ...]
) -> None:
    """Feed ``data`` in ``chunk``-byte reads to a fresh reassembler, then end the stream."""
    r = Reassembler(direction=direction, families=families)
    feed = r.feed
    for i in range(0, len(data), chunk):
        feed(data[i : i + chunk])
    r.end_of_stream()


def ns_per_byte(
    data: bytes, chunk: int, setup: tuple[str, Direction | None, tuple[Family, ...]], repeats: int
) -> float:
    """Best time per byte (ns) over ``repeats`` passes."""
    _, direction, families = setup
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        junk_pass(data, chunk, direction, families)
        best = min(best, time.perf_counter() - start)
    return best / len(data) * 1e9


def interleaved_ns_per_byte(
    streams: dict[str, bytes],
    chunk: int,
    setup: tuple[str, Direction | None, tuple[Family, ...]],
    repeats: int,
) -> dict[str, float]:
    """Best time per byte (ns) of each kind, the kinds taking turns pass by pass: a
    shared machine's slow spell then falls on every kind alike, not on one."""
    best = dict.fromkeys(JUNK_KINDS, float("inf"))
    for _ in range(repeats):
        for kind in JUNK_KINDS:
            best[kind] = min(best[kind], ns_per_byte(streams[kind], chunk, setup, 1))
    return best


def calls_per_byte(
    data: bytes, chunk: int, setup: tuple[str, Direction | None, tuple[Family, ...]]
) -> float:
    """Function calls (Python and C) per byte fed, counted by cProfile: work, not time."""
    _, direction, families = setup
    junk_pass(
        data, chunk, direction, families
    )  # once unprofiled: one-time set-up is no work per byte
    profiler = cProfile.Profile()
    profiler.runcall(junk_pass, data, chunk, direction, families)
    stats = pstats.Stats(profiler)
    return float(stats.total_calls) / len(data)  # type: ignore[attr-defined]


def work_table() -> dict[str, dict[str, dict[str, float]]]:
    """Calls per byte for each set-up, kind and read size (deterministic: no clock)."""
    streams = junk_streams(WORK_BYTES, random.Random(SEED + 1))
    table: dict[str, dict[str, dict[str, float]]] = {}
    print(f"\ncalls per byte fed (cProfile, counted, not timed), {WORK_BYTES:,} bytes per kind")
    print(f"{'set-up':10} {'read':>5} " + " ".join(f"{k[:11]:>11}" for k in JUNK_KINDS))
    for setup in JUNK_SETUPS:
        for chunk in WORK_CHUNKS:
            row = {
                kind: calls_per_byte(streams[setup[0]][kind], chunk, setup) for kind in JUNK_KINDS
            }
            table.setdefault(setup[0], {})[str(chunk)] = {k: round(v, 2) for k, v in row.items()}
            print(f"{setup[0]:10} {chunk:>5} " + " ".join(f"{row[k]:>11.1f}" for k in JUNK_KINDS))
    return table


def junk_table(size: int, repeats: int) -> dict[str, Any]:
    """Measure, print and return the time-per-byte table, each kind relative to random
    junk of the same set-up and read size, measured in the same run."""
    repeats = max(repeats, JUNK_MIN_REPEATS)
    streams = junk_streams(size, random.Random(SEED + 1))
    table: dict[str, dict[str, dict[str, float]]] = {}
    relative: dict[str, dict[str, dict[str, float]]] = {}
    print(f"\ntime per byte (ns), best of {repeats}, {size:,} bytes per kind")
    print("and, below each row, the same relative to random junk (goal: junk within 5x)")
    print(f"{'set-up':10} {'read':>5} " + " ".join(f"{k[:11]:>11}" for k in JUNK_KINDS))
    worst = 0.0
    worst_at = ""
    for setup in JUNK_SETUPS:
        name = setup[0]
        for chunk in JUNK_CHUNKS:
            row = interleaved_ns_per_byte(streams[name], chunk, setup, repeats)
            ratio = {k: v / row["random"] for k, v in row.items()}
            for kind, r in ratio.items():
                if kind != "normal" and r > worst:
                    worst, worst_at = r, f"{name} {chunk} {kind}"
            table.setdefault(name, {})[str(chunk)] = {k: round(v, 1) for k, v in row.items()}
            relative.setdefault(name, {})[str(chunk)] = {k: round(v, 2) for k, v in ratio.items()}
            print(f"{name:10} {chunk:>5} " + " ".join(f"{row[k]:>11,.1f}" for k in JUNK_KINDS))
            print(f"{'':10} {'':>5} " + " ".join(f"{ratio[k]:>10.1f}x" for k in JUNK_KINDS))
    met = worst <= GOAL_JUNK_RATIO
    print(
        f"goal {'junk_within_5x_of_random':30} {'met' if met else 'NOT met'} "
        f"(worst {worst:.1f}x: {worst_at})"
    )
    return {
        "calls_per_byte": work_table(),
        "ns_per_byte": table,
        "relative_to_random": relative,
        "bytes_per_kind": size,
        "worst_ratio": round(worst, 2),
        "worst_at": worst_at,
        "junk_within_5x_of_random": met,
    }


def best_of(paths: list[Path]) -> dict[str, dict[str, dict[str, float]]]:
    """Per set-up, read and kind, the least ns per byte over several ``--junk-only``
    reports (sittings of one tree), and print each kind relative to random junk."""
    best: dict[str, dict[str, dict[str, float]]] = {}
    for path in paths:
        table = json.loads(path.read_text(encoding="utf-8"))["junk"]["ns_per_byte"]
        for name, reads in table.items():
            for read, row in reads.items():
                cell = best.setdefault(name, {}).setdefault(read, {})
                for kind, ns in row.items():
                    cell[kind] = min(cell.get(kind, ns), ns)
    print(f"best of {len(paths)} sittings, relative to random junk (random in ns per byte)")
    print(f"{'set-up':10} {'read':>5} " + " ".join(f"{k[:11]:>11}" for k in JUNK_KINDS))
    for name, reads in best.items():
        for read, row in reads.items():
            cells = [f"{row[k] / row['random']:>10.1f}x" for k in JUNK_KINDS]
            cells[JUNK_KINDS.index("random")] = f"{row['random']:>8.1f} ns"
            print(f"{name:10} {read:>5} " + " ".join(cells))
    return best


# -- reporting ----------------------------------------------------------------------------------


def profile_decoding(chunks: list[bytes]) -> None:
    """Print where decoding time goes (cProfile, top 12 by own time)."""
    profiler = cProfile.Profile()
    profiler.runcall(decoding_pass, chunks)
    pstats.Stats(profiler, stream=sys.stdout).sort_stats("tottime").print_stats(12)


def main(argv: list[str] | None = None) -> int:
    """Run every measurement, print the table, write the JSON report; return 0."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--seconds", type=float, default=2.0, help="per measurement run")
    parser.add_argument("--repeats", type=int, default=3, help="runs per measurement (best)")
    parser.add_argument("--quick", action="store_true", help="0.2 s runs, a smaller stream")
    parser.add_argument("--profile", action="store_true", help="profile the decoding pass")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="JSON report path")
    parser.add_argument("--junk-only", action="store_true", help="only the time-per-byte table")
    parser.add_argument(
        "--best-of", type=Path, nargs="+", help="only print the least ns of these reports"
    )
    args = parser.parse_args(argv)
    if args.best_of:
        best_of(args.best_of)
        return 0
    junk_size = JUNK_BYTES // 4 if args.quick else JUNK_BYTES
    if args.junk_only:
        junk = junk_table(junk_size, args.repeats)
        report_junk: dict[str, Any] = {
            "benchmark": "reassembler-junk",
            "junk": junk,
            "chunks": list(JUNK_CHUNKS),
            "repeats": args.repeats,
            "quick": args.quick,
        }
        out = (
            args.out if args.out != DEFAULT_OUT else DEFAULT_OUT.with_name("reassembler_junk.json")
        )
        write_report(out, report_junk)
        return 0
    seconds = 0.2 if args.quick else args.seconds
    count = STREAM_FRAMES // 4 if args.quick else STREAM_FRAMES

    rng = random.Random(SEED)
    frames = status_frames(count, rng)
    clean = chunks_of(with_garbage(frames, 0.0, rng))
    dirty_stream = with_garbage(frames, GARBAGE_SHARE, rng)
    dirty = chunks_of(dirty_stream)
    pymodbus_pass, pymodbus_version = pymodbus_setup(count, rng)

    rows: list[tuple[str, str, float, int]] = []
    measured: dict[str, float] = {}
    counts_ok = True
    for key, label, garbage, one_pass in (
        ("frames_per_s", "framing", "0 %", lambda: framing_pass(clean)),
        ("frames_per_s_garbage1", "framing", "1 %", lambda: framing_pass(dirty)),
        ("decoded_per_s", "framing + la.decode_status", "0 %", lambda: decoding_pass(clean)),
        (
            "decoded_per_s_garbage1",
            "framing + la.decode_status",
            "1 %",
            lambda: decoding_pass(dirty),
        ),
        ("pymodbus_decoded_per_s", "pymodbus FramerRTU.handleFrame", "0 %", pymodbus_pass),
    ):
        rate, found = best_rate(one_pass, seconds, args.repeats)
        measured[key] = rate
        rows.append((label, garbage, rate, found))
        counts_ok &= found == count

    ratio = measured["decoded_per_s"] / measured["pymodbus_decoded_per_s"]
    goals = {
        "framing_ge_1M_per_s": measured["frames_per_s"] >= GOAL_FRAMES_PER_S,
        "decoded_ge_400k_per_s": measured["decoded_per_s"] >= GOAL_DECODED_PER_S,
        "decoded_ge_5x_pymodbus": ratio >= GOAL_RATIO_VS_PYMODBUS,
        "every_undamaged_frame_found": counts_ok,
    }

    print(f"{'measurement':32} {'garbage':>7} {'frames/s':>12} {'found/pass':>11}")
    for label, garbage, rate, found in rows:
        print(f"{label:32} {garbage:>7} {rate:>12,.0f} {found:>5}/{count}")
    print(
        f"\nmotorbus: one feed() per {CHUNK_SIZE}-byte chunk of 22-byte LA status frames; "
        f"pymodbus {pymodbus_version}: one handleFrame() per 21-byte RTU frame "
        "(it consumes its whole buffer and returns one PDU)."
    )
    print(
        f"decoded vs pymodbus: {ratio:.2f}x  (garbage bytes in the 1 % stream: "
        f"{len(dirty_stream) - count * la.STATUS_FRAME_SIZE})"
    )
    for name, met in goals.items():
        print(f"goal {name:30} {'met' if met else 'NOT met'}")
    junk = junk_table(junk_size, args.repeats)

    report: dict[str, Any] = {
        "benchmark": "reassembler",
        **{k: round(v) for k, v in measured.items()},
        "ratio_vs_pymodbus": round(ratio, 3),
        "goals": {**goals, "junk_within_5x_of_random": junk["junk_within_5x_of_random"]},
        "junk": junk,
        "frames_per_pass": count,
        "chunk_bytes": CHUNK_SIZE,
        "garbage_share": GARBAGE_SHARE,
        "seconds_per_run": seconds,
        "repeats": args.repeats,
        "quick": args.quick,
        "pymodbus": {"version": pymodbus_version, "calls": "one handleFrame per frame"},
    }
    write_report(args.out, report)
    if args.profile:
        profile_decoding(clean)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
