"""``motorbus doctor``'s verdicts: facts in, one :class:`Finding` per check out.

Pure: no I/O, no clock, no asyncio.  :mod:`motorbus.doctor.probe` gathers the facts
(sysfs, /proc, the port, the bus); every judgement is made here, so each rule is a
table test.  Frame costs come from the bus core's occupancy model
(:mod:`motorbus.bus.occupancy`), never redone here.

The host's checks are in :mod:`motorbus.doctor.host`, the cycle budget's in
:mod:`motorbus.doctor.budget`.

Levels: ``green`` (fine), ``yellow`` (works, but costs something: the finding says
what and the one thing to do), ``red`` (this is why the bus fails: the one thing to
do), ``skip`` (could not be checked, and why).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from motorbus.bus.occupancy import BusTiming, Occupancy, command_occupancy, reply_slack
from motorbus.protocol import la
from motorbus.protocol.base import Family

__all__ = [
    "LATE_YELLOW_SHARE",
    "LOST_RED_SHARE",
    "DeviceScan",
    "EchoFacts",
    "Finding",
    "LatencyFacts",
    "Level",
    "LineFacts",
    "PortFacts",
    "TurnaroundFacts",
    "UsbInfo",
    "check_devices",
    "check_echo",
    "check_latency",
    "check_line",
    "check_port",
    "check_turnaround",
    "poll_occupancy",
    "udev_rule",
]

#: Replies lost in the measured sequence beyond this share of requests: red.
LOST_RED_SHARE = 0.05
#: Replies later than their deadline beyond this share of requests: yellow (below it,
#: a loaded host's occasional stall; counted in the summary all the same).
LATE_YELLOW_SHARE = 0.01
#: Where the udev rule that sets the latency timer for good goes.
UDEV_RULE_PATH = "/etc/udev/rules.d/99-motorbus-latency.rules"
#: The command that adds the user to the group owning a serial port (then log in again).
USERMOD = "sudo usermod -aG {group} $USER"


class Level(enum.Enum):
    """How a check came out."""

    GREEN = "green"
    YELLOW = "yellow"
    RED = "red"
    SKIP = "skip"


@dataclass(frozen=True, slots=True)
class Finding:
    """One check's verdict: a one-line ``summary`` and, unless green, the one thing to do."""

    check: str
    level: Level
    summary: str
    fix: str = ""
    data: Mapping[str, Any] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """A JSON-ready form."""
        return {
            "check": self.check,
            "level": self.level.value,
            "summary": self.summary,
            "fix": self.fix,
            "data": dict(self.data),
        }


def skipped(check: str, why: str) -> Finding:
    """A check that could not run, and why."""
    return Finding(check, Level.SKIP, f"not checked: {why}")


# -- 1. the port -------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class UsbInfo:
    """What sysfs tells about a USB serial adapter."""

    vid: str
    pid: str
    driver: str = ""
    serial: str = ""
    product: str = ""
    manufacturer: str = ""

    def describe(self) -> str:
        parts = [f"USB {self.vid}:{self.pid}"]
        name = " ".join(p for p in (self.manufacturer, self.product) if p)
        if name:
            parts.append(name)
        if self.driver:
            parts.append(f"driver {self.driver}")
        if self.serial:
            parts.append(f"serial {self.serial}")
        return ", ".join(parts)


@dataclass(frozen=True, slots=True)
class PortFacts:
    """A local serial port as the system sees it.

    ``kind``: "usb" (a usb-serial adapter), "pty" (a pseudo-terminal: a simulator or a
    bridge), "tty" (another character device), "file" (not a character device).
    ``holders``: other processes that have it open, ``(pid, name)``.
    """

    url: str
    path: str
    kind: str
    mode: int
    owner_uid: int
    group_gid: int
    group_name: str
    uid: int
    gids: frozenset[int]
    holders: tuple[tuple[int, str], ...] = ()
    usb: UsbInfo | None = None

    @property
    def accessible(self) -> bool:
        """Readable and writable by this user (by the mode bits, as open(2) decides)."""
        need = 0o6
        if self.uid == 0:
            return True
        if self.uid == self.owner_uid:
            return (self.mode >> 6) & need == need
        if self.group_gid in self.gids:
            return (self.mode >> 3) & need == need
        return self.mode & need == need


