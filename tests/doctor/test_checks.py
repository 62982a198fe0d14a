"""The doctor's verdicts, fact by fact (pure: no port, no clock)."""

from __future__ import annotations

import json
import math

import pytest

from motorbus.bus.bus import DEFAULT_TURNAROUND
from motorbus.bus.occupancy import BusTiming
from motorbus.doctor import DoctorReport, Finding, Level
from motorbus.doctor.budget import MeasuredBudget, budget_theory, check_budget
from motorbus.doctor.checks import (
    DeviceScan,
    EchoFacts,
    LatencyFacts,
    LineFacts,
    PortFacts,
    TurnaroundFacts,
    UsbInfo,
    check_devices,
    check_echo,
    check_latency,
    check_line,
    check_port,
    check_turnaround,
)
from motorbus.doctor.host import HostFacts, check_host
from motorbus.doctor.report import SCHEMA


def timing(baud: int = 921600, margin: float = 2e-3) -> BusTiming:
    return BusTiming(baud, 1e-3, margin, DEFAULT_TURNAROUND)


# -- the cycle budget: a table on the occupancy model ---------------------------------------
# Wire time is 10 bits a byte.  Status query 8 bytes, status reply 22, follow 0x20 9 bytes,
# 0xF3 broadcast 6 + 3N bytes, LA turnaround 800 us, spacing 1 ms.  Each row by hand:
# poll = max(1 ms, (8 + 22) * 10 / baud + 0.8 ms); tick = sum over frames of
# max(1 ms, (6 + 3N) * 10 / baud); polls = floor((period - tick) / poll); the capacities
# are what Streamer.follow admits: floor(0.8 * period / frame) frames of 15 by broadcast,
# floor(0.8 * period / max(1 ms, (9 + 22) * 10 / baud + 0.8 ms)) with feedback.
BUDGET_ROWS = [
    # baud, actuators, period ms, tick ms, frames, poll ms, polls, broadcast cap, feedback cap
    (921600, 1, 10, 1.0, 1, 1.125521, 7, 120, 7),
    (921600, 8, 10, 1.0, 1, 1.125521, 7, 120, 7),
    (921600, 15, 10, 1.0, 1, 1.125521, 7, 120, 7),
    (921600, 16, 10, 2.0, 2, 1.125521, 7, 120, 7),
    (921600, 31, 10, 3.0, 3, 1.125521, 6, 120, 7),
    (115200, 15, 20, 4.427083, 1, 3.404167, 4, 45, 4),
    (19200, 1, 50, 4.6875, 1, 16.425, 2, 15, 2),
]


@pytest.mark.parametrize(
    ("baud", "n", "period_ms", "tick_ms", "frames", "poll_ms", "polls", "bcap", "fcap"),
    BUDGET_ROWS,
)
def test_the_cycle_budget_theory_is_the_occupancy_model(
    baud: int,
    n: int,
    period_ms: float,
    tick_ms: float,
    frames: int,
    poll_ms: float,
    polls: int,
    bcap: int,
    fcap: int,
) -> None:
    t = budget_theory(timing(baud), n, period_ms / 1e3)
    assert t.tick_s * 1e3 == pytest.approx(tick_ms, abs=1e-5)
    assert t.broadcast_frames == frames
    assert t.poll_s * 1e3 == pytest.approx(poll_ms, abs=1e-5)
    assert t.polls_between_ticks == polls
    assert (t.broadcast_capacity, t.feedback_capacity) == (bcap, fcap)
    assert t.shortest_period_polled_s == pytest.approx(t.tick_s + n * t.poll_s)


def _measured(per_tick: float) -> MeasuredBudget:
    return MeasuredBudget(100, round(per_tick * 100), 0, per_tick, 0.0, 1.0)


def test_a_measurement_within_20_percent_of_theory_is_green_beyond_it_yellow_with_reason() -> None:
    theory = budget_theory(timing(), 1, 0.010)  # 7 reads a tick
    assert check_budget(theory, _measured(6.0)).level is Level.GREEN
    assert check_budget(theory, _measured(9.0)).level is Level.GREEN  # the model is a worst case
    host = check_budget(theory, _measured(5.0))
    assert host.level is Level.YELLOW and "host jitter" in host.summary
    assert "29 % short" in host.summary and host.data["gap"] == pytest.approx(2 / 7)
    adapter = check_budget(theory, _measured(5.0), adapter_ms=16, slow_device=True)
    assert "adapter" in adapter.summary
    slow = check_budget(theory, _measured(5.0), slow_device=True)
    assert "device turnaround" in slow.summary
    lossy = check_budget(theory, _measured(5.0), line=LineFacts(100, 9, 2, 40, 0))
    assert "lost on the line" in lossy.summary
    late = check_budget(theory, _measured(5.0), line=LineFacts(100, 9, 9, 0, 0))
    assert "host jitter" in late.summary
    assert check_budget(theory, None).level is Level.GREEN


# -- the port ---------------------------------------------------------------------------------

DIALOUT = 20


