"""Zenoh's user/password authentication in front of a served bus: the right credential
is let in, a wrong one is refused before anything reaches the bus."""

from __future__ import annotations

import json
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("zenoh")

import motorbus
from motorbus import BusClosedError, InspireLA
from motorbus.protocol import la
from motorbus.serve import ServedSite
from motorbus.sim import SimProcess
from tests.serve.conftest import free_endpoint, serve


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
            # Nor a setting, nor enabling the power stage; reads and stops go through.
            limit = la.WriteRegister(1, la.Register.OVER_CURRENT_LIMIT, 600)
            work = la.Control(1, la.ControlAction.WORK)
            for refused in (limit, work):
                with pytest.raises(ServeRefused, match=type(refused).__name__):
                    await bus.request(refused)
            assert await bus.request(la.ReadRegister(1, la.Register.OVER_CURRENT_LIMIT)) > 0
            await bus.request(la.Control(2, la.ControlAction.PAUSE))
            await bus.request(la.Control(2, la.ControlAction.ESTOP))
        sent = [bytes.fromhex(r["hex"]) for r in la_sim.log_records()]
        assert la.MoveTo(1, 1000, True).encode() not in sent
        assert limit.encode() not in sent and work.encode() not in sent
        assert la.Control(2, la.ControlAction.ESTOP).encode() in sent
    finally:
        server.finish()


# -- mutual TLS with examples/serve/*-auth.json5 and make-certs.sh ------------------------

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "serve"
OPERATOR = ("operator", "op-secret")
WATCHER = ("watcher", "watch-secret")


