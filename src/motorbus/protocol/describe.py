"""Describe what the reassembler cut from a stream: one JSON-ready value per item.

Pure code: no asyncio, no clock, no I/O.  ``motorbus decode`` prints these; a sniffer or
a log can use them too.  :func:`describe` never raises on a frame, however odd its bytes:
a frame no decoder accepts becomes an ``"Unknown"`` description with the raw fields the
framing alone can tell, and the decoder's complaint in ``reason``.

Stepper replies carry no type and no checksum, so the 6-byte ``FF AA`` replies of the
two stepper families can look alike (docs/protocols.md A0-05).  Which family a reply belongs
to is the caller's knowledge: ``family_hint`` supplies it, and without it the family the
reassembler guessed is used, falling back to the other stepper family if that one's
decoder refuses the bytes.

The stepper families' modules are imported when a frame of theirs is first described:
a process that only sees LA frames (an LA simulator, ``motorbus capture`` on an LA bus)
does not pay for importing them at start-up.
"""

from __future__ import annotations

import dataclasses
import enum
import json
from dataclasses import dataclass
from typing import Any, TypeAlias

from motorbus.errors import MotorbusError
from motorbus.protocol import la
from motorbus.protocol.base import FF_AA, Direction, Family, format_hex
from motorbus.protocol.reassembler import Discarded, Frame, ProjectFinishedMarker

__all__ = [
    "KIND_EVENT",
    "KIND_FRAME",
    "KIND_GARBAGE",
    "NAME_GARBAGE",
    "NAME_UNKNOWN",
    "Description",
    "JSONValue",
    "describe",
]

#: A value ``json.dumps`` accepts as is.
JSONValue: TypeAlias = int | str | bool | list["JSONValue"] | dict[str, "JSONValue"] | None

KIND_FRAME = "frame"
KIND_EVENT = "event"
KIND_GARBAGE = "garbage"
#: Name of a framed frame that no decoder of its family accepts.
NAME_UNKNOWN = "Unknown"
#: Name of a run of discarded bytes.
NAME_GARBAGE = "garbage"

#: Decoded values whose class name is not what a user would call them.
_RENAMED: dict[type, str] = {la.UnknownReply: NAME_UNKNOWN}
#: Dataclass fields never shown: the frame's bytes are already in ``Description.hex``.
_SKIPPED_FIELDS = frozenset(("raw",))
_STEPPERS = (Family.PROJECT_STEPPER, Family.QUAD_STEPPER)


@dataclass(frozen=True, slots=True)
class Description:
    """One frame, event or run of garbage, described for people and for JSON.

    Attributes:
        kind: ``"frame"``, ``"event"`` (the project stepper's ``EE DD``) or ``"garbage"``.
        family: ``"la"``, ``"project_stepper"``, ``"quad_stepper"``; ``None`` for garbage.
        direction: ``"request"`` (host to device) or ``"reply"``; ``None`` for garbage.
        name: the decoded value's class (``"MoveTo"``, ``"Status"``, ``"Ack"``,
            ``"ProjectDump"``, ``"ProjectFinished"`` ...), ``"Unknown"`` for a frame no
            decoder accepts, ``"garbage"`` for discarded bytes.
        fields: the decoded values, JSON-ready: ints, strs, bools, lists and dicts; enums
            as their names, flags as lists of names, bytes as upper-case hex.  The dict is
            not copied, so a ``Description`` is immutable by convention and not hashable.
        hex: every byte of the item, upper-case and space-separated.
        reason: why the bytes were discarded (garbage) or could not be decoded
            (``"Unknown"``); ``None`` otherwise.
    """

    kind: str
    family: str | None
    direction: str | None
    name: str
    fields: dict[str, JSONValue]
    hex: str
    reason: str | None = None

    def to_json(self) -> dict[str, JSONValue]:
        """Return a dict for ``json.dumps``: every attribute, ``reason`` only when set."""
        out: dict[str, JSONValue] = {
            "kind": self.kind,
            "family": self.family,
            "direction": self.direction,
            "name": self.name,
            "fields": self.fields,
            "hex": self.hex,
        }
        if self.reason is not None:
            out["reason"] = self.reason
        return out

    def to_line(self) -> str:
        """Return one human-readable line, e.g.
        ``la request MoveTo id=1 position=1300 reply=True  [55 AA 04 01 21 37 14 05 76]``.
        """
        if self.kind == KIND_GARBAGE:
            count = len(self.hex.split())
            head = f"garbage ({self.reason}) {count} byte{'s' if count != 1 else ''}"
        else:
            where = self.direction if self.kind == KIND_FRAME else KIND_EVENT
            parts = [str(self.family), str(where), self.name]
            # None means "not in this kind of reply": noise on a line, kept in JSON.
            parts += [
                f"{key}={_render(value)}" for key, value in self.fields.items() if value is not None
            ]
            if self.reason is not None:
                parts.append(f"({self.reason})")
            head = " ".join(parts)
        return f"{head}  [{self.hex}]"


