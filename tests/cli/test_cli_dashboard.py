"""``motorbus dashboard`` as a user runs it: against ``motorbus sim`` on a pty, the page
opened in a real headless browser (Debian's chromium, which CI installs), driven over
the DevTools protocol with a small client on aiohttp's WebSocket client."""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import pytest

from motorbus.cli.bus_options import ENV_VARS
from motorbus.protocol import framelog, la
from motorbus.protocol.base import format_hex
from motorbus.sim.process import SimProcess
from motorbus.transport.serial import port_lock_holders
from tests.helpers import NO_CONFIG_DIR, cli

aiohttp = pytest.importorskip("aiohttp")

CHROMIUM = shutil.which("chromium")
needs_browser = pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")
#: Generous bound on anything the test waits for (a stuck run fails instead of hanging).
WAIT_S = 30.0
#: la:1 moves at 400 units/s, so a 900-unit move is seen at several positions on the way.
DEVICES = ["la:1,position=300,stroke_speed=400", "la:2,position=300", "la:3,temperature=95"]


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ENV_VARS}
    env["XDG_CONFIG_HOME"] = NO_CONFIG_DIR
    return env


@asynccontextmanager
async def dashboard(
    sim: SimProcess | None,
    *extra: str,
    pids: list[int] | None = None,
    labelled: list[tuple[str, str]] | None = None,
) -> AsyncIterator[str]:
    """Run ``motorbus dashboard`` (on the simulator's pty, if given); yield the URL it
    printed (and append its process ID to ``pids``).  On the way out it gets SIGTERM, and
    must end with status 0.  Listening on a wildcard address it prints a URL a line,
    each followed by what it is: those go to ``labelled`` as (URL, what), and the one for
    this machine is yielded."""
    port = ["--port", sim.path, "--ids", "1-3"] if sim is not None else []
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "motorbus", "dashboard", *port,
        "--listen", "127.0.0.1:0", "--interval", "0.05", *extra,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env(),
    )  # fmt: skip
    assert proc.stdout is not None and proc.stderr is not None
    if pids is not None:
        pids.append(proc.pid)
    try:
        line = (await asyncio.wait_for(proc.stdout.readline(), WAIT_S)).decode().strip()
        if not line:
            raise AssertionError((await proc.stderr.read()).decode())
        while labelled is not None and line.endswith(")"):
            url, _, what = line.partition("  (")
            labelled.append((url, what.removesuffix(")")))
            if what == "this machine only)":
                line = url
                break
            line = (await asyncio.wait_for(proc.stdout.readline(), WAIT_S)).decode().strip()
        assert re.fullmatch(r"http://[\d.]+:\d+/(\?token=[\w-]+)?", line), line
        yield line
    finally:
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
        _, err = await asyncio.wait_for(proc.communicate(), WAIT_S)
    assert proc.returncode == 0, err.decode()


