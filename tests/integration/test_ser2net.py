"""Buses on a remote serial server: the real ser2net in front of a simulator process.

Every installed serial backend talks to ``socket://127.0.0.1:PORT`` (ser2net's raw TCP
accepter, ``chardelay: false``): request/reply, and a broadcast follow stream whose
frames the simulator logs.  The RFC 2217 accepter is tried too; where a backend cannot
use it (docs/platform.md section 2), the test skips and says why.

A new TCP connection to ser2net has a short settling window: on this machine the first
round trip of a fresh connection took 9-25 ms instead of ~1 ms with the serialx and
pyserial-asyncio backends (raw sockets see it too, a few ms after connecting).  Every
test therefore starts with one status query given a long timeout, and counts timeouts
only from there on (docs/remote-buses.md tells users the same).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

import pytest

from motorbus.bus.bus import Bus
from motorbus.devices.la import InspireLA
from motorbus.doctor import DoctorConfig, diagnose
from motorbus.doctor.checks import Level
from motorbus.errors import BusClosedError, ReplyTimeoutError
from motorbus.protocol import la
from motorbus.protocol.base import Family
from motorbus.streams import Streamer
from motorbus.transport.serial import BACKENDS, available_backends, open_transport
from tests.integration.conftest import (
    SIM_BAUD,
    Ser2netServer,
    broadcast_targets,
    is_broadcast_follow,
    received_frames,
)

BACKEND_PARAMS = [
    pytest.param(
        name,
        marks=pytest.mark.skipif(
            name not in available_backends(), reason=f"backend {name!r} is not installed"
        ),
    )
    for name in BACKENDS
]
#: The backends that hand over what ser2net said before it closed a connection.
QUOTING_PARAMS = [p for p in BACKEND_PARAMS if p.values[0] != "pyserial-asyncio"]

#: Host-latency allowance of a remote bus (docs/remote-buses.md): the default 2 ms is
#: sized for a local port; through ser2net two more processes sit in every round trip,
#: and on this 2-core machine under load (other tests running) round trips of 3-5 ms
#: were seen.  The LAN adds its own latency on a real deployment.
REMOTE_HOST_MARGIN_S = 20e-3
#: How long remote_bus keeps trying new connections while ser2net refuses them, and the
#: pause between two tries.
CONNECT_WINDOW_S = 5.0
CONNECT_PAUSE_S = 0.02
#: Reply budget of the first query on a new connection (see the module docstring).
SETTLE_TIMEOUT_S = 0.5
#: The stream: 30 ticks at 10 ms to IDs 1-3, one broadcast frame a tick.
STREAM_TICKS = 30
STREAM_PERIOD_S = 0.010
IDS = (1, 2, 3)
#: How long the RFC 2217 attempt may take before it counts as failed (serialx's open
#: never completes, so it takes this long every time).
RFC2217_ATTEMPT_S = 1.0
#: The pyserial family's attempt ends with its own option timeout; this bounds it, with
#: room for a loaded machine, where its open alone took over a second.
RFC2217_PYSERIAL_ATTEMPT_S = 10.0
#: pyserial's rfc2217 handler waits this long (its ``timeout`` URL option, seconds) for
#: the server's option replies; its default of 3 s would make the test slow.
RFC2217_OPTION_TIMEOUT_S = 0.5


def stream_targets(backend: str) -> list[list[int]]:
    """30 ticks of targets, distinct per backend so each test finds its own frames."""
    base = 100 + 500 * BACKENDS.index(backend)
    return [[base + k, base + 100 + k, base + 200 + k] for k in range(STREAM_TICKS)]


async def settle(bus: Bus) -> None:
    """First round trip on a new connection, with a budget for ser2net's settling."""
    status = await bus.request(
        la.Control(1, la.ControlAction.QUERY_STATUS), timeout=SETTLE_TIMEOUT_S, retries=0
    )
    assert status.id == 1


