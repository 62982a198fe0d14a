"""The reply frame of a served request: the command the server submits keeps the raw
bytes it decoded, so the server can send them on as they came off the wire.

The bus hands a request's caller the *decoded* reply.  A served bus must forward the
frame itself (the client decodes it with the same ``Command``), so the server submits a
*tapped* copy of the client's command: an instance of a subclass that remembers the
last frame its ``decode_reply`` or ``decode_matched`` (the bus's path) saw.  It is
otherwise the same command: the same fields, ``isinstance`` of the same classes, equal
(both ways) to the plain command, so leases, safety (``safety.covers``), fault events
and done watches treat it as such.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from motorbus.protocol.base import Command

__all__ = ["raw_reply", "reply_mark", "tapped"]

_CLASSES: dict[type, type] = {}


def _tapped_class(base: Any) -> type:
    cls = _CLASSES.get(base)
    if cls is not None:
        return cls

    def decode_reply(self: Any, raw: bytes) -> Any:
        _seen(self, raw)
        return base.decode_reply(self, raw)

    def decode_matched(self: Any, raw: bytes) -> Any:
        _seen(self, raw)
        return base.decode_matched(self, raw)

    def __eq__(self: Any, other: object) -> bool:
        other_base: Any = getattr(type(other), "_served_base", type(other))
        if other_base is not base:
            return NotImplemented
        return all(
            getattr(self, f.name) == getattr(other, f.name) for f in dataclasses.fields(base)
        )

    def __hash__(self: Any) -> int:
        return hash(tuple(getattr(self, f.name) for f in dataclasses.fields(base)))

    cls = type(
        base.__name__,
        (base,),
        {
            "decode_reply": decode_reply,
            "decode_matched": decode_matched,
            "__eq__": __eq__,
            "__hash__": __hash__,
            "_served_base": base,
            "__module__": base.__module__,
            "__qualname__": base.__qualname__,
        },
    )
    _CLASSES[base] = cls
    return cls


def _seen(cmd: Any, raw: bytes) -> None:
    """A tapped command's reply is being decoded: keep it, and the marker's value now."""
    object.__setattr__(cmd, "_served_raw", bytes(raw))
    marker = getattr(cmd, "_served_marker", None)
    if marker is not None:
        object.__setattr__(cmd, "_served_mark", marker())


def tapped(cmd: Command[Any], marker: Callable[[], int] | None = None) -> Command[Any]:
    """A copy of ``cmd`` that keeps the raw reply (``raw_reply``) and, with ``marker``,
    its value when that reply was decoded (``reply_mark``): the bus decodes a reply as
    it takes it off the wire, in order with the frames and events around it, where the
    request's awaiter runs only later."""
    base: Any = type(cmd)
    values = {f.name: getattr(cmd, f.name) for f in dataclasses.fields(base) if f.init}
    out: Command[Any] = _tapped_class(base)(**values)
    if marker is not None:
        object.__setattr__(out, "_served_marker", marker)
    return out


def raw_reply(cmd: Command[Any]) -> bytes | None:
    """The frame the last decode of a tapped command saw (None: no reply)."""
    value: bytes | None = getattr(cmd, "_served_raw", None)
    return value


def reply_mark(cmd: Command[Any]) -> int | None:
    """The ``marker``'s value at the last decode of a tapped command (None: none)."""
    value: int | None = getattr(cmd, "_served_mark", None)
    return value