def port(
    mode: int = 0o20660, uid: int = 1000, gids: frozenset[int] = frozenset({1000}), **kw: object
) -> PortFacts:
    values: dict[str, object] = {
        "url": "/dev/ttyUSB0",
        "path": "/dev/ttyUSB0",
        "kind": "usb",
        "mode": mode,
        "owner_uid": 0,
        "group_gid": DIALOUT,
        "group_name": "dialout",
        "uid": uid,
        "gids": gids,
        "usb": UsbInfo("0403", "6001", "ftdi_sio", "A50285BI", "FT232R USB UART", "FTDI"),
    }
    values.update(kw)
    return PortFacts(**values)  # type: ignore[arg-type]


def test_a_user_outside_dialout_gets_the_exact_usermod_line() -> None:
    f = check_port(port())
    assert f.level is Level.RED
    assert f.fix == "sudo usermod -aG dialout $USER, then log out and in again"
    assert "mode 660" in f.summary


@pytest.mark.parametrize(
    ("mode", "uid", "gids"),
    [
        (0o20660, 1000, frozenset({1000, DIALOUT})),  # in the group
        (0o20600, 0, frozenset({0})),  # root
        (0o20666, 1000, frozenset({1000})),  # everyone may
    ],
)
def test_a_port_the_user_may_open_is_green_and_names_the_adapter(
    mode: int, uid: int, gids: frozenset[int]
) -> None:
    f = check_port(port(mode, uid, gids))
    assert f.level is Level.GREEN
    assert "USB 0403:6001" in f.summary and "ftdi_sio" in f.summary and "A50285BI" in f.summary
    assert f.data["usb"]["serial"] == "A50285BI"


def test_another_process_on_a_serial_port_is_red_and_named_but_a_ptys_server_is_not() -> None:
    held = check_port(port(gids=frozenset({DIALOUT}), holders=((4242, "minicom"),)))
    assert held.level is Level.RED and "minicom (pid 4242)" in held.summary
    assert "kill 4242" in held.fix
    pty = check_port(
        port(gids=frozenset({DIALOUT}), kind="pty", usb=None, holders=((77, "motorbus"),))
    )
    assert pty.level is Level.GREEN and "served by motorbus (pid 77)" in pty.summary


# -- the adapter's latency -------------------------------------------------------------------


def test_latency_timer_16_ms_is_red_2_ms_yellow_1_ms_green_and_the_udev_rule_is_written_out() -> (
    None
):
    red = check_latency(LatencyFacts("ttyUSB0", "ftdi_sio", 16, False), timing(), 0.010)
    assert red.level is Level.RED  # 16 ms > 0.8 ms turnaround + 2 ms margin
    assert "/sys/bus/usb-serial/devices/ttyUSB0/latency_timer" in red.fix
    assert 'DRIVER=="ftdi_sio", ATTR{latency_timer}="1"' in red.fix
    assert red.data["udev_rule_path"] == "/etc/udev/rules.d/99-motorbus-latency.rules"
    # The cost by the occupancy model: 8 status reads in 10 ms become 0.
    assert (red.data["polls_per_period"], red.data["polls_per_period_now"]) == (8, 0)
    yellow = check_latency(LatencyFacts("ttyUSB0", "ftdi_sio", 2, False), timing(), 0.010)
    assert yellow.level is Level.YELLOW and yellow.data["cost_per_request_ms"] == 2
    green = check_latency(LatencyFacts("ttyUSB0", "ftdi_sio", 1, True), timing(), 0.010)
    assert green.level is Level.GREEN and "ASYNC_LOW_LATENCY on" in green.summary
    assert check_latency(LatencyFacts(None), timing(), 0.010).level is Level.GREEN


# -- echo ----------------------------------------------------------------------------------------

QUERY = bytes.fromhex("55 AA 03 01 04 00 22 2A")
REPLY = bytes.fromhex("AA 55 11 01 04") + bytes(17)


def test_our_own_bytes_coming_back_first_are_an_echo_and_remove_echo_is_the_fix() -> None:
    f = check_echo(EchoFacts(QUERY, QUERY + REPLY, remove_echo=False), "[[bus]] 'arm'")
    assert f.level is Level.RED
    assert "remove_echo = true in [[bus]] 'arm'" in f.fix
    assert check_echo(EchoFacts(QUERY, QUERY + REPLY, True), "x").level is Level.GREEN
    assert check_echo(EchoFacts(QUERY, REPLY, False), "x").level is Level.GREEN
    assert check_echo(EchoFacts(QUERY, b"", False), "x").data["echoes"] is False


# -- baud and IDs -----------------------------------------------------------------------------


def test_devices_all_found_is_green_a_configured_id_missing_is_red() -> None:
    ok = check_devices(DeviceScan(921600, (1, 2), True, (1, 2)), "x")
    assert ok.level is Level.GREEN and "la:1,2" in ok.summary
    late = check_devices(DeviceScan(921600, (1, 2), True, (1, 2), late=(2,)), "x")
    assert late.level is Level.GREEN and "la:2 only after the scan's budget" in late.summary
    missing = check_devices(DeviceScan(921600, (1, 2, 3), True, (1, 3)), "x")
    assert missing.level is Level.RED and "la:2 silent" in missing.summary