@contextlib.asynccontextmanager
async def remote_bus(server: Ser2netServer, backend: str) -> AsyncIterator[Bus]:
    """A settled bus on ser2net's raw accepter.

    ser2net refuses a new connection (it sends "Port's device already in use" and closes)
    while another connection holds the device, or is still being closed after its client
    left.  The fixture gives each accepter its own device, which ended the refusals CI
    saw (test_a_client_of_the_rfc2217_accepter_does_not_hold_the_raw_device fails with
    one device for both); a connection that follows another on the same accepter waits
    its turn (it did in 250 tries here, with and without CPU hogs).  Should one
    still be refused before its first reply, it is retried on a new connection, with a
    pause, until CONNECT_WINDOW_S has passed; anything after the settling round trip
    fails the test.
    """
    loop = asyncio.get_running_loop()
    deadline = loop.time() + CONNECT_WINDOW_S
    attempts = 0
    while True:
        attempts += 1
        transport = open_transport(server.raw_url, baudrate=SIM_BAUD, backend=backend)
        bus = Bus(transport, name="remote", families=[Family.LA], host_margin=REMOTE_HOST_MARGIN_S)
        async with contextlib.AsyncExitStack() as stack:
            await stack.enter_async_context(bus)
            try:
                await settle(bus)
            except BusClosedError as err:
                if loop.time() >= deadline:
                    log = server.log_file.read_text(errors="replace").strip()
                    raise AssertionError(
                        f"ser2net closed {attempts} new connections in {CONNECT_WINDOW_S} s "
                        f"before their first reply ({err}); ser2net's log: {log!r}"
                    ) from err
                await asyncio.sleep(CONNECT_PAUSE_S)  # bounded by the deadline above
                continue
            yield bus
            return


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
async def test_request_reply_through_ser2net(ser2net_server: Ser2netServer, backend: str) -> None:
    async with remote_bus(ser2net_server, backend) as bus:
        timeouts_before = bus.stats.timeouts
        replies_before = bus.stats.replies
        actuator = InspireLA(bus, 2)

        status = await actuator.status()
        assert status.id == 2
        assert not status.errors

        moved = await actuator.move_to(1234)
        assert moved is not None and moved.target == 1234

        assert await actuator.read(la.Register.TARGET) == 1234
        for ident in IDS:
            assert (await InspireLA(bus, ident).status()).id == ident

        assert bus.stats.timeouts == timeouts_before
        assert bus.stats.replies - replies_before == 3 + len(IDS)
        assert bus.stats.garbage_bytes == 0


async def test_a_client_of_the_rfc2217_accepter_does_not_hold_the_raw_device(
    ser2net_server: Ser2netServer,
) -> None:
    # ser2net refuses a connection to a device another connection holds; with both
    # accepters on one device, the RFC 2217 test's connection, still closing, made the next
    # raw test fail in a fresh-clone CI run.  The fixture now gives each its own device.
    host, port = ser2net_server.rfc2217_url.removeprefix("rfc2217://").split(":")
    reader, writer = await asyncio.open_connection(host, int(port))
    try:
        async with remote_bus(ser2net_server, "fast") as bus:
            assert (await InspireLA(bus, 1).status()).id == 1
            assert bus.stats.garbage_bytes == 0
    finally:
        writer.close()
        await writer.wait_closed()
    del reader


async def test_a_second_program_on_the_port_is_refused_and_the_first_goes_on(
    ser2net_server: Ser2netServer,
) -> None:
    # docs/remote-buses.md's configuration (no kickolduser): one client at a time, as a
    # local port's lock gives.  The second is told why; the first loses nothing.  (With
    # kickolduser the two took the port from each other in turn, each losing requests.)
    async with remote_bus(ser2net_server, "fast") as first:
        transport = open_transport(ser2net_server.raw_url, baudrate=SIM_BAUD)
        async with Bus(transport, name="second", families=[Family.LA], reconnect=False) as second:
            with pytest.raises(BusClosedError, match='saying "Port already in use"'):
                await second.request(
                    la.Control(1, la.ControlAction.QUERY_STATUS), timeout=SETTLE_TIMEOUT_S
                )
        # Each status with the settling budget: what is counted is a lost request, not a
        # loaded machine's slow turn (eight workers on two CPUs once read one past the
        # remote margin, and its retry answered).
        for ident in IDS:
            status = await first.request(
                la.Control(ident, la.ControlAction.QUERY_STATUS), timeout=SETTLE_TIMEOUT_S
            )
            assert status.id == ident
        assert first.stats.disconnects == 0 and first.stats.timeouts == 0


async def test_the_doctor_names_a_busy_port_and_a_missing_device_with_what_to_do(
    ser2net_server: Ser2netServer,
) -> None:
    # What `motorbus doctor --port socket://...` reports where it used to stop with a
    # traceback-free but bare "lost its port": a red "open" line with ser2net's reason.
    async with remote_bus(ser2net_server, "fast"):  # another program holds the port
        busy = await diagnose(DoctorConfig(ser2net_server.raw_url, SIM_BAUD, measure_s=0))
    missing = await diagnose(DoctorConfig(ser2net_server.missing_url, SIM_BAUD, measure_s=0))
    for report, said, advice in (
        (busy, "Port already in use", "another client is connected to this port"),
        (missing, "Device open failure", "the server cannot open its serial device"),
    ):
        found = {f.check: f for f in report.findings}
        assert found["open"].level is Level.RED, report.findings
        assert said in found["open"].summary and advice in found["open"].fix
        assert {found[c].level for c in ("echo", "devices", "line")} == {Level.SKIP}