def make_certs(folder: Path) -> Path:
    """examples/serve/make-certs.sh into ``folder`` (the documented commands)."""
    if shutil.which("openssl") is None:
        pytest.skip("needs the openssl command (Debian package openssl)")
    done = subprocess.run(
        ["sh", str(EXAMPLES / "make-certs.sh"), str(folder)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    return folder


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_certs(tmp_path_factory.mktemp("pki"))


@pytest.fixture(scope="module")
def other_pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Another CA, with a client certificate of its own."""
    return make_certs(tmp_path_factory.mktemp("other-pki"))


def example(name: str, folder: Path, replace: dict[str, str], drop: str = "") -> str:
    """An example configuration with its file names made absolute (and its values
    replaced), written to ``folder``."""
    text = (EXAMPLES / name).read_text(encoding="utf-8")
    for old, new in replace.items():
        assert old in text, f"{name} has no {old}"
        text = text.replace(old, new)
    if drop:
        text = "\n".join(line for line in text.splitlines() if drop not in line)
    path = folder / f"{len(list(folder.iterdir()))}-{name}"
    path.write_text(text, encoding="utf-8")
    return str(path)


def client_file(
    folder: Path, pki: Path, user: tuple[str, str], certs: Path | None = None, drop: str = ""
) -> str:
    certs = certs or pki
    return example(
        "client-auth.json5",
        folder,
        {
            '"ca.pem"': json.dumps(str(pki / "ca.pem")),
            '"client-key.pem"': json.dumps(str(certs / "client-key.pem")),
            '"client-cert.pem"': json.dumps(str(certs / "client-cert.pem")),
            'user: "operator", password: "change-me"': (
                f"user: {json.dumps(user[0])}, password: {json.dumps(user[1])}"
            ),
        },
        drop,
    )


@pytest.fixture
def tls_server(la_sim: SimProcess, pki: Path, tmp_path: Path) -> Iterator[str]:
    credentials = tmp_path / "credentials.txt"
    credentials.write_text(f"{':'.join(OPERATOR)}\n{':'.join(WATCHER)}\n", encoding="utf-8")
    server_file = example(
        "server-auth.json5",
        tmp_path,
        {
            '"server-key.pem"': json.dumps(str(pki / "server-key.pem")),
            '"server-cert.pem"': json.dumps(str(pki / "server-cert.pem")),
            '"ca.pem"': json.dumps(str(pki / "ca.pem")),
            '"credentials.txt"': json.dumps(str(credentials)),
        },
    )
    endpoint = "tls/localhost:" + free_endpoint().rsplit(":", 1)[1]
    server = serve(la_sim.path, 921600, "la:1-2", endpoint, "--zenoh-config", server_file)
    try:
        yield endpoint
    finally:
        server.finish()


def watch_query(endpoint: str, config_file: str, payload: dict[str, str]) -> str:
    """The answer of one raw query on ``.../watch`` of bus "bus", as text."""
    import zenoh

    from motorbus.serve import keys as k
    from motorbus.serve.zconf import client_config

    with zenoh.open(client_config(endpoint, config_file)) as session:
        key = k.bus_key("bus", "watch")
        for reply in session.get(key, payload=json.dumps(payload), timeout=10):
            sample = reply.ok if reply.ok is not None else reply.err
            return sample.payload.to_bytes().decode()
    raise AssertionError("no answer on .../watch")


def frames_at(sim: SimProcess) -> list[bytes]:
    return [bytes.fromhex(r["hex"]) for r in sim.log_records() if r["direction"] == "request"]


async def test_mutual_tls_and_the_password_let_the_operator_move(
    la_sim: SimProcess, tls_server: str, pki: Path, tmp_path: Path
) -> None:
    from motorbus.protocol import la

    operator = client_file(tmp_path, pki, OPERATOR)
    async with motorbus.connect(tls_server, config_file=operator) as site:
        actuator = InspireLA(site.bus(), 1)
        assert (await actuator.status()).id == 1
        await actuator.move_to(700)
    assert la.MoveTo(1, 700, True).encode() in frames_at(la_sim)


@pytest.mark.parametrize("wrong", ["password", "other CA", "no certificate", "plain tcp"])
async def test_a_wrong_credential_is_refused_before_anything_is_sent(
    la_sim: SimProcess, tls_server: str, pki: Path, other_pki: Path, tmp_path: Path, wrong: str
) -> None:
    endpoint = tls_server
    if wrong == "password":
        config_file = client_file(tmp_path, pki, (OPERATOR[0], "guess"))
    elif wrong == "other CA":  # a certificate the server's CA did not sign
        config_file = client_file(tmp_path, pki, OPERATOR, certs=other_pki)
    elif wrong == "no certificate":  # TLS, but no client certificate for mutual TLS
        config_file = client_file(tmp_path, pki, OPERATOR, drop="connect_")
    else:  # the right credential over plain TCP to the TLS port
        config_file = client_file(tmp_path, pki, OPERATOR)
        endpoint = endpoint.replace("tls/", "tcp/")
    before = frames_at(la_sim)
    with pytest.raises(BusClosedError, match="cannot reach"):
        async with motorbus.connect(endpoint, config_file=config_file) as site:
            await InspireLA(site.bus(), 1).move_to(1000)
    assert frames_at(la_sim) == before
    # The server still serves the operator.
    async with motorbus.connect(tls_server, config_file=client_file(tmp_path, pki, OPERATOR)):
        pass


async def test_a_watcher_reads_hears_lease_changes_and_sends_no_frame(
    la_sim: SimProcess, tls_server: str, pki: Path, tmp_path: Path
) -> None:
    import zenoh

    from motorbus.serve import keys as k
    from motorbus.serve.zconf import client_config
    from tests.waiting import eventually

    operator = client_file(tmp_path, pki, OPERATOR)
    watcher = client_file(tmp_path, pki, WATCHER)
    published: list[bytes] = []
    with zenoh.open(client_config(tls_server, watcher)) as session:
        # The watcher may subscribe: it hears the lease changes as they happen.
        session.declare_subscriber(
            k.bus_key("bus", "leases"), lambda sample: published.append(sample.payload.to_bytes())
        )
        async with motorbus.connect(tls_server, config_file=operator) as op_site:
            await InspireLA(op_site.bus(), 2).move_to(400)
            await eventually(
                lambda: any(b'"la:2"' in p for p in published), "the lease change published"
            )
            await _watch(la_sim, tls_server, watcher, op_site)


async def _watch(la_sim: SimProcess, tls_server: str, watcher: str, op_site: ServedSite) -> None:
    """The watcher's reads, and its refused frames and leases (nothing sent)."""
    before = frames_at(la_sim)
    async with motorbus.connect(tls_server, config_file=watcher) as site:
        bus = site.bus()
        # Reads: the server's buses, the leases (the operator's move), the counters.
        assert site.instance and bus.name == "bus"
        assert [i.key for i in bus.leases] == ["la:2"]
        stats = await bus.fetch_stats()
        assert stats["requests"] >= 1
        # A status query goes on .../watch, which the watcher may use: one frame.
        assert (await InspireLA(bus, 1).status()).id == 1
        assert len(frames_at(la_sim)) == len(before) + 1
        before = frames_at(la_sim)
        # No motion (.../request) and no lease (.../lease): the access control lets
        # neither reach the server.
        with pytest.raises(BusClosedError, match="access control"):
            await InspireLA(bus, 1).move_to(1000)
        with pytest.raises(BusClosedError, match="access control"):
            bus.lease("la:1", owner="watcher")
        with pytest.raises(BusClosedError, match="access control"):
            await bus.release()
        # Nor can it pass motion off as a watch: the server refuses it by name.
        move = la.Follow(1, 1000, False).encode().hex()
        answer = watch_query(tls_server, watcher, {"client": "w", "frame": move})
        assert "carries reads and stops only" in answer, answer
    assert frames_at(la_sim) == before
    # The operator's lease is untouched by the watcher.
    assert [i.key for i in op_site.bus().leases] == ["la:2"]


def test_the_documented_certificate_commands_are_the_scripts() -> None:
    docs = (EXAMPLES.parents[1] / "docs" / "serve.md").read_text(encoding="utf-8")
    script = (EXAMPLES / "make-certs.sh").read_text(encoding="utf-8")
    body = script[script.index('ec="') : script.index("rm -f")]
    assert body in docs
