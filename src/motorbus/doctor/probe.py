"""The asyncio shell of ``motorbus doctor``: gather the facts, let checks.py judge them.

The sequence is short and bounded, and read-only: status queries (LA ``0x22``/``0x04``)
and nothing else, unless ``fix=True`` (then only the USB adapter's latency timer is
written, if the user may).  Steps, in order:

1. the port: what it is, permissions, who else holds it, the USB adapter (sysfs, /proc;
   :mod:`motorbus.doctor.system` reads them);
2. the adapter's latency timer and ``ASYNC_LOW_LATENCY`` (sysfs, ``TIOCGSERIAL``);
3. echo: one status query written with echo removal off; what comes back is compared;
4. baud and IDs: ``motorbus.devices.la.scan`` at the baud; if nothing answers, at the
   other LA rates;
5. turnaround: ``requests`` status queries to each device found, timed by the bus;
6. the line: the bus counters over steps 5 and 7;
7. the cycle budget: the occupancy model's theory, and status reads in the gaps the
   stream's ticks would leave, for ``measure_s`` seconds;
8. the host: timer, real-time grant, CPU governor, other real-time processes.
"""

from __future__ import annotations

import asyncio
import itertools
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from motorbus.bus.bus import (
    DEFAULT_HOST_MARGIN_S,
    DEFAULT_TURNAROUND,
    MIN_SPACING_S,
    Bus,
    Priority,
)
from motorbus.bus.occupancy import BusTiming
from motorbus.bus.timer import default_timer
from motorbus.devices.la import InspireLA, ScanReport, scan
from motorbus.doctor import checks
from motorbus.doctor.budget import BudgetTheory, MeasuredBudget, StreamMeasured, budget_theory
from motorbus.doctor.budget import check_budget as judge_budget
from motorbus.doctor.checks import (
    DeviceScan,
    EchoFacts,
    Finding,
    LatencyFacts,
    Level,
    LineFacts,
    TurnaroundFacts,
    skipped,
)
from motorbus.doctor.host import check_host
from motorbus.doctor.report import DoctorReport
from motorbus.doctor.system import host_facts, latency_facts, port_facts
from motorbus.errors import (
    BusClosedError,
    LocalProtocolError,
    NotSentError,
    RemoteProtocolError,
    ReplyTimeoutError,
)
from motorbus.manager import BusManager
from motorbus.protocol import la
from motorbus.protocol.base import Family, check_int, wire_time
from motorbus.protocol.families import STEPPER_DEFAULT_BAUD
from motorbus.streams import PERIOD_MAX_S, PERIOD_MIN_S, SafeAction, Streamer
from motorbus.transport import usb
from motorbus.transport.base import Transport
from motorbus.transport.serial import DEFAULT_BACKEND, open_transport
from motorbus.validation import check_number

__all__ = ["DOCTOR_BAUDS", "DoctorConfig", "diagnose"]

#: The rates some family uses: the LA baud codes and the steppers' 9600 bit/s.
DOCTOR_BAUDS = tuple(sorted({STEPPER_DEFAULT_BAUD, *(c.baud for c in la.BaudCode)}))
#: Status queries per device for its turnaround.
DEFAULT_REQUESTS = 30
#: Seconds of measured cycle budget.
DEFAULT_MEASURE_S = 2.0
#: Reply budget of the turnaround queries: patient, so that a slow device is measured
#: rather than timed out (the scan's budget for late answers).
PATIENT_S = 0.050
#: After the echo probe's write, how long to collect what comes back (at least).
ECHO_WAIT_S = 0.030


