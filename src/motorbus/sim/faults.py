"""Seeded, reproducible fault injection for the simulated bus.

``FaultConfig`` says *what* may go wrong and how often; ``FaultInjector`` draws from
a seeded ``random.Random`` to decide what does go wrong to each frame a device sends.
``SimBus`` applies both to the device -> host direction only: the host's requests
always reach the models intact (a corrupted request would simply be discarded by the
device, which looks to the host exactly like a dropped reply).

Same configuration, same seed, same requests: same bytes out, byte for byte.

Fault kinds (the keys of ``SimStats.faults_injected`` and the ``"fault"`` field of a
log line):

* ``drop``: one byte of a reply is lost (counted per byte).
* ``flip``: one bit of one byte is inverted (counted per byte).
* ``garbage``: 1..8 random bytes are inserted before or inside a reply.
* ``late``: a reply is delivered ``late_reply_delay_s`` after it would have arrived.
* ``duplicate``: a reply is sent twice, back to back.
* ``silent``: a device heard a request but its answer was suppressed.
* ``disconnect``: the link went away (pty master closed, memory peer unplugged).
"""

from __future__ import annotations

import math
import random
from collections.abc import Iterator
from dataclasses import dataclass, field

from motorbus.errors import LocalProtocolError

__all__ = [
    "DEFAULT_LATE_REPLY_DELAY_S",
    "DEFAULT_RECONNECT_AFTER_S",
    "FAULT_KINDS",
    "GARBAGE_MAX_BYTES",
    "GARBAGE_MIN_BYTES",
    "FaultConfig",
    "FaultInjector",
    "FaultedReply",
]

#: Every kind of fault the simulator can inject, in the order they are reported.
FAULT_KINDS = ("drop", "flip", "garbage", "late", "duplicate", "silent", "disconnect")
#: Size range of one garbage burst.  Eight bytes is enough to fake a partial header plus
#: a plausible LA Len byte, which is what exercises a reassembler's resync path.
GARBAGE_MIN_BYTES = 1
GARBAGE_MAX_BYTES = 8
#: Default extra delay of a late reply: longer than the 5 ms (921600 bit/s) and 10 ms
#: (115200 bit/s) LA timeouts of docs/protocols.md A2-15 and the 50 ms stepper timeout of A0-14.
DEFAULT_LATE_REPLY_DELAY_S = 0.06
#: Default outage length for ``disconnect=AFTER`` without an explicit reconnect time.
DEFAULT_RECONNECT_AFTER_S = 1.0

_SPEC_FORMS = (
    "drop=RATE, flip=RATE, garbage=RATE, late=RATE[:DELAY_S], dup=RATE, silent, "
    "silent=START_S:END_S, disconnect=AFTER_S[:RECONNECT_S[:COUNT]] "
    "(comma separated, e.g. 'drop=0.01,late=0.01:0.05,disconnect=5:1')"
)


def _check_rate(name: str, value: float) -> None:
    if not (isinstance(value, int | float) and not isinstance(value, bool)) or not (
        0.0 <= value <= 1.0
    ):
        raise LocalProtocolError(
            f"{name}={value!r} is out of range: allowed 0.0..1.0 (a probability)",
            field=name,
            value=value,
        )


def _check_seconds(name: str, value: float, *, positive: bool = False) -> None:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (positive and value == 0):
        bound = "> 0" if positive else ">= 0"
        raise LocalProtocolError(
            f"{name}={value!r} is out of range: allowed {bound} seconds", field=name, value=value
        )