def describe(
    item: Frame | ProjectFinishedMarker | Discarded, *, family_hint: Family | None = None
) -> Description:
    """Describe one item returned by ``Reassembler.feed`` or ``end_of_stream``.

    Args:
        item: a frame, the ``EE DD`` event, or a run of discarded bytes.
        family_hint: the stepper family the caller knows it is talking to; it overrides
            the reassembler's guess for ``FF AA`` frames (A0-05).  Ignored for LA frames,
            whose header says what they are.

    Returns:
        The description; a frame no decoder accepts gets the name ``"Unknown"``.
        Never raises for any frame bytes.
    """
    if isinstance(item, Discarded):
        return Description(
            KIND_GARBAGE, None, None, NAME_GARBAGE, {}, format_hex(item.raw), item.reason
        )
    if isinstance(item, ProjectFinishedMarker):
        return Description(
            KIND_EVENT,
            Family.PROJECT_STEPPER.value,
            Direction.REPLY.value,
            "ProjectFinished",
            {},
            format_hex(item.raw),
        )
    raw = bytes(item.raw)
    families = _candidate_families(item, family_hint)
    errors: list[str] = []
    for family in families:
        try:
            value = _decode(family, item.direction, raw)
        except (MotorbusError, ValueError) as err:
            # Decoders report odd bytes with RemoteProtocolError (or LocalProtocolError,
            # a ValueError, from a value's own validation): keep the first complaint.
            errors.append(str(err))
            continue
        return Description(
            KIND_FRAME,
            family.value,
            item.direction.value,
            _name_of(value),
            _fields_of(family, value),
            format_hex(raw),
        )
    family = families[0]
    return Description(
        KIND_FRAME,
        family.value,
        item.direction.value,
        NAME_UNKNOWN,
        _raw_fields(family, item.direction, raw),
        format_hex(raw),
        errors[0],
    )


# -- choosing and running a decoder --------------------------------------------------------


def _candidate_families(frame: Frame, hint: Family | None) -> tuple[Family, ...]:
    """Families to try, best first: the hint, else the reassembler's guess then the other."""
    if frame.family not in _STEPPERS:
        return (frame.family,)
    if hint is not None and hint in _STEPPERS:
        return (hint,)
    project = Family.PROJECT_STEPPER
    other = Family.QUAD_STEPPER if frame.family is project else project
    # Requests carry a checksum and a length that names their family; only replies are
    # worth a second opinion.
    return (frame.family, other) if frame.direction is Direction.REPLY else (frame.family,)


def _decode(family: Family, direction: Direction, raw: bytes) -> object:
    """Run the decoder of ``family`` for ``direction``; raises what the decoder raises."""
    request = direction is Direction.REQUEST
    if family is Family.LA:
        return la.decode_request(raw) if request else la.decode_reply(raw)
    if family is Family.PROJECT_STEPPER:
        from motorbus.protocol import project_stepper  # lazily: see the docstring

        if request:
            return project_stepper.decode_request(raw)
        return project_stepper.decode_reply_context_free(raw)
    from motorbus.protocol import quad_stepper  # lazily: see the docstring

    if request:
        return quad_stepper.decode_request(raw)
    return quad_stepper.decode_reply_context_free(raw)


def _name_of(value: object) -> str:
    return _RENAMED.get(type(value), type(value).__name__)


# -- turning decoded values into JSON-ready fields -------------------------------------------


