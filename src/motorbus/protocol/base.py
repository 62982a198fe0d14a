"""Building blocks shared by the three device protocols.

Pure code: no asyncio, no clock, no I/O.  Everything here is small and used by
``la``, ``project_stepper``, ``quad_stepper`` and ``reassembler``.
"""

from __future__ import annotations

import abc
import enum
import math
import numbers
import operator
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import ClassVar, Generic, NamedTuple, TypeVar

from motorbus.errors import LocalProtocolError, RemoteProtocolError

__all__ = [
    "BAUD_MAX",
    "BAUD_MIN",
    "BITS_PER_BYTE",
    "FF_AA",
    "LA_REPLY_HEADER",
    "LA_REQUEST_HEADER",
    "PROJECT_FINISHED_BYTES",
    "WAIT_TIMEOUT_MAX_S",
    "Command",
    "Direction",
    "Family",
    "FaultState",
    "FrameShape",
    "ProjectFinishedMarker",
    "ReplyT_co",
    "as_real",
    "check_choice",
    "check_flag",
    "check_int",
    "check_timeout",
    "format_hex",
    "parse_hex",
    "sum8",
    "wire_time",
]

#: Header of every stepper request and reply (docs 000 and 001, "FF AA").
FF_AA = b"\xff\xaa"
#: Header of an LA request, host -> actuator (doc 002 section 3.3).
LA_REQUEST_HEADER = b"\x55\xaa"
#: Header of an LA reply, actuator -> host (doc 002 section 3.4).
LA_REPLY_HEADER = b"\xaa\x55"
#: The bare completion marker the project stepper sends when a project ends (doc 000, 0x4E).
PROJECT_FINISHED_BYTES = b"\xee\xdd"


class Family(enum.Enum):
    """The three device families motorbus speaks."""

    LA = "la"
    PROJECT_STEPPER = "project_stepper"
    QUAD_STEPPER = "quad_stepper"

    # Members are singletons compared by identity: hashed by identity too, in C (Enum's
    # own __hash__ is a Python call, on every per-frame dict and set lookup of a family).
    __hash__ = object.__hash__


class Direction(enum.Enum):
    """Which way a frame travels."""

    REQUEST = "request"  # host -> device
    REPLY = "reply"  # device -> host


#: A UART byte on the wire: start bit, 8 data bits, stop bit (8N1, all three manuals).
BITS_PER_BYTE = 10


def wire_time(nbytes: int, baud: int) -> float:
    """Seconds that ``nbytes`` take on the wire at ``baud`` (8N1: 10 bits a byte)."""
    return nbytes * BITS_PER_BYTE / baud


def sum8(data: bytes | bytearray | memoryview) -> int:
    """Return the low 8 bits of the sum of ``data`` (the checksum of all three manuals)."""
    return sum(data) & 0xFF


def _is_bool(value: object) -> bool:
    # ``bool`` and numpy's ``bool_`` (which is no ``bool`` subclass): a flag is not a number.
    if isinstance(value, bool):
        return True
    kind = type(value)
    return kind.__name__ in ("bool_", "bool") and kind.__module__ == "numpy"


def _as_int(value: object) -> int | None:
    """``value`` as a plain int if it is an integer (an ``int`` or any object with
    ``__index__``, such as a numpy integer scalar), else None.  Bools are not integers."""
    if type(value) is int:
        return value
    if _is_bool(value):
        return None
    if isinstance(value, int):
        return int(value)  # an IntEnum member or another int subclass
    index = getattr(type(value), "__index__", None)
    if index is None:
        return None
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:  # e.g. a numpy array of more than one element
        return None


def check_int(field: str, value: object, lo: int, hi: int) -> int:
    """Return ``value`` as an ``int`` if it is an integer in ``lo..hi``; else raise
    ``LocalProtocolError``.

    The error names the field, the value and the allowed range, so a user can fix the
    call without reading the source.  ``bool`` is refused: ``True`` is not a position.
    Integer-like objects (numpy integer scalars: anything with ``__index__``) are
    accepted and returned as a plain ``int``; floats are refused, even ``2.0``.
    """
    number = value if type(value) is int else _as_int(value)
    if number is None:
        raise LocalProtocolError(
            f"{field} must be an integer in {lo}..{hi}, got {value!r} ({type(value).__name__})",
            field=field,
            value=value,
        )
    if not lo <= number <= hi:
        raise LocalProtocolError(
            f"{field}={number} is out of range: allowed {lo}..{hi}", field=field, value=value
        )
    return number


def check_choice(field: str, value: object, allowed: Sequence[int], meaning: str = "") -> int:
    """Return ``value`` (as an ``int``) if it is one of ``allowed``; else raise
    ``LocalProtocolError``."""
    number = _as_int(value)
    if number is None or number not in allowed:
        shown = ", ".join(str(a) for a in allowed)
        extra = f" ({meaning})" if meaning else ""
        raise LocalProtocolError(
            f"{field}={value!r} is not allowed: choose one of {shown}{extra}",
            field=field,
            value=value,
        )
    return value if isinstance(value, int) else number


