"""``free_loopback_endpoint``: where the dashboard's own server (and the tests' servers)
listen, picked so that no client's connection takes the port before the server binds it."""

from __future__ import annotations

import socket
from pathlib import Path

from motorbus.dashboard.served import free_loopback_endpoint


def test_a_free_loopback_port_below_the_ephemeral_range() -> None:
    ranges = Path("/proc/sys/net/ipv4/ip_local_port_range")
    low = int(ranges.read_text().split()[0]) if ranges.exists() else None
    ports = set()
    for _ in range(20):
        endpoint = free_loopback_endpoint()
        assert endpoint.startswith("tcp/127.0.0.1:")
        port = int(endpoint.rsplit(":", 1)[1])
        if low is not None and low > 10100:
            assert 10000 <= port < low  # no outgoing connection is given it
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))  # free
        ports.add(port)
    assert len(ports) > 1  # picked, not fixed


def test_which_endpoints_ask_for_any_port() -> None:
    from motorbus.serve.zconf import any_port

    assert any_port("tcp/127.0.0.1:0")
    assert any_port("tcp/[::1]:0")
    assert any_port("tls/localhost:0#iface=lo")
    assert not any_port("tcp/127.0.0.1:7447")
    assert not any_port("udp/10.0.0.1:10")
    assert not any_port("tcp/[::0]:7447")
