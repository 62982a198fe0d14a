"""Serve buses to other programs and hosts over Eclipse Zenoh (the ``serve`` extra).

``motorbus serve`` (:class:`BusServer`) owns the ports and everything that must stay
next to the wire; :func:`connect` gives another program the served buses with the API
of local ones.  The key expressions and payloads are in :mod:`motorbus.serve.keys` and
docs/serve.md.
"""

from __future__ import annotations

from motorbus.serve.client import ServedBus, ServedLease, ServedSite, ServeRefused, connect
from motorbus.serve.keys import LIVENESS_DEFAULT_S, PayloadError
from motorbus.serve.server import BusServer
from motorbus.serve.zconf import DEFAULT_LISTEN, EXTRA_HINT, ServeUnavailable, zenoh

__all__ = [
    "DEFAULT_LISTEN",
    "EXTRA_HINT",
    "LIVENESS_DEFAULT_S",
    "BusServer",
    "PayloadError",
    "ServeRefused",
    "ServeUnavailable",
    "ServedBus",
    "ServedLease",
    "ServedSite",
    "connect",
    "zenoh",
]