def test_nothing_at_the_baud_names_the_baud_where_they_answer() -> None:
    f = check_devices(
        DeviceScan(115200, (1,), True, (), elsewhere={921600: (1,), 57600: ()}), "the bus file"
    )
    assert f.level is Level.RED
    assert "la:1 at 921600" in f.summary
    assert f.fix == "use baud = 921600 in the bus file (or --baud 921600)"


def test_nothing_anywhere_gives_the_wiring_pointers() -> None:
    f = check_devices(DeviceScan(921600, (1,), True, (), elsewhere={115200: ()}), "x")
    assert f.level is Level.RED
    assert "A/B" in f.fix and "termination" in f.fix and "scan --baud all" in f.fix


# -- turnaround -------------------------------------------------------------------------------
# A status query and its reply take (8 + 22) * 10 / 921600 = 325.5 us on the wire.
WIRE = 30 * 10 / 921600


def turnaround(p50: float, p99: float, late: int = 0) -> TurnaroundFacts:
    return TurnaroundFacts("la:1", 30, WIRE + p50, WIRE + p99, WIRE + p99, 30, late, 0)


def test_a_device_answering_2_ms_late_is_red_with_the_setting_and_its_cost() -> None:
    f = check_turnaround(turnaround(2e-3, 2.05e-3), timing(), 0.010)
    assert f.level is Level.RED
    assert f.data["turnaround_us"]["p50"] == pytest.approx(2000)
    assert "Bus(turnaround={Family.LA: 0.0021})" in f.fix  # p99 rounded up to 0.1 ms
    assert f"host_margin_ms = {math.ceil(2 + 2.05 - 0.8 + 0.5)}" in f.fix
    # What it costs: a status read holds the bus 2.05 ms + wire instead of 1.126 ms.
    assert (f.data["polls_per_period"], f.data["polls_per_period_slow"]) == (8, 4)


def test_a_device_within_its_turnaround_is_green_an_occasional_slow_reply_yellow() -> None:
    assert check_turnaround(turnaround(150e-6, 700e-6), timing(), 0.010).level is Level.GREEN
    assert check_turnaround(turnaround(150e-6, 3.5e-3), timing(), 0.010).level is Level.YELLOW
    assert check_turnaround(turnaround(150e-6, 700e-6, late=1), timing(), 0.010).level is (
        Level.YELLOW
    )


# -- the line -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("facts", "level"),
    [
        (LineFacts(100, 0, 0, 0, 0), Level.GREEN),
        (LineFacts(100, 0, 0, 12, 0), Level.YELLOW),  # garbage, nothing lost
        (LineFacts(100, 3, 3, 0, 0), Level.YELLOW),  # late, not lost
        (LineFacts(1000, 5, 5, 0, 0), Level.GREEN),  # 0.5 % late: a loaded host's stall
        (LineFacts(100, 2, 0, 40, 0), Level.YELLOW),  # 2 % lost
        (LineFacts(100, 9, 2, 40, 0), Level.RED),  # 7 % lost
    ],
)
def test_the_line(facts: LineFacts, level: Level) -> None:
    assert check_line(facts).level is level


# -- the host -----------------------------------------------------------------------------------


def test_the_host_is_never_red_and_says_how_to_grant_realtime() -> None:
    bad = check_host(HostFacts("loop", False, False, frozenset({"powersave"}), ((9, "jackd"),)))
    assert [f.level for f in bad] == [Level.YELLOW] * 4
    realtime = next(f for f in bad if f.check == "host realtime")
    assert "rtprio" in realtime.fix and "memlock" in realtime.fix
    assert "jackd (9)" in bad[3].summary
    good = check_host(HostFacts("timerfd", True, True, frozenset({"performance"})))
    assert [f.level for f in good] == [Level.GREEN] * 4


# -- the report ---------------------------------------------------------------------------------


def test_exit_code_text_and_json_of_a_report() -> None:
    report = DoctorReport("/dev/ttyUSB0", 921600, 0.010)
    report.findings.append(Finding("port", Level.GREEN, "fine"))
    assert report.exit_code == 0
    report.findings.append(Finding("echo", Level.YELLOW, "hmm", "do this"))
    assert report.exit_code == 0
    report.findings.append(Finding("devices", Level.RED, "silent", "do that"))
    assert report.exit_code == 1
    text = report.format_text()
    assert text.splitlines()[1].startswith("green  port")
    assert "-> do that" in text and "1 red, 1 yellow, exit 1" in text
    doc = json.loads(report.to_json())
    assert doc["schema"] == SCHEMA and doc["worst"] == "red" and doc["exit_code"] == 1
    assert [c["check"] for c in doc["checks"]] == ["port", "echo", "devices"]
    assert set(doc["checks"][0]) == {"check", "level", "summary", "fix", "data"}