def as_real(value: object) -> float | None:
    """``value`` as a float if it is a real number (int, float, numpy scalar, Fraction...),
    else None.  Bools and text are not numbers; NaN and infinity are returned as such."""
    if type(value) is float or type(value) is int:
        return float(value)
    if _is_bool(value) or not isinstance(value, numbers.Real):
        number = _as_int(value)  # an integer-like object that is not registered as Real
        return None if number is None else float(number)
    return float(value)


#: Plausible serial line speeds, bit/s (motorbus.validation says why): the bus's, the
#: transports' and the command line's ``--baud``.
BAUD_MIN = 300
BAUD_MAX = 4_000_000
#: Longest a call waits for a motion to end (a project's run, a quad move, a quad LED
#: command's done reply), and the command line's longest duration option: one day, a
#: guard against typos such as ``timeout=1e9``, not a device limit.
WAIT_TIMEOUT_MAX_S = 86400.0


def check_timeout(field: str, value: object, maximum: float = math.inf) -> float:
    """Return ``value`` (seconds) as a float if it is a finite number in ``0..maximum``.

    Raises:
        LocalProtocolError: a bool, a non-number, NaN, infinity or out of range (a NaN
            deadline used to reach the timer and break its callback).
    """
    number = as_real(value)
    shown = " or more" if maximum == math.inf else f"..{maximum:g}"
    if number is None:
        raise LocalProtocolError(
            f"{field} must be a number of seconds 0{shown}, got {value!r} ({type(value).__name__})",
            field=field,
            value=value,
        )
    if not math.isfinite(number) or not 0 <= number <= maximum:
        raise LocalProtocolError(
            f"{field}={value!r} is out of range: allowed 0{shown} seconds (a finite number)",
            field=field,
            value=value,
        )
    return number


def check_flag(field: str, value: object) -> bool:
    """Return ``value`` if it is a bool (or a numpy ``bool_``); a truthy string, a number
    or None must not pick a command."""
    if not _is_bool(value):
        raise LocalProtocolError(
            f"{field} must be True or False, got {value!r} ({type(value).__name__})",
            field=field,
            value=value,
        )
    return bool(value)


def parse_hex(text: str) -> bytes:
    """Parse hex text such as ``"55 AA 03 01"`` or ``"55aa0301"`` (spaces, commas, ``0x`` ok).

    Raises ``ValueError`` naming the first offending token.
    """
    cleaned = text.replace(",", " ").replace("0x", " ").replace("0X", " ")
    tokens = cleaned.split()
    out = bytearray()
    for token in tokens:
        if len(token) % 2:
            raise ValueError(f"hex input: {token!r} has an odd number of digits")
        try:
            out += bytes.fromhex(token)
        except ValueError:
            raise ValueError(f"hex input: {token!r} is not hexadecimal") from None
    return bytes(out)


def format_hex(data: bytes | bytearray | memoryview) -> str:
    """Format bytes as space-separated upper-case hex, the notation of the manuals."""
    return bytes(data).hex(" ").upper()


