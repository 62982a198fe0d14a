"""Process groups of a bus file: which program serves which buses, on which CPUs.

One Python process saturates one core (docs/design.md says at how many buses); past
that, a bus file splits its buses into groups, ``process = "arms"`` in each
``[[bus]]`` table, and one program per group opens only its group's buses
(``BusManager.from_toml(path, process="arms")``, ``motorbus dashboard --process
arms``).  A group's ``[process.NAME]`` table says which CPUs its program runs on.

This module holds the group part of the bus-file schema (:mod:`motorbus.busfile` is
the rest, and documents every key): the checks of a group's name and table, and the
:class:`ProcessGroup` value the loaded file gives.  Errors are ``LocalProtocolError``
naming the key, the value and what is allowed; the bus-file reader puts the file and
the table in front.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass

from motorbus.errors import LocalProtocolError
from motorbus.runtime import realtime

__all__ = [
    "GROUP_KEYS",
    "GROUP_NAME_MAX",
    "ProcessGroup",
    "check_group_cpus",
    "check_group_name",
    "check_group_table",
    "choose_group",
]

#: Every key a ``[process.NAME]`` table may set.
GROUP_KEYS = frozenset({"cpus"})
#: Longest group name, characters (a name is a label in logs and on command lines).
GROUP_NAME_MAX = 32
_GROUP_NAME = re.compile(rf"[A-Za-z0-9_-]{{1,{GROUP_NAME_MAX}}}")


def check_group_name(field: str, value: object) -> str:
    """A process group's name: 1..32 ASCII letters, digits, ``-`` or ``_``.

    Raises:
        LocalProtocolError: anything else, naming ``field`` and the value.
    """
    if not isinstance(value, str) or not _GROUP_NAME.fullmatch(value):
        raise LocalProtocolError(
            f"{field}={value!r} is not allowed: a process group name must be "
            f"1..{GROUP_NAME_MAX} ASCII letters, digits, '-' or '_'",
            field=field,
            value=value,
        )
    return value


def check_group_cpus(value: object) -> frozenset[int]:
    """A group's ``cpus``: a list of distinct CPU numbers this machine has.

    Raises:
        LocalProtocolError: not a list, empty, a CPU twice, or a CPU out of range
            (``0..os.cpu_count()-1``, :func:`motorbus.runtime.realtime.check_cpus`).
    """
    if not isinstance(value, list | tuple):
        raise LocalProtocolError(
            f"cpus must be a list of CPU numbers such as [2, 3], got {value!r} "
            f"({type(value).__name__})",
            field="cpus",
            value=value,
        )
    numbers = [c for c in value if type(c) is int]  # others fail the range check below
    twice = sorted({c for c in numbers if numbers.count(c) > 1})
    if twice:
        raise LocalProtocolError(
            f"cpus={list(value)!r} lists CPU {twice[0]} twice: each CPU must be listed once",
            field="cpus",
            value=list(value),
        )
    return realtime.check_cpus(value)


def check_group_table(
    name: object, table: object, named: Mapping[str, object]
) -> frozenset[int] | None:
    """Check the ``[process.NAME]`` table of group ``name``; return its CPUs (``None``
    if it sets none).  ``named`` holds the groups the buses name.

    Raises:
        LocalProtocolError: a bad name, a table that is not a table, an unknown key, a
            group no bus names (a typo: ``[process.arm]`` for ``process = "arms"``), or
            bad ``cpus``.
    """
    check_group_name("process", name)
    if not isinstance(table, Mapping):
        raise LocalProtocolError(
            f"must be a table of keys (cpus = [...]), got {table!r}", field="process", value=table
        )
    unknown = sorted(set(table) - GROUP_KEYS)
    if unknown:
        raise LocalProtocolError(
            f"unknown keys {unknown}; allowed: {sorted(GROUP_KEYS)}", field="process"
        )
    if name not in named:
        groups = ", ".join(named) or "none"
        raise LocalProtocolError(
            f"no [[bus]] has process = {name!r}: a group must serve a bus "
            f"(the groups the buses name: {groups})",
            field="process",
            value=name,
        )
    return check_group_cpus(table["cpus"]) if "cpus" in table else None


@dataclass(frozen=True, slots=True)
class ProcessGroup:
    """A process group of a bus file (checked on construction).

    Attributes:
        name: the group's name, as the buses' ``process`` keys give it.
        buses: the names of its buses, in file order.
        cpus: the CPUs its program runs on; ``None``: wherever the system puts it.
    """

    name: str
    buses: tuple[str, ...]
    cpus: frozenset[int] | None = None

    def __post_init__(self) -> None:
        check_group_name("process", self.name)
        if self.cpus is not None:
            object.__setattr__(self, "cpus", realtime.check_cpus(self.cpus))


def choose_group(groups: Mapping[str, ProcessGroup], process: object) -> ProcessGroup:
    """The group called ``process``; the error names the groups there are.

    Raises:
        LocalProtocolError: not a group name, or no group of that name.
    """
    name = check_group_name("process", process)
    if name not in groups:
        there = (
            f"choose one of {', '.join(groups)}"
            if groups
            else "the file has none (no [[bus]] sets process)"
        )
        raise LocalProtocolError(
            f"process={name!r} is not a process group of this file: {there}",
            field="process",
            value=name,
        )
    return groups[name]