@dataclass(frozen=True, slots=True)
class DoctorConfig:
    """What to diagnose; every value checked on construction (nothing is sent before).

    Build it from a port (``DoctorConfig(url, baud)``) or from a bus file
    (:meth:`from_bus_file`, every key of the ``[[bus]]`` table honoured).
    """

    url: str
    baud: int
    backend: str = DEFAULT_BACKEND
    rs485: bool = False
    remove_echo: bool = False
    low_latency: bool = True
    min_spacing_s: float = MIN_SPACING_S
    host_margin_s: float = DEFAULT_HOST_MARGIN_S
    families: frozenset[Family] = frozenset({Family.LA})
    ids: tuple[int, ...] | None = None
    bus_name: str | None = None
    period_s: float = PERIOD_MIN_S
    requests: int = DEFAULT_REQUESTS
    measure_s: float = DEFAULT_MEASURE_S
    fix: bool = False
    stream: bool = False
    where: str = "your bus options"

    def __post_init__(self) -> None:
        if self.baud not in DOCTOR_BAUDS:
            raise LocalProtocolError(
                f"baud={self.baud!r} is not a rate any family uses: choose one of "
                f"{', '.join(str(b) for b in DOCTOR_BAUDS)}",
                field="baud",
                value=self.baud,
            )
        check_number("period", self.period_s, PERIOD_MIN_S, PERIOD_MAX_S, "s", slack=1e-9)
        check_int("requests", self.requests, 1, 1000)
        check_number("measure_s", self.measure_s, 0.0, 60.0, "s")
        if self.ids is not None:
            object.__setattr__(
                self, "ids", tuple(check_int("id", i, la.ID_MIN, la.ID_MAX) for i in self.ids)
            )
        if usb.is_usb_url(self.url):
            usb.parse_usb_url(self.url, field="port")  # whether it is plugged in: a finding
        elif "://" not in self.url and not os.path.exists(self.url):
            raise LocalProtocolError(
                f"port {self.url!r} does not exist", field="port", value=self.url
            )

    @classmethod
    def from_bus_file(
        cls, path: str | Path, bus: str | None = None, **options: Any
    ) -> DoctorConfig:
        """The bus ``bus`` of a bus file (``BusManager.from_toml``: every key checked).

        Raises:
            LocalProtocolError: a bad file (naming the key), or no such bus.
            OSError: the file cannot be read.
        """
        specs = BusManager.from_toml(path, safe_stop=False).specs
        if bus is None:
            if len(specs) != 1:
                raise LocalProtocolError(
                    f"{path} has {len(specs)} buses: choose one of {', '.join(specs)}",
                    field="bus",
                )
            bus = next(iter(specs))
        if bus not in specs:
            raise LocalProtocolError(
                f"{path} has no bus {bus!r}: choose one of {', '.join(specs)}",
                field="bus",
                value=bus,
            )
        spec = specs[bus]
        ids = tuple(i for d in spec.devices if d.kind == "la" for i in d.ids)
        return cls(
            url=spec.url,
            baud=spec.baud,
            backend=spec.backend,
            rs485=spec.rs485,
            remove_echo=spec.remove_echo,
            low_latency=spec.low_latency,
            min_spacing_s=spec.min_spacing_ms / 1e3,
            host_margin_s=spec.host_margin_ms / 1e3,
            families=frozenset(spec.families()),
            ids=ids or None,
            bus_name=bus,
            where=f"[[bus]] {bus!r} of {path}",
            **options,
        )


# -- facts from the bus ----------------------------------------------------------------------


def _query(ident: int) -> la.Control:
    return la.Control(ident, la.ControlAction.QUERY_STATUS)


def _transport(config: DoctorConfig, baud: int, remove_echo: bool) -> Transport:
    return open_transport(
        config.url,
        baudrate=baud,
        backend=config.backend,
        rs485=config.rs485,
        remove_echo=remove_echo,
        low_latency=config.low_latency,
    )


def _bus(config: DoctorConfig, baud: int, remove_echo: bool) -> Bus:
    return Bus(
        _transport(config, baud, remove_echo),
        name=config.bus_name or config.url,
        families=config.families,
        min_spacing=config.min_spacing_s,
        host_margin=config.host_margin_s,
        retries=0,
        reconnect=False,
    )


async def echo_facts(config: DoctorConfig, ident: int) -> EchoFacts:
    """Write one status query with echo removal off; keep what comes back."""
    transport = _transport(config, config.baud, False)
    got = bytearray()
    lost: list[BaseException | None] = []
    await transport.open(got.extend, lost.append)
    raw = _query(ident).encode()
    try:
        transport.write(raw)
        await asyncio.sleep(ECHO_WAIT_S + wire_time(3 * la.STATUS_FRAME_SIZE, config.baud))
    finally:
        await transport.close()
    if lost:  # a server that would not serve closed it (its reason is in the error)
        raise lost[0] if isinstance(lost[0], OSError) else BusClosedError(f"{config.url} closed")
    return EchoFacts(raw, bytes(got), config.remove_echo)