def check_port(facts: PortFacts) -> Finding:
    """Exists (the probe refuses a missing port earlier), permissions, holders, adapter."""
    what = {
        "usb": facts.usb.describe() if facts.usb else "USB serial adapter",
        "pty": "pseudo-terminal (a simulator or a bridge)",
        "tty": "serial port",
        "file": "not a character device",
    }.get(facts.kind, facts.kind)
    data: dict[str, Any] = {
        "path": facts.path,
        "kind": facts.kind,
        "mode": f"{facts.mode & 0o777:03o}",
        "group": facts.group_name,
        "holders": [{"pid": p, "name": n} for p, n in facts.holders],
    }
    if facts.usb is not None:
        data["usb"] = {
            "vid": facts.usb.vid,
            "pid": facts.usb.pid,
            "driver": facts.usb.driver,
            "serial": facts.usb.serial,
            "product": facts.usb.product,
            "manufacturer": facts.usb.manufacturer,
        }
    where = (
        f"{facts.url} ({what})"
        if facts.path == facts.url
        else (f"{facts.url} -> {facts.path} ({what})")
    )
    if not facts.accessible:
        group = facts.group_name or str(facts.group_gid)
        if facts.group_gid != 0 and facts.group_gid not in facts.gids:
            fix = f"{USERMOD.format(group=group)}, then log out and in again"
        else:
            fix = f"sudo chmod g+rw {facts.path} (or a udev rule giving group {group} rw)"
        return Finding(
            "port",
            Level.RED,
            f"{where}: no read/write permission (mode {facts.mode & 0o777:03o}, group {group})",
            fix,
            data,
        )
    if facts.holders and facts.kind != "pty":
        names = ", ".join(f"{n} (pid {p})" for p, n in facts.holders)
        return Finding(
            "port",
            Level.RED,
            f"{where}: also open in {names}; two readers steal each other's replies",
            f"stop {names.split(' (')[0]} (kill {facts.holders[0][0]}) before using the bus",
            data,
        )
    if facts.kind == "file":
        return Finding(
            "port",
            Level.RED,
            f"{where}",
            "give the serial device path (ls /dev/serial/by-id)",
            data,
        )
    held = ""
    if facts.holders:  # a pty's other end is its simulator's or bridge's: expected
        held = "; served by " + ", ".join(f"{n} (pid {p})" for p, n in facts.holders)
    return Finding("port", Level.GREEN, f"{where}: readable and writable{held}", "", data)


# -- 2. the adapter's latency ---------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class LatencyFacts:
    """The receive latency of a USB serial adapter (``None``: not known / not USB)."""

    tty_name: str | None
    driver: str = ""
    latency_timer_ms: int | None = None
    low_latency_flag: bool | None = None
    fixed: str = ""  # what ``--fix`` changed (or why it could not), if anything
    wrote: bool = False  # ``--fix`` wrote the latency timer


def udev_rule(driver: str) -> str:
    """The udev rule that gives every adapter of ``driver`` a 1 ms latency timer."""
    return (
        f'ACTION=="add", SUBSYSTEM=="usb-serial", DRIVER=="{driver or "ftdi_sio"}", '
        'ATTR{latency_timer}="1"'
    )


def poll_occupancy(timing: BusTiming) -> Occupancy:
    """A status query and its reply (the doctor's and the streams' poll)."""
    return command_occupancy(timing, la.Control(la.ID_MIN, la.ControlAction.QUERY_STATUS))


def _with_la_turnaround(timing: BusTiming, turnaround_s: float) -> BusTiming:
    """``timing`` with another LA turnaround: what a slower reply costs, by the model."""
    return replace(timing, turnaround={**timing.turnaround, Family.LA: turnaround_s})


