"""Zenoh: importing it (an optional extra), and the session configurations of a server
and of a client."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any

from motorbus.errors import LocalProtocolError, ServeUnavailable

__all__ = [
    "DEFAULT_LISTEN",
    "EXTRA_HINT",
    "ServeUnavailable",
    "any_port",
    "bound_endpoint",
    "check_endpoint",
    "client_config",
    "on_zenoh_thread",
    "server_config",
    "zenoh",
    "zenoh_error_text",
]

#: Where ``motorbus serve`` listens unless told: loopback only.
DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
EXTRA_HINT = "pip install 'motorbus[serve]'"
_PROTOCOLS = ("tcp", "tls", "udp", "quic", "unixsock-stream", "ws")


def zenoh() -> Any:
    """The ``zenoh`` module; ``ServeUnavailable`` naming the extra if it is missing."""
    try:
        import zenoh as module
    except ImportError:
        raise ServeUnavailable(
            f"serving a bus needs Eclipse Zenoh, the serve extra: {EXTRA_HINT}"
        ) from None
    return module


def on_zenoh_thread(callback: Any, drop: Any = None) -> Any:
    """``callback`` as a Zenoh handler run on the Zenoh thread that received the data.

    Zenoh's default for a Python callable runs it on a Python thread of its own, started
    when the handler is declared: for a query that is one thread started per query, and
    the caller (the event loop) waits for it to start (``threading.Thread.start``): a
    served dashboard spent a fifth of its CPU on it.  Every callback motorbus gives
    Zenoh is short and never blocks: it decodes a payload or hands the sample to an
    event loop (``call_soon_threadsafe``), so it runs where the data arrives.  Zenoh's
    calls release the GIL while they wait, so this cannot deadlock with the loop."""
    return zenoh().handlers.Callback(callback, drop, indirect=False)


def check_endpoint(field: str, value: object) -> str:
    """A Zenoh endpoint such as ``tcp/127.0.0.1:7447``."""
    if not isinstance(value, str) or "/" not in value or value.split("/", 1)[0] not in _PROTOCOLS:
        raise LocalProtocolError(
            f"{field}={value!r} is not a Zenoh endpoint: PROTOCOL/ADDRESS with PROTOCOL one "
            f"of {', '.join(_PROTOCOLS)}, e.g. {DEFAULT_LISTEN}",
            field=field,
            value=value,
        )
    return value


#: Longest client name (it goes into the client's ID, the server's lease owners, logs).
CLIENT_NAME_MAX = 64


def check_client_name(name: object) -> str:
    """A client's label (``connect(name=...)``): text of at most ``CLIENT_NAME_MAX``."""
    if not isinstance(name, str) or len(name) > CLIENT_NAME_MAX:
        raise LocalProtocolError(
            f"name={name!r}: a label of at most {CLIENT_NAME_MAX} characters (default: none)",
            field="name",
            value=name,
        )
    return name


def check_config_file(config_file: object) -> str | None:
    """The path of an existing Zenoh configuration file, or None."""
    if config_file is None:
        return None
    if not isinstance(config_file, str | os.PathLike) or not Path(config_file).is_file():
        raise LocalProtocolError(
            f"config_file={config_file!r}: the path of an existing Zenoh configuration "
            "file, or None",
            field="config_file",
            value=config_file,
        )
    return os.fspath(config_file)


def _base(config_file: str | None) -> Any:
    z = zenoh()
    try:
        config = z.Config.from_file(config_file) if config_file else z.Config()
    except Exception as err:  # zenoh.ZError: no such file, not JSON5, an unknown key
        raise LocalProtocolError(
            f"config_file={config_file!r}: {zenoh_error_text(err)}",
            field="config_file",
            value=config_file,
        ) from None
    if not config_file:
        # Hermetic unless a configuration file asks for discovery: no multicast.
        config.insert_json5("scouting/multicast/enabled", "false")
    return config


def zenoh_error_text(err: BaseException) -> str:
    """Zenoh's message on one line, without the Rust source location it ends with
    (``... at /root/.cargo/.../lib.rs:1507.``); a JSON5 parse error's drawing of the
    line becomes ``line L, column C: what was expected``."""
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?$", "", str(err).strip())
    where = re.search(r"-->\s*(\d+):(\d+)", text)
    said = re.search(r"^\s*=\s*(.+)$", text, re.MULTILINE)
    if where and said:
        return f"line {where[1]}, column {where[2]}: {said[1].strip()}"
    return " ".join(text.split())


def any_port(endpoint: str) -> bool:
    """Whether ``endpoint`` asks for any free port (``tcp/127.0.0.1:0``): the server
    then learns the port it was given from Zenoh's admin space (``server_config``)."""
    address = endpoint.split("/", 1)[1].split("#", 1)[0].split("?", 1)[0]
    return ":" in address and address.rsplit(":", 1)[1] == "0"


def bound_endpoint(session: Any, listen: str) -> str:
    """``listen`` with port 0 replaced by the port the session was given (blocking: a
    query of the session's own admin space, which ``server_config`` turned on)."""
    protocol, address = listen.split("/", 1)
    cut = min((i for i in (address.find("#"), address.find("?")) if i >= 0), default=len(address))
    host, rest = address[:cut].rsplit(":", 1)[0], address[cut:]  # rest: "#..." or "?..."
    for reply in session.get(f"@/{session.info.zid()}/*", timeout=5.0):
        if reply.ok is None:
            continue
        try:
            locators = json.loads(reply.ok.payload.to_bytes()).get("locators", [])
        except (ValueError, AttributeError):
            continue
        for locator in locators:
            if locator.startswith(f"{protocol}/"):
                port = locator.split("#", 1)[0].split("?", 1)[0].rsplit(":", 1)[1]
                return f"{protocol}/{host}:{port}{rest}"
    raise LocalProtocolError(
        f"listen={listen!r}: Zenoh did not say which port it was given", field="listen"
    )


def server_config(listen: str, config_file: str | None = None) -> Any:
    """A peer that listens on ``listen`` (a configuration file may add TLS, access
    control, more endpoints).

    With port 0 it turns Zenoh's admin space on, read only, so that the server can ask
    its own session which port it was given (``BusServer.endpoint``)."""
    config = _base(config_file)
    config.insert_json5("mode", json.dumps("peer"))
    config.insert_json5("listen/endpoints", json.dumps([check_endpoint("listen", listen)]))
    if any_port(listen):
        config.insert_json5("adminspace/enabled", "true")
        config.insert_json5("adminspace/permissions", '{"read": true, "write": false}')
    return config


def client_config(connect: str, config_file: str | None = None, lease_s: float = 1.0) -> Any:
    """A client session connected to ``connect``.  Its link lease (how soon the server
    notices a frozen client at the Zenoh level) is ``lease_s``; the server's own
    heartbeat check is the authority (``motorbus.serve.server``)."""
    config = _base(config_file)
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([check_endpoint("endpoint", connect)]))
    config.insert_json5("transport/link/tx/lease", str(max(100, int(lease_s * 1000))))
    return config
