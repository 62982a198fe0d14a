"""Which ``Host`` names the dashboard answers to: the defence against DNS rebinding.

A page of ``attacker.example`` whose DNS name the attacker re-points at 127.0.0.1 is
same-origin with itself, so a browser sends its requests, with ``Origin`` and ``Host``
both ``attacker.example``.  Comparing the two proves nothing; comparing ``Host`` with the
names the server itself answers to does.  Pure (no aiohttp), so the command checks its
options before anything opens.
"""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable

__all__ = ["LOOPBACK_NAMES", "HostCheck", "host_name"]

#: The names of this machine's loopback interface: what a server on 127.0.0.1 answers to.
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


def host_name(header: str) -> str:
    """The name part of a ``Host`` header, lower case: ``[::1]:8765`` -> ``::1``."""
    text = header.strip().lower()
    if text.startswith("["):
        return text[1 : text.find("]")] if "]" in text else text
    name, sep, port = text.rpartition(":")
    if sep and port.isdigit() and ":" not in name:
        text = name
    return text.rstrip(".")


class HostCheck:
    """Which ``Host`` names the server answers to.

    Args:
        names: the names and addresses allowed (compared without port, case-blind).
        any_address: also allow any IP address literal (a server listening on every
            interface, 0.0.0.0 or ::).  An address cannot be re-pointed by DNS, so it is
            no rebinding risk; names still have to be listed.
    """

    def __init__(self, names: Iterable[str], *, any_address: bool = False) -> None:
        self.names = frozenset(host_name(n) for n in names)
        self.any_address = any_address

    def allows(self, header: str | None) -> bool:
        """Whether a request whose ``Host`` header is ``header`` may be answered."""
        if not header:
            return False
        name = host_name(header)
        if name in self.names:
            return True
        if not self.any_address:
            return False
        try:
            ipaddress.ip_address(name)
        except ValueError:
            return False
        return True

    def __repr__(self) -> str:
        extra = ", any address" if self.any_address else ""
        return f"HostCheck({sorted(self.names)}{extra})"