def open_failed(url: str, err: BaseException) -> Finding:
    """The red finding of a port that did not open, or was closed at once."""
    said = str(err).removeprefix(f"{url}: ")
    return Finding("open", Level.RED, f"cannot open {url}: {said}", open_advice(url, err))


def open_advice(url: str, err: BaseException) -> str:
    """The one thing to do about a port that did not open (or was closed at once)."""
    said = str(err)
    if "already in use" in said:  # ser2net: "Port already in use", "Port's device ..."
        return (
            "another client is connected to this port on the server, which serves one at a "
            "time: end that program (docs/remote-buses.md)"
        )
    if "Device open failure" in said:
        return (
            "the server cannot open its serial device: check the adapter on that machine "
            "and the device path in its ser2net configuration"
        )
    if "://" in url:
        return "check that the server runs and listens at this address (docs/remote-buses.md)"
    return "see the port check"


async def scan_devices(config: DoctorConfig, remove_echo: bool) -> DeviceScan:
    """``scan`` at the configured baud; at the other LA rates only if nothing answered."""
    asked = config.ids or tuple(range(la.ID_MIN, la.ID_MAX + 1))
    report = ScanReport()
    async with _bus(config, config.baud, remove_echo) as bus:
        await scan(bus, asked, report=report)
    found = tuple(sorted({*report.found, *report.late}))  # late, but there: measured next
    elsewhere: dict[int, tuple[int, ...]] = {}
    if not found:
        for code in reversed(la.BaudCode):  # the factory rate first
            if code.baud == config.baud:
                continue
            # Two passes, as at the configured baud: a reply late for the first pass's
            # tight budget (a busy host) is asked again patiently, and late ones count.
            other_report = ScanReport()
            async with _bus(config, code.baud, remove_echo) as other:
                await scan(other, asked, report=other_report)
            elsewhere[code.baud] = tuple(sorted({*other_report.found, *other_report.late}))
    return DeviceScan(
        baud=config.baud,
        asked=tuple(asked),
        configured=config.ids is not None,
        found=found,
        late=tuple(report.late),
        elsewhere=elsewhere,
    )


