"""The one grammar of device-ID lists: ``"3"``, ``"1-15"``, ``"1,4,7"``, ``"1-3,7"``.

Shared by the bus files (``BusManager``: ``devices = ["la:1-15"]``), the simulator's
device specs (``motorbus sim la:1-15``) and the command line (``--ids 1-3,7``), so all
three accept and refuse the same lists:

* an item is an ID or a range ``FIRST-LAST``; an ID is decimal (``16``) or hex
  (``0x10``); spaces around the numbers and the dash are allowed;
* every ID is checked against the family's range (LA 1..254, see
  ``protocol.families``);
* a reversed range (``5-3``) is refused, never read as empty or as ``3-5``;
* an ID listed twice (``1-3,2``) is refused: two devices with one ID answer together
  (A2-12).

Errors are ``IdListError`` (a ``LocalProtocolError``) whose ``reason`` says what is
wrong with the list; each front end puts it after its own context (the option, the bus
file item or the spec).  Sans-I/O: no asyncio, no clock.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Iterable

from motorbus.errors import IdListError, LocalProtocolError
from motorbus.protocol.base import check_int
from motorbus.protocol.families import LA_ID_MAX, LA_ID_MIN

__all__ = ["IdListError", "parse_id_items", "parse_id_list"]

_NUMBER = r"(0[xX][0-9a-fA-F]+|\d+)"
_ITEM = re.compile(rf"\s*{_NUMBER}\s*(?:-\s*{_NUMBER})?\s*")


def _number(text: str) -> int:
    return int(text, 16) if text[1:2] in ("x", "X") else int(text)


def parse_id_items(
    items: Iterable[str], *, lo: int = LA_ID_MIN, hi: int = LA_ID_MAX, id_field: str = "id"
) -> list[int]:
    """The IDs that ``items`` (each an ID or a range) list, in the order written.

    Args:
        items: e.g. ``["1-3", "7"]``.
        lo: the lowest allowed ID (default: the LA's 1).
        hi: the highest allowed ID (default: the LA's 254).
        id_field: the name an out-of-range ID is given in the message
            (``"id=300 is out of range: allowed 1..254"``).

    Raises:
        IdListError: see the module docstring; an out-of-range ID is reported with
            ``check_int``'s message (field, value, allowed range).
    """
    ids: list[int] = []
    for item in items:
        m = _ITEM.fullmatch(item)
        if m is None:
            raise IdListError(
                f"{item.strip()!r} is not an ID or a range like 1-15",
                problem="syntax",
                item=item.strip(),
                field=id_field,
                value=item,
            )
        try:
            first = check_int(id_field, _number(m.group(1)), lo, hi)
            last = check_int(id_field, _number(m.group(2)) if m.group(2) else first, lo, hi)
        except LocalProtocolError as err:
            raise IdListError(
                str(err), problem="range", item=item.strip(), field=id_field, value=err.value
            ) from None
        if last < first:
            raise IdListError(
                f"reversed range {first}-{last}: write {last}-{first}",
                problem="reversed",
                item=item.strip(),
                first=first,
                last=last,
                field=id_field,
                value=item,
            )
        ids.extend(range(first, last + 1))
    twice = sorted(i for i, n in Counter(ids).items() if n > 1)
    if twice:  # the lowest, whatever the order written
        raise IdListError(
            f"lists ID {twice[0]} twice",
            problem="duplicate",
            item=str(twice[0]),
            field=id_field,
            value=twice[0],
        )
    return ids


def parse_id_list(
    text: str, *, lo: int = LA_ID_MIN, hi: int = LA_ID_MAX, id_field: str = "id"
) -> list[int]:
    """``parse_id_items`` of the comma-separated ``text``: ``"1-3,7"`` -> ``[1, 2, 3, 7]``.

    An empty item (``"1,,2"``, ``""``) is a syntax error.
    """
    return parse_id_items(text.split(","), lo=lo, hi=hi, id_field=id_field)