def check_latency(facts: LatencyFacts, timing: BusTiming, period_s: float) -> Finding:
    """The latency timer and ``ASYNC_LOW_LATENCY``, what they cost a request and a tick."""
    data: dict[str, Any] = {
        "tty": facts.tty_name,
        "latency_timer_ms": facts.latency_timer_ms,
        "async_low_latency": facts.low_latency_flag,
    }
    if facts.fixed:
        data["fixed"] = facts.fixed
    if facts.tty_name is None:
        return Finding(
            "latency", Level.GREEN, "not a USB serial adapter: no latency timer", "", data
        )
    if facts.latency_timer_ms is None:
        return Finding(
            "latency",
            Level.GREEN,
            f"{facts.tty_name}: driver {facts.driver or '?'} has no latency timer in sysfs",
            "",
            data,
        )
    ms = facts.latency_timer_ms
    flag = {True: "on", False: "off", None: "unknown"}[facts.low_latency_flag]
    if ms <= 1:
        return Finding(
            "latency",
            Level.GREEN,
            f"{facts.tty_name}: latency timer {ms} ms, ASYNC_LOW_LATENCY {flag}",
            "",
            data,
        )
    # The adapter may hold a reply up to the timer: each round trip costs that much more.
    poll = poll_occupancy(timing)
    slow = poll_occupancy(_with_la_turnaround(timing, timing.turnaround[Family.LA] + ms / 1e3))
    fits = math.floor(period_s / poll.answered)
    fits_slow = math.floor(period_s / slow.answered)
    rule = udev_rule(facts.driver)
    data.update(
        cost_per_request_ms=ms,
        polls_per_period=fits,
        polls_per_period_now=fits_slow,
        udev_rule=rule,
        udev_rule_path=UDEV_RULE_PATH,
    )
    slack = reply_slack(timing)
    level = Level.RED if ms / 1e3 > slack else Level.YELLOW
    why = (
        f"{facts.tty_name}: latency timer {ms} ms (ASYNC_LOW_LATENCY {flag}): each reply may "
        f"wait up to {ms} ms in the adapter; status reads per {period_s * 1e3:g} ms drop from "
        f"{fits} to {fits_slow}"
    )
    if level is Level.RED:
        why += f", and the {slack * 1e3:.1f} ms reply slack cannot hold: replies time out"
    fix = (
        f"now: echo 1 | sudo tee /sys/bus/usb-serial/devices/{facts.tty_name}/latency_timer "
        f"(or motorbus doctor --fix); for good: echo '{rule}' | sudo tee {UDEV_RULE_PATH}"
    )
    return Finding("latency", level, why, fix, data)


# -- 3. echo ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class EchoFacts:
    """What came back after one request was written with echo removal off."""

    sent: bytes
    received: bytes
    remove_echo: bool  # what the bus is configured with

    @property
    def echoes(self) -> bool:
        return bool(self.sent) and self.received.startswith(self.sent)


def check_echo(facts: EchoFacts, where: str) -> Finding:
    """An adapter that echoes what it sends, named from the bytes that came back."""
    data = {
        "sent": facts.sent.hex(" "),
        "received": facts.received[:64].hex(" "),
        "echoes": facts.echoes,
        "remove_echo": facts.remove_echo,
    }
    if facts.echoes and not facts.remove_echo:
        return Finding(
            "echo",
            Level.RED,
            f"the adapter echoes what it sends ({len(facts.sent)} bytes of our request came "
            "back before anything else): half-duplex RS-485 without receiver disable",
            f"set remove_echo = true in {where} (Bus: open_transport(..., remove_echo=True))",
            data,
        )
    if facts.echoes:
        return Finding(
            "echo", Level.GREEN, "the adapter echoes; remove_echo = true removes it", "", data
        )
    return Finding("echo", Level.GREEN, "no echo of our own bytes", "", data)