class Page:
    """One browser tab, driven over the DevTools protocol."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.next_id = 0
        self.events: list[dict[str, Any]] = []
        self.replies: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self.reader = asyncio.create_task(self._read())

    async def _read(self) -> None:
        async for msg in self.ws:
            doc = json.loads(msg.data)
            if "id" in doc:
                self.replies.pop(doc["id"]).set_result(doc)
            else:
                self.events.append(doc)

    async def call(self, method: str, **params: Any) -> dict[str, Any]:
        self.next_id += 1
        future = self.replies[self.next_id] = asyncio.get_running_loop().create_future()
        await self.ws.send_str(json.dumps({"id": self.next_id, "method": method, "params": params}))
        doc = await asyncio.wait_for(future, WAIT_S)
        assert "error" not in doc, doc
        return dict(doc["result"])

    async def js(self, expression: str) -> Any:
        doc = await self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        assert "exceptionDetails" not in doc, doc
        return doc["result"].get("value")

    async def until(self, expression: str) -> Any:
        """Wait until ``expression`` is truthy in the page; return its value."""
        async with asyncio.timeout(WAIT_S):
            while True:
                value = await self.js(expression)
                if value:
                    return value
                await asyncio.sleep(0.05)


@asynccontextmanager
async def browser(tmp: Path) -> AsyncIterator[Page]:
    assert CHROMIUM is not None
    proc = await asyncio.create_subprocess_exec(
        CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--remote-debugging-port=0",
        f"--user-data-dir={tmp}", "--disable-background-networking", "--no-first-run",
        "--proxy-server=127.0.0.1:9", "about:blank",
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    assert proc.stderr is not None
    try:
        async with asyncio.timeout(WAIT_S):
            while True:
                line = (await proc.stderr.readline()).decode()
                assert line, "chromium ended before it listened"
                m = re.search(r"DevTools listening on ws://([\d.]+:\d+)/", line)
                if m:
                    break
        async with aiohttp.ClientSession() as http:
            async with asyncio.timeout(WAIT_S):
                while True:
                    targets = await (await http.get(f"http://{m.group(1)}/json/list")).json()
                    pages = [t for t in targets if t["type"] == "page"]
                    if pages:
                        break
                    await asyncio.sleep(0.1)
            async with http.ws_connect(pages[0]["webSocketDebuggerUrl"], max_msg_size=0) as ws:
                page = Page(ws)
                for domain in ("Page", "Runtime", "Network"):
                    await page.call(f"{domain}.enable")
                yield page
                page.reader.cancel()
    finally:
        proc.kill()
        await proc.wait()


def sim_frames(sim: SimProcess, direction: str) -> list[dict[str, Any]]:
    """The frames the simulator received (``request``) or sent (``reply``), decoded."""
    out = []
    for record in sim.log_records():
        if record["direction"] == direction and record["kind"] == "frame":
            out += [d.to_json() for d in framelog.describe_record(record)]
    return out


@pytest.fixture
def sim(tmp_path: Path) -> Iterator[SimProcess]:
    with SimProcess(DEVICES, baud=921600, log_file=tmp_path / "frames.jsonl") as s:
        yield s


POSITIONS = "[...document.querySelectorAll('.la [data-f=position]')].map(e => e.textContent)"


@needs_browser
async def test_the_page_shows_live_actuators_and_its_estop_reaches_the_simulator(
    sim: SimProcess, tmp_path: Path
) -> None:
    async with dashboard(sim, "--control") as url, browser(tmp_path / "chromium") as page:
        await page.call("Page.navigate", url=url)
        await page.until("document.querySelectorAll('.la').length === 3")
        await page.until("document.getElementById('conn').textContent === 'live'")
        assert await page.until(f"{POSITIONS}.every(p => p !== '-') && {POSITIONS}") == [
            "300", "300", "0"
        ]  # fmt: skip
        # The over-temperature of la:3 shows by name.
        assert "OVER_TEMPERATURE" in await page.until(
            "document.querySelector('.la[data-id=\"3\"] [data-f=errors]').textContent"
        )

        # Move la:1 from the page: a position, Move, then Confirm.
        await page.js(
            "document.querySelector('[data-move=\"1\"]').value = '1200';"
            "document.querySelector('.la[data-id=\"1\"] [data-action=move]').click();"
            "document.querySelector('[data-action=confirm-move]').click(); true"
        )
        seen: list[int] = []
        async with asyncio.timeout(WAIT_S):
            while not seen or seen[-1] != 1200:
                seen.append(int((await page.js(POSITIONS))[0]))
                await asyncio.sleep(0.1)
        moving = sorted(set(seen) - {300, 1200})
        assert len(moving) >= 3, seen  # the values on the page change over time...
        reported = {f["fields"]["position"] for f in sim_frames(sim, "reply")
                    if f["fields"].get("id") == 1}  # fmt: skip
        assert set(seen) <= reported  # ...and are what the simulator reported
        assert seen == sorted(seen)
        assert await page.js("data[Object.keys(data)[0]].position.length") >= len(seen)

        # The bus's e-stop button: every actuator of the bus gets the e-stop frame.
        await page.js("document.querySelector('section.bus h2 [data-action=estop]').click(); 1")
        estops = {format_hex(la.Control(i, la.ControlAction.ESTOP).encode()) for i in (1, 2, 3)}
        async with asyncio.timeout(WAIT_S):
            while not estops <= {str(r["hex"]) for r in sim.log_records()}:
                await asyncio.sleep(0.05)
        await page.until(
            "[...document.querySelectorAll('.la [data-f=mode]')]"
            ".every(e => e.textContent === 'estop')"
        )

        # A phone: nothing scrolls sideways, the big e-stop stays on screen.
        await page.call(
            "Emulation.setDeviceMetricsOverride",
            width=390, height=844, deviceScaleFactor=2, mobile=True,
        )  # fmt: skip
        await page.call("Page.reload")
        await page.until("document.querySelectorAll('.la').length === 3")
        assert await page.js("document.documentElement.scrollWidth <= window.innerWidth")
        box = await page.js(
            "JSON.stringify(document.getElementById('estop-all').getBoundingClientRect())"
        )
        rect = json.loads(box)
        assert rect["width"] > 0 and rect["top"] >= 0 and rect["bottom"] <= 844
        assert rect["right"] <= 390

        # Nothing was requested from anywhere but the dashboard itself.
        host = url.removeprefix("http://").rstrip("/")
        urls = [e["params"]["request"]["url"] for e in page.events
                if e["method"] == "Network.requestWillBeSent"]  # fmt: skip
        urls += [
            e["params"]["url"] for e in page.events if e["method"] == "Network.webSocketCreated"
        ]
        assert any(u.startswith(f"ws://{host}/ws") for u in urls)
        assert [u for u in urls if not re.match(rf"(http|ws)://{re.escape(host)}/", u)] == []

    # Exit: la:1 (moved by the page) was e-stopped already; the dashboard's exit sends
    # la:1 its safe action (pause) and nothing to the actuators it never moved.  After
    # the pause, nothing but a status query (a viewer's poll still on its way to the
    # server, seen once) reaches the simulator.
    frames = sim_frames(sim, "request")
    requests = [f for f in frames if f["name"] == "Control"]
    assert_only_status_queries_after(frames, {"id": 1, "action": "PAUSE"})
    assert {"id": 2, "action": "PAUSE"} not in [r["fields"] for r in requests]


@needs_browser
async def test_without_control_the_page_has_no_buttons_and_a_forged_write_is_refused(
    sim: SimProcess, tmp_path: Path
) -> None:
    async with dashboard(sim) as url, browser(tmp_path / "chromium") as page:
        # Waits for the page's own condition (every actuator drawn with a live value), not
        # for a virtual-time budget: `--dump-dom` after 3 s of virtual time dumped a page
        # with no actuator yet when the first snapshot came late (CI, a slow machine).
        await page.call("Page.navigate", url=url)
        await page.until(
            f"document.querySelectorAll('.la').length === 3 && {POSITIONS}[0] === '300'"
        )
        html = await page.js("document.documentElement.outerHTML")
        assert html.count('class="la"') == 3
        assert re.search(r'data-f="position">300<', html)
        main = html[html.index('<main id="buses">') : html.index("</main>")]
        assert "<button" not in main and "data-action" not in main
        assert '<button id="estop-all" hidden="">' in html
        request = urllib.request.Request(
            url + "api/estop", data=b"{}", headers={"Content-Type": "application/json"}
        )
        with pytest.raises(urllib.error.HTTPError) as refused:
            await asyncio.to_thread(urllib.request.urlopen, request)
        assert refused.value.code == 403
    names = {f["fields"].get("action") for f in sim_frames(sim, "request")}
    assert names == {"QUERY_STATUS"}  # watching sent only status queries, on exit too


def test_bad_options_are_refused_before_the_port_opens() -> None:
    for args, message in [
        (["--listen", "localhost"], "--listen='localhost' is not HOST:PORT"),
        (["--listen", "127.0.0.1:70000"], "port 0..65535"),
        (["--interval", "0"], "--interval=0.0 is out of range"),
        (["--window", "500:100"], "window high=100 is out of range"),
        (["--ids", "0"], "--ids id=0 is out of range"),
        (["--devices", "la:1,servo"], "kind 'servo' is unknown"),
    ]:
        r = cli("dashboard", "--port", "/dev/nonexistent-port", *args)
        assert r.returncode == 2, (args, r.stderr)
        assert message in r.stderr, (args, r.stderr)


def test_without_aiohttp_it_says_which_extra_to_install(tmp_path: Path) -> None:
    # A module named aiohttp that fails to import stands for a missing package.
    (tmp_path / "aiohttp.py").write_text("raise ImportError('No module named aiohttp')\n")
    env = {"PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    r = cli("dashboard", "--port", "/dev/nonexistent-port", env=env)
    assert r.returncode == 2
    assert r.stderr.strip() == (
        "motorbus dashboard needs the dashboard extra: pip install 'motorbus[dashboard]'"
    )


def get_json(url: str, body: dict[str, Any] | None = None) -> Any:
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=WAIT_S) as r:
        return json.load(r)


async def test_every_bus_of_a_bus_file_with_its_keys(tmp_path: Path) -> None:
    with (
        SimProcess(["la:1-2"], baud=921600, log_file=tmp_path / "arm.jsonl") as arm,
        SimProcess(["project-stepper", "quad-stepper"], baud=9600,
                   log_file=tmp_path / "feeder.jsonl") as feeder,
    ):  # fmt: skip
        buses = tmp_path / "buses.toml"
        buses.write_text(
            f'[[bus]]\nname = "arm"\nurl = "{arm.path}"\nbaud = 921600\n'
            'devices = ["la:1-2"]\nla_safe_action = "estop"\n'
            f'[[bus]]\nname = "feeder"\nurl = "{feeder.path}"\nbaud = 9600\n'
            'devices = ["project-stepper", "quad-stepper"]\n'
        )
        async with dashboard(None, "--bus-file", str(buses), "--control") as url:
            async with asyncio.timeout(WAIT_S):
                while True:
                    state = await asyncio.to_thread(get_json, url + "api/state")
                    a, f = state["buses"]
                    if len(f["project"]["projects"]) == 4 and all(d["latest"] for d in a["la"]):
                        break
                    await asyncio.sleep(0.1)
            assert (a["name"], f["name"]) == ("arm", "feeder")
            assert [d["id"] for d in a["la"]] == [1, 2] and f["la"] == []
            assert f["quad"] == {"axes": {}, "last_done": None}
            move = {"bus": "arm", "id": 1, "position": 600, "confirm": True}
            moved = await asyncio.to_thread(get_json, url + "api/move", move)
            assert moved["results"][0]["ok"], moved["results"][0]["error"]
            stop = await asyncio.to_thread(get_json, url + "api/pause", {"bus": "feeder"})
            assert [r["command"] for r in stop["results"]] == [
                "StopProject", "ManualStop", "StopAll"
            ]  # fmt: skip
        frames = sim_frames(arm, "request")
        arm_sent = [f["fields"] for f in frames if f["name"] == "Control"]
        # The bus file's la_safe_action: the actuator the dashboard moved is e-stopped on
        # the way out; the other one gets nothing.  After it, nothing but a status query
        # (the poll still on its way to the server, seen once with eight workers).
        assert_only_status_queries_after(frames, {"id": 1, "action": "ESTOP"})
        assert {"id": 2, "action": "ESTOP"} not in arm_sent
        names = [f["name"] for f in sim_frames(feeder, "request")]
        assert names.count("ReadProject") == 4
        assert {"StopProject", "ManualStop", "StopAll"} <= set(names)


def assert_only_status_queries_after(frames: list[dict[str, Any]], stop: dict[str, Any]) -> None:
    """``stop`` (a Control frame's fields) reached the simulator, and after its last one
    nothing but status queries did: no motion follows a safe end."""
    last = max(i for i, f in enumerate(frames) if f["name"] == "Control" and f["fields"] == stop)
    after = frames[last + 1 :]
    assert all(f["name"] == "Control" and f["fields"]["action"] == "QUERY_STATUS" for f in after)


def threads_cpus(pid: int) -> set[frozenset[int]]:
    """The CPU sets of every thread of process ``pid``."""
    tasks = Path(f"/proc/{pid}/task")
    return {frozenset(os.sched_getaffinity(int(t.name))) for t in tasks.iterdir()}


async def test_a_bus_file_process_group_is_served_on_its_cpus(tmp_path: Path) -> None:
    pytest.importorskip("zenoh", reason="the bus runs in the dashboard without the serve extra")
    allowed = os.sched_getaffinity(0)
    if len(allowed) < 2:
        pytest.skip("this process may use one CPU only: a pin could not be seen")
    cpu = max(allowed)
    missing = "/dev/motorbus-no-such-port"  # any bus but the group's fails the dashboard
    with SimProcess(["la:1"], baud=921600) as arm:
        buses = tmp_path / "buses.toml"
        buses.write_text(
            f'[[bus]]\nname = "spare"\nurl = "{missing}-1"\nbaud = 921600\n'
            f'[[bus]]\nname = "arm"\nurl = "{arm.path}"\nbaud = 921600\nprocess = "arms"\n'
            'devices = ["la:1"]\n'
            f'[[bus]]\nname = "hip"\nurl = "{missing}-2"\nbaud = 921600\nprocess = "legs"\n'
            f"[process.arms]\ncpus = [{cpu}]\n"
        )
        pids: list[int] = []
        async with dashboard(None, "--bus-file", str(buses), "--process", "arms", pids=pids) as url:
            state = await asyncio.to_thread(get_json, url + "api/state")
            assert [b["name"] for b in state["buses"]] == ["arm"]
            # The bus runs in the dashboard's motorbus serve child, on the group's CPUs
            # (every thread of it); the dashboard itself stays off them.
            ((holder, _),) = port_lock_holders(arm.path)
            assert holder != pids[0]
            assert threads_cpus(holder) == {frozenset({cpu})}
            assert threads_cpus(pids[0]) == {frozenset(allowed)}
    r = cli("dashboard", "--bus-file", str(buses), "--process", "hands")
    assert r.returncode == 2
    assert r.stderr.strip() == (
        f"motorbus dashboard: {buses}: process='hands' is not a process group of this "
        "file: choose one of arms, legs"
    )
    r = cli("dashboard", "--port", missing, "--process", "arms")
    assert r.returncode == 2
    assert "--process chooses buses of the bus file; --port names one" in r.stderr


async def test_listening_beyond_loopback_needs_the_printed_token(sim: SimProcess) -> None:
    labelled: list[tuple[str, str]] = []
    async with dashboard(sim, "--listen", "0.0.0.0:0", labelled=labelled) as url:
        assert "?token=" in url
        local, token = url.split("?token=")
        assert local.startswith("http://127.0.0.1:")
        with pytest.raises(urllib.error.HTTPError) as refused:
            await asyncio.to_thread(get_json, local + "api/state")
        assert refused.value.code == 401
        state = await asyncio.to_thread(get_json, f"{local}api/state?token={token}")
        assert [d["id"] for d in state["buses"][0]["la"]] == [1, 2, 3]
        # Every URL printed is one another machine could open: no 0.0.0.0; the host
        # name first, then this machine's addresses, each saying what it is.
        assert all("0.0.0.0" not in u for u, _ in labelled), labelled
        first, what = labelled[0]
        assert what == "host name", labelled
        assert urllib.parse.urlsplit(first).hostname in (socket.getfqdn(), socket.gethostname())
        for printed, what in labelled:
            assert what in ("host name", "address", "this machine only"), labelled
            assert printed.endswith(f"/?token={token}")
        for printed, what in labelled:
            if what == "address":  # this machine's own address reaches the page too
                base = printed.split("?")[0]
                state = await asyncio.to_thread(get_json, f"{base}api/state?token={token}")
                assert state["buses"][0]["la"]


async def test_record_writes_what_motorbus_replay_reads(sim: SimProcess, tmp_path: Path) -> None:
    folder = tmp_path / "rec"
    async with dashboard(sim, "--record", str(folder)) as url:
        async with asyncio.timeout(WAIT_S):
            while not (await asyncio.to_thread(get_json, url + "api/state"))["buses"][0]["la"][2][
                "polls"
            ]:
                await asyncio.sleep(0.1)
    (log,) = folder.glob("*-frames.jsonl")
    shown = cli("replay", str(log))
    assert shown.returncode == 0, shown.stderr
    for i in (1, 2, 3):
        assert f"la request Control id={i} action=QUERY_STATUS" in shown.stdout
        assert f"la reply Status id={i} target=" in shown.stdout
    rows = (folder / "plots.csv").read_text().splitlines()
    assert rows[0] == "t_s,bus,id,position,target,current_ma,force_g,temperature_c,errors"
    assert {r.split(",")[2] for r in rows[1:]} == {"1", "2", "3"}


async def test_without_the_serve_extra_the_bus_runs_in_the_dashboard_with_a_warning(
    sim: SimProcess, tmp_path: Path
) -> None:
    # A module named zenoh that fails to import stands for a missing serve extra.
    (tmp_path / "zenoh.py").write_text("raise ImportError('No module named zenoh')\n")
    env = {**_env(), "PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "motorbus", "dashboard", "--port", sim.path, "--ids", "1-3",
        "--listen", "127.0.0.1:0", stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env,
    )  # fmt: skip
    assert proc.stdout is not None
    try:
        url = (await asyncio.wait_for(proc.stdout.readline(), WAIT_S)).decode().strip()
        assert url.startswith("http://127.0.0.1:"), url
        state = await asyncio.to_thread(get_json, url + "api/state")
        assert state["buses"][0]["served"] is None
        assert [pid for pid, _ in port_lock_holders(sim.path)] == [proc.pid]
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = await asyncio.wait_for(proc.communicate(), WAIT_S)
    assert proc.returncode == 0, err.decode()
    assert err.decode().splitlines()[0] == (
        "motorbus dashboard: warning: the serve extra is not installed "
        "(pip install 'motorbus[serve]'): the bus runs in the dashboard's own process"
    )
    r = cli("dashboard", "--connect", "tcp/127.0.0.1:7447", "--ids", "1", env=env)
    assert r.returncode == 2
    assert "--connect needs the serve extra: pip install 'motorbus[serve]'" in r.stderr