def _fields_of(family: Family, value: object) -> dict[str, JSONValue]:
    """The shown fields of a value ``_decode`` gave for ``family``, plus a few derived
    ones worth seeing."""
    if isinstance(value, la.Broadcast):
        # (id, position) pairs read better as objects than as nested lists.
        return {
            "mode": value.mode.name,
            "entries": [{"id": i, "position": p} for i, p in value.entries],
        }
    fields = _dataclass_dict(value)
    if isinstance(value, la.Status):
        fields["fault"] = value.fault
    elif isinstance(value, la.ReadReply):
        register = la.Register.at(value.index, len(value.data))
        if register is not None:
            # A read covering exactly one documented register is worth naming and decoding.
            fields["register"] = register.name
            fields["value"] = register.decode_value(value.data)
    elif family is Family.QUAD_STEPPER:
        from motorbus.protocol.quad_stepper import QuadReply

        if isinstance(value, QuadReply):
            fields["motor"] = value.motor
    elif family is Family.PROJECT_STEPPER:
        from motorbus.protocol.project_stepper import RepeatCount

        if isinstance(value, RepeatCount):
            fields["forever"] = value.forever
    return fields


def _dataclass_dict(value: object) -> dict[str, JSONValue]:
    """The fields of a dataclass (or NamedTuple) value, minus raw bytes and hidden fields."""
    if isinstance(value, tuple) and hasattr(value, "_asdict"):
        return {k: _jsonable(v) for k, v in value._asdict().items() if k not in _SKIPPED_FIELDS}
    if not dataclasses.is_dataclass(value) or isinstance(value, type):
        return {}
    return {
        f.name: _jsonable(getattr(value, f.name))
        for f in dataclasses.fields(value)
        # repr=False marks bulk bytes the dataclass's author chose not to show (the dump's
        # reserved and unused step bytes); the frame's hex still holds them.
        if f.repr and f.name not in _SKIPPED_FIELDS
    }


def _jsonable(value: object) -> JSONValue:
    """Convert one decoded value: flags to name lists, enums to names, bytes to hex."""
    if isinstance(value, enum.Flag):
        return _flag_names(value)
    if isinstance(value, enum.Enum):
        return value.name
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, bytes | bytearray | memoryview):
        return format_hex(value)
    if isinstance(value, tuple) and hasattr(value, "_asdict"):
        return _dataclass_dict(value)
    if isinstance(value, tuple | list):
        return [_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return _dataclass_dict(value)
    return repr(value)


def _flag_names(value: enum.Flag) -> list[JSONValue]:
    """Names of the set bits; bits the enum does not define become ``BITn`` (A2-19)."""
    bits = int(value.value)
    names: list[JSONValue] = []
    known = 0
    for member in type(value):
        mask = int(member.value)
        if mask and bits & mask == mask and member.name is not None:
            names.append(member.name)
            known |= mask
    rest = bits & ~known
    names += [f"BIT{n}" for n in range(rest.bit_length()) if rest >> n & 1]
    return names


# -- what the bytes alone can tell -------------------------------------------------------------


def _raw_fields(family: Family, direction: Direction, raw: bytes) -> dict[str, JSONValue]:
    """Fields of a frame no decoder accepts, read straight from the frame layout."""
    if family is Family.LA:
        # 55 AA / AA 55, Len, ID, CMD, IDX, data..., CS (doc 002 section 3.3).
        out: dict[str, JSONValue] = {}
        for key, at in (("length", 2), ("id", 3), ("cmd", 4), ("index", 5)):
            if at < len(raw) - 1:
                out[key] = raw[at]
        out["data"] = format_hex(raw[6:-1])
        return out
    if raw[:2] != FF_AA:
        return {"data": format_hex(raw)}
    body = raw[2:-1] if direction is Direction.REQUEST else raw[2:]
    out = {"address": body[0]} if body else {}
    if len(body) > 1:
        out["command"] = body[1]
    out["data"] = format_hex(body[2:])
    return out


def _render(value: Any) -> str:
    """A field value in a line: ints and names bare, everything else compact JSON."""
    if isinstance(value, bool | int):
        return str(value)
    if isinstance(value, str) and value and " " not in value:
        return value
    return json.dumps(value, separators=(",", ":"), ensure_ascii=False)
