"""Run ``python -m motorbus ARGS`` as a fork of a process that has already imported it.

The suite runs the command line about 350 times, ``motorbus serve`` about 100 and
simulators (``SimProcess``) about 240, and each fresh interpreter spent ~100-150 ms of
CPU starting and importing before it did anything: the largest part of the suite's
CPU.  Here a *zygote* per worker and environment imports the command line once
(``python -c``, with exactly the environment the command is to see, so that what
modules read from it at import is what a fresh ``python -m motorbus`` would read), then
forks a child per run.  An environment's first run starts fresh, its second starts the
zygote (environments that name a test's temporary folder are often used once); a
worker keeps four, and retires the least recently used.

The child is a real process of its own: its own PID (signals, the guard's watch of its
parent), a zombie until its status is read, a session of its own if asked, the
caller's working directory and environment, standard input from ``/dev/null`` or the
given text, its output into pipes, the ``sys.argv`` and ``sys.path`` of ``python -m
motorbus``, and it ends as the interpreter would (``SystemExit`` codes, a traceback and
1 for an uncaught exception, death by SIGINT after an uncaught ``KeyboardInterrupt``;
threads joined, ``atexit`` run, garbage collected, output flushed).  What differs: it
does not repeat the interpreter's start and the imports (tests of start-up itself
start their own interpreters), a traceback shows the zygote's frames, and what an
import prints or warns once is the zygote's.  ``MOTORBUS_TESTS_FRESH=1`` runs every
command fresh.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import locale
import os
import select
import selectors
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from subprocess import Popen

ROOT = Path(__file__).resolve().parents[1]
#: Set to 1 to run every command in a fresh interpreter (what a user's shell does).
FRESH_ENV = "MOTORBUS_TESTS_FRESH"
#: Imported by the zygote ahead of any command, after every module of ``motorbus.cli``:
#: what the commands import when they run.  A module that fails to import (an extra
#: hidden by a test's environment) is left for the command to fail on, as it would.
PRELOAD = (
    "motorbus.bus.bus",
    "motorbus.manager",
    "motorbus.devices.la",
    "motorbus.devices.project_stepper",
    "motorbus.devices.quad_stepper",
    "motorbus.rig",
    "motorbus.streams",
    "motorbus.serve.client",
    "motorbus.sim.pty",
)


def run_motorbus(
    args: Sequence[str],
    env: Mapping[str, str] | None = None,
    timeout: float = 60,
    input: str | None = None,
) -> subprocess.CompletedProcess[str]:
    """``subprocess.run([python, -m, motorbus, *args], env=env, input=input,
    capture_output=True, text=True, timeout=timeout)``, forked from the zygote of
    ``env`` (default: this process's environment); standard input is ``input``, or
    empty (``/dev/null``, as under the suite's workers)."""
    command = [sys.executable, "-m", "motorbus", *args]
    env = dict(os.environ if env is None else env)
    zygote = None if env.get(FRESH_ENV) == "1" or not _forkable() else _zygote(env)
    if zygote is None:
        return subprocess.run(
            command,
            capture_output=True,
            text=True,
            timeout=timeout,
            env=env,
            input=input,
            stdin=None if input is not None else subprocess.DEVNULL,
        )
    return zygote.run(command, list(args), env, timeout, input)


def _forkable() -> bool:
    return hasattr(os, "pidfd_open") and hasattr(socket, "send_fds")


def spawn_motorbus(args: Sequence[str], *, new_session: bool = False) -> Popen[str] | ForkedProcess:
    """``subprocess.Popen([python, -m, motorbus, *args], stdout=PIPE, stderr=PIPE,
    text=True, start_new_session=new_session)`` in this process's environment, forked
    from its zygote: a process to talk to, signal and end (what the suite does with
    ``motorbus serve``)."""
    command = [sys.executable, "-m", "motorbus", *args]
    env = dict(os.environ)
    zygote = None if env.get(FRESH_ENV) == "1" or not _forkable() else _zygote(env)
    if zygote is None:
        return subprocess.Popen(
            command,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=new_session,
        )
    return ForkedProcess(zygote, command, env, new_session)


#: What pytest changes for every test: left out of a zygote's key (no module reads it at
#: import), and given to each child as the caller has it.
VOLATILE = ("PYTEST_CURRENT_TEST",)

#: Zygotes a worker keeps, the least recently used ended first (environments that
#: name a test's temporary folder come and go).
ZYGOTES_MAX = 4
#: Children forked so far by this process's zygotes (tests/test_zygote.py checks that a
#: run it compares was forked).
forks = 0

_ZYGOTES: dict[frozenset[tuple[str, str]], _Zygote] = {}
_SEEN: set[frozenset[tuple[str, str]]] = set()
_RETIRED: list[_Zygote] = []
_LOCK = threading.Lock()


def _zygote(env: Mapping[str, str]) -> _Zygote | None:
    """The zygote of ``env``; None the first time ``env`` is asked for (a zygote pays
    for itself from its second run: it imports more than one command needs)."""
    steady = {k: v for k, v in env.items() if k not in VOLATILE}
    key = frozenset(steady.items())
    with _LOCK:
        if key not in _SEEN:
            _SEEN.add(key)
            return None
        zygote = _ZYGOTES.pop(key, None)
        if zygote is None or zygote.proc.poll() is not None:
            zygote = _Zygote(steady)
        _ZYGOTES[key] = zygote  # the most recently used last
        while len(_ZYGOTES) > ZYGOTES_MAX:
            _ZYGOTES.pop(next(iter(_ZYGOTES))).retire()
        return zygote


def warm(env: Mapping[str, str]) -> None:
    """Have the zygote of ``env`` running now, so that the next run in ``env`` forks
    (tests/test_zygote.py compares forked runs with fresh ones)."""
    while _zygote(env) is None:
        pass


@atexit.register
def _end_zygotes() -> None:
    for zygote in [*_ZYGOTES.values(), *_RETIRED]:
        zygote.close()


class _Zygote:
    def __init__(self, env: dict[str, str]) -> None:
        self.folder = tempfile.mkdtemp(prefix="motorbus-zygote-")
        self.path = os.path.join(self.folder, "socket")
        code = (
            "import sys\n"
            "path = list(sys.path)\n"
            f"sys.path.insert(1, {str(ROOT)!r})\n"
            "from tests.zygote import serve\n"
            "serve(sys.argv[1], path)\n"
        )
        # stdin: a pipe whose end at the caller closes with it, so the zygote ends too
        # (and kills the children still running); "ready" on stdout; stderr is its own.
        self.proc = subprocess.Popen(
            [sys.executable, "-c", code, self.path],
            env=env,
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        )
        assert self.proc.stdout is not None and self.proc.stderr is not None
        ready = self.proc.stdout.readline()
        if ready != b"ready\n":
            self.proc.kill()
            _, err = self.proc.communicate()
            raise RuntimeError(f"the zygote did not start: {ready!r}{err.decode()[-3000:]}")

    def retire(self) -> None:
        """Fork no more: the zygote ends once its last child has ended and been waited
        for (its children keep running, each test ends its own)."""
        with (
            socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn,
            contextlib.suppress(OSError),
        ):
            conn.connect(self.path)
            conn.sendall(json.dumps({"retire": True}).encode())
        _RETIRED.append(self)

    def close(self) -> None:
        """End the zygote and the children it still runs (its caller's end does)."""
        try:
            self.proc.communicate(timeout=10)  # which closes its standard input first
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.communicate()
        try:
            os.unlink(self.path)
            os.rmdir(self.folder)
        except OSError:
            pass

    def run(
        self,
        command: list[str],
        args: list[str],
        env: dict[str, str],
        timeout: float,
        input: str | None,
    ) -> subprocess.CompletedProcess[str]:
        if input is None:
            stdin_fd = os.open(os.devnull, os.O_RDONLY)
        else:  # a file, read from its start: no writer to keep up with the reader
            with tempfile.TemporaryFile() as f:
                f.write(input.encode(locale.getpreferredencoding(False)))
                f.flush()
                stdin_fd = os.dup(f.fileno())
            os.lseek(stdin_fd, 0, os.SEEK_SET)
        conn, out_r, err_r = self.start(args, env, stdin_fd, new_session=False)
        return _collect(conn, out_r, err_r, command, timeout)

    def start(
        self, args: list[str], env: dict[str, str], stdin_fd: int, *, new_session: bool
    ) -> tuple[socket.socket, int, int]:
        """Fork a child with ``stdin_fd`` (closed here) as its standard input: the
        connection that gives its PID and then its status, and its output's pipes."""
        global forks
        out_r, out_w = os.pipe()
        err_r, err_w = os.pipe()
        conn = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            request = {"args": args, "cwd": os.getcwd(), "env": env, "session": new_session}
            conn.connect(self.path)
            socket.send_fds(conn, [json.dumps(request).encode()], [stdin_fd, out_w, err_w])
        except BaseException:
            conn.close()
            os.close(out_r)
            os.close(err_r)
            raise
        finally:
            for fd in (stdin_fd, out_w, err_w):
                os.close(fd)
        forks += 1
        return conn, out_r, err_r


#: Longest wait for the zygote to say a child's PID (it forks at once).
PID_TIMEOUT_S = 60.0


class ForkedProcess:
    """A ``Popen(..., stdin=DEVNULL, stdout=PIPE, stderr=PIPE, text=True)`` whose child a
    zygote forked: ``pid``, ``stdout``, ``stderr``, ``poll``, ``wait``, ``send_signal``,
    ``kill`` and ``communicate`` as ``Popen`` has them."""

    def __init__(
        self, zygote: _Zygote, command: list[str], env: dict[str, str], new_session: bool
    ) -> None:
        self.args = command
        stdin_fd = os.open(os.devnull, os.O_RDONLY)
        self._conn, out_r, err_r = zygote.start(command[3:], env, stdin_fd, new_session=new_session)
        encoding = locale.getpreferredencoding(False)
        self.stdout = open(out_r, encoding=encoding)  # noqa: SIM115 - closed as Popen's are
        self.stderr = open(err_r, encoding=encoding)  # noqa: SIM115
        self._status = b""
        self._unread: dict[int, list[bytes]] = {out_r: [], err_r: []}  # communicate() read
        self.returncode: int | None = None
        line = self._read_line(PID_TIMEOUT_S)
        if not line:
            raise RuntimeError(f"the zygote gave no PID for {command} in {PID_TIMEOUT_S} s")
        self.pid = int(line)

    def _read_line(self, timeout: float | None = None) -> bytes:
        """The next line from the zygote (the PID, then the status); b"" at a timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while b"\n" not in self._status:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not select.select([self._conn], [], [], left)[0]:
                return b""
            data = self._conn.recv(64)
            if not data:
                raise RuntimeError(f"the zygote of {self.args} ended")
            self._status += data
        line, self._status = self._status.split(b"\n", 1)
        return line

    def poll(self) -> int | None:
        return self.wait(0) if self.returncode is None else self.returncode

    def wait(self, timeout: float | None = None) -> int | None:
        if self.returncode is None:
            line = self._read_line(timeout)
            if line:
                self.returncode = int(line)
                self._conn.close()
            elif timeout != 0:
                raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.returncode is None:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        if self.returncode is None:
            _kill(self.pid)

    def communicate(self, timeout: float | None = None) -> tuple[str, str]:
        """Read both outputs to their ends (from the pipes, as ``Popen`` does: what a
        file object already buffered stays there) and wait for the status."""
        deadline = None if timeout is None else time.monotonic() + timeout
        open_fds = [fd for fd in self._unread if not self._ended(fd)]
        while open_fds:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            ready = select.select(open_fds, [], [], left)[0]
            if not ready:
                raise subprocess.TimeoutExpired(self.args, timeout or 0.0)
            for fd in ready:
                data = os.read(fd, 65536)
                self._unread[fd].append(data)
                if not data:
                    open_fds.remove(fd)
        left = None if deadline is None else max(0.0, deadline - time.monotonic())
        self.wait(left)
        out, err = (_text(b"".join(chunks)) for chunks in self._unread.values())
        return out, err

    def _ended(self, fd: int) -> bool:
        return bool(self._unread[fd]) and self._unread[fd][-1] == b""


_POPEN = subprocess.Popen


class SubprocessForkingSimulators:
    """``subprocess`` as ``motorbus.sim.process`` sees it in the suite: ``SimProcess``'s
    ``python -m motorbus sim`` forks from the zygote (the suite starts about 240
    simulators); everything else is ``subprocess``'s own."""

    def __getattr__(self, name: str) -> object:
        return getattr(subprocess, name)

    @staticmethod
    def Popen(args: Sequence[str], **options: object) -> object:
        simulator = [sys.executable, "-m", "motorbus", "sim"]
        expected = {
            "stdout": subprocess.PIPE,
            "stderr": subprocess.PIPE,
            "text": True,
            "start_new_session": True,
        }
        fresh = os.environ.get(FRESH_ENV) == "1" or not _forkable()
        patched = subprocess.Popen is not _POPEN  # a test's own stand-in has its say
        if not (fresh or patched) and list(args[:4]) == simulator and options == expected:
            return spawn_motorbus(args[3:], new_session=True)
        return subprocess.Popen(args, **options)  # type: ignore[call-overload]


def fork_simulators() -> None:
    """From now on, ``SimProcess`` forks its simulator from the zygote."""
    import motorbus.sim.process

    motorbus.sim.process.subprocess = SubprocessForkingSimulators()  # type: ignore[assignment,attr-defined]


class ForkedTimeout(subprocess.TimeoutExpired):
    """``TimeoutExpired`` of a forked run, with the PID of the child it killed."""

    def __init__(self, pid: int | None, *args: object) -> None:
        super().__init__(*args)  # type: ignore[arg-type]
        self.pid = pid


def _collect(
    conn: socket.socket, out_r: int, err_r: int, command: list[str], timeout: float
) -> subprocess.CompletedProcess[str]:
    """Read the child's output to its end and its status, as ``subprocess.run`` does
    (which kills its child whatever ends the wait: a timeout, or an exception such as
    pytest-timeout's)."""
    deadline = time.monotonic() + timeout
    #: After a timeout's kill, how long to wait for the output's end: a process the
    #: command started may hold its pipes (``subprocess.run`` would wait for ever).
    drain_s = 5.0
    chunks: dict[object, list[bytes]] = {out_r: [], err_r: [], conn: []}
    pid: int | None = None
    status: int | None = None
    timed_out = False
    try:
        with selectors.DefaultSelector() as sel:
            sel.register(out_r, selectors.EVENT_READ)
            sel.register(err_r, selectors.EVENT_READ)
            sel.register(conn, selectors.EVENT_READ)
            while sel.get_map():
                left = deadline - time.monotonic()
                if left <= 0 and not timed_out:
                    timed_out = True
                    deadline += drain_s
                    left = drain_s
                    if pid is not None:
                        _kill(pid)
                elif left <= 0:
                    break
                for key, _ in sel.select(left):
                    source = key.fileobj
                    data = conn.recv(4096) if source is conn else os.read(key.fd, 65536)
                    if not data:
                        sel.unregister(source)
                        continue
                    chunks[source].append(data)
                    if source is conn:
                        lines = b"".join(chunks[conn]).split(b"\n")
                        if pid is None and len(lines) > 1:
                            pid = int(lines[0])
                            if timed_out:
                                _kill(pid)
                        if len(lines) > 2:  # the status: the zygote reaps once we close
                            status = int(lines[1])
                            sel.unregister(conn)
    finally:
        if status is None and pid is not None:
            _kill(pid)
        conn.close()
        os.close(out_r)
        os.close(err_r)
    stdout, stderr = (_text(b"".join(chunks[fd])) for fd in (out_r, err_r))
    if timed_out:
        raise ForkedTimeout(pid, command, timeout, stdout, stderr)
    if status is None:
        raise RuntimeError(f"the zygote gave no status for {command}: {stderr[-2000:]}")
    return subprocess.CompletedProcess(command, status, stdout, stderr)


def _kill(pid: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)


def _text(data: bytes) -> str:
    """As ``subprocess.run(text=True)`` decodes: the locale's encoding, newlines
    translated."""
    text = data.decode(locale.getpreferredencoding(False))
    return text.replace("\r\n", "\n").replace("\r", "\n")


# -- the zygote ---------------------------------------------------------------------------


def serve(path: str, sys_path: list[str]) -> None:
    """The zygote's loop: fork a child per request, report its PID and its status.

    ``sys_path``: the interpreter's own path, before this module's folder was added.
    It ends when its caller goes (standard input at its end), killing the children it
    still runs; or, retired, once the last of them has ended and been waited for.
    """
    import gc
    import importlib
    import pkgutil

    commands: list[str] = []
    with contextlib.suppress(Exception):
        found = pkgutil.iter_modules(importlib.import_module("motorbus.cli").__path__)
        commands = [f"motorbus.cli.{m.name}" for m in found]
    for name in [*PRELOAD, *commands]:
        with contextlib.suppress(Exception):  # the command meets it, as it would
            importlib.import_module(name)
    # What is loaded now stays: a child's collections leave it alone.
    gc.collect()
    gc.freeze()
    # A fork keeps only the thread that forks: nothing imported may have started one
    # (Zenoh's runtime starts its threads with a session, not at import).
    assert len(os.listdir("/proc/self/task")) == 1, os.listdir("/proc/self/task")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(64)
    sys.stdout.write("ready\n")
    sys.stdout.flush()
    running: dict[int, tuple[int, socket.socket]] = {}  # pidfd -> (pid, connection)
    ended: dict[socket.socket, int] = {}  # connection -> PID, not yet reaped
    retired = False
    with selectors.DefaultSelector() as sel:
        sel.register(listener, selectors.EVENT_READ, "accept")
        sel.register(sys.stdin.fileno(), selectors.EVENT_READ, "caller")
        while not (retired and not running and not ended):
            for key, _ in sel.select():
                if key.data == "caller":  # the caller has gone: so does the zygote
                    for pid, _conn in running.values():
                        _kill(pid)
                    os._exit(0)
                if key.data == "accept":
                    conn, _ = listener.accept()
                    request, fds = _request(conn)
                    if request is None or request.get("retire"):
                        retired = retired or request is not None
                        if retired:
                            sel.unregister(listener)
                            listener.close()
                        for fd in fds:
                            os.close(fd)
                        conn.close()
                        continue
                    pid = os.fork()
                    if pid == 0:
                        _child(request, fds, sys_path)  # never returns
                    for fd in fds:
                        os.close(fd)
                    with contextlib.suppress(OSError):  # a caller gone: its run still ends
                        conn.sendall(b"%d\n" % pid)
                    pidfd = os.pidfd_open(pid)
                    running[pidfd] = (pid, conn)
                    sel.register(pidfd, selectors.EVENT_READ, "child")
                elif key.data == "child":  # ended: its status, but not reaped yet
                    pid, conn = running.pop(key.fd)
                    sel.unregister(key.fd)
                    os.close(key.fd)
                    status = os.waitid(os.P_PID, pid, os.WEXITED | os.WNOWAIT)
                    assert status is not None  # (None only with WNOHANG)
                    with contextlib.suppress(OSError):
                        conn.sendall(b"%d\n" % _returncode(status))
                    ended[conn] = pid
                    sel.register(conn, selectors.EVENT_READ, "ended")
                else:  # the caller has its status: the PID may go (Popen.wait reaps)
                    caller = key.fileobj
                    assert isinstance(caller, socket.socket)
                    with contextlib.suppress(OSError):
                        if caller.recv(64):
                            continue
                    sel.unregister(caller)
                    caller.close()
                    os.waitpid(ended.pop(caller), 0)


def _request(conn: socket.socket) -> tuple[dict[str, object] | None, list[int]]:
    """A caller's request and the descriptors it sent; None for one that is not (a
    caller that connected and then failed): the zygote goes on for the others."""
    conn.settimeout(10)
    fds: list[int] = []
    try:
        message, fds, _flags, _addr = socket.recv_fds(conn, 1 << 20, 3)
        request = json.loads(message)
    except (OSError, ValueError):
        return None, fds
    if not isinstance(request, dict) or (len(fds) != 3 and not request.get("retire")):
        return None, fds
    conn.settimeout(None)
    return request, fds


def _returncode(ended: os.waitid_result) -> int:
    """As ``Popen.returncode``: the exit status, or minus the signal that killed it."""
    if ended.si_code == os.CLD_EXITED:
        return ended.si_status
    return -ended.si_status


def _child(request: dict[str, object], fds: list[int], sys_path: list[str]) -> None:
    """Become ``python -m motorbus ARGS`` in the caller's directory, and end as it would."""
    import gc
    import runpy
    import traceback

    stdin, stdout, stderr = fds
    for fd, target in ((stdin, 0), (stdout, 1), (stderr, 2)):
        os.dup2(fd, target)
    # Nothing else open, as in a fresh interpreter: above all not the connections of
    # the other runs, whose callers wait for them to close.
    os.closerange(3, os.sysconf("SC_OPEN_MAX"))
    if request.get("session"):
        os.setsid()
    env = request["env"]
    assert isinstance(env, dict)
    os.environ.clear()
    os.environ.update(env)
    cwd = str(request["cwd"])
    os.chdir(cwd)
    sys.path[:] = [cwd, *sys_path[1:]]  # python -m: the working folder first
    args = request["args"]
    assert isinstance(args, list)
    code = 0
    interrupted = False
    try:
        sys.argv = ["-m", *args]  # runpy sets sys.argv[0] to motorbus/__main__.py
        runpy.run_module("motorbus", run_name="__main__", alter_sys=True)
    except SystemExit as end:
        code = _exit_code(end)
    except KeyboardInterrupt:
        traceback.print_exc()
        interrupted = True
    except BaseException:
        traceback.print_exc()
        code = 1
    # The interpreter's end, in its order: threads joined, atexit, what is left
    # collected (a task destroyed while pending says so), the output flushed.
    try:
        threading._shutdown()  # type: ignore[attr-defined]
        atexit._run_exitfuncs()
        gc.collect()
    finally:
        try:
            sys.stdout.flush()
        except Exception:
            code = 120
        with contextlib.suppress(Exception):
            sys.stderr.flush()
        if interrupted:  # as the interpreter: die of SIGINT, or 130 if it cannot
            signal.signal(signal.SIGINT, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGINT)
            code = 130
        os._exit(code)


def _exit_code(end: SystemExit) -> int:
    """The status ``SystemExit(end.code)`` gives, printing what the interpreter prints."""
    value = end.code
    if value is None:
        return 0
    if isinstance(value, int):
        return value & 0xFF
    print(value, file=sys.stderr)
    return 1
