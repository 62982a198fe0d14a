"""One place for each fact about a device family: names, default baud, turnaround, IDs.

Sans-I/O and dependency-free (it imports only ``protocol.base``), so the bus, the
devices, the simulator and the CLI all read the same numbers::

    >>> from motorbus.protocol.families import FAMILIES, Family, by_spec_name
    >>> FAMILIES[Family.LA].default_baud
    921600
    >>> by_spec_name("quad-stepper").family
    <Family.QUAD_STEPPER: 'quad_stepper'>
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from types import MappingProxyType

from motorbus.errors import LocalProtocolError
from motorbus.protocol.base import Family

__all__ = [
    "DEFAULT_BAUD",
    "DEFAULT_TURNAROUND",
    "FAMILIES",
    "LA_BROADCAST_ID",
    "LA_DEFAULT_BAUD",
    "LA_ID_MAX",
    "LA_ID_MIN",
    "SPEC_NAMES",
    "STEPPER_DEFAULT_BAUD",
    "Family",
    "FamilyInfo",
    "by_spec_name",
    "default_bus_baud",
]

#: Factory rate of the LVTTL ("D" interface) LA actuator (LA manual 3.1, control table
#: 12; doc 002 C.1, A2-13).
LA_DEFAULT_BAUD = 921600
#: Doc 000 A.1 states 9600 8N1 for the project stepper; doc 001 (quad stepper) states
#: none and we follow its vendor's sibling (A1-01).
STEPPER_DEFAULT_BAUD = 9600
#: Valid LA actuator IDs; 255 is broadcast and never answers (doc 002 C.2).
LA_ID_MIN = 1
LA_ID_MAX = 254
LA_BROADCAST_ID = 255


@dataclass(frozen=True)
class FamilyInfo:
    """What motorbus knows about one family.

    Attributes:
        family: the ``Family`` member.
        spec_name: its name in device specs (``motorbus sim``, bus files): ``"la"``,
            ``"project-stepper"``, ``"quad-stepper"``.
        key: its name in stats, frame logs and JSON output (``Family.value``).
        default_baud: the rate the device ships with, bit/s.
        turnaround_s: worst-case turnaround (request end to reply start) the bus
            allows by default.  LA: "120 us typical, up to 800 us" (manual 3.4.2).
            The stepper manuals give none; A0-14 recommends a timeout of at least
            50 ms for a 6-byte reply at 9600 baud, which 11.5 ms (request) + 6.25 ms
            (reply) + 30 ms turnaround + the host margin meets.
        id_range: the addressable device IDs (inclusive), ``None`` if a family has
            no device IDs on the bus (one controller per bus).
        broadcast_id: the ID every device obeys and none answers, if any.
    """

    family: Family
    spec_name: str
    default_baud: int
    turnaround_s: float
    id_range: tuple[int, int] | None = None
    broadcast_id: int | None = None

    @property
    def key(self) -> str:
        return self.family.value


#: The registry, in the order help texts list the families.
FAMILIES: Mapping[Family, FamilyInfo] = MappingProxyType(
    {
        Family.LA: FamilyInfo(
            Family.LA, "la", LA_DEFAULT_BAUD, 800e-6, (LA_ID_MIN, LA_ID_MAX), LA_BROADCAST_ID
        ),
        Family.PROJECT_STEPPER: FamilyInfo(
            Family.PROJECT_STEPPER, "project-stepper", STEPPER_DEFAULT_BAUD, 30e-3
        ),
        Family.QUAD_STEPPER: FamilyInfo(
            Family.QUAD_STEPPER, "quad-stepper", STEPPER_DEFAULT_BAUD, 30e-3
        ),
    }
)

#: Spec names in registry order: ``("la", "project-stepper", "quad-stepper")``.
SPEC_NAMES: tuple[str, ...] = tuple(info.spec_name for info in FAMILIES.values())
#: Default rate per family, bit/s.
DEFAULT_BAUD: Mapping[Family, int] = MappingProxyType(
    {f: info.default_baud for f, info in FAMILIES.items()}
)
#: Worst-case device turnaround per family, seconds (see ``FamilyInfo.turnaround_s``).
DEFAULT_TURNAROUND: Mapping[Family, float] = MappingProxyType(
    {f: info.turnaround_s for f, info in FAMILIES.items()}
)

_BY_SPEC_NAME = {info.spec_name: info for info in FAMILIES.values()}


def by_spec_name(name: str) -> FamilyInfo:
    """The family whose spec name is ``name``; ``LocalProtocolError`` naming the choices."""
    info = _BY_SPEC_NAME.get(name)
    if info is None:
        raise LocalProtocolError(
            f"family {name!r} is unknown: allowed {', '.join(SPEC_NAMES)}",
            field="family",
            value=name,
        )
    return info


def default_bus_baud(families: Iterable[Family]) -> int:
    """The rate of a bus carrying ``families``: the LA rate if they are all LA, else the
    steppers' rate (an LA can be set to 9600, a stepper cannot go faster)."""
    return LA_DEFAULT_BAUD if set(families) == {Family.LA} else STEPPER_DEFAULT_BAUD