@dataclass(frozen=True, slots=True)
class FaultConfig:
    """What may go wrong on the simulated link, and how often.

    Rates are probabilities in 0..1: ``drop_byte_rate`` and ``bit_flip_rate`` per byte
    sent, the others per reply frame.  Times are seconds; windows and the disconnect
    schedule count from the simulator's epoch (when it started serving).

    Args:
        drop_byte_rate: chance that each reply byte is lost.
        bit_flip_rate: chance that each reply byte has one random bit inverted.
        garbage_rate: chance that 1..8 random bytes are inserted before or inside a reply.
        late_reply_rate: chance that a reply is held back by ``late_reply_delay_s``.
        late_reply_delay_s: how late a late reply is (choose it past the host's timeout).
        duplicate_reply_rate: chance that a reply is sent twice.
        silent: devices hear and act on requests but never answer.
        silent_windows: ``(start_s, end_s)`` intervals during which devices do not answer.
        disconnect_after_s: the link drops after this much connected time (``None``: never).
        reconnect_after_s: how long the link stays down each time.
        disconnect_count: how many outages in total (``None``: repeat for ever).

    Raises:
        LocalProtocolError: a rate outside 0..1, a negative time, an empty window.
    """

    drop_byte_rate: float = 0.0
    bit_flip_rate: float = 0.0
    garbage_rate: float = 0.0
    late_reply_rate: float = 0.0
    late_reply_delay_s: float = DEFAULT_LATE_REPLY_DELAY_S
    duplicate_reply_rate: float = 0.0
    silent: bool = False
    silent_windows: tuple[tuple[float, float], ...] = field(default=())
    disconnect_after_s: float | None = None
    reconnect_after_s: float = DEFAULT_RECONNECT_AFTER_S
    disconnect_count: int | None = None

    def __post_init__(self) -> None:
        _check_rate("drop_byte_rate", self.drop_byte_rate)
        _check_rate("bit_flip_rate", self.bit_flip_rate)
        _check_rate("garbage_rate", self.garbage_rate)
        _check_rate("late_reply_rate", self.late_reply_rate)
        _check_rate("duplicate_reply_rate", self.duplicate_reply_rate)
        _check_seconds("late_reply_delay_s", self.late_reply_delay_s)
        _check_seconds("reconnect_after_s", self.reconnect_after_s, positive=True)
        if self.disconnect_after_s is not None:
            _check_seconds("disconnect_after_s", self.disconnect_after_s, positive=True)
        if self.disconnect_count is not None and (
            isinstance(self.disconnect_count, bool)
            or not isinstance(self.disconnect_count, int)
            or self.disconnect_count < 1
        ):
            raise LocalProtocolError(
                f"disconnect_count={self.disconnect_count!r} is out of range: allowed >= 1 "
                "or None (for ever)",
                field="disconnect_count",
                value=self.disconnect_count,
            )
        for window in self.silent_windows:
            if len(window) != 2:
                raise LocalProtocolError(
                    f"silent_windows entry {window!r} must be (start_s, end_s)",
                    field="silent_windows",
                    value=window,
                )
            start, end = window
            _check_seconds("silent_windows start", start)
            _check_seconds("silent_windows end", end)
            if end <= start:
                raise LocalProtocolError(
                    f"silent_windows entry {window!r} is empty: end must be > start",
                    field="silent_windows",
                    value=window,
                )

    @property
    def active(self) -> bool:
        """True if any fault is configured."""
        return self != FaultConfig()

    def is_silent(self, elapsed: float) -> bool:
        """Return True if devices must not answer ``elapsed`` seconds after the epoch."""
        if self.silent:
            return True
        return any(start <= elapsed < end for start, end in self.silent_windows)

    def link_schedule(self) -> Iterator[tuple[float, float]]:
        """Yield ``(down_s, up_s)`` outages, in seconds after the epoch, in order.

        The link is up for ``disconnect_after_s``, down for ``reconnect_after_s``, and so
        on, ``disconnect_count`` times (for ever if ``None``).  Nothing if no disconnect.
        """
        if self.disconnect_after_s is None:
            return
        t = 0.0
        n = 0
        while self.disconnect_count is None or n < self.disconnect_count:
            down = t + self.disconnect_after_s
            up = down + self.reconnect_after_s
            yield down, up
            t = up
            n += 1

    @classmethod
    def parse(cls, spec: str) -> FaultConfig:
        """Parse the CLI form, e.g. ``"drop=0.01,flip=0.001,late=0.01:0.05,disconnect=5:1"``.

        Items (comma separated): ``drop=RATE``, ``flip=RATE``, ``garbage=RATE``,
        ``late=RATE[:DELAY_S]``, ``dup=RATE`` (or ``duplicate=``), ``silent`` (always),
        ``silent=START_S:END_S`` (a window; repeat the item for several), and
        ``disconnect=AFTER_S[:RECONNECT_S[:COUNT]]``.  An empty string means no faults.

        Raises:
            LocalProtocolError: an unknown item or a bad value, naming it and the forms.
        """
        values: dict[str, object] = {}
        windows: list[tuple[float, float]] = []
        for raw_item in spec.split(","):
            item = raw_item.strip()
            if not item:
                continue
            key, sep, value = item.partition("=")
            key = key.strip().lower()
            parts = [p.strip() for p in value.split(":")] if sep else []
            try:
                if key == "silent" and not sep:
                    values["silent"] = True
                elif key == "silent" and len(parts) == 2:
                    windows.append((float(parts[0]), float(parts[1])))
                elif key in _RATE_KEYS and len(parts) == 1:
                    values[_RATE_KEYS[key]] = float(parts[0])
                elif key == "late" and len(parts) == 2:
                    values["late_reply_rate"] = float(parts[0])
                    values["late_reply_delay_s"] = float(parts[1])
                elif key == "disconnect" and 1 <= len(parts) <= 3:
                    values["disconnect_after_s"] = float(parts[0])
                    if len(parts) >= 2:
                        values["reconnect_after_s"] = float(parts[1])
                    if len(parts) == 3:
                        values["disconnect_count"] = int(parts[2])
                else:
                    raise LocalProtocolError(
                        f"fault spec item {item!r} is not understood; accepted: {_SPEC_FORMS}",
                        field="faults",
                        value=item,
                    )
            except ValueError as err:
                if isinstance(err, LocalProtocolError):
                    raise
                raise LocalProtocolError(
                    f"fault spec item {item!r} has a bad number ({err}); accepted: {_SPEC_FORMS}",
                    field="faults",
                    value=item,
                ) from err
        if windows:
            values["silent_windows"] = tuple(windows)
        try:
            return cls(**values)  # type: ignore[arg-type]
        except LocalProtocolError as err:
            raise LocalProtocolError(
                f"fault spec {spec!r}: {err}", field=err.field, value=err.value
            ) from err