@pytest.mark.parametrize("backend", QUOTING_PARAMS)
async def test_a_missing_device_behind_ser2net_is_named_in_the_error(
    ser2net_server: Ser2netServer, backend: str
) -> None:
    # ser2net accepts the connection, writes why it cannot serve and closes it: the
    # error the program gets quotes it, where it used to say only "closed".  (Not with
    # pyserial-asyncio: pyserial drops what it read when it finds the connection closed;
    # tests/transport/test_serial_transport.py says how.)
    transport = open_transport(ser2net_server.missing_url, baudrate=SIM_BAUD, backend=backend)
    async with Bus(transport, name="remote", families=[Family.LA], reconnect=False) as bus:
        with pytest.raises(BusClosedError) as caught:
            await bus.request(
                la.Control(1, la.ControlAction.QUERY_STATUS), timeout=SETTLE_TIMEOUT_S, retries=0
            )
        assert bus.stats.disconnects == 1
    assert 'the server closed the connection, saying "Device open failure' in str(caught.value)


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
async def test_follow_stream_reaches_the_simulator(
    ser2net_server: Ser2netServer, backend: str
) -> None:
    targets = stream_targets(backend)
    async with remote_bus(ser2net_server, backend) as bus:
        actuators = [InspireLA(bus, i) for i in IDS]
        streamer = Streamer(bus)
        try:
            stream = streamer.follow(actuators, targets, period=STREAM_PERIOD_S)
            await asyncio.wait_for(stream.wait(), timeout=5.0)
        finally:
            await streamer.close(safe=False)
        # A reply to a later request proves every earlier frame crossed ser2net: the
        # bus, TCP and the pty all keep order, and the simulator logs a frame as it
        # arrives, before answering anything after it.
        assert (await actuators[0].status()).id == 1

    # Every row sent or its tick skipped; a skip past the end still sends the last row,
    # one tick later (streaming/targets.py).
    assert stream.stats.ticks + stream.stats.skipped in (STREAM_TICKS, STREAM_TICKS + 1)
    assert stream.stats.ticks >= 1
    expected = [dict(zip(IDS, item, strict=True)) for item in targets]
    broadcasts = [
        broadcast_targets(f)
        for f in received_frames(ser2net_server.sim.log_records())
        if is_broadcast_follow(f)
    ]
    ours = [t for t in broadcasts if t in expected]
    assert len(ours) == stream.stats.frames == stream.stats.ticks
    # Each tick's targets arrived once and in order: none duplicated, none reordered.
    indexes = [expected.index(t) for t in ours]
    assert indexes == sorted(set(indexes))
    assert indexes[-1] == STREAM_TICKS - 1 or stream.stats.skipped > 0


@pytest.mark.parametrize("backend", BACKEND_PARAMS)
async def test_rfc2217_accepter_is_reported(ser2net_server: Ser2netServer, backend: str) -> None:
    url = ser2net_server.rfc2217_url
    attempt_s = RFC2217_ATTEMPT_S
    if backend != "serialx":
        url += f"?timeout={RFC2217_OPTION_TIMEOUT_S}"
        attempt_s = RFC2217_PYSERIAL_ATTEMPT_S
    try:
        transport = open_transport(url, baudrate=SIM_BAUD, backend=backend)
        async with asyncio.timeout(attempt_s):
            async with Bus(transport, name="rfc2217", families=[Family.LA]) as bus:
                status = await bus.request(
                    la.Control(1, la.ControlAction.QUERY_STATUS), timeout=SETTLE_TIMEOUT_S
                )
    except (TimeoutError, OSError, ReplyTimeoutError) as err:
        known = {
            # docs/platform.md section 2: "fails (known upstream bug)" for the pyserial family;
            # pyserial's rfc2217 handler waits for an answer to SET_CONTROL that ser2net
            # does not give for a pty.
            "fast": "timeout while waiting for option",
            "pyserial-asyncio": "timeout while waiting for option",
            # docs/platform.md section 2: serialx "waits for a modem-state ack that ser2net does
            # not send for a pty", so the open never completes.
            "serialx": "",
        }[backend]
        # Or ser2net drops the connection during the negotiation (seen when this is the
        # first RFC 2217 client of a fresh ser2net, as when the test runs alone or first
        # on its xdist worker): the client's next write breaks the pipe, or is reset, with
        # serialx as with pyserial (fresh-clone CI runs saw both with serialx).
        gone = isinstance(err, BrokenPipeError | ConnectionResetError)
        if backend == "serialx":
            assert gone or isinstance(err, TimeoutError), f"serialx failed in a new way: {err!r}"
        else:
            assert gone or known in str(err), f"{backend} failed in a new way: {err!r}"
        pytest.skip(
            f"rfc2217:// through ser2net does not work with backend {backend!r} "
            f"(known, docs/platform.md section 2; use socket:// with a raw TCP accepter): "
            f"{type(err).__name__}: {err}"
        )
    assert status.id == 1
