"""Zenoh's user/password authentication in front of a served bus: the right credential
is let in, a wrong one is refused before anything reaches the bus."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

import motorbus
from motorbus import BusClosedError, InspireLA
from motorbus.sim import SimProcess
from tests.serve.conftest import serve


def config(path: Path, usrpwd: dict[str, str]) -> str:
    path.write_text(
        json.dumps(
            {
                "scouting": {"multicast": {"enabled": False}},
                "transport": {"auth": {"usrpwd": usrpwd}},
            }
        ),
        encoding="utf-8",
    )
    return str(path)


async def test_a_wrong_password_is_refused_and_sends_nothing(
    la_sim: SimProcess, endpoint: str, tmp_path: Path
) -> None:
    (tmp_path / "credentials.txt").write_text("operator:right-one\n", encoding="utf-8")
    server_file = config(
        tmp_path / "server.json5",
        {"user": "server", "password": "s", "dictionary_file": str(tmp_path / "credentials.txt")},
    )
    server = serve(la_sim.path, 921600, "la:1-2", endpoint, "--zenoh-config", server_file)
    try:
        wrong = config(tmp_path / "wrong.json5", {"user": "operator", "password": "guess"})
        before = len(la_sim.log_records())
        with pytest.raises(BusClosedError, match="cannot reach"):
            async with motorbus.connect(endpoint, config_file=wrong) as site:
                await InspireLA(site.bus(), 1).move_to(1000)
        assert len(la_sim.log_records()) == before
        right = config(tmp_path / "right.json5", {"user": "operator", "password": "right-one"})
        async with motorbus.connect(endpoint, config_file=right) as site:
            assert (await InspireLA(site.bus(), 1).status()).id == 1
    finally:
        server.finish()


async def test_a_watch_only_server_answers_queries_and_refuses_motion_and_leases(
    la_sim: SimProcess, endpoint: str
) -> None:
    from motorbus.protocol import la
    from motorbus.serve import ServeRefused

    server = serve(la_sim.path, 921600, "la:1-2", endpoint, "--watch-only")
    try:
        async with motorbus.connect(endpoint) as site:
            bus = site.bus()
            assert (await InspireLA(bus, 1).status()).id == 1
            with pytest.raises(ServeRefused, match="only watch"):
                await InspireLA(bus, 1).move_to(1000)
            with pytest.raises(ServeRefused, match="only watch"):
                bus.lease("la:2", owner="arm")
            assert bus.leases == ()
        sent = [bytes.fromhex(r["hex"]) for r in la_sim.log_records()]
        assert la.MoveTo(1, 1000, True).encode() not in sent
    finally:
        server.finish()