def _percentile(sorted_values: Sequence[float], p: float) -> float:
    if not sorted_values:
        return 0.0
    rank = max(1, -(-len(sorted_values) * p // 100))
    return sorted_values[int(rank) - 1]


async def turnaround_facts(bus: Bus, ident: int, requests: int) -> TurnaroundFacts:
    """``requests`` status queries to one device, each timed by the bus (write to reply)."""
    key = f"la:{ident}"
    deadline = bus.occupancy(_query(ident)).budget
    latencies: list[float] = []
    lost = 0
    for _ in range(requests):
        device = bus.stats.device(key)
        before = device.latency.total, device.latency.count
        try:
            await bus.request(_query(ident), timeout=PATIENT_S, retries=0)
        except (ReplyTimeoutError, RemoteProtocolError):  # no reply, or none it could use
            lost += 1
            continue
        if device.latency.count == before[1] + 1:
            latencies.append(device.latency.total - before[0])
    latencies.sort()
    return TurnaroundFacts(
        key=key,
        requests=requests,
        p50=_percentile(latencies, 50),
        p99=_percentile(latencies, 99),
        max=latencies[-1] if latencies else 0.0,
        replies=len(latencies),
        late=sum(1 for x in latencies if x > deadline),
        lost=lost,
    )


async def measure_budget(
    bus: Bus, ids: Sequence[int], theory: BudgetTheory, seconds: float
) -> MeasuredBudget:
    """Status reads round-robin in the gaps the stream's ticks would leave (read-only).

    Each tick's own window (``theory.tick_s``) is left free, as the broadcast would hold
    it; then reads go back to back, each only if it can be answered before the next tick
    (``start_by``), as the stream's polls do.
    """
    timer = bus.timer
    period = theory.period_s
    ticks = max(1, round(seconds / period))
    order = itertools.cycle(ids)
    polls = lost = 0
    start = timer.now() + period
    for k in range(ticks):
        tick = start + k * period
        following = tick + period
        await timer.sleep_until(tick + theory.tick_s)
        while True:
            latest = following - theory.poll_s
            if timer.now() > latest:
                break
            future = bus.submit(
                _query(next(order)), retries=0, start_by=latest, priority=Priority.BACKGROUND
            )
            try:
                await future
            except NotSentError:
                break
            except (ReplyTimeoutError, RemoteProtocolError):
                lost += 1
            else:
                polls += 1
    end = start + ticks * period
    return MeasuredBudget(ticks, polls, lost, polls / ticks, start, end)


async def measure_stream(
    bus: Bus, ids: Sequence[int], period: float, seconds: float
) -> StreamMeasured:
    """A real broadcast follow stream (``--stream``) sending each actuator the position it
    reports now, so nothing travels, with status polls in the free slots.

    The LA reports no pause state: a paused actuator is powered again by the first
    follow target (manual 3.5.4) and then holds where it is.
    """
    positions: dict[int, int] = {}
    for ident in ids:
        try:
            status = await bus.request(_query(ident), timeout=PATIENT_S, retries=2)
        except (ReplyTimeoutError, RemoteProtocolError):
            continue  # its position is not known: it is not streamed
        positions[ident] = min(la.POSITION_MAX, max(la.POSITION_MIN, status.position))
    ticks = max(1, round(seconds / period))
    if not positions:
        return StreamMeasured(ticks, 0, 0, 0, 0, 0, 0, 0.0)
    streamer = Streamer(bus)
    try:
        stream = streamer.follow(
            [InspireLA(bus, i) for i in positions],
            [list(positions.values())] * ticks,
            period=period,
            poll_status=True,
            safe_action=SafeAction.HOLD,
        )
        await stream.wait()
    finally:
        await streamer.close(safe=False)
    st = stream.stats
    return StreamMeasured(
        ticks_planned=ticks,
        ticks=st.ticks,
        late=st.late,
        skipped=st.skipped,
        slipped=st.slipped,
        polls=st.polls,
        polls_skipped=st.polls_skipped,
        jitter_p99_s=st.jitter.percentile(99),
    )


@dataclass(slots=True)
class _Line:
    """Bus counters at the start of the measured sequence."""

    values: dict[str, int] = field(default_factory=dict)

    @staticmethod
    def take(bus: Bus) -> _Line:
        s = bus.stats
        return _Line(
            {
                "requests": s.requests,
                "timeouts": s.timeouts,
                "late_replies": s.late_replies,
                "garbage_bytes": s.garbage_bytes,
                "unexpected_frames": s.unexpected_frames,
            }
        )

    def since(self, bus: Bus, reasons_before: dict[str, int]) -> LineFacts:
        now = _Line.take(bus).values
        d = {k: now[k] - v for k, v in self.values.items()}
        reasons = {
            k: v - reasons_before.get(k, 0)
            for k, v in bus.stats.discarded_by_reason.items()
            if v - reasons_before.get(k, 0)
        }
        return LineFacts(discarded_by_reason=reasons, **d)


# -- the whole sequence --------------------------------------------------------------------


def _usb_device(url: str, sysfs: str, add: Callable[[Finding], None]) -> str | None:
    """The device a local ``url`` names now (a ``usb:`` URL resolved), or None after
    adding a red port finding when no adapter, or more than one, matches."""
    if not usb.is_usb_url(url):
        return url
    try:
        return usb.resolve_port(url, sysfs=sysfs)
    except OSError as err:
        add(Finding("port", Level.RED, str(err), "plug the adapter in; motorbus ports lists them"))
        return None


async def diagnose(
    config: DoctorConfig,
    *,
    uid: int | None = None,
    gids: Iterable[int] | None = None,
    sysfs: str = "/sys",
    proc: str = "/proc",
) -> DoctorReport:
    """Run the doctor's bounded sequence on one bus; return its report.

    Read-only (status queries) unless ``config.fix`` (the latency timer may be
    written) or ``config.stream`` (a real follow stream to the positions reported);
    ``report.read_only`` says whether anything was changed or streamed.

    ``uid``/``gids`` judge the port's permissions for another user (default: this
    process's); ``sysfs``/``proc`` are where the system is read (tests point them at a
    fake tree).
    """
    target = config.url if config.bus_name is None else f"{config.bus_name} ({config.url})"
    report = DoctorReport(target, config.baud, config.period_s)
    add = report.findings.append
    later = ["echo", "devices", "line"]
    # The timing the bus will have (``Bus.timing``), before any bus is opened.
    timing = BusTiming(config.baud, config.min_spacing_s, config.host_margin_s, DEFAULT_TURNAROUND)

    adapter_ms: int | None = None
    usable = True
    if "://" in config.url:
        add(Finding("port", Level.GREEN, f"{config.url}: network port, no local checks"))
        add(checks.check_latency(LatencyFacts(None), timing, config.period_s))
    elif (device := _usb_device(config.url, sysfs, add)) is None:
        usable = False
        add(checks.check_latency(LatencyFacts(None), timing, config.period_s))
    else:
        pf = port_facts(device, uid=uid, gids=gids, sysfs=sysfs, proc=proc)
        port = checks.check_port(pf)
        add(port)
        usable = port.level is not Level.RED
        lf = latency_facts(device, pf.usb.driver if pf.usb else "", fix=config.fix)
        adapter_ms = lf.latency_timer_ms
        report.read_only = not lf.wrote
        add(checks.check_latency(lf, timing, config.period_s))
    la_bus = Family.LA in config.families
    if usable and not la_bus:
        usable = False
        why = "the doctor checks LA actuators; this bus lists only stepper controllers"
    else:
        why = "the port is not usable (see the port check)"
    remove_echo = config.remove_echo
    found: tuple[int, ...] = ()
    slow_device = False
    streamed: StreamMeasured | None = None
    line_facts: LineFacts | None = None
    measured: MeasuredBudget | None = None
    n_theory = len(config.ids) if config.ids else 1
    if usable:
        try:
            echo = await echo_facts(config, (config.ids or (la.ID_MIN,))[0])
        except OSError as err:
            add(open_failed(config.url, err))
            usable, why = False, "the port did not open"
        else:
            add(checks.check_echo(echo, config.where))
            remove_echo = remove_echo or echo.echoes
            later.remove("echo")
    if usable:
        try:
            devices = await scan_devices(config, remove_echo)
        except BusClosedError as err:  # a server that closed the connection a moment later
            add(open_failed(config.url, err))
            usable, why = False, "the port did not open"
    if usable:
        add(checks.check_devices(devices, config.where))
        later.remove("devices")
        found = devices.found
        if not found:
            usable, why = False, f"no device answers at {config.baud} bit/s"
    if usable:
        n_theory = len(found)
        async with _bus(config, config.baud, remove_echo) as bus:
            line = _Line.take(bus)
            reasons = dict(bus.stats.discarded_by_reason)
            for ident in found:
                facts = await turnaround_facts(bus, ident, config.requests)
                finding = checks.check_turnaround(facts, bus.timing, config.period_s)
                slow_device |= finding.level is Level.RED
                add(finding)
            theory = budget_theory(timing, n_theory, config.period_s)
            if config.measure_s > 0:
                measured = await measure_budget(bus, found, theory, config.measure_s)
                if config.stream:
                    report.read_only = False
                    streamed = await measure_stream(bus, found, config.period_s, config.measure_s)
            line_facts = line.since(bus, reasons)
            add(checks.check_line(line_facts))
            later.remove("line")
    for check in later:
        add(skipped(check, why))
    if la_bus:
        theory = budget_theory(timing, n_theory, config.period_s)
        add(
            judge_budget(
                theory,
                measured,
                adapter_ms=adapter_ms,
                slow_device=slow_device,
                line=line_facts,
                stream=streamed,
            )
        )
    else:
        add(skipped("budget", why))
    host = host_facts(default_timer().name, sysfs=sysfs, proc=proc)
    report.findings.extend(check_host(host))
    return report
