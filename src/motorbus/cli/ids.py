"""Actuator ID arguments: ``3``, ``1,2,3``, ``1-3,7``, checked against the family's range."""

from __future__ import annotations

import argparse
from collections.abc import Iterable

from motorbus.errors import LocalProtocolError
from motorbus.protocol import la
from motorbus.protocol.base import check_int
from motorbus.protocol.ids import IdListError, parse_id_list

__all__ = ["add_ids_argument", "check_ids", "parse_id_args", "parse_ids"]


def parse_ids(
    text: str, field: str = "--ids", lo: int = la.ID_MIN, hi: int = la.ID_MAX
) -> list[int]:
    """Parse an ID list such as ``"1-3,7"`` into ``[1, 2, 3, 7]`` (order kept, no repeats).

    Args:
        text: comma-separated IDs and ranges ``A-B`` (``A <= B``).
        field: the option or argument named in errors.
        lo, hi: the allowed IDs (LA actuators: 1..254).

    Raises:
        LocalProtocolError: a bad token, a reversed range, an ID outside ``lo..hi``,
            an ID listed twice.
    """
    id_field = field if field == "id" else f"{field} id"
    try:
        return parse_id_list(text, lo=lo, hi=hi, id_field=id_field)
    except IdListError as err:
        if err.problem == "range":
            raise  # "--ids id=255 is out of range: allowed 1..254"
        sep = " " if err.problem == "duplicate" else ": "
        raise LocalProtocolError(
            f"{field}={text!r}{sep}{err.reason}", field=field, value=text
        ) from None


def parse_id_args(values: Iterable[str], field: str = "id") -> list[int]:
    """Join ID arguments such as ``["1-3", "7,9", "12"]`` into one list (see :func:`parse_ids`).

    Raises:
        LocalProtocolError: a bad token or range, an ID out of range or listed twice.
    """
    ids: list[int] = []
    for value in values:
        ids.extend(parse_ids(value, field))
    return parse_ids(",".join(map(str, ids)), field) if ids else ids


def add_ids_argument(parser: argparse.ArgumentParser) -> None:
    """Add the positional ``ID...`` of a multi-actuator command (``1 2 3``, ``1-3,7``)."""
    parser.add_argument(
        "ids",
        metavar="ID",
        nargs="+",
        help="actuator IDs 1..254: one or more of 3, 1,2,3 or 1-3,7",
    )


def check_ids(values: Iterable[int], field: str = "id") -> list[int]:
    """Return LA IDs given as integers after checking each is 1..254.

    Raises:
        LocalProtocolError: naming the field, the value and the range.
    """
    return [check_int(field, v, la.ID_MIN, la.ID_MAX) for v in values]