# -- 4. baud and IDs ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class DeviceScan:
    """Who answered a status query: at the configured baud, and elsewhere if none did."""

    baud: int
    asked: tuple[int, ...]
    configured: bool  # the IDs come from the bus file or --ids (else: every ID)
    found: tuple[int, ...]
    late: tuple[int, ...] = ()
    elsewhere: Mapping[int, tuple[int, ...]] = field(default_factory=dict)


def _ids(ids: Sequence[int]) -> str:
    return ",".join(str(i) for i in ids)


def check_devices(scan: DeviceScan, where: str) -> Finding:
    """Which LA actuators answer at the baud; when none does, where they do."""
    data: dict[str, Any] = {
        "baud": scan.baud,
        "asked": len(scan.asked),
        "found": list(scan.found),
        "late": list(scan.late),
        "elsewhere": {str(b): list(ids) for b, ids in scan.elsewhere.items()},
    }
    if scan.found:
        missing = [i for i in scan.asked if i not in scan.found] if scan.configured else []
        text = f"la:{_ids(scan.found)} answer at {scan.baud} bit/s"
        if scan.late:
            text += f" (la:{_ids(scan.late)} only after the scan's budget)"
        if missing:
            return Finding(
                "devices",
                Level.RED,
                f"{text}; la:{_ids(missing)} silent",
                f"check power and wiring of la:{_ids(missing)}, or its ID "
                f"(motorbus scan --port ... lists the IDs that answer)",
                data,
            )
        return Finding("devices", Level.GREEN, text, "", data)
    answered = {b: ids for b, ids in scan.elsewhere.items() if ids}
    if answered:
        baud = next(iter(answered))
        others = "; ".join(f"la:{_ids(i)} at {b}" for b, i in answered.items())
        return Finding(
            "devices",
            Level.RED,
            f"nothing answers at {scan.baud} bit/s; {others} bit/s",
            f"use baud = {baud} in {where} (or --baud {baud})",
            data,
        )
    tried = ", ".join(str(b) for b in (scan.baud, *scan.elsewhere))
    return Finding(
        "devices",
        Level.RED,
        f"no LA actuator answers ({len(scan.asked)} ID{'s' if len(scan.asked) != 1 else ''} "
        f"asked at {tried} bit/s)",
        "check the power supply, A/B (D+/D-) not swapped, a common ground, 120 ohm "
        "termination at the ends, and the IDs (motorbus scan --baud all)",
        data,
    )


# -- 5. turnaround --------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TurnaroundFacts:
    """N status queries to one device: reply latency (completed write to reply seen)."""

    key: str
    requests: int
    p50: float
    p99: float
    max: float
    replies: int
    late: int  # replies later than the bus's own deadline for a status query
    lost: int  # no reply within the doctor's patient budget


def _turnaround(latency: float, poll: Occupancy) -> float:
    """The turnaround inside a measured latency: what the wire does not explain."""
    return max(0.0, latency - poll.write - poll.reply_wire)