@dataclass(frozen=True, slots=True)
class FrameShape:
    """What an unframed stepper reply must look like (it has no length and no checksum).

    ``pattern[i]`` is the set of values allowed at byte ``i`` (``None`` = any byte);
    positions past the end of ``pattern`` accept anything.  ``length`` is the total size.
    The reassembler uses shapes to cut stepper replies out of the stream and to refuse
    look-alike garbage; the bus derives them from the request it sent.
    """

    length: int
    pattern: tuple[frozenset[int] | None, ...]
    #: ``pattern`` without its ``None`` entries: (position, allowed values), in order.
    _checks: tuple[tuple[int, frozenset[int]], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        checks = tuple((i, a) for i, a in enumerate(self.pattern) if a is not None)
        object.__setattr__(self, "_checks", checks)

    def matches(self, raw: bytes | bytearray | memoryview) -> bool:
        """Return True if the first ``len(raw)`` bytes fit this shape (a prefix may match)."""
        return self.matches_at(raw, 0, len(raw))

    def matches_at(self, buf: bytes | bytearray | memoryview, p: int, avail: int) -> bool:
        """``matches`` for the ``avail`` bytes of ``buf`` from ``p``, without copying them."""
        for i, allowed in self._checks:
            if i >= avail:
                return True
            if buf[p + i] not in allowed:
                return False
        return True

    @classmethod
    def exact(cls, length: int, *prefix: int | frozenset[int] | None) -> FrameShape:
        """Build a shape from per-byte values: an int, a set of ints, or ``None`` for any."""
        pattern: list[frozenset[int] | None] = []
        for p in prefix:
            if p is None or isinstance(p, frozenset):
                pattern.append(p)
            else:
                pattern.append(frozenset((p,)))
        return cls(length, tuple(pattern))


class ProjectFinishedMarker(NamedTuple):
    """The project stepper's bare ``EE DD``: the running project has finished (A0-06).

    A stream item (the reassembler's); the bus turns it into the event
    ``motorbus.bus.events.ProjectFinished`` for its subscribers.
    """

    raw: bytes = PROJECT_FINISHED_BYTES


class FaultState(NamedTuple):
    """A device's fault flags as one reply reported them (see ``Command.fault_state``)."""

    device_id: int
    errors: int


#: The type of a command's decoded reply (``Command[Status]``, ``Command[Ack]``).
ReplyT_co = TypeVar("ReplyT_co", covariant=True)


class Command(abc.ABC, Generic[ReplyT_co]):
    """A request to a device, as a value: build it, encode it, know its reply.

    ``Command[R]`` decodes its reply into an ``R``, so ``await bus.request(cmd)`` is
    typed: ``bus.request(la.Control(...))`` is a ``Status``.  A command that expects
    no reply (a broadcast, the no-reply ``MoveTo``, an ID-255 request) resolves to
    ``None`` at run time; its static type names the reply of the addressed form.

    Subclasses are frozen dataclasses that validate their fields on construction
    (raising ``LocalProtocolError``), so a ``Command`` that exists can always be sent.
    """

    __slots__ = ()

    def __init_subclass__(cls, **kwargs: object) -> None:
        # Every command validates in ``__post_init__``; run ``_plain_fields`` first, so
        # that a numpy integer given for an ID or a position is checked and stored as
        # the plain int that ``encode`` (``int.to_bytes``) needs.
        super().__init_subclass__(**kwargs)
        post = cls.__dict__.get("__post_init__")
        if post is None or getattr(post, "_plain_fields", False):
            return

        def __post_init__(self: Command[object]) -> None:
            _plain_fields(self)
            post(self)

        __post_init__._plain_fields = True  # type: ignore[attr-defined]
        __post_init__.__doc__ = post.__doc__
        cls.__post_init__ = __post_init__  # type: ignore[attr-defined]

    #: Which device family understands this command.
    family: ClassVar[Family]
    #: True for commands that start motion: the bus never retries them blindly.
    starts_motion: ClassVar[bool] = False

    @abc.abstractmethod
    def encode(self) -> bytes:
        """Return the exact request bytes, checksum included."""

    @abc.abstractmethod
    def reply_lengths(self) -> tuple[int, ...]:
        """Every total length the (first) reply may have; ``()`` if the device stays silent."""

    @abc.abstractmethod
    def matches_reply(self, raw: bytes) -> bool:
        """Return True if the complete frame ``raw`` is a reply to this request."""

    @abc.abstractmethod
    def decode_reply(self, raw: bytes) -> ReplyT_co:
        """Decode a frame for which ``matches_reply`` is True into a typed value."""

    def decode_matched(self, raw: bytes) -> ReplyT_co:
        """``decode_reply`` of a frame ``matches_reply`` has just accepted (the bus's
        path): a family may skip the checks that match made.  Same value, same errors."""
        return self.decode_reply(raw)

    def reply_shapes(self) -> tuple[FrameShape, ...]:
        """Shapes of the reply for unframed (stepper) protocols; ``()`` for LA frames."""
        return ()

    def done_shapes(self) -> tuple[FrameShape, ...]:
        """Shapes of a later "done" reply (quad stepper run and LED commands), else ``()``."""
        return ()

    def matches_done(self, raw: bytes) -> bool:
        """Return True if the complete frame ``raw`` is a later "done" reply of this
        request: the length and every byte of one of its ``done_shapes``."""
        return any(len(raw) == s.length and s.matches(raw) for s in self.done_shapes())

    @property
    def expects_reply(self) -> bool:
        """True if the device answers this request."""
        return bool(self.reply_lengths())

    @property
    def device_key(self) -> str:
        """Stats key of the device this command addresses (``"quad_stepper"``; an LA
        command answers ``"la:3"``): each family says how its devices are told apart."""
        return self.family.value

    def reaches(self, key: str) -> bool:
        """True if this command addresses the device whose ``device_key`` is ``key``:
        the bus keeps the queue order of requests that reach a common device."""
        return key == self.device_key

    def fault_state(self, reply: object) -> FaultState | None:
        """The fault flags a decoded ``reply`` reports, if the family reports any.

        The bus compares them with the device's previous ones and publishes a
        ``FaultChanged`` event when they differ; it needs no family knowledge for it.
        """
        return None


#: Field values ``_plain_fields`` leaves alone without a closer look.
_PLAIN_TYPES = frozenset((int, bool, float, str, bytes, type(None), tuple))


def _plain_fields(cmd: Command[object]) -> None:
    """Replace integer-like field values (numpy scalars) of a dataclass command by ints."""
    for name in cmd.__dataclass_fields__:  # type: ignore[attr-defined]
        value = getattr(cmd, name)
        if type(value) in _PLAIN_TYPES or isinstance(value, int | enum.Enum):
            continue
        number = _as_int(value)
        if number is not None:
            object.__setattr__(cmd, name, number)


def require_reply(cmd: Command[object], raw: bytes) -> None:
    """Raise ``RemoteProtocolError`` unless ``raw`` is a reply to ``cmd``."""
    if not cmd.matches_reply(raw):
        raise RemoteProtocolError(
            f"{format_hex(raw)} is not a reply to {type(cmd).__name__}", raw=raw
        )