_RATE_KEYS = {
    "drop": "drop_byte_rate",
    "flip": "bit_flip_rate",
    "garbage": "garbage_rate",
    "late": "late_reply_rate",
    "dup": "duplicate_reply_rate",
    "duplicate": "duplicate_reply_rate",
}


@dataclass(frozen=True, slots=True)
class FaultedReply:
    """What becomes of one reply frame on its way to the host.

    ``data`` is the bytes as sent (after drops, flips and garbage), ``copies`` is 1 or 2
    (duplicate), ``extra_delay_s`` is the late-reply delay (0 if on time) and ``kinds``
    names the faults applied, in the order of ``FAULT_KINDS`` (empty if none).
    """

    data: bytes
    copies: int
    extra_delay_s: float
    kinds: tuple[str, ...]


class FaultInjector:
    """Applies a ``FaultConfig`` to reply frames, drawing from a seeded generator.

    Args:
        config: the faults to inject.
        rng: the generator; the same seed gives the same faults for the same frames.

    ``counts`` holds the number of faults injected per kind (bytes for ``drop`` and
    ``flip``, frames or bursts otherwise); ``SimBus`` adds ``silent`` and ``disconnect``.
    """

    def __init__(self, config: FaultConfig, rng: random.Random) -> None:
        self.config = config
        self.rng = rng
        self.counts: dict[str, int] = dict.fromkeys(FAULT_KINDS, 0)

    def apply(self, frame: bytes) -> FaultedReply:
        """Decide the fate of one reply ``frame``; update ``counts``; return the outcome."""
        cfg = self.config
        rng = self.rng
        kinds: list[str] = []
        data = frame
        if cfg.drop_byte_rate or cfg.bit_flip_rate:
            out = bytearray()
            dropped = flipped = 0
            for b in data:
                if cfg.drop_byte_rate and rng.random() < cfg.drop_byte_rate:
                    dropped += 1
                    continue
                if cfg.bit_flip_rate and rng.random() < cfg.bit_flip_rate:
                    b ^= 1 << rng.randrange(8)
                    flipped += 1
                out.append(b)
            data = bytes(out)
            if dropped:
                kinds.append("drop")
                self.counts["drop"] += dropped
            if flipped:
                kinds.append("flip")
                self.counts["flip"] += flipped
        if cfg.garbage_rate and rng.random() < cfg.garbage_rate:
            burst = rng.randbytes(rng.randint(GARBAGE_MIN_BYTES, GARBAGE_MAX_BYTES))
            at = rng.randrange(len(data) + 1)  # 0: before the reply ("between" two replies)
            data = data[:at] + burst + data[at:]
            kinds.append("garbage")
            self.counts["garbage"] += 1
        delay = 0.0
        if cfg.late_reply_rate and rng.random() < cfg.late_reply_rate:
            delay = cfg.late_reply_delay_s
            kinds.append("late")
            self.counts["late"] += 1
        copies = 1
        if cfg.duplicate_reply_rate and rng.random() < cfg.duplicate_reply_rate:
            copies = 2
            kinds.append("duplicate")
            self.counts["duplicate"] += 1
        return FaultedReply(data, copies, delay, tuple(kinds))