def check_turnaround(facts: TurnaroundFacts, timing: BusTiming, period_s: float) -> Finding:
    """p50/p99/max of one device's turnaround against the family's budget."""
    poll = poll_occupancy(timing)
    budget = timing.turnaround[Family.LA]
    t50, t99, tmax = (_turnaround(x, poll) for x in (facts.p50, facts.p99, facts.max))
    data: dict[str, Any] = {
        "requests": facts.requests,
        "replies": facts.replies,
        "late": facts.late,
        "lost": facts.lost,
        "latency_us": {"p50": facts.p50 * 1e6, "p99": facts.p99 * 1e6, "max": facts.max * 1e6},
        "turnaround_us": {"p50": t50 * 1e6, "p99": t99 * 1e6, "max": tmax * 1e6},
        "budget_us": budget * 1e6,
    }
    name = f"turnaround {facts.key}"
    if not facts.replies:
        return Finding(
            name, Level.RED, f"{facts.key}: no reply to {facts.requests} queries", "", data
        )
    text = (
        f"{facts.key}: turnaround p50 {t50 * 1e6:.0f} us, p99 {t99 * 1e6:.0f} us, max "
        f"{tmax * 1e6:.0f} us (budget {budget * 1e6:.0f} us); {facts.late} late, "
        f"{facts.lost} lost of {facts.requests}"
    )
    if t50 <= budget and t99 <= budget + timing.host_margin and not facts.late:
        return Finding(name, Level.GREEN, text, "", data)
    # What would make it usable, and what that costs a stream.
    need = max(t99, t50)
    margin_ms = math.ceil((timing.host_margin + need - budget) * 1e3 + 0.5)
    data.update(host_margin_ms=margin_ms)
    if t50 <= budget:
        # Only the tail is slow: the device now and then, or this host (the reply time
        # includes the host's wake-ups).  A longer margin keeps those replies.
        return Finding(
            name,
            Level.YELLOW,
            text + ": the tail is slow (the device now and then, or this host)",
            f"host_margin_ms = {margin_ms} in the bus file (Bus(host_margin="
            f"{margin_ms / 1e3:g})); on this host, try again with --realtime",
            data,
        )
    slow = poll_occupancy(_with_la_turnaround(timing, need))
    fits, fits_slow = (math.floor(period_s / o.answered) for o in (poll, slow))
    data.update(polls_per_period=fits, polls_per_period_slow=fits_slow)
    turnaround_s = math.ceil(need * 1e4) / 1e4  # up to the next 0.1 ms
    data.update(turnaround_s=turnaround_s)
    fix = (
        f"Bus(turnaround={{Family.LA: {turnaround_s:g}}}), or host_margin_ms = {margin_ms} in "
        f"the bus file, so its replies are not timed out; each status read then holds the "
        f"bus {slow.answered * 1e3:.2f} ms instead of {poll.answered * 1e3:.2f} ms: "
        f"{fits_slow} instead of {fits} per {period_s * 1e3:g} ms"
    )
    return Finding(name, Level.RED, text, fix, data)


# -- line quality -----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class LineFacts:
    """The bus counters over the doctor's measured sequence (not the scan)."""

    requests: int
    timeouts: int
    late_replies: int
    garbage_bytes: int
    unexpected_frames: int
    discarded_by_reason: Mapping[str, int] = field(default_factory=dict)


def check_line(facts: LineFacts) -> Finding:
    """Lost replies and bytes that make no frame: noise, wiring, a second master.

    A reply that came after its deadline is late, not lost (the turnaround checks say
    why); a reply that never came, or bytes that make no frame, are the line's.
    """
    lost = max(0, facts.timeouts - facts.late_replies)
    data = {
        "requests": facts.requests,
        "timeouts": facts.timeouts,
        "lost": lost,
        "late_replies": facts.late_replies,
        "garbage_bytes": facts.garbage_bytes,
        "unexpected_frames": facts.unexpected_frames,
        "discarded_by_reason": dict(facts.discarded_by_reason),
    }
    per = facts.garbage_bytes / facts.requests if facts.requests else 0.0
    text = (
        f"{facts.requests} requests: {lost} lost, {facts.late_replies} late, "
        f"{facts.garbage_bytes} garbage bytes ({per:.2f} a request), "
        f"{facts.unexpected_frames} unexpected frames"
    )
    fix = (
        "noise or wiring: twisted pair for A/B, a common ground, 120 ohm termination at both "
        "ends only, no second master on the line"
    )
    lost_share = lost / facts.requests if facts.requests else 0.0
    if lost_share > LOST_RED_SHARE:
        return Finding("line", Level.RED, text, fix, data)
    if lost or facts.garbage_bytes or facts.unexpected_frames:
        return Finding("line", Level.YELLOW, text, fix, data)
    if facts.late_replies > LATE_YELLOW_SHARE * facts.requests:
        return Finding(
            "line",
            Level.YELLOW,
            text,
            "late replies: a slow device or a busy host (see the turnaround checks); "
            "raise host_margin_ms",
            data,
        )
    return Finding("line", Level.GREEN, text, "", data)
